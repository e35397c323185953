// logger — data logger (thesis §3.3: a module that only gathers data): writes
// the chosen variables to a CSV file at its own rate (its FREQ), with the file
// writing done by a background thread, off the real-time path and outside the
// table's critical section.
//
//   INVAR   any variables (numeric types) — the columns, in the order listed
//   OUTVAR  none
//   LOCAL   FILE name|/path     CSV file, created/truncated (mode 0600) on `on`: a
//                               name goes to the subsystem's output folder
//                               (output_file.hpp, README.md); an absolute path
//                               only to a folder no one else may write to
//           [DECIMATE k]        log every k-th cycle (default 1)
//           [BUFFER rows]       rows buffered between cycle and writer (default 8192)
//
// The cycle copies one row (time since `on`, then every element of every
// in-var) into a preallocated single-producer/single-consumer ring; the writer
// thread formats and writes the rows. If the writer falls behind, rows are
// dropped (never blocking the cycle) and `off` reports how many as a warning.
// Header line: t,NAME[0],NAME[1],... (or NAME for a scalar).
#include <chimera/module.hpp>

#include <fcntl.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <thread>
#include <vector>

#include "output_file.hpp"
#include "robotics/ports.hpp"

namespace rb = chimera::robotics;

namespace {

double now_seconds() noexcept {
    timespec ts{};
    clock_gettime(CLOCK_MONOTONIC, &ts);  // vDSO: no system call
    return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

// The LOCAL keys this module reads (module.hpp, LocalKey): what `set` may change.
constexpr chimera::LocalKey kLoggerLocalKeys[] = {
    {"FILE", chimera::LocalType::output_file, -chimera::unbounded, chimera::unbounded, false, "CSV file written: a name (in the subsystem's output folder) or an absolute path", ""},
    {"DECIMATE", chimera::LocalType::integer, 1.0, 1000000000.0, false, "log every Nth cycle", "1"},
    {"BUFFER", chimera::LocalType::integer, 1.0, 1000000000.0, false, "rows buffered between the cycle and the writer", "8192"},
};

class Logger : public chimera::Module {
public:
    std::span<const chimera::LocalKey> local_keys() const noexcept override { return kLoggerLocalKeys; }

    chimera::Result init(chimera::Task& t) override {
        path_ = rb::local_word(t, "FILE", "");
        if (path_.empty()) rb::module_error(t, "LOCAL FILE (the CSV file to write) is required");
        try {
            target_ = chimera::output::resolve(path_, std::string(t.subsystem()));
        } catch (const std::runtime_error& e) {
            rb::module_error(t, std::string("LOCAL FILE ") + path_ + ": " + e.what());
        }
        decimate_ = static_cast<long>(rb::local_number(t, "DECIMATE", 1));
        const long rows = static_cast<long>(rb::local_number(t, "BUFFER", 8192));
        if (decimate_ < 1) rb::module_error(t, "LOCAL DECIMATE must be >= 1");
        if (rows < 16) rb::module_error(t, "LOCAL BUFFER must be >= 16 rows");
        width_ = 1;
        header_ = "t";
        auto& global = t.local_table().global();
        for (const std::string& port : t.rmod_file().in_vars) {
            const std::string name = t.global_name(port);
            const chimera::svar::VarInfo info = global.var(name);
            if (info.type() == chimera::svar::Type::struct_) {
                rb::module_error(t, "cannot log " + name + ": struct variables have no columns");
            }
            Column c{t.local_table().translate_any(name), info.type(), info.nelem()};
            cols_.push_back(c);
            for (std::size_t k = 0; k < info.nelem(); ++k) {
                header_ += "," + name;
                if (info.nelem() > 1) header_ += "[" + std::to_string(k) + "]";
            }
            width_ += info.nelem();
        }
        if (cols_.empty()) rb::module_error(t, "nothing to log: list the variables as INVAR");
        capacity_ = static_cast<std::size_t>(rows);
        ring_.assign(capacity_ * width_, 0.0);
        return chimera::Result::OK;
    }

    chimera::Result on(chimera::Task& t) override {
        const int fd = chimera::output::open_for_writing(target_);
        if (fd < 0 || !(file_ = ::fdopen(fd, "w"))) {
            const int e = errno;
            if (fd >= 0) ::close(fd);
            t.warning("logger: cannot write " + target_.dir + "/" + target_.name + ": " + std::strerror(e) +
                      (e == ELOOP ? " (a symlink: not followed)" : ""));
            return chimera::Result::OFF;
        }
        head_.store(0);
        tail_.store(0);
        dropped_ = 0;
        count_ = 0;
        t0_ = now_seconds();
        stop_.store(false);
        writer_ = std::thread([this] { write_loop(); });
        return chimera::Result::OK;
    }

    chimera::Result cycle(chimera::Task&) override {
        if (count_++ % decimate_ != 0) return chimera::Result::OK;
        const std::size_t head = head_.load(std::memory_order_relaxed);
        if (head - tail_.load(std::memory_order_acquire) >= capacity_) {
            ++dropped_;
            return chimera::Result::OK;
        }
        double* row = &ring_[(head % capacity_) * width_];
        *row++ = now_seconds() - t0_;
        for (const Column& c : cols_) {
            for (std::size_t k = 0; k < c.nelem; ++k) *row++ = element(c, k);
        }
        head_.store(head + 1, std::memory_order_release);
        return chimera::Result::OK;
    }

    chimera::Result off(chimera::Task& t) override {
        stop_writer();
        if (dropped_ > 0) {
            t.warning("logger: " + std::to_string(dropped_) + " rows dropped (writer too slow); raise BUFFER or DECIMATE");
        }
        return chimera::Result::OK;
    }

    chimera::Result kill(chimera::Task&) override {
        stop_writer();
        return chimera::Result::OK;
    }

    ~Logger() override {
        stop_writer();
        if (target_.dir_fd >= 0) ::close(target_.dir_fd);
    }

private:
    struct Column {
        const void* data;
        chimera::svar::Type type;
        std::size_t nelem;
    };

    static double element(const Column& c, std::size_t k) noexcept {
        using chimera::svar::Type;
        switch (c.type) {
            case Type::byte_: return static_cast<const std::uint8_t*>(c.data)[k];
            case Type::char_: return static_cast<const char*>(c.data)[k];
            case Type::word: return static_cast<const std::uint16_t*>(c.data)[k];
            case Type::short_: return static_cast<const std::int16_t*>(c.data)[k];
            case Type::unsigned_: return static_cast<const std::uint32_t*>(c.data)[k];
            case Type::int_: return static_cast<const std::int32_t*>(c.data)[k];
            case Type::float_: return static_cast<const float*>(c.data)[k];
            case Type::double_: return static_cast<const double*>(c.data)[k];
            case Type::struct_: return 0;
        }
        return 0;
    }

    void write_loop() {
        std::fprintf(file_, "%s\n", header_.c_str());
        for (;;) {
            const bool stopping = stop_.load(std::memory_order_acquire);
            std::size_t tail = tail_.load(std::memory_order_relaxed);
            const std::size_t head = head_.load(std::memory_order_acquire);
            for (; tail != head; ++tail) {
                const double* row = &ring_[(tail % capacity_) * width_];
                std::fprintf(file_, "%.6f", row[0]);
                for (std::size_t i = 1; i < width_; ++i) std::fprintf(file_, ",%.9g", row[i]);
                std::fputc('\n', file_);
                tail_.store(tail + 1, std::memory_order_release);
            }
            if (stopping) break;
            std::fflush(file_);
            std::this_thread::sleep_for(std::chrono::milliseconds(20));
        }
    }

    void stop_writer() {
        if (writer_.joinable()) {
            stop_.store(true, std::memory_order_release);
            writer_.join();
        }
        if (file_) {
            std::fclose(file_);
            file_ = nullptr;
        }
    }

    std::string path_, header_;
    chimera::output::Target target_;  // the folder, held open from spawn so it cannot be swapped
    long decimate_ = 1;
    long count_ = 0;
    std::size_t width_ = 0, capacity_ = 0;
    std::vector<Column> cols_;
    std::vector<double> ring_;
    std::atomic<std::size_t> head_{0}, tail_{0};
    std::atomic<bool> stop_{false};
    std::size_t dropped_ = 0;
    double t0_ = 0;
    std::FILE* file_ = nullptr;
    std::thread writer_;
};

}  // namespace

CHIMERA_MODULE(logger, Logger)
