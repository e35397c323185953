// The SPP entries of the hardware configuration file (§7.4.1).
#include "chimera/cfg.hpp"
#include "chimera/spp.hpp"

namespace chimera::spp {

namespace {

int ranged(cfg::Reader& r, const cfg::Line& l, std::string_view what, std::int64_t lo, std::int64_t hi) {
    r.require_args(l, 1);
    const std::int64_t v = r.to_int(l, 0, what);
    if (v < lo || v > hi)
        r.fail(l, std::string(what) + " must be " + std::to_string(lo) + ".." + std::to_string(hi) +
                      ", found " + std::to_string(v));
    return static_cast<int>(v);
}

std::vector<Config> parse(cfg::Reader& r) {
    std::vector<Config> out;
    while (r.peek()) {
        const cfg::Line head = r.expect("SPP");
        r.require_args(head, 1);
        Config c;
        c.name = head.args[0];
        c.file = r.file();
        c.line = head.number;
        for (const Config& o : out)
            if (o.name == c.name)
                r.fail(head, "SPP " + c.name + " is defined twice (first at line " +
                                 std::to_string(o.line) + ")");
        for (;;) {
            std::optional<cfg::Line> l = r.next();
            if (!l) r.fail(r.end_line(), "SPP " + c.name + ": missing END");
            const std::string& k = l->keyword;
            if (k == "END") {
                r.require_args(*l, 0);
                break;
            } else if (k == "DRIVER") {
                r.require_args(*l, 1);
                if (l->args[0] != "thread")
                    r.fail(*l, "SPP " + c.name + ": unknown driver " + l->args[0] + " (thread)");
                c.driver = l->args[0];
            } else if (k == "MEMSIZE") {
                r.require_args(*l, 1);
                const std::int64_t v = r.to_int(*l, 0, "MEMSIZE");
                if (v <= 0 || v > (std::int64_t{1} << 34)) r.fail(*l, "MEMSIZE must be 1..16G bytes");
                c.memsize = static_cast<std::size_t>(v);
            } else if (k == "QUEUE") {
                c.queue = ranged(r, *l, "QUEUE", 2, 1 << 16);
            } else if (k == "TASKS") {
                c.tasks = ranged(r, *l, "TASKS", 1, 256);
            } else if (k == "CPU") {
                c.cpu = ranged(r, *l, "CPU", 0, 4095);
            } else if (k == "PRIORITY") {
                c.priority = ranged(r, *l, "PRIORITY", 1, 99);
            } else {
                r.fail(*l, "unknown keyword " + k + " in SPP " + c.name);
            }
        }
        if (c.memsize == 0) r.fail(head, "SPP " + c.name + ": MEMSIZE missing");
        out.push_back(std::move(c));
    }
    r.expect_end();
    return out;
}

}  // namespace

std::vector<Config> parse_config(std::string_view text, std::string name) {
    try {
        cfg::Reader r = cfg::Reader::from_string(text, std::move(name));
        return parse(r);
    } catch (const cfg::ParseError& e) {
        throw Error(e.what());
    }
}

std::vector<Config> load_config(const std::string& path) {
    try {
        cfg::Reader r = cfg::Reader::from_file(path);
        return parse(r);
    } catch (const cfg::ParseError& e) {
        throw Error(e.what());
    }
}

const Config& find_config(const std::vector<Config>& configs, std::string_view name) {
    for (const Config& c : configs)
        if (c.name == name) return c;
    throw Error("spp: no SPP named " + std::string(name) + " in the configuration");
}

void Library::add_routine(std::string name, Routine fn) {
    if (used(name)) throw Error("spp library: " + name + " is defined twice");
    if (!fn) throw Error("spp library: routine " + name + " has no code");
    routines_.push_back({std::move(name), fn});
}

void Library::add_variable(std::string name, std::size_t bytes, std::size_t align) {
    if (used(name)) throw Error("spp library: " + name + " is defined twice");
    if (bytes == 0) throw Error("spp library: variable " + name + " has no size");
    if (align == 0 || (align & (align - 1)) != 0)
        throw Error("spp library: variable " + name + ": alignment must be a power of two");
    variables_.push_back({std::move(name), bytes, align});
}

bool Library::used(std::string_view name) const noexcept {
    for (const auto& r : routines_)
        if (r.name == name) return true;
    for (const auto& v : variables_)
        if (v.name == name) return true;
    return false;
}

}  // namespace chimera::spp
