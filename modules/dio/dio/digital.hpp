// dio/digital.hpp — what the digital in/out SAI modules (thesis §7.3) share:
// their LOCAL configuration, checked against the device database (§7.2) and
// the SVAR ports at init, the mapping between port values and SVAR elements,
// and opening the ports. Everything here runs in init or set (it allocates and
// throws); only store() and load() run in the cycle.
//
// Errors are dio::ConfigError whose message starts with the .rmod, and with
// the LOCAL line when a LOCAL value is at fault:
//   "lab/din8.rmod:14: LOCAL INVERT: 0x1f does not fit the 4-bit ports of device dio0"
#pragma once

#include <chimera/iod.hpp>
#include <chimera/module.hpp>
#include <chimera/svar.hpp>

#include <cstddef>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace chimera::dio {

/// din reads its ports into the SVAR; dout writes the SVAR to its ports.
enum class Direction { in, out };

class ConfigError : public std::invalid_argument {
public:
    using std::invalid_argument::invalid_argument;
};

/// Error codes the modules raise in the cycle (err.hpp: user codes).
inline constexpr int kErrIo = err::code::user + 70;       ///< the driver's read/write failed
inline constexpr int kErrCommand = err::code::user + 71;  ///< dout: a command no port value matches

/// The LOCAL section of a din or dout .rmod, checked (see README.md).
struct Config {
    std::string rmod;        ///< the .rmod's path, first in every message
    std::string database;    ///< DATABASE, resolved against the .rmod's folder
    iod::Database db;
    iod::DeviceSpec device;  ///< DEVICE, from the database (a PIO device)
    int first_port = 0;      ///< PORTS, device numbering
    int last_port = 0;
    /// INVERT, per port: XORed with the port value in both directions (set
    /// bits are active-low lines: SVAR 1 = line low).
    std::vector<std::uint32_t> invert;
    /// dout SAFE, per port, in SVAR terms (before INVERT): what the outputs
    /// show from init, after off, kill and an error.
    std::vector<std::uint32_t> safe;
    /// dout ILLEGAL safe: SAFE while the illegal-configuration flag is set.
    bool safe_when_illegal = false;
    /// din SYNC_TIMEOUT (synchronous tasks): the longest sync() blocks on a
    /// quiet input before it lets a pending command through, microseconds.
    long sync_timeout_us = 20000;

    int nports() const noexcept { return last_port - first_port + 1; }
    /// Every value bit of one port (WIDTH ones).
    std::uint32_t port_mask() const noexcept;
};

/// Reads and checks the LOCAL section of `rmod` (also loads the database and
/// finds the device in it): unknown keys, missing required keys, values that
/// are not numbers or do not fit the ports. `type` is the task's TASKTYPE.
Config read_config(const RmodFile& rmod, Direction dir, TaskType type);

/// sbsSet of `key`: re-reads the keys that may change while the ports are
/// open (INVERT, SAFE, ILLEGAL, SYNC_TIMEOUT) into `cfg`. Throws ConfigError
/// (and leaves `cfg` as it was) for a bad value, or for DATABASE, DEVICE or
/// PORTS, which need the task killed and spawned again.
void update_config(Config& cfg, const RmodFile& rmod, Direction dir, TaskType type,
                   std::string_view key);

/// The value port (DIN's out-var, DOUT's in-var) in the task's local table.
struct ValuePort {
    void* data = nullptr;
    svar::Type type = svar::Type::byte_;
};

/// Translates the value port `port`: it must be listed as OUTVAR (in) or
/// INVAR (out), have one element per opened port, and be of a type that holds
/// every value of a WIDTH-bit port exactly (exact_bits()).
ValuePort value_port(Task& t, std::string_view port, Direction dir, const Config& cfg);

/// Translates din's optional EDGES out-var: unsigned, one element per port.
std::uint32_t* edges_port(Task& t, std::string_view port, const Config& cfg);

/// Opens the configured ports: READ or WRITE, 32-bit elements, plus `wait`.
/// `initial` (dout): the port values the lines are requested with. iod::Error
/// (database, ports already open, direction, no gpiochip) comes back as
/// ConfigError prefixed with the .rmod.
std::unique_ptr<iod::Device> open_ports(const Config& cfg, Direction dir, unsigned wait,
                                        const std::uint32_t* initial);

// --- value mapping (cycle path: no allocation, no exception) ------------------

/// The widest port (in bits) whose every value 0..2^bits-1 a variable of
/// `type` holds exactly: byte 8, word 16, unsigned 32, short 15, int 31,
/// float 24, double 32. 0 for char and struct, which are not numbers here.
int exact_bits(svar::Type type) noexcept;

/// Element k of a `type` variable := `value` (a port value that fits).
void store(svar::Type type, void* data, std::size_t k, std::uint32_t value) noexcept;

/// Element k of a `type` variable as a port value: false unless it is a whole
/// number in 0..max (a negative, fractional, NaN or too large command matches
/// no port value; it is not wrapped, rounded or clamped).
bool load(svar::Type type, const void* data, std::size_t k, std::uint32_t max,
          std::uint32_t& value) noexcept;

}  // namespace chimera::dio
