// chimera/ipc/segment.hpp — a POSIX shared-memory segment with a common header.
//
// Every shared object (SVAR table, TBUF, mailbox, status block...) is one
// segment named `/chimera.<subsystem>.<object>` (docs/architecture.md §2). At
// offset 0 sits a SegmentHeader that says what the segment is (magic, object
// type, layout version, byte order) so that a process attaching to it with
// another build of the library gets a clear error instead of reading garbage:
//   "segment /chimera.x.y: layout version 3, this library expects 2".
// Inside a segment every reference is an Offset<T> from the segment's start,
// never a pointer: each process maps the segment at its own address.
//
// Life cycle: create() maps a new, zero-filled segment whose header is marked
// "being built"; the creator fills the body and calls publish(). Until then
// attach() refuses it, and if the creating Segment is destroyed (an exception
// during set-up) the name is unlinked, so a failed creation leaves nothing
// behind. detach_destroy_if_last() gives services "destroyed by the last
// user" semantics.
//
// Users are counted by the kernel, not by a counter in the segment: every
// mapping keeps the segment's file open with a shared open-file-description
// lock (fcntl F_OFD_SETLK, F_RDLCK) on it, which the kernel drops when the
// process dies, however it dies. A user that detaches with
// detach_destroy_if_last() asks to turn its shared lock into an exclusive one;
// the kernel grants that only when no other mapping (of any live process)
// holds a lock, and only then is the name removed. So a process killed by
// SIGKILL at any instruction is counted out at once, and the last live user
// frees the segment (issue #15.2). The locks sit on an open file description
// that only the process's descriptor table holds; the mapping has one of its
// own. A dying process closes its descriptors whoever still holds its memory
// (a reader of its /proc/PID/stat, such as ps or top, holds it for the read;
// a process sharing it, for longer), whereas a mapping lives as long as the
// memory does. (Where /proc is not mounted, the mapping shares the locks'
// description, and such a holder delays the count.) A handle copied into a
// child by fork() neither counts nor frees: only the process that attached
// releases.
//
// Watchers (issue 16.7, docs/permissions.md): watch() maps a published
// segment read-only (O_RDONLY, PROT_READ) and takes no lock at all, so a
// watcher is not a user: it keeps no segment alive, never delays the last
// user's destroy, and never waits for anything a real-time task holds. Its
// mapping stays readable after the segment is destroyed (the header then
// says `destroyed`). A segment created with group bits in its mode is given
// to the watch group (watch_group_name(), `chimera` by default), whose
// members may watch it; the mode is set with fchmod, so the umask does not
// narrow it.
#pragma once

#include "chimera/export.hpp"

#include <sys/types.h>

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <ctime>
#include <stdexcept>
#include <string>
#include <string_view>

#include "chimera/ipc/fault.hpp"

namespace chimera::ipc {

/// "CHIM" in memory order on a little-endian machine.
inline constexpr std::uint32_t kSegmentMagic = 0x4D494843u;
/// Written in native order; a reader of the other byte order sees 0x04030201.
inline constexpr std::uint32_t kByteOrderCode = 0x01020304u;

/// Object types of the segments the project defines (one registry, so two
/// services never reuse a number).
enum class ObjectType : std::uint32_t {
    test = 1,
    svar_table = 2,
    tbuf = 3,
    xmail_mailbox = 4,
    xmail_shm = 5,
    xmail_sem = 6,
    xmail_msg = 7,
    prof_status = 8,
    sbs_control = 9,
    name_server = 10,
    sampler_ring = 11,
};

/// The name of an ObjectType for messages ("svar_table"), or "type N".
CHIMERA_API std::string object_type_name(ObjectType type);

/// State of a segment's header.
enum class SegmentState : std::uint32_t {
    building = 0,   ///< created, body being filled; attach() refuses it
    ready = 1,      ///< published
    destroyed = 2,  ///< the last user is unlinking it; attach() refuses it
};

/// At offset 0 of every segment. Plain data: no pointers, fixed sizes.
struct SegmentHeader {
    std::uint32_t magic;            ///< kSegmentMagic
    std::uint32_t layout_version;   ///< version of the object's layout
    std::uint32_t object_type;      ///< ObjectType
    std::uint32_t byte_order;       ///< kByteOrderCode as written by the creator
    std::uint64_t total_size;       ///< bytes, header included
    std::atomic<std::uint32_t> attaches;      ///< attach() calls so far (a statistic: live users are Segment::users())
    std::int32_t creator_pid;
    std::atomic<std::uint32_t> state;         ///< SegmentState
    std::uint32_t header_size;      ///< sizeof(SegmentHeader) of the creator
    std::uint64_t created_ns;       ///< CLOCK_MONOTONIC at creation
    std::uint8_t reserved[16];
};
static_assert(sizeof(SegmentHeader) == 64, "SegmentHeader is part of every layout");
static_assert(std::atomic<std::uint32_t>::is_always_lock_free);

/// An offset from the start of a segment to a T inside it.
template <typename T>
struct Offset {
    std::uint64_t value = 0;

