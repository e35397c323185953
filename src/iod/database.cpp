// The device database (thesis §7.2: "a global database of device
// information"), in the project's configuration-file style.
#include "chimera/cfg.hpp"
#include "chimera/iod.hpp"

#include <algorithm>

namespace chimera::iod {

namespace {

DeviceClass parse_class(cfg::Reader& r, const cfg::Line& l, const std::string& s) {
    static constexpr std::pair<std::string_view, DeviceClass> table[] = {
        {"SIO", DeviceClass::SIO}, {"PIO", DeviceClass::PIO}, {"ADC", DeviceClass::ADC},
        {"DAC", DeviceClass::DAC}, {"RCB", DeviceClass::RCB}, {"SBS", DeviceClass::SBS},
        {"MEM", DeviceClass::MEM}};
    for (auto& [name, c] : table)
        if (name == s) return c;
    r.fail(l, "unknown device class " + s + " (SIO, PIO, ADC, DAC, RCB, SBS, MEM)");
}

// The driver each class has on Linux (docs/architecture.md §13).
std::string_view driver_for(DeviceClass c) {
    switch (c) {
    case DeviceClass::PIO: return "gpio";
    case DeviceClass::RCB: return "socketcan";
    case DeviceClass::SIO: return "termios";
    case DeviceClass::MEM: return "shm";
    default: return "";
    }
}

int small_int(cfg::Reader& r, const cfg::Line& l, std::size_t arg, std::string_view what, int lo,
              int hi) {
    auto v = r.to_int(l, arg, what);
    if (v < lo || v > hi)
        r.fail(l, std::string(what) + " must be " + std::to_string(lo) + ".." +
                      std::to_string(hi) + ", found " + std::to_string(v));
    return static_cast<int>(v);
}

DeviceSpec parse_device(cfg::Reader& r) {
    cfg::Line head = r.expect("DEVICE");
    r.require_args(head, 3);
    DeviceSpec d;
    d.name = head.args[0];
    d.device_class = parse_class(r, head, head.args[1]);
    d.driver = head.args[2];
    d.file = r.file();
    d.line = head.number;
    if (driver_for(d.device_class).empty())
        r.fail(head, "device " + d.name + ": no Linux driver for class " + head.args[1]);
    if (d.driver != driver_for(d.device_class))
        r.fail(head, "device " + d.name + ": class " + head.args[1] + " uses driver " +
                         std::string(driver_for(d.device_class)) + ", found " + d.driver);
    bool have_lines = false;
    for (;;) {
        std::optional<cfg::Line> l = r.next();
        if (!l) r.fail(r.end_line(), "device " + d.name + ": missing END");
        const std::string& k = l->keyword;
        if (k == "END") {
            r.require_args(*l, 0);
            break;
        }
        auto only_for = [&](DeviceClass c) {
            if (d.device_class != c)
                r.fail(*l, k + " is not a keyword of class " +
                               std::string(class_name(d.device_class)) + " devices");
        };
        if (k == "PATH") {
            r.require_args(*l, 1);
            d.path = l->args[0];
        } else if (k == "LINES") {
            only_for(DeviceClass::PIO);
            r.require_args(*l, 1);
            d.lines = small_int(r, *l, 0, "LINES", 1, 64);
            have_lines = true;
        } else if (k == "WIDTH") {
            only_for(DeviceClass::PIO);
            r.require_args(*l, 1);
            d.width = small_int(r, *l, 0, "WIDTH", 1, 32);
        } else if (k == "DIRECTION") {
            only_for(DeviceClass::PIO);
            r.require_args(*l, 1);
            const std::string& v = l->args[0];
            if (v == "IN") d.directions = READ;
            else if (v == "OUT") d.directions = WRITE;
            else if (v == "INOUT") d.directions = RW;
            else r.fail(*l, "DIRECTION must be IN, OUT or INOUT, found " + v);
        } else if (k == "FRAME") {
            only_for(DeviceClass::RCB);
            r.require_args(*l, 4);
            FrameSpec f;
            auto id = r.to_int(*l, 0, "CAN identifier");
            if (id < 0 || id > 0x1FFFFFFF) r.fail(*l, "CAN identifier out of range");
            f.can_id = static_cast<std::uint32_t>(id);
            if (l->args[1] == "IN") f.input = true;
            else if (l->args[1] == "OUT") f.input = false;
            else r.fail(*l, "FRAME direction must be IN or OUT, found " + l->args[1]);
            f.ports = small_int(r, *l, 2, "ports per frame", 1, 64);
            f.port_bits = small_int(r, *l, 3, "bits per port", 1, 32);
            if (f.ports * f.port_bits > 64)
                r.fail(*l, "FRAME " + l->args[0] + ": " + std::to_string(f.ports) + " ports of " +
                               std::to_string(f.port_bits) + " bits do not fit in 8 bytes");
            for (const FrameSpec& g : d.frames)
                if (g.can_id == f.can_id)
                    r.fail(*l, "FRAME " + l->args[0] + " appears twice in device " + d.name);
            f.first_port = d.port_count();
            d.frames.push_back(f);
        } else if (k == "EXTENDED") {
            only_for(DeviceClass::RCB);
            r.require_args(*l, 0);
            d.extended = true;
        } else if (k == "BAUD") {
            only_for(DeviceClass::SIO);
            r.require_args(*l, 1);
            d.sio.baud_rx = d.sio.baud_tx = small_int(r, *l, 0, "BAUD", 50, 4000000);
        } else if (k == "BITS") {
            only_for(DeviceClass::SIO);
            r.require_args(*l, 1);
            d.sio.bits = static_cast<std::uint8_t>(small_int(r, *l, 0, "BITS", 5, 8));
        } else if (k == "STOP") {
            only_for(DeviceClass::SIO);
            r.require_args(*l, 1);
            d.sio.stop = static_cast<std::uint8_t>(small_int(r, *l, 0, "STOP", 1, 2));
        } else if (k == "PARITY") {
            only_for(DeviceClass::SIO);
            r.require_args(*l, 1);
            static constexpr std::string_view names[] = {"NONE", "ODD", "EVEN", "MARK", "SPACE"};
            auto it = std::find(std::begin(names), std::end(names), l->args[0]);
            if (it == std::end(names))
                r.fail(*l, "PARITY must be NONE, ODD, EVEN, MARK or SPACE, found " + l->args[0]);
            d.sio.parity = static_cast<std::uint8_t>(it - std::begin(names));
        } else if (k == "SIZE") {
            only_for(DeviceClass::MEM);
            r.require_args(*l, 1);
            auto v = r.to_int(*l, 0, "SIZE");
            if (v <= 0 || v > (std::int64_t{1} << 32)) r.fail(*l, "SIZE must be 1..4G bytes");
            d.size = static_cast<std::size_t>(v);
        } else {
            r.fail(*l, "unknown keyword " + k + " in device " + d.name);
        }
    }
    auto missing = [&](const std::string& what) {
        r.fail(head, "device " + d.name + ": " + what);
    };
    if (d.path.empty()) missing("PATH missing");
    switch (d.device_class) {
    case DeviceClass::PIO:
        if (!have_lines) missing("LINES missing");
        if (d.lines % d.width != 0)
            missing("LINES " + std::to_string(d.lines) + " is not a multiple of WIDTH " +
                    std::to_string(d.width));
        break;
    case DeviceClass::RCB:
        if (d.frames.empty()) missing("no FRAME");
        break;
    case DeviceClass::MEM:
        if (d.size == 0) missing("SIZE missing");
        break;
    default: break;
    }
    return d;
}

std::vector<DeviceSpec> parse_devices(cfg::Reader& r);

}  // namespace

std::string_view class_name(DeviceClass c) noexcept {
    switch (c) {
    case DeviceClass::SIO: return "SIO";
    case DeviceClass::PIO: return "PIO";
    case DeviceClass::ADC: return "ADC";
    case DeviceClass::DAC: return "DAC";
    case DeviceClass::RCB: return "RCB";
    case DeviceClass::SBS: return "SBS";
    case DeviceClass::MEM: return "MEM";
    }
    return "?";
}

int DeviceSpec::port_count() const noexcept {
    switch (device_class) {
    case DeviceClass::PIO: return width > 0 ? lines / width : 0;
    case DeviceClass::RCB: {
        int n = 0;
        for (const FrameSpec& f : frames) n += f.ports;
        return n;
    }
    default: return 1;  // streams and memory: one port (§7.2.1)
    }
}

int DeviceSpec::port_bits(int port) const noexcept {
    if (port < 0 || port >= port_count()) return -1;
    switch (device_class) {
    case DeviceClass::PIO: return width;
    case DeviceClass::RCB:
        for (const FrameSpec& f : frames)
            if (port < f.first_port + f.ports) return f.port_bits;
        return -1;
    default: return 8;
    }
}

namespace {

std::vector<DeviceSpec> parse_devices(cfg::Reader& r) {
    std::vector<DeviceSpec> out;
    while (r.peek()) {
        DeviceSpec d = parse_device(r);
        for (const DeviceSpec& e : out)
            if (e.name == d.name)
                r.fail(d.line, "device " + d.name + " is defined twice (first at line " +
                                   std::to_string(e.line) + ")");
        out.push_back(std::move(d));
    }
    r.expect_end();
    return out;
}

}  // namespace

Database Database::from_string(std::string_view text, std::string name) {
    try {
        cfg::Reader r = cfg::Reader::from_string(text, std::move(name));
        Database db;
        db.devices_ = parse_devices(r);
        return db;
    } catch (const cfg::ParseError& e) {
        throw Error(e.what());
    }
}

Database Database::load(const std::string& path) {
    try {
        cfg::Reader r = cfg::Reader::from_file(path);
        Database db;
        db.devices_ = parse_devices(r);
        return db;
    } catch (const cfg::ParseError& e) {
        throw Error(e.what());
    }
}

const DeviceSpec* Database::find(std::string_view name) const noexcept {
    for (const DeviceSpec& d : devices_)
        if (d.name == name) return &d;
    return nullptr;
}

}  // namespace chimera::iod
