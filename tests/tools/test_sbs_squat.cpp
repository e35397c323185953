// Names another user squats do not stop root's `sbs` (issue #29.5,
// docs/permissions.md). As `nobody`, a forked child makes what any local user
// could: a fake /dev/shm/chimera.X.svar and .status whose header names pid 1
// (root's init, alive) as the creator, or a /tmp/chimera-0 folder of its own.
// Root's real `sbs` then starts X anyway, saying what it removed or moved
// aside. /tmp is a private tmpfs in a mount namespace of the test's own, so
// the machine's /tmp/chimera-0 (other root tests' sockets) is never touched.
#include "chimera/ipc/segment.hpp"
#include "sbs_harness.hpp"
#include "server.hpp"

#include <gtest/gtest.h>

#include <fcntl.h>
#include <sched.h>
#include <sys/mman.h>
#include <sys/mount.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <glob.h>
#include <pwd.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "as_user.hpp"

using sbs_test::Workspace;
namespace ipc = chimera::ipc;

namespace {

// Text a forked child leaves for the parent (a shared anonymous page).
struct Report {
    char text[4096];
};

Report* shared_report() {
    void* p = ::mmap(nullptr, sizeof(Report), PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
    EXPECT_NE(p, MAP_FAILED);
    return static_cast<Report*>(p);
}

int wait_for_exit(pid_t pid) {
    int st = 0;
    if (::waitpid(pid, &st, 0) != pid) return -1;
    return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
}

// Runs `body` as nobody in a forked child; its exit status.
template <typename Body>
int as_nobody(Body body) {
    const pid_t pid = ::fork();
    if (pid == 0) _exit(chimera::test::become_nobody({}) ? body() : 10);
    return wait_for_exit(pid);
}

// A published segment `name` of `type`, its header naming pid 1 as creator, left behind.
int plant_fake(const std::string& name, ipc::ObjectType type) {
    ipc::Segment fake = ipc::Segment::create(name, 4096, {type, 1});
    fake.header().creator_pid = 1;
    fake.publish();
    _exit(0);  // no destructor: the file stays
}

// In a child of its own: a new mount namespace with a private tmpfs on /tmp,
// the working directory kept on the test's folder (hidden by the mount, still
// reachable as "."). The folders under /tmp that `keep` names (a build tree
// cloned there: the sbs program, its modules) are bound back into the new
// /tmp from the old one, reached through a descriptor taken before the mount.
// 77 when the namespace or a mount is not permitted.
int in_private_tmp(const std::string& cwd, const std::vector<std::string>& keep) {
    if (::unshare(CLONE_NEWNS) != 0) return 77;
    if (::mount(nullptr, "/", nullptr, MS_REC | MS_PRIVATE, nullptr) != 0) return 77;
    if (::chdir(cwd.c_str()) != 0) return 11;
    const int old_tmp = ::open("/tmp", O_PATH | O_DIRECTORY | O_CLOEXEC);
    if (old_tmp < 0) return 13;
    if (::mount("tmpfs", "/tmp", "tmpfs", 0, "mode=1777") != 0) return 77;
    for (const std::string& path : keep) {
        if (path.rfind("/tmp/", 0) != 0) continue;
        const std::string top = path.substr(5, path.find('/', 5) - 5);  // /tmp/TOP/...
        const std::string at = "/tmp/" + top;
        const std::string from = "/proc/self/fd/" + std::to_string(old_tmp) + "/" + top;
        if (::access(at.c_str(), F_OK) == 0) continue;  // bound already
        if (::mkdir(at.c_str(), 0700) != 0 || ::mount(from.c_str(), at.c_str(), nullptr, MS_BIND | MS_REC, nullptr) != 0)
            return 77;
    }
    ::close(old_tmp);
    return 0;
}

// "uid 0 mode 0700" of `path` (lstat), or "missing".
std::string owner_mode(const std::string& path) {
    struct stat st {};
    if (::lstat(path.c_str(), &st) != 0) return "missing";
    char s[64];
    std::snprintf(s, sizeof s, "uid %u mode %04o", static_cast<unsigned>(st.st_uid),
                  static_cast<unsigned>(st.st_mode & 07777));
    return s;
}

std::string the_one_match(const std::string& pattern) {
    glob_t g{};
    std::string found = ::glob(pattern.c_str(), 0, nullptr, &g) == 0 && g.gl_pathc == 1 ? g.gl_pathv[0] : "";
    ::globfree(&g);
    return found;
}

uid_t nobody_uid() { return ::getpwnam("nobody")->pw_uid; }

}  // namespace

TEST(SbsSquat, FakeSegmentsNamingPid1DoNotStopRootsSbs) {
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    Workspace ws;
    const std::string svar = ipc::segment_name(ws.subsystem(), "svar");
    const std::string status = ipc::segment_name(ws.subsystem(), "status");
    ASSERT_EQ(as_nobody([&] { return plant_fake(svar, ipc::ObjectType::svar_table); }), 0);
    ASSERT_EQ(as_nobody([&] { return plant_fake(status, ipc::ObjectType::prof_status); }), 0);

    const auto run = ws.sbs_run({"-c", "status"});
    EXPECT_EQ(run.status, 0) << run.err;  // was 1: "subsystem ... is already running"
    const std::string nobody = "nobody's (uid " + std::to_string(nobody_uid()) + ", mode 0600)";
    for (const auto& name : {svar, status})
        EXPECT_NE(run.err.find("chimera: segment " + name + ", " + nobody +
                               ": squatted: its header names as its creator pid 1, a process of root, not of its "
                               "owner: removed, to be created anew\n"),
                  std::string::npos)
            << run.err;
    EXPECT_EQ(run.err.find("watching it read-only"), std::string::npos) << "a fake is nobody's subsystem to watch";
    EXPECT_FALSE(ipc::Segment::exists(svar));  // the real run finished and removed its own
    EXPECT_FALSE(ipc::Segment::exists(status));
}

TEST(SbsSquat, ATmpChimera0OfNobodysDoesNotStopListenWithoutXdgRuntimeDir) {
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    Workspace ws;
    Report* report = shared_report();
    const std::string sbs_file = ws.subsystem() + ".sbs";  // relative: /tmp is covered in the child
    const pid_t child = ::fork();
    if (child == 0) {
        if (const int err = in_private_tmp(ws.dir(), {sbs_test::env("SBS_EXE"), sbs_test::env("SBS_TEST_DATA")});
            err != 0)
            _exit(err);
        if (as_nobody([] { ::umask(022); return ::mkdir("/tmp/chimera-0", 0755) == 0 ? 0 : 1; }) != 0) _exit(12);
        ::unsetenv("XDG_RUNTIME_DIR");  // as under sudo
        const auto run = sbs_test::run(sbs_test::env("SBS_EXE"),
                                       {sbs_file, "--module-path", sbs_test::env("SBS_TEST_DATA"), "--listen", "-c",
                                        "status"});
        const std::string aside = the_one_match("/tmp/chimera-0.squatted-*");
        std::snprintf(report->text, sizeof report->text, "status %d\nnew %s\naside %s %s\nerr %s", run.status,
                      owner_mode("/tmp/chimera-0").c_str(), aside.c_str(), owner_mode(aside).c_str(),
                      run.err.c_str());
        _exit(0);
    }
    const int st = wait_for_exit(child);
    if (st == 77) GTEST_SKIP() << "no private mount namespace here (unshare or mount refused), so /tmp cannot be faked";
    ASSERT_EQ(st, 0);
    const std::string r = report->text;
    EXPECT_NE(r.find("status 0\nnew uid 0 mode 0700\naside /tmp/chimera-0.squatted-"), std::string::npos) << r;
    EXPECT_NE(r.find(" uid " + std::to_string(nobody_uid()) + " mode 0755\n"), std::string::npos)
        << "nobody's folder is kept, aside: " << r;
    EXPECT_NE(r.find("sbs: socket directory /tmp/chimera-0 was nobody's (uid " + std::to_string(nobody_uid()) +
                     "), mode 0755, a directory: moved aside to /tmp/chimera-0.squatted-"),
              std::string::npos)
        << r;
    EXPECT_NE(r.find("listening on unix socket /tmp/chimera-0/" + ws.subsystem() + ".sock"), std::string::npos) << r;
}

// A user who may not move another's folder aside is told whose it is and what to do.
TEST(SbsSquat, ASquattedFolderIsRefusedNamingItsOwnerToAnotherUser) {
    if (!chimera::test::can_switch_user()) GTEST_SKIP() << "needs root (setresuid to nobody)";
    Report* report = shared_report();
    const pid_t child = ::fork();
    if (child == 0) {
        if (const int err = in_private_tmp("/", {}); err != 0) _exit(err);
        const std::string dir = "/tmp/chimera-" + std::to_string(nobody_uid());
        if (::mkdir(dir.c_str(), 0755) != 0) _exit(12);  // root's, where nobody's should be
        _exit(as_nobody([&] {
            ::unsetenv("XDG_RUNTIME_DIR");
            try {
                chimera::cli::default_socket_path("x");
                return 3;
            } catch (const chimera::cli::ServerError& e) {
                std::snprintf(report->text, sizeof report->text, "%s", e.what());
                return 0;
            }
        }));
    }
    const int st = wait_for_exit(child);
    if (st == 77) GTEST_SKIP() << "no private mount namespace here (unshare or mount refused), so /tmp cannot be faked";
    ASSERT_EQ(st, 0);
    const std::string dir = "/tmp/chimera-" + std::to_string(nobody_uid());
    EXPECT_EQ(std::string(report->text),
              "socket directory " + dir + " must belong to this user with mode 0700, and it is root's (uid 0), mode "
              "0755, a directory: ask its owner or root to remove it (sudo rm -r " + dir +
              "), or set XDG_RUNTIME_DIR to a folder of your own");
}