    T* in(void* base) const noexcept {
        return reinterpret_cast<T*>(static_cast<std::byte*>(base) + value);
    }
    const T* in(const void* base) const noexcept {
        return reinterpret_cast<const T*>(static_cast<const std::byte*>(base) + value);
    }
    explicit operator bool() const noexcept { return value != 0; }
};
static_assert(sizeof(Offset<int>) == 8);

/// Rounds `n` up to a multiple of `align` (a power of two).
constexpr std::size_t align_up(std::size_t n, std::size_t align) noexcept {
    return (n + align - 1) & ~(align - 1);
}

/// An error creating, attaching or validating a segment; what() names it.
class CHIMERA_API SegmentError : public std::runtime_error {
public:
    SegmentError(std::string name, std::string message, int error_number = 0);
    const std::string& name() const noexcept { return name_; }
    /// errno of the failing call, or 0.
    int error_number() const noexcept { return errno_; }

private:
    std::string name_;
    int errno_;
};

/// "/chimera.<subsystem>.<object>"; throws SegmentError when either part is
/// empty or holds '/', or the result is longer than NAME_MAX.
CHIMERA_API std::string segment_name(std::string_view subsystem, std::string_view object);

/// What the attaching process expects to find.
struct SegmentKind {
    ObjectType type;
    std::uint32_t layout_version;
};

struct CreateOptions {
    /// Set exactly (fchmod: the umask does not narrow it). Group bits give the
    /// segment to the watch group (watch_group_name()); without that group
    /// they are dropped (owner only), and the first such creation says so on
    /// stderr. 0600, owner only, by default; 0640 lets the group watch.
    mode_t mode = 0600;
    bool prefault = true; ///< touch every page now, not in the first cycle
    bool lock = false;    ///< mlock the mapping (best effort: see Segment::locked())
};

struct AttachOptions {
    bool prefault = true;
    bool lock = false;
    /// How long attach() waits for a segment still being built.
    std::int64_t ready_timeout_ns = 1'000'000'000;
};

/// One mapping of a segment (RAII). Move-only. Destruction detaches (and
/// unlinks a segment that was created but never published).
class CHIMERA_API Segment {
public:
    Segment() noexcept = default;
    Segment(Segment&& other) noexcept;
    Segment& operator=(Segment&& other) noexcept;
    Segment(const Segment&) = delete;
    Segment& operator=(const Segment&) = delete;
    ~Segment();

