// chimera/svar.hpp — the global state variable table (SVAR, thesis §5.5, §6.6).
//
// Tasks never talk to each other directly: every input and output port is a
// state variable in one table in POSIX shared memory (the *global* table).
// Each task keeps a *local* table holding only its own variables; at the start
// of a cycle it copies its in-vars global → local, runs on the local copy, and
// copies its out-vars local → global. Each copy is a whole set under ONE
// acquisition of the table's single lock, so a reader never sees half of a
// writer's set (§5.5, §6.6).
//
// The table's contents come from a `.svar` file (§5.5.2):
//
//     DEFINE DOF 7
//     NAME  Q_REF                  # at most 15 characters, unique
//     TYPE  double                 # byte char word short unsigned int float double struct[N]
//     DESC  reference joint position
//     UNITS radians
//     NELEM DOF
//     INIT  0 0 0 0 0 0 0          # optional; missing values are 0; not for struct
//     MIN   -1 -1 -1 -1 -1 -1 -1   # optional, MIN and MAX both or neither,
//     MAX   1 1 1 1 1 1 1          #   all NELEM values; not for struct
//     EOF
//
// The keywords come in exactly this order. Types: byte = uint8, char = char,
// word = uint16, short = int16, unsigned = uint32, int = int32, float, double,
// struct[N] = N untyped bytes per element. MIN/MAX are kept and exposed, never
// enforced on write (§5.5.2).
//
// Error model: set-up (parse, create, attach, LocalTable construction,
// translate) throws rich errors naming file/line/table/variable. The cycle
// path (read, write, copy_*) is noexcept, allocation-free and system-call-free
// when the lock is free, and returns a Status.
//
// The lock and a holder that died: see chimera/ipc/lock.hpp. Every write into
// the global table first saves the old contents of the variables it is about
// to overwrite into an undo area in the segment, marks the undo record active,
// writes, and clears the mark. A waiter that takes the lock over from a dead
// holder finds the mark set and rolls the interrupted write-set back, so the
// table holds the last complete set — never half of one — and the copy that
// did the recovery returns Status::recovered. Only the thesis's blind reset
// after a timeout (opt-in, LockOptions::reset_on_timeout) can tear data; it
// returns Status::forced.
#pragma once

#include "chimera/export.hpp"

#include <cstddef>
#include <cstdint>
#include <initializer_list>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <utility>
#include <string_view>
#include <type_traits>
#include <vector>

#include "chimera/ipc/lock.hpp"
#include "chimera/ipc/segment.hpp"

namespace chimera::svar {

/// Maximum length of a variable name (thesis §5.5.2: "a maximum of 15
/// characters"); enforced by the parser.
inline constexpr std::size_t kMaxNameLength = 15;
/// The largest table: the data of all its variables together (NELEM × element
/// size, summed) may not pass 256 MiB. A .svar asking for more is refused at
/// the line that passes it, before anything is allocated, by chimcfg check as
/// by every program that creates the table.
inline constexpr std::size_t kMaxTableDataBytes = std::size_t{256} << 20;

/// Layout version of the table segment; attach() refuses other versions.
/// 2: the header's write sequence counter (Table::watch() reads by it).
inline constexpr std::uint32_t kLayoutVersion = 2;

/// The variable types of §5.5.2.
enum class Type : std::uint32_t {
    byte_ = 0,   ///< "byte": unsigned char
    char_,       ///< "char": char
    word,        ///< "word": unsigned short (uint16)
    short_,      ///< "short": int16
    unsigned_,   ///< "unsigned": uint32
    int_,        ///< "int": int32
    float_,      ///< "float"
    double_,     ///< "double"
    struct_,     ///< "struct[N]": N untyped bytes per element
};

/// "byte", "char", ..., "struct".
CHIMERA_API std::string_view type_name(Type type) noexcept;
/// Element size of a fixed-size type; 0 for struct_.
CHIMERA_API std::size_t type_size(Type type) noexcept;
/// The values a fixed-size type can hold, as doubles (what INIT/MIN/MAX and
/// `setvar` are checked against); unbounded for struct_.
CHIMERA_API std::pair<double, double> type_range(Type type) noexcept;
/// One element of a fixed-size type, at `element` (any alignment), as a
/// double; 0 for struct_. No allocation, no lock: real-time safe.
CHIMERA_API double element_value(Type type, const void* element) noexcept;
/// The type written as in a .svar file: "double", "struct[32]".
CHIMERA_API std::string type_spelling(Type type, std::size_t elem_size);

/// The svar::Type that a C++ type maps to (std::nullopt: only as struct).
template <typename T>
constexpr std::optional<Type> type_of() noexcept {
    using U = std::remove_cv_t<T>;
    if constexpr (std::is_same_v<U, std::uint8_t>) return Type::byte_;
    else if constexpr (std::is_same_v<U, char> || std::is_same_v<U, signed char>) return Type::char_;
    else if constexpr (std::is_same_v<U, std::uint16_t>) return Type::word;
    else if constexpr (std::is_same_v<U, std::int16_t>) return Type::short_;
    else if constexpr (std::is_same_v<U, std::uint32_t>) return Type::unsigned_;
    else if constexpr (std::is_same_v<U, std::int32_t>) return Type::int_;
    else if constexpr (std::is_same_v<U, float>) return Type::float_;
    else if constexpr (std::is_same_v<U, double>) return Type::double_;
    else return std::nullopt;
}

// ---------------------------------------------------------------------------
// .svar files

/// One variable as the .svar file defines it.
struct VarSpec {
    std::string name;
    Type type = Type::double_;
    std::size_t elem_size = 0;     ///< bytes per element
    std::size_t nelem = 1;
    std::string desc;
    std::string units;
    bool has_init = false;         ///< an INIT line was given
    std::vector<double> init;      ///< the INIT values given (at most nelem); the others
                                   ///< are 0 (init_at()). Never padded to nelem: a 52-byte
                                   ///< file can declare 2^28 elements
    double init_at(std::size_t k) const noexcept { return k < init.size() ? init[k] : 0.0; }
    bool has_range = false;
    std::vector<double> min, max;  ///< nelem values each when has_range
    int line = 0;                  ///< line of the NAME keyword

