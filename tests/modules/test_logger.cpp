// The logger writes only where it is safe to, as root too (issue #29.4): the
// shipped qlog.rmod's relative FILE goes to the subsystem's output folder
// ($XDG_STATE_HOME/chimera/SUBSYSTEM), created 0700; a folder someone else
// owns or may write to, or a symlinked one, is refused at spawn naming it; the
// file is created 0600 without following a symlink, so one planted at the old
// fixed path (/tmp/chimera_qlog.csv) or at the new one changes nothing.
// Each test has its own XDG_STATE_HOME and HOME, never the real home.
#include "fig3_7.hpp"

#include <chimera/sbs.hpp>

#include <gtest/gtest.h>
#include <pwd.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <thread>

namespace {

namespace fs = std::filesystem;
using chimera::sbs::Subsystem;
using chimera::sbs::TaskId;

std::string read_all(const fs::path& p) {
    std::ifstream in(p);
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
}

bool has(const std::string& text, const std::string& part) { return text.find(part) != std::string::npos; }

class Logger : public ::testing::Test {
protected:
    void SetUp() override {
        tmp_ = fs::temp_directory_path() / ("chimera_logger" + std::to_string(::getpid()));
        fs::remove_all(tmp_);
        fs::create_directories(tmp_);
        fs::permissions(tmp_, fs::perms::owner_all);
        ::setenv("XDG_STATE_HOME", (tmp_ / "state").c_str(), 1);
        ::setenv("HOME", (tmp_ / "home").c_str(), 1);
        ::unsetenv("CHIMERA_OUTPUT_DIR");
        subsystem_ = "logger" + std::to_string(::getpid());
        out_dir_ = tmp_ / "state" / "chimera" / subsystem_;
        // The file a planted symlink points at: root's (the test's user's) 0600 file.
        victim_ = tmp_ / "victim";
        std::ofstream(victim_) << "secret\n";
        fs::permissions(victim_, fs::perms::owner_read | fs::perms::owner_write);
        victim_mtime_ = fs::last_write_time(victim_);
        sbs_ = Subsystem::init(fig3_7::load_sbs(nullptr, subsystem_));
        fig3_7::add_module_dirs(*sbs_);
        qlog_rmod_ = (fs::path(fig3_7::rmod("jpid")).parent_path().parent_path() / "logger" / "qlog.rmod").string();
    }
    void TearDown() override {
        if (sbs_) sbs_->finish();
        fs::remove_all(tmp_);
    }

    // Spawns the shipped qlog.rmod, runs it for a moment; the error of `on`, "" when none.
    std::string run_qlog() {
        const TaskId id = sbs_->spawn(qlog_rmod_, "ctrl");
        try {
            sbs_->control(id, chimera::sbs::Control::on);
        } catch (const chimera::sbs::Error& e) {
            return std::string(e.what()) + " / warning: " + sbs_->status(id).warning;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(200));
        sbs_->control(id, chimera::sbs::Control::off);
        return "";
    }

    // The message of a refused spawn of qlog.rmod.
    std::string spawn_refusal(const std::string& rmod) {
        try {
            sbs_->spawn(rmod, "ctrl");
        } catch (const chimera::sbs::Error& e) {
            return e.what();
        }
        ADD_FAILURE() << rmod << " was spawned";
        return "";
    }

    void expect_victim_untouched() {
        EXPECT_EQ(read_all(victim_), "secret\n");
        EXPECT_EQ(fs::last_write_time(victim_), victim_mtime_);
    }

