// The Python extension chimera._core (issue #18): what its parts share.
#pragma once

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <chimera/ipc/segment.hpp>
#include <chimera/prof.hpp>
#include <chimera/svar.hpp>

#include <atomic>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

namespace chimera::python {

namespace py = pybind11;

// The exceptions Python sees (chimera.SvarError, ...), all under chimera.ChimeraError.
struct SvarError : std::runtime_error { using std::runtime_error::runtime_error; };
struct LockTimeout : SvarError { using SvarError::SvarError; };
struct ProducerConflict : SvarError { using SvarError::SvarError; };
struct TbufError : std::runtime_error { using std::runtime_error::runtime_error; };
/// chimera.SubsystemGone: the master of the object's subsystem has finished.
struct SubsystemGone : std::runtime_error { using std::runtime_error::runtime_error; };

/// The end of a subsystem as one of its Python objects sees it (issue #29.8).
/// It watches the master's status segment: a watcher's mapping (no lock, so it
/// keeps nothing alive and delays no destroy), whose header the master marks
/// destroyed when it finishes (StatusSegment::close) and whose creator pid is
/// gone when the master died. check() costs one load and one kill(pid, 0).
/// Once the end is seen, the owner's `release` unmaps its segments, and every
/// later call raises SubsystemGone too. Calls that read a mapping with the GIL
/// released hold a Use, so a release seen from another thread waits for them.
/// All of it runs with the GIL held, which orders it.
class Lifeline {
public:
    /// Watches the master of `subsystem` if one runs now (else never gone: an
    /// object made without a master); `object` names the owner for the message.
    void watch(const std::string& subsystem, std::string object, std::function<void()> release);
    /// Raises SubsystemGone when the master has finished.
    void check();
    /// True once the master has finished (then releases, unless a Use is open).
    bool gone();
    const std::string& subsystem() const { return subsystem_; }

    class Use {
    public:
        explicit Use(Lifeline& l) : l_(l) { l_.check(); ++l_.uses_; }
        ~Use() { if (--l_.uses_ == 0 && l_.gone_) l_.release_now(); }
        Use(const Use&) = delete;
        Use& operator=(const Use&) = delete;
    private:
        Lifeline& l_;
    };

    /// "/chimera.SUBSYSTEM.OBJECT" -> "SUBSYSTEM" ("" for another name).
    static std::string subsystem_of(const std::string& segment);
    /// True when a master of `subsystem` runs: its status segment is published
    /// and its creator process lives (what running_subsystems() lists).
    static bool master_alive(const std::string& subsystem);

private:
    void release_now();
    std::string subsystem_, object_;
    ipc::Segment status_;
    int pid_ = 0;
    bool gone_ = false, released_ = false;
    int uses_ = 0;
    std::function<void()> release_;
};

/// "a,b,c" (a status segment's port list) as names.
std::vector<std::string> split_names(const std::string& list);
/// Raises LockTimeout / SvarError unless `st` moved the data.
void throw_if_not_transferred(svar::Status st, const std::string& table, const char* what);

/// One variable as Python lists it.
struct VarRecord {
    std::string name;
    std::size_t index = 0;
    std::string type;  ///< as in the .svar: "double", "struct[32]"
    std::size_t nelem = 0, elem_size = 0;
    std::string desc, units;
    py::object dtype, shape, init, min, max;
    std::vector<std::string> producers, consumers;  ///< live tasks writing / reading it
};

/// A process's mapping of a subsystem's global table.
class PyTable : public std::enable_shared_from_this<PyTable> {
public:
    static std::shared_ptr<PyTable> attach(const std::string& subsystem, double lock_timeout_s);
    static std::shared_ptr<PyTable> create(const std::string& subsystem, const std::string& svar_file,
                                           double lock_timeout_s);
    ~PyTable();

