#include "source.hpp"

#include <pwd.h>
#include <sys/stat.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <filesystem>

#include "chimera/ipc/clock.hpp"
#include "chimera/ipc/segment.hpp"

namespace chimtop {

using chimera::prof::StatusReader;

namespace {

constexpr const char* kShm = "/dev/shm/";
constexpr std::string_view kPrefix = "chimera.";
constexpr std::string_view kSuffix = ".status";

std::string user_name(uid_t uid) {
    if (const passwd* pw = ::getpwuid(uid)) return pw->pw_name;
    return "uid " + std::to_string(uid);
}

std::string segment_path(const std::string& subsystem) { return kShm + std::string(kPrefix) + subsystem + std::string(kSuffix); }

}  // namespace

std::string permission_advice(const std::string& subsystem, bool write) {
    const std::string advice = chimera::ipc::permission_advice(chimera::ipc::segment_name(subsystem, "status"), write);
    return write ? advice + " (--half-tick changes the subsystem's accounting)" : advice;
}

std::vector<SubsystemEntry> running_subsystems() {
    std::vector<SubsystemEntry> out;
    std::error_code ec;
    for (std::filesystem::directory_iterator it(kShm, ec), end; !ec && it != end; it.increment(ec)) {
        const std::string file = it->path().filename().string();
        if (file.size() <= kPrefix.size() + kSuffix.size() || file.rfind(kPrefix, 0) != 0 ||
            file.compare(file.size() - kSuffix.size(), kSuffix.size(), kSuffix) != 0)
            continue;
        SubsystemEntry e;
        e.name = file.substr(kPrefix.size(), file.size() - kPrefix.size() - kSuffix.size());
        struct stat st {};
        if (::stat(it->path().c_str(), &st) == 0) {
            e.owner = st.st_uid;
            e.mode = st.st_mode & 07777;
        }
        int err = 0;
        std::string why;
        if (auto r = StatusReader::try_watch(e.name, err, why)) {
            e.readable = true;
            e.alive = r->alive();
            e.creator_pid = r->creator_pid();
            e.tasks = r->snapshot().size();
        } else {
            e.problem = err == EACCES || err == EPERM ? permission_advice(e.name, false) : why;
        }
        out.push_back(std::move(e));
    }
    std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) { return a.name < b.name; });
    return out;
}

std::string entry_line(const SubsystemEntry& e) {
    char buf[160];
    std::snprintf(buf, sizeof buf, "%-20s ", e.name.c_str());
    if (!e.readable) return buf + e.problem;
    std::snprintf(buf, sizeof buf, "%-20s %-22s %3zu task%s  owner %s", e.name.c_str(),
                  e.alive ? ("running (pid " + std::to_string(e.creator_pid) + ")").c_str() : "stopped (left behind)",
                  e.tasks, e.tasks == 1 ? " " : "s", user_name(e.owner).c_str());
    return buf;
}

Attachment::Attachment(std::string subsystem, std::int64_t half_tick_ns)
    : subsystem_(std::move(subsystem)), path_(segment_path(subsystem_)), half_tick_ns_(half_tick_ns) {}

bool Attachment::refresh() {
    if (reader_ && (!reader_->alive() || inode() != inode_)) {
        reader_.reset();
        ++restarts_;
    }
    if (reader_) return true;
    const ino_t before = inode();
    int err = 0;
    std::string why;
    // A watcher (read-only, takes no lock, not a user of the segment), unless
    // --half-tick must change the accounting: that is the owner's.
    const bool write = half_tick_ns_ >= 0;
    reader_ = write ? StatusReader::try_attach(subsystem_, err, why) : StatusReader::try_watch(subsystem_, err, why);
    if (reader_ && inode() != before) reader_.reset();  // replaced while attaching
    denied_ = !reader_ && (err == EACCES || err == EPERM);
    if (!reader_) {
        problem_ = denied_          ? permission_advice(subsystem_, write)
                   : err == ENOENT ? "segment " + chimera::ipc::segment_name(subsystem_, "status") + " not found"
                                   : why;
        return false;
    }
    problem_.clear();
    inode_ = before;
    window_ = chimera::prof::StatusWindow{};  // a new subsystem: since its start
    apply_accounting();
    return true;
}

std::vector<chimera::prof::TaskStatus> Attachment::snapshot() const {
    return reader_ ? window_.snapshot(*reader_) : std::vector<chimera::prof::TaskStatus>{};
}

std::vector<chimera::prof::RtpuEpoch> Attachment::rtpus() const {
    std::vector<chimera::prof::RtpuEpoch> out;
    if (!reader_) return out;
    for (std::uint32_t r = 0; r < reader_->rtpus(); ++r) out.push_back(reader_->rtpu_epoch(static_cast<int>(r)));
    return out;
}

void Attachment::restart_window() {
    if (reader_) window_.restart(*reader_);
}

std::optional<double> Attachment::window_seconds() const {
    if (window_.started_ns() == 0) return std::nullopt;
    return static_cast<double>(chimera::ipc::now_ns() - window_.started_ns()) * 1e-9;
}

void Attachment::apply_accounting() {
    if (half_tick_ns_ < 0) return;
    using chimera::prof::Accounting;
    try {
        for (std::uint32_t r = 0; r < reader_->rtpus(); ++r)
            reader_->set_accounting(static_cast<int>(r),
                                    half_tick_ns_ > 0 ? Accounting::half_tick : Accounting::nanoseconds,
                                    half_tick_ns_);
        error_.clear();
    } catch (const std::exception& e) {
        error_ = e.what();
    }
}

ino_t Attachment::inode() const {
    struct stat st {};
    return ::stat(path_.c_str(), &st) == 0 ? st.st_ino : 0;
}

}  // namespace chimtop
