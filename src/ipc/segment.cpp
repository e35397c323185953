// POSIX shared-memory segments with the common header (segment.hpp).
#include "chimera/ipc/segment.hpp"

#include <fcntl.h>
#include <grp.h>
#include <pthread.h>
#include <pwd.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <climits>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <mutex>
#include <thread>
#include <utility>

#include "chimera/ipc/clock.hpp"

namespace chimera::ipc {
namespace {

std::string describe(const std::string& name, const std::string& message) {
    return "segment " + name + ": " + message;
}

[[noreturn]] void fail_errno(const std::string& name, const std::string& what, int err) {
    throw SegmentError(name, what + ": " + std::strerror(err), err);
}

void check_name(const std::string& name) {
    if (name.size() < 2 || name[0] != '/')
        throw SegmentError(name, "a segment name starts with '/' and is not empty");
    if (name.find('/', 1) != std::string::npos)
        throw SegmentError(name, "a segment name holds no '/' after the first");
    if (name.size() > NAME_MAX)
        throw SegmentError(name, "name longer than " + std::to_string(NAME_MAX) + " characters");
}

// A new open file description of the file `fd` names (whatever its name now),
// opened with `flags`; or -1 (no /proc, or the file's mode no longer lets this
// user open it so).
int reopen(int fd, int flags) noexcept {
    char self[32];
    std::snprintf(self, sizeof self, "/proc/self/fd/%d", fd);
    return open(self, flags | O_CLOEXEC);
}

// The mapping's own description (reopen), apart from `fd`'s, which carries
// the user locks and which only the descriptor table holds: a dying process
// closes it in exit_files(), whoever holds its memory. A mapping holds its
// description as long as the process's memory exists, and a reader of
// /proc/PID/stat or status (ps, top) keeps that memory past the process's
// death. Locks on the mapped description made such a dead user count on until
// the read ended (issue #15.2's kill loop saw it), and a child made by fork(),
// which keeps the mappings, kept the parent's locks.
int description_for_mapping(int fd) noexcept { return reopen(fd, O_RDWR); }

// Maps the file of `fd` and applies the prefault/lock options; returns the
// address. A user's mapping gets a description of its own when it can (see
// description_for_mapping); a watcher's, which carries no lock, needs none.
void* map_fd(const std::string& name, int fd, std::size_t size, bool prefault, bool lock,
             bool& locked, bool read_only = false) {
    int flags = MAP_SHARED;
    if (prefault) flags |= MAP_POPULATE;
    const int own = read_only ? -1 : description_for_mapping(fd);
    void* base = mmap(nullptr, size, read_only ? PROT_READ : PROT_READ | PROT_WRITE, flags, own >= 0 ? own : fd, 0);
    const int err = errno;
    if (own >= 0) close(own);  // the mapping keeps its description
    if (base == MAP_FAILED) fail_errno(name, "mmap", err);
    locked = lock && mlock(base, size) == 0;
    return base;
}

// A lock request on `len` bytes from `start` (fcntl's record-lock form).
struct flock byte_range(short type, off_t start, off_t len) noexcept {
    struct flock fl {};
    fl.l_type = type;
    fl.l_whence = SEEK_SET;
    fl.l_start = start;
    fl.l_len = len;
    return fl;
}

// The user lock: a shared (F_RDLCK) or exclusive (F_WRLCK) open-file-
// description lock on the segment's first byte. OFD locks belong to the open
// file, not to the process, so two mappings in one process are two users too,
// and the kernel drops them when the last descriptor of the file closes (a
// process that dies closes all of them).
bool set_user_lock(int fd, short type, bool wait) noexcept {
    struct flock fl = byte_range(type, 0, 1);
    for (;;) {
        if (fcntl(fd, wait ? F_OFD_SETLKW : F_OFD_SETLK, &fl) == 0) return true;
        if (errno != EINTR) return false;
    }
}

// The shared user lock for an attach. A last user holds the exclusive lock
// only for the few system calls that unlink the name, so this polls instead of
// blocking (F_OFD_SETLKW): where the mapping shares the locks' description (no
// /proc: see description_for_mapping), the exclusive lock may outlive its
// holder's detach when a child made by fork() keeps the holder's mapping, and
// that child may be this very attacher, which would then wait for itself. While it waits,
// it reads the segment's state through the descriptor: a segment marked
// destroyed is given up at once (ESHUTDOWN). 0 or an errno.
int wait_for_user_lock(int fd) noexcept {
    const std::int64_t give_up = now_ns() + 10'000'000'000;  // a holder that never lets go
    for (;;) {
        if (set_user_lock(fd, F_RDLCK, false)) return 0;
        if (errno != EAGAIN && errno != EACCES) return errno;
        std::uint32_t state = 0;
        if (pread(fd, &state, sizeof state, offsetof(SegmentHeader, state)) == sizeof state &&
            state == static_cast<std::uint32_t>(SegmentState::destroyed))
            return ESHUTDOWN;
        if (now_ns() > give_up) return EDEADLK;
        std::this_thread::sleep_for(std::chrono::microseconds(100));
    }
}

// Each mapping also holds an exclusive lock on one byte of its own in
// [1, kUserSlots]: users() counts those locks exactly with F_OFD_GETLK
// (/proc/locks cannot: it is read a page at a time, and locks that come and go
// elsewhere in the system between pages make lines repeat or vanish).
constexpr off_t kUserSlots = 1 << 16;

bool lock_one_free_slot(int fd) noexcept {
    for (off_t slot = 1; slot <= kUserSlots; ++slot) {
        struct flock fl = byte_range(F_WRLCK, slot, 1);
        if (fcntl(fd, F_OFD_SETLK, &fl) == 0) return true;
        if (errno == EINTR) --slot;
        else if (errno != EAGAIN && errno != EACCES) return false;
    }
    errno = EUSERS;
    return false;
}

// Slot locks held in [first, last], probed through `probe`, an open file
// description of its own (so that every mapping's lock conflicts with it).
// The kernel reports one conflicting lock, not necessarily the lowest: split
// the range around it.
std::uint32_t count_slot_locks(int probe, off_t first, off_t last) noexcept {
    if (first > last) return 0;
    struct flock fl = byte_range(F_WRLCK, first, last - first + 1);
    if (fcntl(probe, F_OFD_GETLK, &fl) != 0 || fl.l_type == F_UNLCK) return 0;
    const off_t lo = std::max(first, fl.l_start);
    const off_t hi = fl.l_len == 0 ? last : std::min(last, fl.l_start + fl.l_len - 1);
    return static_cast<std::uint32_t>(hi - lo + 1) + count_slot_locks(probe, first, lo - 1) +
           count_slot_locks(probe, hi + 1, last);
}

// The descriptors of this process's mappings. A child made by fork()
// inherits them, and with them the open file descriptions that carry the
// parent's user locks: while the child lived, the parent's locks would
// outlive the parent's detach (a segment never freed), and a child attaching
// to a segment its parent was destroying would wait for a lock it holds itself.
// So the child closes them at once (pthread_atfork), keeping the mappings. A
// fixed table of atomics: the child handler may take no lock.
constexpr std::size_t kTrackedFds = 1024;
std::atomic<int> g_segment_fds[kTrackedFds];

void close_inherited_segment_fds() noexcept {
    for (auto& slot : g_segment_fds) {
        const int fd = slot.exchange(-1, std::memory_order_relaxed);
        if (fd >= 0) close(fd);
    }
}

const bool g_fork_handler = [] {
    for (auto& slot : g_segment_fds) slot.store(-1, std::memory_order_relaxed);
    return pthread_atfork(nullptr, nullptr, &close_inherited_segment_fds) == 0;
}();

void track_fd(int fd) noexcept {
    (void)g_fork_handler;
    for (auto& slot : g_segment_fds) {
        int expected = -1;
        if (slot.compare_exchange_strong(expected, fd, std::memory_order_relaxed)) return;
    }
    // More than kTrackedFds mappings: this one stays open in a forked child.
}

void untrack_fd(int fd) noexcept {
    for (auto& slot : g_segment_fds) {
        int expected = fd;
        if (slot.compare_exchange_strong(expected, -1, std::memory_order_relaxed)) return;
    }
}

// Same file (device and inode) as `fd`?
bool names_file(const std::string& name, int fd) noexcept {
    struct stat mine {}, now {};
    if (fstat(fd, &mine) != 0) return false;
    const int other = shm_open(name.c_str(), O_RDONLY, 0);
    if (other < 0) return false;
    const bool same = fstat(other, &now) == 0 && now.st_dev == mine.st_dev && now.st_ino == mine.st_ino;
    close(other);
    return same;
}

#ifndef CHIMERA_WATCH_GROUP
#define CHIMERA_WATCH_GROUP "chimera"
#endif

std::string user_name(uid_t uid) {
    if (const passwd* pw = getpwuid(uid)) return pw->pw_name;
    return "uid " + std::to_string(uid);
}

std::string group_name(gid_t gid) {
    if (const group* gr = getgrgid(gid)) return gr->gr_name;
    return "gid " + std::to_string(gid);
}

// Gives a new segment's file the mode asked for: group bits go to the watch
// group, or are dropped (said once per process) when there is none to give.
void set_mode(const std::string& name, int fd, mode_t mode) {
    if ((mode & 070) != 0) {
        const std::string group = watch_group_name();
        const struct group* gr = group.empty() ? nullptr : getgrnam(group.c_str());
        std::string why;
        if (group.empty()) why = "no watch group is set (CHIMERA_GROUP is empty)";
        else if (!gr) why = "group " + group + " does not exist (groupadd --system " + group + ")";
        else if (fchown(fd, static_cast<uid_t>(-1), gr->gr_gid) != 0)
            why = "cannot give it to group " + group + " (" + std::strerror(errno) +
                  ": the creator must be root or a member)";
        if (!why.empty()) {
            static std::once_flag said;
            std::call_once(said, [&] {
                std::fprintf(stderr,
                             "chimera: %s: shared segments are owner-only (0600) from %s on, so only "
                             "their owner and root can watch them (docs/permissions.md)\n",
                             why.c_str(), name.c_str());
            });
            mode &= ~static_cast<mode_t>(077);
        }
    }
    // fchmod: the umask must not narrow the mode the caller asked for.
    if (fchmod(fd, mode) != 0) fail_errno(name, "fchmod", errno);
}

// The owner and mode of segment `name`: fstat of the open segment, or lstat
// of its file when this user may not open it, or when it is a symbolic link
// (shm_open never follows one: O_NOFOLLOW, ELOOP). False when there is none.
bool owner_and_mode(const std::string& name, struct stat& st) noexcept {
    const int fd = shm_open(name.c_str(), O_RDONLY, 0);
    if (fd >= 0) {
        const bool ok = fstat(fd, &st) == 0;
        close(fd);
        return ok;
    }
    return (errno == EACCES || errno == ELOOP) && lstat(("/dev/shm" + name).c_str(), &st) == 0;
}

// "nobody's (uid 65534, mode 0644)"
std::string owner_text(const struct stat& st) {
    char mode[8];
    std::snprintf(mode, sizeof mode, "%04o", static_cast<unsigned>(st.st_mode & 07777));
    return user_name(st.st_uid) + "'s (uid " + std::to_string(st.st_uid) + ", mode " + mode + ")";
}

// Whose the squatted file `st` under `name` is and what to do: ": it is
// nobody's (uid 65534, mode 0644), and only nobody or root may remove it
// (sudo rm /dev/shm/NAME), then start again".
std::string whose_and_remedy(const std::string& name, const struct stat& st) {
    const std::string may = st.st_uid == 0 ? "root" : user_name(st.st_uid) + " or root";
    return ": it is " + owner_text(st) + ", and only " + may + " may remove it (sudo rm /dev/shm" + name +
           "), then start again";
}

// A watcher's refusal of the squatted segment `name` (`why`: squat_reason()):
// it shows nobody's data as a subsystem's, and, not being the runner,
// removes nothing. "does not exist" when the file went meanwhile.
[[noreturn]] void refuse_to_watch(const std::string& name, const std::string& why) {
    struct stat st {};
    if (!owner_and_mode(name, st)) throw SegmentError(name, "does not exist", ENOENT);
    throw SegmentError(name, why + whose_and_remedy(name, st), EPERM);
}

// shm_open(), with EACCES explained (who owns the segment, what to do).
int open_segment(const std::string& name, int flags) {
    const int fd = shm_open(name.c_str(), flags, 0);
    if (fd >= 0) return fd;
    const int err = errno;
    if (err == ENOENT) throw SegmentError(name, "does not exist", ENOENT);
    if (err == ELOOP) {  // a symbolic link planted under the name: never followed
        const std::string why = "squatted: a symbolic link, not a segment";
        if ((flags & O_ACCMODE) == O_RDONLY) refuse_to_watch(name, why);
        make_way(name, why);
        throw SegmentError(name, "does not exist", ENOENT);
    }
    if (err == EACCES) throw SegmentError(name, permission_advice(name, (flags & O_ACCMODE) != O_RDONLY), EACCES);
    fail_errno(name, "shm_open", err);
}

// The effective uid of the live process `pid` (/proc/PID/status, which a
// non-dumpable process shows too), or -1 when there is none.
uid_t process_uid(int pid) noexcept {
    if (pid <= 0) return static_cast<uid_t>(-1);
    char path[32];
    std::snprintf(path, sizeof path, "/proc/%d/status", pid);
    FILE* f = std::fopen(path, "re");
    if (!f) return static_cast<uid_t>(-1);
    char line[256];
    unsigned real = 0, effective = 0;
    bool found = false;
    while (!found && std::fgets(line, sizeof line, f))
        found = std::sscanf(line, "Uid: %u %u", &real, &effective) == 2;
    std::fclose(f);
    return found ? static_cast<uid_t>(effective) : static_cast<uid_t>(-1);
}

// True when process `pid` runs (kill(pid, 0), as is_stale() asks).
bool process_runs(int pid) noexcept { return pid > 0 && (kill(pid, 0) == 0 || errno == EPERM); }

// What a segment's header claims about it.
struct Claim {
    std::uint32_t magic = 0;
    std::int32_t creator_pid = 0;
};

// A file without a chimera header may be one being made (a few system calls
// between shm_open and init_header): it counts as abandoned only once it has
// been so for kHeaderlessGraceSeconds, judged at `now`.
constexpr std::time_t kHeaderlessGraceSeconds = 10;
bool headerless_long_enough(const struct stat& st, std::time_t now) noexcept {
    return now - st.st_ctime >= kHeaderlessGraceSeconds;
}

// Why a segment file of owner and mode `st` whose header claims `h` (nullptr:
// this user may not read it) is not to be believed at time `now`, or "". One
// check for squatted() by name and for attach() and watch() on the open descriptor.
std::string squat_reason(const struct stat& st, const Claim* h, std::time_t now) {
    if (S_ISLNK(st.st_mode)) return "squatted: a symbolic link, not a segment";
    if (!S_ISREG(st.st_mode)) return "squatted: not a regular file";
    if ((st.st_mode & 022) != 0) return "squatted: group or others may write to it";
    if (!h) return "";
    const bool chimeras = h->magic == kSegmentMagic;
    const int pid = chimeras ? h->creator_pid : 0;
    const uid_t creator = process_uid(pid);
    if (creator != static_cast<uid_t>(-1) && creator != st.st_uid)
        return "squatted: its header names as its creator pid " + std::to_string(pid) + ", a process of " +
               user_name(creator) + ", not of its owner";
    // Another user's file that no live process of theirs stands behind: a
    // fake naming a dead pid, or a crashed run's, is nobody's segment for us.
    if (st.st_uid == geteuid()) return "";
    if (chimeras && !process_runs(pid))
        return "squatted: it is another user's, and the creator its header names, pid " + std::to_string(pid) +
               ", is not running";
    if (!chimeras && headerless_long_enough(st, now))
        return "squatted: it is another user's, and holds no chimera header";
    return "";
}

// What the header of the open segment `fd` claims; all zero (no chimera
// header) when the file is too small to hold one, so that an empty file
// planted under a name counts as one without a header, not as one this user
// may not read.
Claim read_claim(int fd) noexcept {
    unsigned char bytes[sizeof(SegmentHeader)] = {};
    Claim c;
    if (pread(fd, bytes, sizeof bytes, 0) != static_cast<ssize_t>(sizeof bytes)) return c;
    std::memcpy(&c.magic, bytes + offsetof(SegmentHeader, magic), sizeof c.magic);
    std::memcpy(&c.creator_pid, bytes + offsetof(SegmentHeader, creator_pid), sizeof c.creator_pid);
    return c;
}

}  // namespace

std::string watch_group_name() {
    if (const char* env = std::getenv("CHIMERA_GROUP")) return env;
    return CHIMERA_WATCH_GROUP;
}

std::string permission_advice(const std::string& name, bool write) {
    const std::string path = "/dev/shm" + name;
    struct stat st {};
    if (stat(path.c_str(), &st) != 0) return "permission denied: " + path;
    char mode[8];
    std::snprintf(mode, sizeof mode, "%04o", static_cast<unsigned>(st.st_mode & 07777));
    const std::string owner = user_name(st.st_uid), group = group_name(st.st_gid);
    std::string s = "permission denied: " + path + " is " + owner + "'s (group " + group + ", mode " + mode + "): ";
    const bool group_reads = (st.st_mode & S_IRGRP) != 0;
    const std::string run_as = "run as " + owner + (st.st_uid == 0 ? " (sudo)" : " or root");
    if (write) {
        s += "only " + owner + " may change it: " + run_as;
        if (group_reads) s += "; members of group " + group + " may only watch it";
    } else if (group_reads) {
        s += "add yourself to group " + group + " (usermod -aG " + group + " " + user_name(geteuid()) +
             "), then log in again";
    } else {
        const std::string watchers = watch_group_name().empty() ? "chimera" : watch_group_name();
        s += "only " + owner + " may read it: " + run_as + ", or let group " + watchers +
             " watch (groupadd --system " + watchers + ", then restart the subsystem)";
    }
    return s;
}

std::string squatted(const std::string& name) { return squatted(name, std::time(nullptr)); }

std::string squatted(const std::string& name, std::time_t now) {
    const int fd = shm_open(name.c_str(), O_RDONLY, 0);
    if (fd < 0) {
        struct stat st {};
        return owner_and_mode(name, st) ? squat_reason(st, nullptr, now) : "";
    }
    struct stat st {};
    const Claim h = read_claim(fd);
    std::string why;
    if (fstat(fd, &st) == 0) why = squat_reason(st, &h, now);
    close(fd);
    return why;
}

void make_way(const std::string& name, const std::string& why) {
    struct stat st {};
    if (!owner_and_mode(name, st)) return;
    const uid_t me = geteuid();
    if (me != 0 && st.st_uid != me) throw SegmentError(name, why + whose_and_remedy(name, st), EPERM);
    std::fprintf(stderr, "chimera: segment %s, %s: %s: removed, to be created anew\n", name.c_str(),
                 owner_text(st).c_str(), why.c_str());
    if (shm_unlink(name.c_str()) != 0 && errno != ENOENT) fail_errno(name, "shm_unlink", errno);
}

namespace {

// Segment::create() found `name` taken. A squatted file is made way for
// (make_way: root or its owner removes it, anyone else is refused naming the
// owner), and so is another user's this user may not read, which it cannot
// tell from a running segment and may not use either. True when the name was
// freed (or vanished meanwhile); false when it stands: this user's own, or a
// live segment of another user's.
bool make_way_for_create(const std::string& name) {
    std::string why = squatted(name);
    if (why.empty()) {
        struct stat st {};
        if (!owner_and_mode(name, st)) return true;
        const int fd = shm_open(name.c_str(), O_RDONLY, 0);
        if (fd >= 0) close(fd);
        if (st.st_uid == geteuid() || fd >= 0) return false;
        why = "taken by another user's file, which this user may not read";
    }
    make_way(name, why);
    return true;
}

}  // namespace

std::string describe(std::string_view segment, const Fault& f) {
    if (!f) return "";
    std::string s = "segment ";
    s += segment;
    s += ": ";
    s += f.field;
    if (f.index >= 0) s += " [" + std::to_string(f.index) + "]";
    s += " is " + std::to_string(f.value) + " (must be " + f.rule + " " + std::to_string(f.limit) + ")";
    return s;
}

std::string object_type_name(ObjectType type) {
    switch (type) {
        case ObjectType::test: return "test";
        case ObjectType::svar_table: return "svar_table";
        case ObjectType::tbuf: return "tbuf";
        case ObjectType::xmail_mailbox: return "xmail_mailbox";
        case ObjectType::xmail_shm: return "xmail_shm";
        case ObjectType::xmail_sem: return "xmail_sem";
        case ObjectType::xmail_msg: return "xmail_msg";
        case ObjectType::prof_status: return "prof_status";
        case ObjectType::sbs_control: return "sbs_control";
        case ObjectType::name_server: return "name_server";
        case ObjectType::sampler_ring: return "sampler_ring";
    }
    return "type " + std::to_string(static_cast<std::uint32_t>(type));
}

SegmentError::SegmentError(std::string name, std::string message, int error_number)
    : std::runtime_error(describe(name, message)), name_(std::move(name)), errno_(error_number) {}

std::string segment_name(std::string_view subsystem, std::string_view object) {
    std::string name = "/chimera.";
    name += subsystem;
    name += '.';
    name += object;
    if (subsystem.empty() || object.empty())
        throw SegmentError(name, "subsystem and object names must not be empty");
    if (subsystem.find('/') != std::string_view::npos || object.find('/') != std::string_view::npos)
        throw SegmentError(name, "subsystem and object names hold no '/'");
    check_name(name);
    return name;
}

void init_header(SegmentHeader& h, SegmentKind kind, std::size_t total_size) noexcept {
    h.magic = kSegmentMagic;
    h.layout_version = kind.layout_version;
    h.object_type = static_cast<std::uint32_t>(kind.type);
    h.byte_order = kByteOrderCode;
    h.total_size = total_size;
    h.attaches.store(0, std::memory_order_relaxed);
    h.creator_pid = static_cast<std::int32_t>(getpid());
    h.state.store(static_cast<std::uint32_t>(SegmentState::building), std::memory_order_relaxed);
    h.header_size = sizeof(SegmentHeader);
    h.created_ns = static_cast<std::uint64_t>(now_ns());
    std::memset(h.reserved, 0, sizeof h.reserved);
}

void validate_header(const std::string& name, const SegmentHeader& h, SegmentKind kind,
                     std::size_t mapped_size) {
    if (mapped_size < sizeof(SegmentHeader))
        throw SegmentError(name, "size " + std::to_string(mapped_size) +
                                     " bytes is smaller than a segment header");
    if (h.magic == __builtin_bswap32(kSegmentMagic) && h.byte_order == __builtin_bswap32(kByteOrderCode))
        throw SegmentError(name, "byte-order code 0x04030201: created by a machine of the other "
                                 "byte order");
    if (h.magic != kSegmentMagic) {
        char buf[128];
        std::snprintf(buf, sizeof buf, "bad magic 0x%08x (expected 0x%08x): not a chimera segment",
                      h.magic, kSegmentMagic);
        throw SegmentError(name, buf);
    }
    if (h.byte_order != kByteOrderCode) {
        char buf[128];
        std::snprintf(buf, sizeof buf,
                      "byte-order code 0x%08x, this machine writes 0x%08x: created with the "
                      "other byte order",
                      h.byte_order, kByteOrderCode);
        throw SegmentError(name, buf);
    }
    if (h.object_type != static_cast<std::uint32_t>(kind.type))
        throw SegmentError(name, "holds a " + object_type_name(static_cast<ObjectType>(h.object_type)) +
                                     ", expected a " + object_type_name(kind.type));
    if (h.layout_version != kind.layout_version)
        throw SegmentError(name, "layout version " + std::to_string(h.layout_version) +
                                     ", this library expects " +
                                     std::to_string(kind.layout_version));
    if (h.header_size != sizeof(SegmentHeader))
        throw SegmentError(name, "header size " + std::to_string(h.header_size) +
                                     ", this library expects " +
                                     std::to_string(sizeof(SegmentHeader)));
    if (h.total_size != mapped_size)
        throw SegmentError(name, "header says " + std::to_string(h.total_size) +
                                     " bytes, the segment has " + std::to_string(mapped_size));
}

Fault header_fault(const void* image, std::size_t size, SegmentKind kind) noexcept {
    if (size < sizeof(SegmentHeader)) return {"segment size", -1, size, sizeof(SegmentHeader), "at least"};
    const auto& h = *static_cast<const SegmentHeader*>(image);
    if (Fault f = fault_if(h.magic != kSegmentMagic, "magic", h.magic, kSegmentMagic, "equal to")) return f;
    if (Fault f = fault_if(h.byte_order != kByteOrderCode, "byte-order code", h.byte_order,
                           kByteOrderCode, "equal to"))
        return f;
    const auto type = static_cast<std::uint32_t>(kind.type);
    if (Fault f = fault_if(h.object_type != type, "object type", h.object_type, type, "equal to")) return f;
    if (Fault f = fault_if(h.layout_version != kind.layout_version, "layout version",
                           h.layout_version, kind.layout_version, "equal to"))
        return f;
    if (Fault f = fault_if(h.header_size != sizeof(SegmentHeader), "header size", h.header_size,
                           sizeof(SegmentHeader), "equal to"))
        return f;
    return fault_if(h.total_size != size, "total size", h.total_size, size, "equal to");
}

Segment::Segment(Segment&& o) noexcept
    : name_(std::move(o.name_)),
      base_(std::exchange(o.base_, nullptr)),
      size_(std::exchange(o.size_, 0)),
      fd_(std::exchange(o.fd_, -1)),
      owner_(std::exchange(o.owner_, 0)),
      locked_(std::exchange(o.locked_, false)),
      creator_(std::exchange(o.creator_, false)),
      published_(std::exchange(o.published_, false)) {}

Segment& Segment::operator=(Segment&& o) noexcept {
    if (this != &o) {
        detach();
        name_ = std::move(o.name_);
        base_ = std::exchange(o.base_, nullptr);
        size_ = std::exchange(o.size_, 0);
        fd_ = std::exchange(o.fd_, -1);
        owner_ = std::exchange(o.owner_, 0);
        locked_ = std::exchange(o.locked_, false);
        creator_ = std::exchange(o.creator_, false);
        published_ = std::exchange(o.published_, false);
    }
    return *this;
}

Segment::~Segment() { detach(); }

Segment Segment::create(const std::string& name, std::size_t size, SegmentKind kind,
                        const CreateOptions& options) {
    check_name(name);
    if (size < sizeof(SegmentHeader))
        throw SegmentError(name, "size " + std::to_string(size) + " is smaller than the header");
    int fd = shm_open(name.c_str(), O_RDWR | O_CREAT | O_EXCL, options.mode);
    if (fd < 0 && errno == EEXIST && make_way_for_create(name))
        fd = shm_open(name.c_str(), O_RDWR | O_CREAT | O_EXCL, options.mode);
    if (fd < 0) {
        if (errno == EEXIST) throw SegmentError(name, "already exists", EEXIST);
        fail_errno(name, "shm_open", errno);
    }
    Segment seg;
    seg.name_ = name;
    seg.creator_ = true;
    try {
        set_mode(name, fd, options.mode);
        if (ftruncate(fd, static_cast<off_t>(size)) != 0) fail_errno(name, "ftruncate", errno);
        // Polls: a cleanup of a stale segment of this name (destroy_if_unused)
        // may hold the exclusive lock for a moment while it finds this one new.
        if (const int err = wait_for_user_lock(fd); err != 0) fail_errno(name, "fcntl(F_OFD_SETLK)", err);
        if (!lock_one_free_slot(fd)) fail_errno(name, "user slot lock", errno);
        seg.base_ = map_fd(name, fd, size, options.prefault, options.lock, seg.locked_);
        seg.size_ = size;
    } catch (...) {
        close(fd);
        shm_unlink(name.c_str());
        throw;
    }
    seg.fd_ = fd;
    track_fd(fd);
    seg.owner_ = getpid();
    init_header(seg.header(), kind, size);
    return seg;
}

Segment Segment::attach(const std::string& name, SegmentKind kind, const AttachOptions& options) {
    return map_published(name, kind, options, false);
}

Segment Segment::watch(const std::string& name, SegmentKind kind, const AttachOptions& options) {
    return map_published(name, kind, options, true);
}

Segment Segment::map_published(const std::string& name, SegmentKind kind, const AttachOptions& options,
                               bool read_only) {
    check_name(name);
    const int fd = open_segment(name, read_only ? O_RDONLY : O_RDWR);
    struct stat st {};
    if (fstat(fd, &st) != 0) {
        const int err = errno;
        close(fd);
        fail_errno(name, "fstat", err);
    }
    // The file opened is believed only when its owner stands behind it
    // (squat_reason on this very descriptor). An attaching user makes way for
    // a squatted one (root removes it, so that its creator makes it anew); a
    // watcher, not the runner, refuses it naming whose it is.
    const Claim claim = read_claim(fd);
    if (const std::string why = squat_reason(st, &claim, std::time(nullptr)); !why.empty()) {
        close(fd);
        if (read_only) refuse_to_watch(name, why);
        make_way(name, why);
        throw SegmentError(name, "does not exist", ENOENT);
    }
    const auto size = static_cast<std::size_t>(st.st_size);
    if (size < sizeof(SegmentHeader)) {
        close(fd);
        throw SegmentError(name, "size " + std::to_string(size) +
                                     " bytes is smaller than a segment header");
    }
    // Count ourselves in first: from here a detach_destroy_if_last() of
    // another user cannot remove the segment, and one that removed it before
    // has marked it destroyed, which we see below.
    // A watcher takes no lock: it is nobody's user, and waits for nobody.
    if (const int err = read_only ? 0 : wait_for_user_lock(fd); err != 0) {
        close(fd);
        if (err == ESHUTDOWN) throw SegmentError(name, "is being destroyed");
        fail_errno(name, "fcntl(F_OFD_SETLK)", err);
    }
    if (!read_only && !lock_one_free_slot(fd)) {
        const int err = errno;
        close(fd);
        fail_errno(name, "user slot lock", err);
    }
    Segment seg;  // from here its destructor unmaps and closes on a throw
    seg.name_ = name;
    seg.fd_ = fd;
    track_fd(fd);
    seg.owner_ = getpid();
    seg.base_ = map_fd(name, fd, size, options.prefault, options.lock, seg.locked_, read_only);
    seg.size_ = size;
    SegmentHeader& h = seg.header();
    // A segment still being built: wait for publish() a bounded time.
    const std::int64_t deadline = now_ns() + options.ready_timeout_ns;
    for (;;) {
        const auto state = static_cast<SegmentState>(h.state.load(std::memory_order_acquire));
        if (state == SegmentState::ready) break;
        if (state == SegmentState::destroyed) throw SegmentError(name, "is being destroyed");
        if (now_ns() > deadline)
            throw SegmentError(name, "is still being built by pid " + std::to_string(h.creator_pid));
        std::this_thread::sleep_for(std::chrono::microseconds(200));
    }
    validate_header(name, h, kind, size);
    if (!read_only) h.attaches.fetch_add(1, std::memory_order_relaxed);
    seg.published_ = true;
    return seg;
}

bool Segment::read_only() const noexcept {
    if (fd_ < 0 || owner_ != getpid()) return false;
    const int flags = fcntl(fd_, F_GETFL);
    return flags >= 0 && (flags & O_ACCMODE) == O_RDONLY;
}

void Segment::publish() noexcept {
    if (!base_) return;
    header().state.store(static_cast<std::uint32_t>(SegmentState::ready), std::memory_order_release);
    published_ = true;
}

bool Segment::release(bool destroy_if_last) noexcept {
    // A copy inherited through fork() is the parent's mapping, not a user of
    // its own: its descriptor was closed in the child (close_inherited_segment_fds).
    const bool mine = owner_ == getpid();
    if (!base_) {
        if (fd_ >= 0 && mine) {  // attach() failed after opening
            untrack_fd(fd_);
            close(fd_);
        }
        fd_ = -1;
        return false;
    }
    bool destroy = false;
    if (mine) {
        if (creator_ && !published_) {
            destroy = true;  // a creation that failed half-way leaves nothing behind
        } else if (destroy_if_last && !read_only() && set_user_lock(fd_, F_WRLCK, false)) {
            // No other live mapping holds a lock: the segment is ours to remove.
            // `destroyed` first, so that an attacher that opened the name and
            // waits for its shared lock learns it as soon as it gets it. The
            // name may meanwhile have been unlinked and reused: remove only ours.
            header().state.store(static_cast<std::uint32_t>(SegmentState::destroyed),
                                 std::memory_order_seq_cst);
            destroy = names_file(name_, fd_);
        }
    }
    if (locked_) munlock(base_, size_);
    munmap(base_, size_);
    if (destroy) shm_unlink(name_.c_str());
    if (fd_ >= 0 && mine) {  // drops this mapping's user lock
        untrack_fd(fd_);
        close(fd_);
    }
    base_ = nullptr;
    size_ = 0;
    fd_ = -1;
    locked_ = false;
    return destroy;
}

std::uint32_t Segment::users() const noexcept {
    if (fd_ < 0 || owner_ != getpid()) return 0;
    // A description of its own, so that every mapping's lock conflicts with it.
    const int probe = reopen(fd_, O_RDONLY);
    if (probe < 0) return 0;
    const std::uint32_t n = count_slot_locks(probe, 1, kUserSlots);
    close(probe);
    return n;
}

bool Segment::destroy_if_unused(const std::string& name) noexcept {
    const int fd = shm_open(name.c_str(), O_RDWR, 0);
    if (fd < 0) return false;
    bool removed = false;
    struct stat st {};
    if (set_user_lock(fd, F_WRLCK, false) && fstat(fd, &st) == 0 &&
        static_cast<std::size_t>(st.st_size) >= sizeof(SegmentHeader)) {
        void* p = mmap(nullptr, sizeof(SegmentHeader), PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
        if (p != MAP_FAILED) {
            auto* h = static_cast<SegmentHeader*>(p);
            // Still being built by a live creator holds its lock; a dead one's
            // is garbage too. But a creator that has just made the file and not
            // yet locked it leaves it without a header for a few system calls:
            // a young file without one is somebody's new segment, not garbage
            // (a cleanup of a name reused at once removed the new segment).
            const bool being_made = h->magic != kSegmentMagic && !headerless_long_enough(st, std::time(nullptr));
            if (!being_made)
                h->state.store(static_cast<std::uint32_t>(SegmentState::destroyed), std::memory_order_seq_cst);
            munmap(p, sizeof(SegmentHeader));
            removed = !being_made && names_file(name, fd) && shm_unlink(name.c_str()) == 0;
        }
    }
    close(fd);
    return removed;
}

bool Segment::in_use(const std::string& name) noexcept {
    const int fd = shm_open(name.c_str(), O_RDONLY, 0);
    if (fd < 0) return false;
    struct flock fl = byte_range(F_WRLCK, 0, 1);
    const bool used = fcntl(fd, F_OFD_GETLK, &fl) == 0 && fl.l_type != F_UNLCK;
    close(fd);
    return used;
}

bool Segment::end_for_all() noexcept {
    bool removed = false;
    if (base_ && fd_ >= 0 && owner_ == getpid() && !read_only()) {
        header().state.store(static_cast<std::uint32_t>(SegmentState::destroyed), std::memory_order_seq_cst);
        removed = names_file(name_, fd_) && shm_unlink(name_.c_str()) == 0;
    }
    release(false);
    return removed;
}

void Segment::detach() noexcept { release(false); }

bool Segment::detach_destroy_if_last() noexcept { return release(true); }

bool Segment::unlink(const std::string& name) noexcept { return shm_unlink(name.c_str()) == 0; }

bool Segment::exists(const std::string& name) noexcept {
    const int fd = shm_open(name.c_str(), O_RDONLY, 0);
    if (fd < 0) return false;
    close(fd);
    return true;
}

bool Segment::is_stale(const std::string& name) noexcept {
    const int fd = shm_open(name.c_str(), O_RDONLY, 0);
    if (fd < 0) return false;
    struct stat st {};
    bool stale = true;  // too small or unreadable to be anybody's segment
    if (fstat(fd, &st) == 0 && static_cast<std::size_t>(st.st_size) >= sizeof(SegmentHeader)) {
        void* p = mmap(nullptr, sizeof(SegmentHeader), PROT_READ, MAP_SHARED, fd, 0);
        if (p != MAP_FAILED) {
            const auto* h = static_cast<const SegmentHeader*>(p);
            const int pid = h->magic == kSegmentMagic ? h->creator_pid : 0;
            stale = !(pid > 0 && (kill(pid, 0) == 0 || errno == EPERM));
            munmap(p, sizeof(SegmentHeader));
        }
    }
    close(fd);
    return stale;
}

}  // namespace chimera::ipc