    std::size_t bytes() const noexcept { return elem_size * nelem; }
};

/// A parsed .svar file.
struct CHIMERA_API TableSpec {
    std::string file;
    std::vector<VarSpec> vars;

    /// Index of `name`, or nullopt.
    [[nodiscard]] std::optional<std::size_t> find(std::string_view name) const noexcept;
};

/// Parses a .svar file; throws cfg::ParseError ("FILE:LINE: message").
CHIMERA_API TableSpec parse_svar_file(const std::string& path);
/// Parses .svar text; `name` stands for FILE in errors.
CHIMERA_API TableSpec parse_svar_string(std::string_view text, const std::string& name);

// ---------------------------------------------------------------------------
// Errors and statuses

/// A set-up error naming the table and the variable or list involved.
class CHIMERA_API Error : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

/// Result of a cycle-path operation.
enum class [[nodiscard]] Status : int {
    ok = 0,       ///< done
    recovered,    ///< done; the lock was taken over from a dead holder, and its
                  ///< interrupted write (if any) was rolled back first
    forced,       ///< done; the lock was reset blindly after a timeout (opt-in):
                  ///< the old holder may still be writing, data may be torn
    lock_lost,    ///< done, but the lock was reset under us while we held it
                  ///< (someone forced it): the transfer may be torn
    timed_out,    ///< nothing transferred: the lock was not obtained in time
    reentered,    ///< nothing transferred: this thread holds the table lock already
    bad_argument, ///< nothing transferred: unknown pointer or index
    lock_corrupt, ///< nothing transferred: the table lock's word names no thread
                  ///< that could hold it (overwritten by another process); the
                  ///< word is left alone (see chimera/ipc/lock.hpp)
    read_only,    ///< nothing transferred: a watcher's table (Table::watch()) is not written
};
CHIMERA_API const char* to_string(Status s) noexcept;
/// True when data was transferred (ok, recovered, forced, lock_lost).
constexpr bool transferred(Status s) noexcept {
    return s == Status::ok || s == Status::recovered || s == Status::forced ||
           s == Status::lock_lost;
}

// ---------------------------------------------------------------------------
// The global table

namespace detail {
struct TableHeader;
struct Descriptor;
}  // namespace detail

class Table;

/// Checks a table's image of `size` bytes as attach() does: the segment
/// header, every offset and length of the header and of each variable's
/// descriptor inside the segment (data, INIT/MIN/MAX values, DESC/UNITS
/// strings, source name), sizes that match their types without overflow,
/// names that end inside their field, and an active undo record's count and
/// indices. The first bound broken, or none. A pure function over the bytes.
CHIMERA_API ipc::Fault validate_table(const void* image, std::size_t size) noexcept;

/// Read-only view of one variable's descriptor in the global table.
class CHIMERA_API VarInfo {
public:
    std::size_t index() const noexcept;     ///< unique index in the table (svarYyyIx)
    std::string_view name() const noexcept;
    Type type() const noexcept;
    std::size_t elem_size() const noexcept;
    std::size_t nelem() const noexcept;
    std::size_t bytes() const noexcept { return elem_size() * nelem(); }
    std::string_view desc() const noexcept;
    std::string_view units() const noexcept;
    bool has_range() const noexcept;
    bool has_init() const noexcept;  ///< the .svar gave an INIT line
    /// INIT / MIN / MAX element k as a double (0 for struct; min/max 0 when
    /// !has_range()).
    double init(std::size_t k) const noexcept;
    double min(std::size_t k) const noexcept;
    double max(std::size_t k) const noexcept;

private:
    friend class Table;
    VarInfo(const Table* table, const detail::Descriptor* d) noexcept : table_(table), d_(d) {}
    const Table* table_;
    const detail::Descriptor* d_;
};

struct TableOptions {
    ipc::CreateOptions segment{};   ///< mode, prefault, mlock (create)
    ipc::AttachOptions attach{};    ///< prefault, mlock (attach)
    ipc::LockOptions lock{};        ///< spin, timeout, reset_on_timeout
};

/// Counters kept in the table header (shared by every user).
struct TableStats {
    std::uint32_t recoveries;   ///< dead lock holders taken over
    std::uint32_t rollbacks;    ///< interrupted write-sets rolled back
    std::uint32_t timeouts;     ///< lock acquisitions that timed out
    std::uint32_t forced;       ///< blind resets after a timeout
};

/// One process's mapping of a global table (svarCreate / svarAttach).
/// Move-only; destruction detaches. Any number of threads of a process may
/// share one Table.
class CHIMERA_API Table {
public:
    Table() noexcept;
    Table(Table&&) noexcept;
    Table& operator=(Table&&) noexcept;
    ~Table();