    fs::path tmp_, out_dir_, victim_;
    fs::file_time_type victim_mtime_;
    std::string subsystem_, qlog_rmod_;
    std::unique_ptr<Subsystem> sbs_;
};

mode_t mode_of(const fs::path& p) {
    struct stat st{};
    EXPECT_EQ(::lstat(p.c_str(), &st), 0) << p;
    return st.st_mode & 07777;
}

// (d) The normal case: the CSV in a new 0700 output folder, mode 0600, even
// when a file of another mode was there.
TEST_F(Logger, WritesTheCsvInTheSubsystemsOutputFolder) {
    const TaskId first = sbs_->spawn(qlog_rmod_, "ctrl");  // makes the folder
    EXPECT_EQ(sbs_->get(first, "FILE"), "qlog.csv");
    sbs_->control(first, chimera::sbs::Control::kill);
    std::ofstream(out_dir_ / "qlog.csv") << "old\n";
    fs::permissions(out_dir_ / "qlog.csv", fs::perms::owner_all | fs::perms::group_read | fs::perms::others_read);
    ASSERT_EQ(run_qlog(), "");
    EXPECT_EQ(mode_of(out_dir_), 0700u);
    EXPECT_EQ(mode_of(out_dir_ / "qlog.csv"), 0600u);
    const std::string csv = read_all(out_dir_ / "qlog.csv");
    EXPECT_EQ(csv.rfind("t,Q_REF[0],", 0), 0u) << csv;
    EXPECT_GE(std::count(csv.begin(), csv.end(), '\n'), 3) << csv;
}

// (a) A symlink at the old fixed path to root's 0600 file: the shipped
// qlog.rmod writes its own file and leaves the target alone.
TEST_F(Logger, ASymlinkAtTheOldTmpPathIsNotWrittenThrough) {
    const fs::path old_path = "/tmp/chimera_qlog.csv";
    std::error_code ec;
    if (fs::exists(fs::symlink_status(old_path, ec)))
        GTEST_SKIP() << old_path << " exists already (another run's?): not replaced by this test";
    fs::create_symlink(victim_, old_path);
    const std::string error = run_qlog();
    fs::remove(old_path);
    EXPECT_EQ(error, "");
    expect_victim_untouched();
    EXPECT_TRUE(fs::is_regular_file(out_dir_ / "qlog.csv"));
}

// (b) A symlink at the new path: `on` fails naming the file, the target is untouched.
TEST_F(Logger, ASymlinkInTheOutputFolderIsNotFollowed) {
    fs::create_directories(out_dir_);
    fs::permissions(out_dir_, fs::perms::owner_all);
    fs::create_symlink(victim_, out_dir_ / "qlog.csv");
    const std::string error = run_qlog();
    std::printf("on refused: %s\n", error.c_str());
    EXPECT_TRUE(has(error, "on() returned OFF")) << error;
    EXPECT_TRUE(has(error, (out_dir_ / "qlog.csv").string())) << error;
    EXPECT_TRUE(has(error, "a symlink: not followed")) << error;
    expect_victim_untouched();
    EXPECT_TRUE(fs::is_symlink(out_dir_ / "qlog.csv"));
}

// (c) An output folder others may write to, another user's, or a symlink: refused at spawn, named.
TEST_F(Logger, AnOutputFolderNotOwnedAndClosedIsRefused) {
    fs::create_directories(out_dir_);
    fs::permissions(out_dir_, fs::perms::all);
    std::string why = spawn_refusal(qlog_rmod_);
    std::printf("spawn refused: %s\n", why.c_str());
    EXPECT_TRUE(has(why, "qlog.rmod: LOCAL FILE qlog.csv: output folder " + out_dir_.string())) << why;
    EXPECT_TRUE(has(why, "with mode 0777")) << why;
    EXPECT_TRUE(has(why, "CHIMERA_OUTPUT_DIR")) << why;

    fs::remove(out_dir_);
    fs::create_directories(tmp_ / "elsewhere");
    fs::permissions(tmp_ / "elsewhere", fs::perms::owner_all);
    fs::create_directory_symlink(tmp_ / "elsewhere", out_dir_);
    why = spawn_refusal(qlog_rmod_);
    EXPECT_TRUE(has(why, "output folder " + out_dir_.string() + " is a symlink")) << why;
    EXPECT_TRUE(fs::is_empty(tmp_ / "elsewhere"));

    const passwd* nobody = ::getpwnam("nobody");
    if (::geteuid() != 0 || !nobody) GTEST_SKIP() << "another user's folder: needs root and user nobody";
    fs::remove(out_dir_);
    fs::create_directories(out_dir_);
    fs::permissions(out_dir_, fs::perms::owner_all);
    ASSERT_EQ(::chown(out_dir_.c_str(), nobody->pw_uid, nobody->pw_gid), 0);
    why = spawn_refusal(qlog_rmod_);
    EXPECT_TRUE(has(why, "output folder " + out_dir_.string() + " is owned by nobody")) << why;
}

// An absolute FILE in a folder anyone may write to (/tmp) is refused naming it;
// in a folder of this user's, closed to others, it is written.
TEST_F(Logger, AnAbsoluteFileOnlyInAClosedFolder) {
    const auto rmod = [&](const std::string& name, const std::string& file) {
        std::string text = read_all(qlog_rmod_);
        text.replace(text.find("qlog.csv"), 8, file);
        std::ofstream(tmp_ / (name + ".rmod")) << text;
        return (tmp_ / (name + ".rmod")).string();
    };
    const std::string why = spawn_refusal(rmod("tmplog", "/tmp/chimera_qlog.csv"));
    EXPECT_TRUE(has(why, "tmplog.rmod: LOCAL FILE /tmp/chimera_qlog.csv: output folder /tmp is owned by")) << why;
    EXPECT_TRUE(has(why, "with mode 1777")) << why;

    qlog_rmod_ = rmod("ownlog", (tmp_ / "own.csv").string());
    ASSERT_EQ(run_qlog(), "");
    EXPECT_EQ(mode_of(tmp_ / "own.csv"), 0600u);
    EXPECT_FALSE(fs::exists(out_dir_));
}

}  // namespace
