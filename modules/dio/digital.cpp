// The digital in/out modules' configuration, port checks and value mapping
// (dio/digital.hpp).
#include "dio/digital.hpp"

#include <chimera/cfg.hpp>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <initializer_list>
#include <optional>
#include <type_traits>

namespace chimera::dio {

namespace {

constexpr std::string_view kInKeys[] = {"DATABASE", "DEVICE", "PORTS", "INVERT", "SYNC_TIMEOUT"};
constexpr std::string_view kOutKeys[] = {"DATABASE", "DEVICE", "PORTS", "INVERT", "SAFE", "ILLEGAL"};
// Keys bound to the open ports: changing them means opening other ports.
constexpr std::string_view kOpenKeys[] = {"DATABASE", "DEVICE", "PORTS"};

template <std::size_t N>
bool among(const std::string_view (&keys)[N], std::string_view key) {
    return std::find(std::begin(keys), std::end(keys), key) != std::end(keys);
}

template <std::size_t N>
std::string listing(const std::string_view (&keys)[N]) {
    std::string s;
    for (std::string_view k : keys) s += (s.empty() ? "" : ", ") + std::string(k);
    return s;
}

std::string_view module_of(Direction dir) { return dir == Direction::in ? "din" : "dout"; }

// Messages: "RMOD: ..." or "RMOD:LINE: LOCAL KEY: ..." (values set at run time
// with sbsSet have no line).
[[noreturn]] void fail(const RmodFile& rmod, const std::string& message) {
    throw ConfigError(rmod.path + ": " + message);
}
[[noreturn]] void fail(const RmodFile& rmod, const LocalConfig::Entry& e, const std::string& message) {
    const std::string where = e.line > 0 ? rmod.path + ":" + std::to_string(e.line) : rmod.path;
    throw ConfigError(where + ": LOCAL " + e.key + (e.line > 0 ? "" : " (as set)") + ": " + message);
}

const LocalConfig::Entry& required(const RmodFile& rmod, std::string_view key, const char* what) {
    const LocalConfig::Entry* e = rmod.local.find(key);
    if (!e) fail(rmod, "LOCAL " + std::string(key) + " is missing (" + what + ")");
    if (e->values.empty()) fail(rmod, *e, std::string("no value (") + what + ")");
    return *e;
}

const std::string& single(const RmodFile& rmod, const LocalConfig::Entry& e) {
    if (e.values.size() != 1)
        fail(rmod, e, "expected one value, found " + std::to_string(e.values.size()));
    return e.values.front();
}

std::string device_name(const iod::DeviceSpec& d) {
    return "device " + d.name + " (" + d.file + ":" + std::to_string(d.line) + ")";
}

std::string hex(std::uint32_t v) {
    char buf[16];
    std::snprintf(buf, sizeof buf, "0x%x", v);
    return buf;
}

// A value per port: one for all ports, or exactly one per opened port, each
// an integer 0..mask (decimal or 0x hex).
std::vector<std::uint32_t> per_port(const RmodFile& rmod, const LocalConfig::Entry& e, const Config& cfg) {
    const std::size_t n = static_cast<std::size_t>(cfg.nports());
    if (e.values.size() != 1 && e.values.size() != n)
        fail(rmod, e, "has " + std::to_string(e.values.size()) + " values, expected 1 (for every port) or " +
                          std::to_string(n) + " (one per port of PORTS " + std::to_string(cfg.first_port) +
                          ".." + std::to_string(cfg.last_port) + ")");
    std::vector<std::uint32_t> out;
    for (const std::string& token : e.values) {
        const std::optional<std::int64_t> v = cfg::parse_int(token);
        if (!v) fail(rmod, e, "expected an integer (decimal or 0x hex), found '" + token + "'");
        if (*v < 0 || static_cast<std::uint64_t>(*v) > cfg.port_mask())
            fail(rmod, e, token + " does not fit the " + std::to_string(cfg.device.width) + "-bit ports of " +
                              device_name(cfg.device) + " (0.." + hex(cfg.port_mask()) + ")");
        out.push_back(static_cast<std::uint32_t>(*v));
    }
    if (out.size() == 1) out.assign(n, out.front());
    return out;
}

// The keys that may change while the ports are open.
void read_tunables(const RmodFile& rmod, Direction dir, TaskType type, Config& cfg) {
    const std::size_t n = static_cast<std::size_t>(cfg.nports());
    if (const LocalConfig::Entry* e = rmod.local.find("INVERT")) cfg.invert = per_port(rmod, *e, cfg);
    else cfg.invert.assign(n, 0);

    if (dir == Direction::out) {
        const LocalConfig::Entry& e =
            required(rmod, "SAFE", "the value of each port from init, after off and kill, and on an error");
        cfg.safe = per_port(rmod, e, cfg);
        cfg.safe_when_illegal = false;
        if (const LocalConfig::Entry* il = rmod.local.find("ILLEGAL")) {
            const std::string& v = single(rmod, *il);
            if (v == "safe") cfg.safe_when_illegal = true;
            else if (v != "hold") fail(rmod, *il, "expected hold or safe, found '" + v + "'");
        }
    } else if (const LocalConfig::Entry* e = rmod.local.find("SYNC_TIMEOUT")) {
        if (type != TaskType::synchronous)
            fail(rmod, *e, "applies to synchronous tasks only (this one is " + std::string(to_string(type)) + ")");
        const std::optional<double> s = cfg::parse_double(single(rmod, *e));
        if (!s || !(*s > 0.0) || *s > 1.0)
            fail(rmod, *e, "expected seconds in (0, 1], found '" + e->values.front() + "'");
        cfg.sync_timeout_us = std::max(1L, std::lround(*s * 1e6));
    }
}

}  // namespace

std::uint32_t Config::port_mask() const noexcept {
    return device.width >= 32 ? 0xFFFFFFFFu : ((std::uint32_t{1} << device.width) - 1u);
}

Config read_config(const RmodFile& rmod, Direction dir, TaskType type) {
    Config cfg;
    cfg.rmod = rmod.path;
    const bool in = dir == Direction::in;
    for (const LocalConfig::Entry& e : rmod.local.entries()) {
        const bool known = in ? among(kInKeys, e.key) : among(kOutKeys, e.key);
        if (!known)
            fail(rmod, e, "not a key of " + std::string(module_of(dir)) + " (" +
                              (in ? listing(kInKeys) : listing(kOutKeys)) + ")");
    }
    if (!in && type == TaskType::synchronous)
        fail(rmod, "TASKTYPE synchronous: dout has no event to wait for; make it periodic (or "
                   "sporadic, to write on each event)");

    // DATABASE: a relative path is taken from the .rmod's folder, so an .rmod
    // and its database move together.
    const LocalConfig::Entry& db = required(rmod, "DATABASE", "the device database file");
    std::filesystem::path path = single(rmod, db);
    if (path.is_relative()) path = std::filesystem::path(rmod.path).parent_path() / path;
    cfg.database = path.lexically_normal().string();
    try {
        cfg.db = iod::Database::load(cfg.database);
    } catch (const iod::Error& e) {
        fail(rmod, db, e.what());
    }

    const LocalConfig::Entry& dev = required(rmod, "DEVICE", "the device's name in the database");
    const iod::DeviceSpec* spec = cfg.db.find(single(rmod, dev));
    if (!spec) {
        std::string names;
        for (const iod::DeviceSpec& d : cfg.db.devices()) names += (names.empty() ? "" : ", ") + d.name;
        fail(rmod, dev, "no device " + dev.values.front() + " in " + cfg.database + " (it has " +
                            (names.empty() ? std::string("none") : names) + ")");
    }
    if (spec->device_class != iod::DeviceClass::PIO)
        fail(rmod, dev, device_name(*spec) + " is class " + std::string(iod::class_name(spec->device_class)) +
                            ": din and dout use PIO (GPIO) devices");
    const unsigned want = in ? iod::READ : iod::WRITE;
    if (!(spec->directions & want))
        fail(rmod, dev, device_name(*spec) + " has DIRECTION " + (in ? "OUT" : "IN") + ": " +
                            std::string(module_of(dir)) + (in ? " reads inputs" : " drives outputs"));
    cfg.device = *spec;

    const LocalConfig::Entry& ports = required(rmod, "PORTS", "the first and last port: PORTS first [last]");
    if (ports.values.size() > 2) fail(rmod, ports, "expected first [last], found " + std::to_string(ports.values.size()) + " values");
    std::int64_t range[2];
    for (std::size_t i = 0; i < 2; ++i) {
        const std::string& token = ports.values[std::min(i, ports.values.size() - 1)];
        const std::optional<std::int64_t> v = cfg::parse_int(token);
        if (!v) fail(rmod, ports, "expected a port number, found '" + token + "'");
        range[i] = *v;
    }
    const int count = spec->port_count();
    if (range[0] < 0 || range[1] < range[0] || range[1] >= count)
        fail(rmod, ports, std::to_string(range[0]) + ".." + std::to_string(range[1]) + " is not a range of the ports 0.." +
                              std::to_string(count - 1) + " of " + device_name(*spec));
    cfg.first_port = static_cast<int>(range[0]);
    cfg.last_port = static_cast<int>(range[1]);

    read_tunables(rmod, dir, type, cfg);
    return cfg;
}

void update_config(Config& cfg, const RmodFile& rmod, Direction dir, TaskType type, std::string_view key) {
    if (among(kOpenKeys, key))
        fail(rmod, "LOCAL " + std::string(key) + " cannot change while the ports are open: kill the task "
                   "and spawn it again");
    const bool known = dir == Direction::in ? among(kInKeys, key) : among(kOutKeys, key);
    if (!known)
        fail(rmod, "LOCAL " + std::string(key) + " is not a key of " + std::string(module_of(dir)) + " (" +
                       (dir == Direction::in ? listing(kInKeys) : listing(kOutKeys)) + ")");
    Config fresh = cfg;
    read_tunables(rmod, dir, type, fresh);
    cfg = std::move(fresh);
}

namespace {

std::string port_name(const Task& t, std::string_view port) {
    const std::string global = t.global_name(port);
    return "port " + std::string(port) + (global == port ? "" : " (SVAR " + global + ")");
}

svar::VarInfo port_info(Task& t, std::string_view port, const std::vector<std::string>& list, const char* kind) {
    const RmodFile& r = t.rmod_file();
    if (std::find(list.begin(), list.end(), port) == list.end())
        fail(r, std::string(port) + " must be listed as " + kind + " (SVARALIAS " + std::string(port) +
                    "=NAME puts it on the variable NAME)");
    return t.local_table().global().var(t.global_name(port));
}

void check_elements(Task& t, std::string_view port, const svar::VarInfo& info, const Config& cfg) {
    if (info.nelem() != static_cast<std::size_t>(cfg.nports()))
        fail(t.rmod_file(), port_name(t, port) + " has " + std::to_string(info.nelem()) + " element" +
                                (info.nelem() == 1 ? "" : "s") + ", but PORTS " + std::to_string(cfg.first_port) +
                                ".." + std::to_string(cfg.last_port) + " opens " + std::to_string(cfg.nports()) +
                                ": one element per port");
}

}  // namespace

ValuePort value_port(Task& t, std::string_view port, Direction dir, const Config& cfg) {
    const RmodFile& r = t.rmod_file();
    const bool in = dir == Direction::in;
    const svar::VarInfo info = port_info(t, port, in ? r.out_vars : r.in_vars, in ? "OUTVAR" : "INVAR");
    const int bits = exact_bits(info.type());
    const std::string type(svar::type_name(info.type()));
    if (bits == 0)
        fail(r, port_name(t, port) + " is " + type + ", which does not hold port values as numbers; use byte, "
                                     "word, unsigned, short, int, float or double");
    if (bits < cfg.device.width) {
        std::string fits;
        for (svar::Type c : {svar::Type::byte_, svar::Type::word, svar::Type::short_, svar::Type::unsigned_,
                             svar::Type::int_, svar::Type::float_, svar::Type::double_})
            if (exact_bits(c) >= cfg.device.width) fits += (fits.empty() ? "" : ", ") + std::string(svar::type_name(c));
        fail(r, port_name(t, port) + " is " + type + ", which holds values of up to " + std::to_string(bits) +
                    " bits exactly: too narrow for the " + std::to_string(cfg.device.width) + "-bit ports of " +
                    device_name(cfg.device) + "; use " + fits);
    }
    check_elements(t, port, info, cfg);
    return ValuePort{t.local_table().translate_any(t.global_name(port)), info.type()};
}

std::uint32_t* edges_port(Task& t, std::string_view port, const Config& cfg) {
    const svar::VarInfo info = port_info(t, port, t.rmod_file().out_vars, "OUTVAR");
    if (info.type() != svar::Type::unsigned_)
        fail(t.rmod_file(), port_name(t, port) + " is " + std::string(svar::type_name(info.type())) +
                                ": edge counts are unsigned (they wrap at 2^32)");
    check_elements(t, port, info, cfg);
    return t.translate<std::uint32_t>(port);
}

std::unique_ptr<iod::Device> open_ports(const Config& cfg, Direction dir, unsigned wait,
                                        const std::uint32_t* initial) {
    const unsigned flags = (dir == Direction::in ? iod::READ : iod::WRITE) | iod::LONG | wait;
    try {
        return iod::open(cfg.db, cfg.device.name, cfg.first_port, cfg.last_port, flags, initial);
    } catch (const iod::Error& e) {
        throw ConfigError(cfg.rmod + ": " + e.what());
    }
}

int exact_bits(svar::Type type) noexcept {
    switch (type) {
    case svar::Type::byte_: return 8;
    case svar::Type::word: return 16;
    case svar::Type::unsigned_: return 32;
    case svar::Type::short_: return 15;
    case svar::Type::int_: return 31;
    case svar::Type::float_: return 24;   // the significand
    case svar::Type::double_: return 32;  // every uint32 is exact
    case svar::Type::char_:
    case svar::Type::struct_: return 0;
    }
    return 0;
}

void store(svar::Type type, void* data, std::size_t k, std::uint32_t value) noexcept {
    switch (type) {
    case svar::Type::byte_: static_cast<std::uint8_t*>(data)[k] = static_cast<std::uint8_t>(value); break;
    case svar::Type::word: static_cast<std::uint16_t*>(data)[k] = static_cast<std::uint16_t>(value); break;
    case svar::Type::unsigned_: static_cast<std::uint32_t*>(data)[k] = value; break;
    case svar::Type::short_: static_cast<std::int16_t*>(data)[k] = static_cast<std::int16_t>(value); break;
    case svar::Type::int_: static_cast<std::int32_t*>(data)[k] = static_cast<std::int32_t>(value); break;
    case svar::Type::float_: static_cast<float*>(data)[k] = static_cast<float>(value); break;
    case svar::Type::double_: static_cast<double*>(data)[k] = static_cast<double>(value); break;
    case svar::Type::char_:
    case svar::Type::struct_: break;  // refused by value_port()
    }
}

namespace {
template <typename F>
bool whole_in_range(F x, std::uint32_t max, std::uint32_t& value) noexcept {
    // NaN fails every comparison: it matches no port value.
    if (!(x >= F(0)) || !(x <= static_cast<F>(max)) || std::floor(x) != x) return false;
    value = static_cast<std::uint32_t>(x);
    return true;
}
template <typename I>
bool int_in_range(I x, std::uint32_t max, std::uint32_t& value) noexcept {
    if constexpr (std::is_signed_v<I>) {
        if (x < 0) return false;
    }
    if (static_cast<std::uint64_t>(x) > max) return false;
    value = static_cast<std::uint32_t>(x);
    return true;
}
}  // namespace

bool load(svar::Type type, const void* data, std::size_t k, std::uint32_t max, std::uint32_t& value) noexcept {
    switch (type) {
    case svar::Type::byte_: return int_in_range(static_cast<const std::uint8_t*>(data)[k], max, value);
    case svar::Type::word: return int_in_range(static_cast<const std::uint16_t*>(data)[k], max, value);
    case svar::Type::unsigned_: return int_in_range(static_cast<const std::uint32_t*>(data)[k], max, value);
    case svar::Type::short_: return int_in_range(static_cast<const std::int16_t*>(data)[k], max, value);
    case svar::Type::int_: return int_in_range(static_cast<const std::int32_t*>(data)[k], max, value);
    case svar::Type::float_: return whole_in_range(static_cast<const float*>(data)[k], max, value);
    case svar::Type::double_: return whole_in_range(static_cast<const double*>(data)[k], max, value);
    case svar::Type::char_:
    case svar::Type::struct_: return false;
    }
    return false;
}

}  // namespace chimera::dio