    /// Parses `svar_file` and creates the segment `segment_name` (e.g.
    /// ipc::segment_name("arm", "svar")). A bad file throws cfg::ParseError
    /// and leaves no segment behind.
    static Table create(const std::string& segment_name, const std::string& svar_file,
                        const TableOptions& options = {});
    /// Creates from an already parsed spec.
    static Table create(const std::string& segment_name, const TableSpec& spec,
                        const TableOptions& options = {});
    /// Attaches to an existing table by name (any process).
    static Table attach(const std::string& segment_name, const TableOptions& options = {});
    /// Maps a table read-only as a watcher (chimtop, a non-owner's query;
    /// docs/permissions.md): not a user of the segment, and read() never
    /// takes the table lock — it copies under the table's write sequence
    /// counter and retries while a writer is in the middle of a write, so a
    /// watcher never delays a task. write(), set_illegal_configuration() and a
    /// LocalTable need the owner's attach(). A table this user may not read
    /// throws ipc::SegmentError (error_number() EACCES, what to do in what()).
    static Table watch(const std::string& segment_name, const TableOptions& options = {});

    /// Unmaps; the table stays for other users.
    void detach() noexcept;
    /// Unmaps, and removes the table if this was the last user (svarDestroy).
    /// Returns true when the table was removed.
    bool destroy() noexcept;
    /// Unmaps and removes the table now, whoever else maps it (they see it
    /// destroyed): the end of a subsystem (ipc::Segment::end_for_all()).
    bool end_for_all() noexcept;

    bool valid() const noexcept { return seg_.valid(); }
    const std::string& name() const noexcept { return seg_.name(); }
    /// The .svar file the table was created from.
    std::string_view source_file() const noexcept;

    std::size_t size() const noexcept;  ///< number of variables
    [[nodiscard]] std::optional<std::size_t> find(std::string_view name) const noexcept;
    /// Index of `name`; throws Error "table T has no variable X".
    std::size_t index_of(std::string_view name) const;
    VarInfo var(std::size_t index) const noexcept;
    VarInfo var(std::string_view name) const { return var(index_of(name)); }

    /// Locked single-variable access to the global table, for tools and
    /// interfaces (sbs set/get, chimtop). `buffer` holds var(index).bytes().
    /// A watcher's read() takes no lock (see watch()): a copy no write ran
    /// through, or timed_out after lock_options().timeout_ns of writes in
    /// progress (a writer that died mid-write, until a user recovers it); its
    /// write() is refused with read_only.
    /// (A timeout that waits forever is the default's 100 ms for a watcher.)
    Status read(std::size_t index, void* buffer) noexcept;
    Status write(std::size_t index, const void* buffer) noexcept;
    /// True for a watcher's table (watch()).
    bool read_only() const noexcept { return read_only_; }