    /// The mapped table; SubsystemGone once the master has finished.
    svar::Table& table() { life_.check(); return table_; }
    /// The table without the check, for a caller holding a Lifeline::Use.
    svar::Table& table_unchecked() { return table_; }
    Lifeline& life() { return life_; }
    bool gone() { return life_.gone(); }
    const std::string& subsystem() const { return subsystem_; }
    std::size_t index_of(const std::string& name) const;
    VarRecord info(const std::string& name) const;
    std::vector<VarRecord> variables() const;
    std::vector<std::string> names() const;
    py::object read(const py::object& names);
    void write(const py::object& what, const py::object& values, bool force);
    /// The producer rule of `sbs setvar`: ProducerConflict when a live task writes one of `names`.
    void check_producers(const std::vector<std::string>& names) const;
    py::dict stats() const;
    void set_lock_timeout(double seconds);
    double lock_timeout() const;

private:
    PyTable() = default;
    struct Users {
        std::vector<std::string> producers, consumers;
    };
    // From the status segment: each task's out-vars and in-vars.
    Users users_of(const std::string& name) const;
    // Every variable's users, read again only when a task was spawned or
    // killed since (the segment's generation moved): a write's producer check
    // is then one load, not a status snapshot.
    const std::map<std::string, Users>& all_users() const;

    bool attach_status() const;

    void release();  // unmaps the table and the status segment (the end of the subsystem)

    mutable Lifeline life_;  // checked by const readers too
    svar::Table table_;
    bool needs_status_ = false;  // attached to a master's table: its status names the producers
    mutable std::optional<prof::StatusReader> status_;
    mutable std::string status_error_;
    mutable ipc::Segment status_map_;  // the same segment, for its header's generation word
    mutable std::optional<std::uint32_t> users_generation_;
    mutable std::map<std::string, Users> users_;
    std::string subsystem_;
    bool owner_ = false;
};

/// A fixed set of variables read together, one lock per read, into a private
/// local table whose numpy views are refreshed in place (the thesis's local
/// table: no allocation per read).
class Reader {
public:
    Reader(std::shared_ptr<PyTable> table, std::vector<std::string> names);
    virtual ~Reader() = default;
    void read();
    const std::vector<std::string>& names() const { return names_; }
    std::size_t size() const { return names_.size(); }
    /// {name: view into the local table}, made once: read() refreshes them in place.
    const py::dict& views(bool writeable);
    /// A new array holding variable i's values in the local table now.
    py::array copy_of(std::size_t i) const;
    std::string last_status() const { return svar::to_string(last_); }

protected:
    // What the views point into: kept alive by the views themselves, so an
    // array outlives its Reader safely (and no reference cycle holds either).
    struct Storage {
        svar::LocalTable local;
        svar::VarSet set;
    };
    py::array view(std::size_t i, bool writeable) const;
    std::shared_ptr<PyTable> table_;
    std::vector<std::string> names_;
    std::shared_ptr<Storage> store_;
    py::dict read_only_, writeable_;
    svar::Status last_ = svar::Status::ok;
    // Set while a transfer runs with the GIL released: a local table is one
    // thread's (as a task's), so a second thread is refused, not let race.
    std::atomic<bool> busy_{false};
    class Busy {
    public:
        explicit Busy(Reader& r);
        ~Busy() { flag_.store(false, std::memory_order_release); }
    private:
        std::atomic<bool>& flag_;
    };
};

/// A fixed set of variables written together: fill the views (or fill()),
/// then write() checks every value against type and MIN/MAX and the producer
/// rule, and copies the whole set under one lock.
class Writer : public Reader {
public:
    Writer(std::shared_ptr<PyTable> table, std::vector<std::string> names, bool force);
    void fill(std::size_t i, const py::object& value);
    void write();
    bool force() const { return force_; }

private:
    void check_local();
    bool force_;
};

void bind_svar(py::module_& m);
void bind_status(py::module_& m);
void bind_tbuf(py::module_& m);
void bind_sampler(py::module_& m);

}  // namespace chimera::python