    /// Creates a new segment of `size` bytes (header included, >= 64); fails
    /// if the name exists ("segment /x: already exists"). A squatted file
    /// under the name (squatted()), or another user's this user may not read,
    /// is made way for first (make_way(): root removes it, saying whose it
    /// was; anyone else gets its EPERM error naming the owner).
    static Segment create(const std::string& name, std::size_t size, SegmentKind kind,
                          const CreateOptions& options = {});
    /// Attaches to a published segment and validates magic, byte order,
    /// object type, layout version and size. The file it opens is first
    /// checked as squatted() checks a name (fstat of the open descriptor; a
    /// symbolic link is never followed): a squatted one is made way for
    /// (make_way()) and the attach fails with "does not exist" (ENOENT), as if
    /// its creator had not made it yet.
    static Segment attach(const std::string& name, SegmentKind kind,
                          const AttachOptions& options = {});
    /// Maps a published segment read-only, as a watcher: validated as by
    /// attach(), but no user lock (not counted by users(), never keeps the
    /// segment alive or blocks its destroy). A segment this user may not read
    /// throws with error_number() EACCES and permission_advice() in what().
    /// The file opened is checked as attach() checks it, but a squatted one
    /// is refused, never removed (a watcher is not the runner): EPERM, its
    /// owner and the remedy in what(), as make_way() says them.
    static Segment watch(const std::string& name, SegmentKind kind,
                         const AttachOptions& options = {});

    /// Marks a created segment ready for attach(). Call once, after the body
    /// is complete (release ordering: attachers see the whole body).
    void publish() noexcept;

    /// Unmaps and gives up this mapping's user lock. The name stays.
    void detach() noexcept;
    /// Unmaps; if no other live mapping exists, unlinks the name. Returns true
    /// when the segment was destroyed. (An attach racing with it either fails
    /// with "is being destroyed" or keeps the segment alive as a new user.)
    bool detach_destroy_if_last() noexcept;
    /// The owner's end of a segment for every user (issue #29.8): marks it
    /// destroyed, removes its name (when it still names this mapping's file)
    /// and detaches, whoever else maps it. They keep their mapping, and see
    /// the header's `destroyed`; attach() refuses the name from now on. A
    /// master ends its table so: another process's mapping (a Python Table
    /// kept after the subsystem finished) must not keep the name in /dev/shm.
    /// True when the name was removed.
    bool end_for_all() noexcept;
    /// Live mappings of this segment, this one included: each holds a lock
    /// on a byte of its own, counted with about two fcntl calls per user (a
    /// slow path, for status and tests). 0 when not attached. A child made by
    /// fork() that still has its parent's mapping keeps the parent's lock, so
    /// the parent counts (and blocks a destroy) until that child exits or
    /// execs: the kernel ties a lock to the open file, which a mapping holds.
    std::uint32_t users() const noexcept;
    /// True when some live process maps the segment `name` (one fcntl probe).
    static bool in_use(const std::string& name) noexcept;
    /// Removes `name` when no live process maps it (its users all detached or
    /// died), as the last user's detach_destroy_if_last() would: an attach
    /// racing with it fails with "is being destroyed". True when removed.
    static bool destroy_if_unused(const std::string& name) noexcept;
    /// Removes a name; false when it did not exist.
    static bool unlink(const std::string& name) noexcept;
    /// True when a segment of this name exists.
    static bool exists(const std::string& name) noexcept;
    /// True when a segment of this name exists but its creator process is
    /// gone (or its header is unreadable): left behind by a crash.
    static bool is_stale(const std::string& name) noexcept;

    bool valid() const noexcept { return base_ != nullptr; }
    const std::string& name() const noexcept { return name_; }
    std::size_t size() const noexcept { return size_; }
    void* base() const noexcept { return base_; }
    SegmentHeader& header() const noexcept { return *static_cast<SegmentHeader*>(base_); }
    /// True when the mapping is mlock'ed (asked for and permitted).
    bool locked() const noexcept { return locked_; }
    /// True when this mapping created the segment.
    bool creator() const noexcept { return creator_; }
    /// True for a watcher's mapping (watch()): PROT_READ, writes would fault.
    bool read_only() const noexcept;