    /// The illegal-configuration flag word of §3.10 (0 = configuration legal).
    /// Set during a reconfiguration or after an error so critical tasks fall
    /// back to locally stable execution.
    std::uint32_t illegal_configuration() const noexcept;
    void set_illegal_configuration(std::uint32_t flags) noexcept;

    TableStats stats() const noexcept;
    const ipc::LockOptions& lock_options() const noexcept { return lock_options_; }
    void set_lock_options(const ipc::LockOptions& options) noexcept { lock_options_ = options; }

    /// The raw table lock (for tests and diagnostics).
    ipc::LockWord& lock_word() const noexcept;

private:
    friend class LocalTable;
    friend class VarInfo;
    explicit Table(ipc::Segment seg, const TableOptions& options) noexcept;
    /// A Table over `seg` once validate_table() accepts its image.
    static Table checked(ipc::Segment seg, const TableOptions& options);
    void bind() noexcept;
    // Defined inline in the library's internal layout header: the cycle path.
    inline Status acquire() noexcept;
    inline Status release(Status acquired) noexcept;
    void save_undo(const std::uint32_t* indices, std::size_t count) noexcept;
    void clear_undo() noexcept;
    void roll_back() noexcept;

    ipc::Segment seg_;
    ipc::LockOptions lock_options_{};
    detail::TableHeader* hdr_ = nullptr;
    // The fixed part of the table, checked on attach (validate_table()) and
    // kept here: what another process writes into the segment later cannot
    // move a copy outside it (issue #15.3).
    std::unique_ptr<detail::Descriptor[]> own_desc_;
    const detail::Descriptor* desc_ = nullptr;
    std::uint32_t nvars_ = 0;
    bool read_only_ = false;  // watch(): in nvars_'s padding, the layout is unchanged
    std::byte* data_ = nullptr;
    std::byte* undo_ = nullptr;
    std::uint32_t* undo_list_ = nullptr;
    std::string_view source_;
};

// ---------------------------------------------------------------------------
// Local tables

/// A set of variables copied together under one lock (a task's in-vars, ...).
/// Built at set-up by LocalTable::make_set(); copying it allocates nothing.
class VarSet {
public:
    std::size_t size() const noexcept { return entries_.size(); }
    bool empty() const noexcept { return entries_.empty(); }

private:
    friend class LocalTable;
    struct Entry {
        std::uint32_t global_index;
        std::uint32_t bytes;
        std::uint64_t global_offset;  // from the table's data area
        std::uint64_t local_offset;   // from the local table's buffer
    };
    std::vector<Entry> entries_;
    std::vector<std::uint32_t> indices_;  // global indices, for the undo record
    bool small_ = true;                   // every variable 8 to 64 bytes (copied inline)
};

/// A task's private copy of the variables it uses (svarAttach's local table).
/// One thread uses a LocalTable; it refers to, and must not outlive, its Table.
class CHIMERA_API LocalTable {
public:
    /// A local table for a port-based object: its .rmod port lists (names as
    /// in the global table, SVARALIAS already applied). A name may appear in
    /// several lists; it is stored once. Throws Error naming the list and the
    /// variable when a name is not in the table.
    LocalTable(Table& global, std::vector<std::string> in_consts,
               std::vector<std::string> out_consts, std::vector<std::string> in_vars,
               std::vector<std::string> out_vars);
    /// A local table holding just `names` (no port sets).
    LocalTable(Table& global, const std::vector<std::string>& names);
    LocalTable(LocalTable&&) noexcept;
    LocalTable& operator=(LocalTable&&) = delete;
    LocalTable(const LocalTable&) = delete;
    ~LocalTable();

    Table& global() const noexcept { return *global_; }
    std::size_t size() const noexcept { return vars_.size(); }
    bool contains(std::string_view name) const noexcept;

    /// svarTranslate: a typed pointer to the variable's first element in the
    /// local table. Throws Error when the name is unknown or not in this local
    /// table, or T does not match its type (for struct[N], any trivially
    /// copyable T of size N, or std::byte).
    template <typename T>
    T* translate(std::string_view name) {
        static_assert(std::is_trivially_copyable_v<T>, "state variables are plain data");
        return static_cast<T*>(translate_raw(name, type_of<T>(), sizeof(T)));
    }
    /// Untyped translate (any type).
    void* translate_any(std::string_view name);
    /// Global index of a translated pointer, or nullopt.
    [[nodiscard]] std::optional<std::size_t> index_of(const void* local) const noexcept;

    // --- single variable (svarRead / svarWrite, and the Ix variants) -------
    /// Global → local for the variable at `local` (a translated pointer).
    Status read(const void* local) noexcept;
    /// Local → global.
    Status write(const void* local) noexcept;
    /// By global index (VarInfo::index()); bad_argument when not local.
    Status read_ix(std::size_t index) noexcept;
    Status write_ix(std::size_t index) noexcept;

    // --- multi-variable (svarCopyFromShm / svarCopyToShm) ------------------
    /// A set for copy_from_global / copy_to_global; throws Error when a name is
    /// not in this local table.
    VarSet make_set(const std::vector<std::string>& names) const;
    VarSet make_set_ix(const std::vector<std::size_t>& indices) const;
    /// Global → local for every variable in `set`, one lock.
    Status copy_from_global(const VarSet& set) noexcept;
    /// Local → global for every variable in `set`, one lock.
    Status copy_to_global(const VarSet& set) noexcept;

    // --- the port sets of the task runtime (each one lock) -----------------
    Status copy_in_consts() noexcept { return copy_from_global(in_consts_); }   ///< before init
    Status copy_out_consts() noexcept { return copy_to_global(out_consts_); }   ///< after init
    Status copy_in_vars() noexcept { return copy_from_global(in_vars_); }       ///< before cycle
    Status copy_out_vars() noexcept { return copy_to_global(out_vars_); }       ///< after cycle, off
    /// Before `on`: in-vars AND out-vars, global → local (so a task switched
    /// on starts from the values its outputs have now).
    Status copy_on() noexcept { return copy_from_global(on_set_); }

    const VarSet& in_consts() const noexcept { return in_consts_; }
    const VarSet& out_consts() const noexcept { return out_consts_; }
    const VarSet& in_vars() const noexcept { return in_vars_; }
    const VarSet& out_vars() const noexcept { return out_vars_; }

    /// The table's illegal-configuration flag word (§3.10).
    std::uint32_t illegal_configuration() const noexcept {
        return global_->illegal_configuration();
    }

private:
    struct LocalVar {
        std::uint32_t global_index;
        std::uint32_t bytes;
        std::uint64_t local_offset;
        std::uint64_t global_offset;  // from the table's data area
    };
    void build(const std::vector<const std::vector<std::string>*>& lists,
               const std::vector<const char*>& list_names);
    void* translate_raw(std::string_view name, std::optional<Type> type, std::size_t size);
    VarSet set_of(const std::vector<std::string>& names, const char* list_name) const;
    // One per 16 bytes (the variables' alignment) of the local buffer; the
    // slot of the variable at local offset `off` is at byte `off` of slots_.
    struct Slot {
        std::uint32_t bytes;          // 0: no variable starts here
        std::uint32_t global_index;
        std::uint64_t global_offset;  // from the table's data area
    };
    const Slot* slot_at(const void* p) const noexcept;
    Status single(std::size_t local_offset, bool to_global) noexcept;
    Status single_slow(std::size_t local_offset, bool to_global) noexcept;
    Status copy_from_global_slow(const VarSet& set) noexcept;
    Status copy_to_global_slow(const VarSet& set) noexcept;

    Table* global_;
    // The global table's cycle-path addresses, taken from global_ when the
    // local table is built: a transfer reaches each with one load.
    detail::TableHeader* hdr_ = nullptr;   // the lock word and the undo record
    std::byte* gdata_ = nullptr;           // the data area
    std::byte* gundo_ = nullptr;           // the undo area (mirrors the data area)
    std::uint32_t* gundo_list_ = nullptr;  // the undo index list
    std::unique_ptr<std::byte[], void (*)(std::byte*)> buffer_;
    std::vector<LocalVar> vars_;              // sorted by local_offset
    // read(ptr)/write(ptr) find their variable, and check that there is one,
    // with one load from here.
    std::vector<Slot> slots_;
    std::vector<std::int32_t> by_global_;     // global index → vars_ index, -1 if absent
    VarSet in_consts_, out_consts_, in_vars_, out_vars_, on_set_;
};

}  // namespace chimera::svar