    template <typename T>
    T* at(Offset<T> offset) const noexcept {
        return offset.in(base_);
    }
    template <typename T = std::byte>
    T* at_bytes(std::size_t offset) const noexcept {
        return reinterpret_cast<T*>(static_cast<std::byte*>(base_) + offset);
    }

private:
    static Segment map_published(const std::string& name, SegmentKind kind, const AttachOptions& options,
                                 bool read_only);
    bool release(bool destroy_if_last) noexcept;

    std::string name_;
    void* base_ = nullptr;
    std::size_t size_ = 0;
    int fd_ = -1;        // open while mapped: it carries this mapping's user lock
    pid_t owner_ = 0;    // the process that mapped it (a fork()ed copy does not release)
    bool locked_ = false;
    bool creator_ = false;
    bool published_ = false;
};

/// The group whose members may watch segments created with group bits in
/// their mode: $CHIMERA_GROUP when set (empty: none), else the build's
/// `watch_group` option (`chimera` unless configured otherwise).
CHIMERA_API std::string watch_group_name();

/// What to do about EACCES on `name`, for an error message: who owns it,
/// its group and mode, and the remedy, e.g. "permission denied:
/// /dev/shm/chimera.arm.status is root's (group chimera, mode 0640): add
/// yourself to group chimera (usermod -aG chimera alice), then log in again".
/// `write`: the access wanted was read-write (only the owner may).
CHIMERA_API std::string permission_advice(const std::string& name, bool write);

/// Why the segment `name` is not to be believed (issue #29.5), or "" when it
/// can be, or when there is none. Any local user can create a file in
/// /dev/shm under any free name, header and all, so a header's claims count
/// only when its owner stands behind them: a segment is squatted when it is a
/// symbolic link or not a regular file, when group or others may write to it
/// (chimera creates 0600 or 0640), when its header's creator is a live
/// process of another user than the file's owner (a fake naming pid 1 under
/// nobody's file), or, for a file of another user than this one, when the
/// creator its header names is not running (a fake naming a dead pid, or a
/// crashed run's) or it has had no chimera header for 10 s. Owner and mode
/// come from fstat of the open segment (lstat of its file when this user may
/// not open it, or when it is a link); the creator's user from
/// /proc/PID/status. E.g. "squatted: its header names as its creator pid 1, a
/// process of root, not of its owner". Segment::create() and attach() apply
/// the same check, and watch() refuses what it finds (issue #29.5: every
/// segment name chimera makes).
CHIMERA_API std::string squatted(const std::string& name);
/// squatted(name) judged at time `now` (time(2) seconds) instead of the
/// clock's: how old a file without a header is (ctime) decides it exactly.
CHIMERA_API std::string squatted(const std::string& name, std::time_t now);

/// Makes way for a segment of this user's called `name` whose old file must
/// go (`why`: squatted() or "left by a process that died"): removes it when
/// this user may (root, or the file's owner), saying so on stderr with its
/// owner and mode; otherwise throws SegmentError (EPERM) naming the owner and
/// the remedy: "segment /chimera.x.svar: squatted: ...: it is nobody's (uid
/// 65534, mode 0644), and only nobody or root may remove it (sudo rm
/// /dev/shm/chimera.x.svar), then start again" (root's: "only root may").
/// Nothing to do when there is no such segment.
CHIMERA_API void make_way(const std::string& name, const std::string& why);

/// Checks a header against what a process expects; throws SegmentError with
/// the mismatch named. Used by attach(), and by objects laid over
/// caller-supplied memory.
CHIMERA_API void validate_header(const std::string& name, const SegmentHeader& header, SegmentKind kind,
                                 std::size_t mapped_size);

/// The same checks as validate_header() as a pure function over an image of
/// `size` bytes (what a fuzzer calls): the first bound broken, or none.
CHIMERA_API Fault header_fault(const void* image, std::size_t size, SegmentKind kind) noexcept;

/// Fills a header for a new object of `total_size` bytes (state: building).
CHIMERA_API void init_header(SegmentHeader& header, SegmentKind kind, std::size_t total_size) noexcept;

}  // namespace chimera::ipc
