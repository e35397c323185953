#include "commands.hpp"

#include "admission.hpp"

#include "command_line.hpp"
#include "status_text.hpp"
#include "svar_values.hpp"

#include <chimera/ipc/segment.hpp>
#include <chimera/sampler.hpp>

#include <signal.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <set>
#include <stdexcept>
#include <thread>

namespace chimera::cli {

namespace fs = std::filesystem;

namespace {

/// A command's own failure: becomes an error reply with this one line.
class CommandError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

std::string fmt(const char* f, double v) {
    char buf[64];
    std::snprintf(buf, sizeof buf, f, v);
    return buf;
}

std::string join(const std::vector<std::string>& v, std::string_view sep = " ") {
    std::string out;
    for (const auto& s : v) {
        if (!out.empty()) out += sep;
        out += s;
    }
    return out;
}

std::string pad(const std::string& s, std::size_t width, bool right = false) {
    if (s.size() >= width) return s;
    const std::string fill(width - s.size(), ' ');
    return right ? fill + s : s + fill;
}

bool is_signal_word(std::string_view w) { return w == "on" || w == "off" || w == "kill" || w == "clear"; }

sbs::Control signal_of(std::string_view w) {
    if (w == "on") return sbs::Control::on;
    if (w == "off") return sbs::Control::off;
    if (w == "kill") return sbs::Control::kill;
    return sbs::Control::clear;
}

// ----------------------------------------------------------------- status

struct Field {
    const char* name;
    std::size_t width;
    bool numeric;
    bool time;  ///< shown in µs, the header says "[us]"
};

const std::vector<Field>& fields() {
    // §4.4.1 in its order, then what the Linux port adds.
    static const std::vector<Field> f = {
        {"rmod", 12, false, false},  {"rtpu", 6, false, false},   {"tid", 7, true, false},
        {"S", 1, false, false},      {"crit", 4, true, false},    {"state", 11, false, false},
        {"cycle", 8, true, false},   {"miss", 6, true, false},    {"refF", 9, true, false},
        {"refT", 10, true, true},    {"mezF", 9, true, false},    {"mezT", 10, true, true},
        {"ptime", 11, true, true},   {"totC", 10, true, true},    {"tick", 9, true, true},
        {"minU", 6, true, false},    {"maxU", 6, true, false},    {"avgU", 6, true, false},
        {"minC", 10, true, true},    {"maxC", 10, true, true},    {"avgC", 10, true, true},
        {"warn", 4, true, false},    {"policy", 24, false, false}, {"cpu", 3, true, false},
        {"module", 10, false, false}, {"cycP50", 12, true, true}, {"cycP99", 12, true, true},
        {"cycMax", 12, true, true},  {"latP50", 12, true, true},  {"latP99", 12, true, true},
        {"latMax", 12, true, true},
    };
    return f;
}

const Field* find_field(std::string_view name) {
    for (const auto& f : fields())
        if (name == f.name) return &f;
    return nullptr;
}

const std::vector<std::string> kDefaultFields = {"rmod", "rtpu", "tid",  "S",    "crit", "state", "cycle",
                                                 "miss", "refF", "mezF", "mezT", "maxC", "warn"};

/// The task's profile from the status segment (§6.7), when the runtime has
/// published one for it.
const prof::TaskStatus* profile_of(const sbs::TaskStatus& t) { return t.profile.rmod.empty() ? nullptr : &t.profile; }

// Counters run "since this interface's last status command" (§4.4.1, a window
// per interface, issue 16.4) when the profile is there; otherwise they are the
// master's own, since the task was turned on. Times in µs.
nlohmann::json field_value(const sbs::TaskStatus& t, std::string_view f) {
    using tools::to_us;
    const auto* p = profile_of(t);
    if (f == "rmod") return t.rmod;
    if (f == "rtpu") return t.rtpu;
    if (f == "tid") return t.tid;
    if (f == "S") return std::string(1, t.type);
    if (f == "crit") return t.crit;
    if (f == "state") return std::string(to_string(t.state));
    if (f == "refF") return t.ref_freq;
    if (f == "refT") return to_us(t.ref_period);
    if (f == "policy") return t.policy;
    if (f == "cpu") return t.cpu;
    if (f == "module") return t.module;
    if (p) return tools::profile_value(*p, f);
    if (f == "cycle") return t.cycles;
    if (f == "miss") return t.misses;
    if (f == "mezF") return t.mez_freq;
    if (f == "mezT") return to_us(t.mez_period);
    if (f == "maxC") return to_us(t.max_cycle_time);
    if (f == "warn") return t.warnings;
    return nullptr;  // the rest exists only in the profile
}

std::string field_text(const sbs::TaskStatus& r, std::string_view f) {
    const Field* fd = find_field(f);
    return tools::value_text(field_value(r, f), fd && fd->time);
}

std::string field_header(const std::string& name) {
    const Field* fd = find_field(name);
    return fd->time ? tools::time_header(name) : name;
}

// ----------------------------------------------------------------- svar values

using tools::numbers_of;
using tools::type_text;

/// Every module (.so) and .rmod file in `dirs`: name -> path, first found wins.
void scan_dirs(const std::vector<std::string>& dirs, std::map<std::string, std::string>& modules,
               std::map<std::string, std::string>& rmods) {
    for (const auto& d : dirs) {
        std::error_code ec;
        for (fs::directory_iterator it(d, ec), end; !ec && it != end; it.increment(ec)) {
            const fs::path p = it->path();
            std::string stem = p.stem().string();
            if (p.extension() == ".so") {
                if (stem.rfind("lib", 0) == 0 && stem.size() > 3) stem.erase(0, 3);
                modules.emplace(stem, p.string());
            } else if (p.extension() == ".rmod") {
                rmods.emplace(stem, p.string());
            }
        }
    }
}

}  // namespace

const std::vector<std::string>& default_status_fields() { return kDefaultFields; }

const std::vector<std::string>& status_field_names() {
    static const std::vector<std::string> names = [] {
        std::vector<std::string> n;
        for (const auto& f : fields()) n.emplace_back(f.name);
        return n;
    }();
    return names;
}

Interpreter::Interpreter(sbs::Subsystem& subsystem, std::vector<std::string> module_dirs)
    : sbs_(subsystem), extra_dirs_(std::move(module_dirs)), fields_(kDefaultFields) {}

std::string Interpreter::prompt() const { return "SBS " + sbs_.name() + "<" + default_rmod_ + "> "; }

std::vector<std::string> Interpreter::module_path() const {
    std::vector<std::string> dirs;
    if (const char* env = std::getenv("CHIMERA_MODULE_PATH")) {
        std::string s = env;
        std::size_t pos = 0;
        while (pos <= s.size()) {
            auto end = s.find(':', pos);
            if (end == std::string::npos) end = s.size();
            if (end > pos) dirs.push_back(s.substr(pos, end - pos));
            pos = end + 1;
        }
    }
    dirs.insert(dirs.end(), extra_dirs_.begin(), extra_dirs_.end());
    const auto sbs_dir = fs::path(sbs_.file().path).parent_path();
    dirs.push_back(sbs_dir.empty() ? std::string(".") : sbs_dir.string());
    for (auto& d : sbs::default_module_dirs()) dirs.push_back(std::move(d));
    return dirs;
}

Reply Interpreter::execute(std::string_view command, Origin origin) {
    std::lock_guard lock(mutex_);
    origin_ = origin;
    // The web console names every task it means: its requests (many pages,
    // polling) must not move the prompt's default RMOD.
    struct KeepDefault {
        Interpreter& in;
        std::string saved, saved_previous;
        bool keep;
        ~KeepDefault() {
            if (!keep) return;
            in.default_rmod_ = saved;
            in.previous_rmod_ = saved_previous;
            if (!saved.empty() && !in.is_task(saved)) in.forget_task(saved);  // a page killed it
        }
    } keep_default{*this, default_rmod_, previous_rmod_, origin == Origin::web};
    // `complete LINE`: the TAB candidates for LINE, raw (a trailing blank
    // matters: it starts a new word), for a prompt attached over the network.
    if (command == "complete" || command.substr(0, 9) == "complete ") {
        Reply r;
        r.command = "complete";
        r.rmod = default_rmod_;
        const auto candidates = complete_locked(command.size() > 9 ? command.substr(9) : std::string_view());
        r.text = join(candidates);
        r.data = {{"candidates", candidates}};
        return r;
    }
    Words words;
    try {
        words = split_words(command);
    } catch (const SyntaxError& e) {
        return Reply::failure("", e.what());
    }
    if (words.empty()) {
        Reply r;
        r.rmod = default_rmod_;
        return r;
    }
    Reply r;
    try {
        r = run(words);
    } catch (const std::exception& e) {
        r = Reply::failure(words[0], e.what());
    }
    r.command = words[0];
    r.rmod = default_rmod_;
    // Padded columns leave blanks at line ends: drop them.
    std::string trimmed;
    std::size_t pos = 0;
    while (pos <= r.text.size()) {
        auto end = r.text.find('\n', pos);
        if (end == std::string::npos) end = r.text.size();
        std::string line = r.text.substr(pos, end - pos);
        while (!line.empty() && line.back() == ' ') line.pop_back();
        trimmed += line;
        if (end < r.text.size()) trimmed += '\n';
        pos = end + 1;
    }
    r.text = std::move(trimmed);
    return r;
}

Reply Interpreter::run(const Words& w) {
    const std::string& c = w[0];
    check_peers();
    if (c == "peer") return cmd_peer(w);
    if (c == "spawn") return cmd_spawn(w);
    if (c == "on") return cmd_control(w, sbs::Control::on);
    if (c == "off") return cmd_control(w, sbs::Control::off);
    if (c == "kill") return cmd_control(w, sbs::Control::kill);
    if (c == "clear") return cmd_control(w, sbs::Control::clear);
    if (c == "set") return cmd_set(w);
    if (c == "status") return cmd_status(w);
    if (c == "display") return cmd_display(w);
    if (c == "module") return cmd_module(w);
    if (c == "reconfig") return cmd_reconfig(w);
    if (c == "freq") return cmd_freq(w);
    if (c == "event") return cmd_event(w);
    if (c == "help") return cmd_help(w);
    if (c == "show") return cmd_show(w);
    if (c == "setvar") return cmd_setvar(w);
    if (c == "save") return cmd_save(w);
    if (c == "sample") return cmd_sample(w);
    if (c == "record")
        throw CommandError("record writes a file, so it runs in the sbs program that asked (sbs FILE.sbs -c 'record "
                           "...'), never over the network: a peer runs `sample` and reads the ring itself");
    Reply r;
    if (c == "sleep") {
        double seconds = -1;
        if (w.size() == 2) {
            char* end = nullptr;
            seconds = std::strtod(w[1].c_str(), &end);
            if (end == w[1].c_str() || *end != '\0') seconds = -1;
        }
        if (!(seconds >= 0 && seconds <= 60)) throw CommandError("usage: sleep SECONDS (0 to 60)");
        std::this_thread::sleep_for(std::chrono::duration<double>(seconds));
        return r;
    }
    if (c == "quit" || c == "finish" || c == "network") {
        if (w.size() > 1) throw CommandError(c + " takes no argument");
        r.action = c == "quit" ? Action::quit : c == "finish" ? Action::finish : Action::network;
        r.text = c == "network" ? "passing control to the network" : c == "quit" ? "" : "finishing subsystem " + sbs_.name();
        return r;
    }
    throw CommandError("unknown command '" + c + "' (type help for the list)");
}

// ----------------------------------------------------------------- tasks

// Live tasks are tracked here rather than asked with status(): status()
// consumes the first warning, which only a status command may show (§4.4.1).
bool Interpreter::is_task(std::string_view name) const { return rmods_.count(std::string(name)) != 0; }

void Interpreter::make_default(const std::string& name) {
    if (name == default_rmod_) return;
    previous_rmod_ = default_rmod_;
    default_rmod_ = name;
}

void Interpreter::forget_task(const std::string& name) {
    rmods_.erase(name);
    if (default_rmod_ != name) return;
    default_rmod_ = is_task(previous_rmod_) ? previous_rmod_ : std::string();
    previous_rmod_.clear();
}

std::vector<std::string> Interpreter::live_rmods() const {
    std::vector<std::string> out;
    for (const auto& [name, file] : rmods_) out.push_back(name);
    return out;
}

namespace {

// A state report that also shows a warning status() has just consumed, so it
// is displayed once rather than lost.
std::string state_line(const sbs::TaskStatus& s) {
    std::string line = s.rmod + ": " + std::string(to_string(s.state));
    if (!s.warning.empty()) line += "\nWARNING> " + s.rmod + ": " + s.warning;
    if (s.state == State::ERROR) line += "\nERROR> " + s.rmod + ": " + s.error;
    return line;
}

}  // namespace

sbs::TaskId Interpreter::task_of(const std::string& rmod) {
    const std::string name = rmod.empty() ? default_rmod_ : rmod;
    if (name.empty()) throw CommandError("no default RMOD (none yet, or it was killed): name the task");
    const auto id = sbs_.find(name);
    if (!id) {
        const auto live = live_rmods();
        throw CommandError("no task " + name + " in subsystem " + sbs_.name() +
                           (live.empty() ? " (no task spawned)" : " (tasks: " + join(live) + ")"));
    }
    make_default(name);
    return *id;
}

std::optional<std::string> Interpreter::find_rmod_file(const std::string& name) const {
    std::vector<std::string> names = {name};
    if (fs::path(name).extension() != ".rmod") names.push_back(name + ".rmod");
    if (origin_ != Origin::local) {
        if (name.find('/') != std::string::npos || name == "." || name == "..")
            throw CommandError("over the network only .rmod files on the master's module path can be named, "
                               "by name without a folder (" + name + " is a path)");
        // Only .rmod files are read for a peer: another file's first line
        // would come back in the parse error.
        names.erase(names.begin(), names.end() - 1);
    } else {
        for (const auto& n : names) {
            std::error_code ec;
            if (fs::is_regular_file(n, ec)) return n;
        }
        if (name.find('/') != std::string::npos) return std::nullopt;
    }
    for (const auto& d : module_path()) {
        for (const auto& n : names) {
            std::error_code ec;
            const fs::path p = fs::path(d) / n;
            if (fs::is_regular_file(p, ec)) return p.string();
        }
    }
    return std::nullopt;
}

namespace {

// What the interpreter records for a combined task a+b+c: one RmodFile whose
// port lists are the global names the task exchanges with the table (a port
// one object produces and another consumes stays inside the task), and whose
// LOCAL holds every object's keys (the first object's value wins).
RmodFile combined_view(const std::string& name, const std::vector<RmodFile>& parts) {
    RmodFile out;
    out.name = name;
    out.path = parts.front().path;
    out.type = parts.front().type;
    out.freq = parts.front().freq;
    out.period = parts.front().period;
    std::vector<std::string> modules;
    std::set<std::string> produced, consumed;
    for (const auto& f : parts) {
        modules.push_back(f.module);
        for (const auto& v : f.global_out_vars()) produced.insert(v);
        for (const auto& v : f.global_out_consts()) produced.insert(v);
        for (const auto& v : f.global_in_vars()) consumed.insert(v);
        for (const auto& v : f.global_in_consts()) consumed.insert(v);
        out.wcet += f.wcet;
        for (const auto& e : f.local.entries())
            if (!out.local.has(e.key)) out.local.set(e.key, e.values, e.line);
    }
    out.module = join(modules, "+");
    auto outside = [](const std::vector<std::string>& v, const std::set<std::string>& inside) {
        std::vector<std::string> kept;
        for (const auto& x : v)
            if (!inside.count(x) && std::find(kept.begin(), kept.end(), x) == kept.end()) kept.push_back(x);
        return kept;
    };
    for (const auto& f : parts) {
        for (const auto& v : outside(f.global_out_vars(), consumed)) out.out_vars.push_back(v);
        for (const auto& v : outside(f.global_out_consts(), consumed)) out.out_consts.push_back(v);
        for (const auto& v : outside(f.global_in_vars(), produced)) out.in_vars.push_back(v);
        for (const auto& v : outside(f.global_in_consts(), produced)) out.in_consts.push_back(v);
    }
    return out;
}

// A task as its RTPU's analysis counts it: a periodic task, or a server
// (sporadic or deferrable with WCET and FREQ), at the rate the interpreter
// last gave it; nullopt for a task never released periodically.
std::optional<muf::TaskSpec> analysed_spec(const std::string& name, const RmodFile& f) {
    const bool server = is_aperiodic(f.type) && f.type != TaskType::background && f.wcet > 0 && f.freq > 0;
    if ((f.type != TaskType::periodic || !(f.freq > 0)) && !server) return std::nullopt;
    muf::TaskSpec t;
    t.name = name;
    t.period = 1.0 / f.freq;
    t.wcet = f.wcet;
    t.effective = f.effective;
    t.crit = server && !f.crit ? std::optional<int>(muf::crit::server) : f.crit;
    return t;
}

}  // namespace

// spawn RMOD [RTPU] | spawn A+B+C [RTPU]: one task, or a combined task
// (§3.8.1: the objects' methods run in the order given, in one thread).
Reply Interpreter::cmd_spawn(const Words& w) {
    if (w.size() < 2 || w.size() > 3) throw CommandError("usage: spawn RMOD[+RMOD...] [RTPU]");
    std::vector<std::string> names_given;
    for (std::size_t at = 0;;) {
        const auto plus = w[1].find('+', at);
        names_given.push_back(w[1].substr(at, plus == std::string::npos ? std::string::npos : plus - at));
        if (plus == std::string::npos) break;
        at = plus + 1;
    }
    std::vector<std::string> paths;
    for (const auto& n : names_given) {
        const auto path = n.empty() ? std::nullopt : find_rmod_file(n);
        if (!path)
            throw CommandError("spawn: no file " + n + (fs::path(n).extension() == ".rmod" ? "" : "[.rmod]") +
                               " here or on the module path (" + join(module_path(), ":") + ")");
        paths.push_back(*path);
    }
    const std::string rtpu = w.size() == 3 ? w[2] : std::string();
    if (!rtpu.empty() && !sbs_.file().find_rtpu(rtpu)) {
        std::vector<std::string> names;
        for (const auto& r : sbs_.file().rtpus) names.push_back(r.name);
        throw CommandError("spawn: no RTPU " + rtpu + " in " + sbs_.file().path + " (RTPUs: " + join(names) + ")");
    }
    std::vector<RmodFile> files;
    std::vector<std::string> stems;
    for (const auto& p : paths) {
        files.push_back(read_rmod(p));
        stems.push_back(files.back().name);
    }
    const std::string name = join(stems, "+");
    if (is_task(name)) throw CommandError("spawn: task " + name + " already exists (kill it first)");
    if (origin_ != Origin::local)
        for (const auto& f : files) refuse_file_writer("spawn", name, sbs::module_local_keys(f, module_path()));
    RmodFile view = files.size() == 1 ? std::move(files[0]) : combined_view(name, files);
    const std::string warning = admit_spawn(name, view, rtpu);
    const sbs::TaskId id = paths.size() == 1 ? sbs_.spawn(paths[0], rtpu) : sbs_.spawn_combined(paths, rtpu);
    rmods_[name] = std::move(view);
    files_of_[name] = paths;
    make_default(name);
    const auto s = sbs_.status(id);
    rtpu_of_[name] = s.rtpu;
    Reply r;
    r.text = "spawned " + name + " (module " + s.module + ") on RTPU " + s.rtpu + "\n" + state_line(s) +
             (warning.empty() ? "" : "\n" + warning);
    r.data = {{"rmod", name}, {"file", join(paths, "+")}, {"files", paths}, {"module", s.module}, {"rtpu", s.rtpu},
              {"state", std::string(to_string(s.state))}};
    if (!warning.empty()) r.data["admission"] = warning;
    return r;
}

// A spawned task is OFF and takes no CPU, so only its rate is checked here
// (the analysis is at `on`, when the tasks beside it are known); a refusal
// names the RTPUs whose range holds the rate.
std::string Interpreter::admit_spawn(const std::string& name, const RmodFile& f, const std::string& rtpu) const {
    const auto task = analysed_spec(name, f);
    if (!task) return {};
    const RtpuSpec& spec = sampler_rtpu(rtpu);
    std::vector<std::string> others;
    for (const RtpuSpec& r : sbs_.file().rtpus)
        if (r.name != spec.name && rate_problem(r, f.freq).empty()) others.push_back(r.name);
    const std::string spawn = "spawn " + name + " ";
    const std::string hint = others.empty() ? "no RTPU runs tasks at " + cfg::number_text(f.freq) + " Hz"
                                            : spawn + join(others, " or " + spawn) + " takes it";
    return admit("spawn " + name, spec.name, *task, f.freq, nullptr, hint);
}

Reply Interpreter::cmd_control(const Words& w, sbs::Control signal) {
    if (w.size() > 2) throw CommandError("usage: " + w[0] + " [RMOD]");
    const sbs::TaskId id = task_of(w.size() == 2 ? w[1] : std::string());
    const std::string name = default_rmod_;
    std::string warning;
    if (signal == sbs::Control::on) {
        refuse_file_writer("on", name, sbs_.local_keys(id));
        warning = admit_on("on", name, tasks_on());
    }
    try {
        sbs_.control(id, signal);
    } catch (const sbs::Error&) {
        if (sbs_.status(id).state == State::NOT_CREATED) forget_task(name);
        throw;
    }
    const auto s = sbs_.status(id);
    if (s.state == State::NOT_CREATED) forget_task(name);
    Reply r;
    r.text = state_line(s) + (warning.empty() ? "" : "\n" + warning);
    r.data = {{"rmod", name}, {"state", std::string(to_string(s.state))}};
    if (!warning.empty()) r.data["admission"] = warning;
    return r;
}

// No command from the network makes a file be written (issue #29.4): a
// peer could otherwise have the master (often root) create or truncate one.
void Interpreter::refuse_file_writer(const std::string& command, const std::string& task,
                                     const std::vector<LocalKey>& keys) const {
    if (origin_ == Origin::local) return;
    for (const LocalKey& k : keys)
        if (k.type == LocalType::output_file)
            throw CommandError(command + " " + task + " refused: its module writes a file (LOCAL " + k.name +
                               "), and over the network no file is written; " + command +
                               " it at the master's own prompt, with -c, or in the .sbs (TASK ... ON)");
}

std::vector<std::string> Interpreter::local_keys(const std::string& rmod) const {
    std::vector<std::string> keys;
    if (auto it = rmods_.find(rmod); it != rmods_.end())
        for (const auto& e : it->second.local.entries()) keys.push_back(e.key);
    return keys;
}

// `set RMOD`: every LOCAL key the module declares, with the value it runs
// with (through get()), its type, range, whether `set` can change it, and
// help; then any LOCAL line of the .rmod the module does not declare.
Reply Interpreter::local_view(sbs::TaskId id) {
    nlohmann::json local = nlohmann::json::object(), keys = nlohmann::json::array();
    std::string text = default_rmod_ + " LOCAL:";
    const auto declared = sbs_.local_keys(id);
    std::set<std::string> shown;
    auto value_of = [&](const std::string& key) -> std::string {
        try {
            return sbs_.get(id, key);
        } catch (const sbs::Error&) {
            return "(unset)";
        }
    };
    for (const LocalKey& d : declared) {
        const std::string name = d.name;
        std::vector<std::string> names;
        if (!name.empty() && name.back() == '*') {
            for (const auto& key : local_keys(default_rmod_))
                if (key.compare(0, name.size() - 1, name, 0, name.size() - 1) == 0 && !shown.count(key)) names.push_back(key);
        } else {
            names.push_back(name);
        }
        for (const auto& key : names) {
            const std::string v = value_of(key);
            text += "\n  " + pad(key, 12) + " " + pad(v, 24) + " " + describe(d).substr(name.size() + 1);
            local[key] = v;
            shown.insert(key);
        }
        keys.push_back({{"name", name}, {"type", std::string(to_string(d.type))},
                        {"min", std::isinf(d.min) ? nlohmann::json(nullptr) : nlohmann::json(d.min)},
                        {"max", std::isinf(d.max) ? nlohmann::json(nullptr) : nlohmann::json(d.max)},
                        {"live", d.live}, {"help", d.help}, {"default", d.fallback}});
    }
    for (const auto& key : local_keys(default_rmod_)) {
        if (shown.count(key)) continue;
        const std::string v = value_of(key);
        text += "\n  " + pad(key, 12) + " " + pad(v, 24) + " (not declared by the module)";
        local[key] = v;
    }
    if (local.empty()) text += " (none)";
    Reply r;
    r.text = text;
    r.data = {{"rmod", default_rmod_}, {"local", local}, {"keys", keys}};
    return r;
}

Reply Interpreter::cmd_set(const Words& w) {
    // set [RMOD] [KEY [VALUE...]]: a first word naming a task is the RMOD.
    std::size_t k = 1;
    std::string rmod;
    if (w.size() > 1 && is_task(w[1])) {
        rmod = w[1];
        k = 2;
    }
    const sbs::TaskId id = task_of(rmod);
    Reply r;
    if (k == w.size()) return local_view(id);
    const std::string& key = w[k];
    if (k + 1 == w.size()) {
        const std::string v = sbs_.get(id, key);
        r.text = default_rmod_ + " " + key + " = " + v;
        r.data = {{"rmod", default_rmod_}, {"key", key}, {"value", v}};
        return r;
    }
    std::vector<std::string> values(w.begin() + static_cast<std::ptrdiff_t>(k) + 1, w.end());
    const std::string value = join(values);
    sbs_.set(id, key, value);
    if (auto it = rmods_.find(default_rmod_); it != rmods_.end()) it->second.local.set(key, values);
    const std::string now = sbs_.get(id, key);
    r.text = default_rmod_ + " " + key + " = " + now;
    r.data = {{"rmod", default_rmod_}, {"key", key}, {"value", now}};
    return r;
}

Reply Interpreter::cmd_status(const Words& w) {
    Reply r;
    if (w.size() >= 2 && w[1] == "set") {
        if (w.size() > 2) {
            std::vector<std::string> chosen;
            if (w.size() == 3 && w[2] == "default") {
                chosen = kDefaultFields;
            } else if (w.size() == 3 && w[2] == "all") {
                chosen = status_field_names();
            } else {
                for (std::size_t i = 2; i < w.size(); ++i) {
                    // "rmod,cycle" and "rmod cycle" both work.
                    std::size_t pos = 0;
                    while (pos <= w[i].size()) {
                        auto end = w[i].find(',', pos);
                        if (end == std::string::npos) end = w[i].size();
                        const std::string f = w[i].substr(pos, end - pos);
                        if (!f.empty()) {
                            if (!find_field(f))
                                throw CommandError("status set: unknown field '" + f +
                                                   "' (fields: " + join(status_field_names()) + ")");
                            if (std::find(chosen.begin(), chosen.end(), f) == chosen.end()) chosen.push_back(f);
                        }
                        pos = end + 1;
                    }
                }
            }
            if (chosen.empty()) throw CommandError("status set: no field chosen");
            fields_ = std::move(chosen);
        }
        r.text = "status fields: " + join(fields_) + "\navailable: " + join(status_field_names());
        r.data = {{"fields", fields_}, {"available", status_field_names()}};
        return r;
    }
    if (w.size() > 2) throw CommandError("usage: status [RMOD|all] | status reset | status set [FIELD...]");
    const bool reset = w.size() == 2 && w[1] == "reset" && !is_task("reset");
    std::vector<sbs::TaskStatus> tasks;
    if (w.size() == 2 && w[1] != "all" && !reset) {
        tasks.push_back(sbs_.status(task_of(w[1])));
    } else {
        tasks = sbs_.status_all();
    }
    // "Since the last status command" (§4.4.1), per interface: this one's
    // window is shown and restarts; nobody else's counts move (issue 16.4).
    if (!prof_) prof_ = prof::StatusReader::try_attach(sbs_.name());
    if (prof_) {
        const std::vector<prof::TaskStatus> window = windows_[static_cast<int>(origin_)].take(*prof_);
        for (auto& row : tasks) {
            if (!profile_of(row)) continue;
            for (const auto& p : window)
                if (p.slot == row.profile.slot) row.profile = p;
        }
        if (reset) prof_->reset_all();  // the thesis's reset, for every reader
    }
    return status_reply(sbs_.name(), tasks, fields_, reset);
}

Reply status_reply(const std::string& subsystem, const std::vector<sbs::TaskStatus>& rows,
                   const std::vector<std::string>& fields, bool reset) {
    Reply r;
    std::string text = "subsystem " + subsystem + ": " + std::to_string(rows.size()) +
                       (rows.size() == 1 ? " task" : " tasks") + " (times in " + tools::kTimeUnit + ")";
    if (reset) text += "\nprofiling reset on every RTPU: every reader's counts start again";
    std::string header;
    for (const auto& f : fields) {
        const Field* fd = find_field(f);
        header += (header.empty() ? "" : " ") + pad(field_header(f), fd->width, fd->numeric);
    }
    text += "\n" + header;
    nlohmann::json jtasks = nlohmann::json::array();
    for (const auto& row : rows) {
        std::string line;
        for (const auto& f : fields) {
            const Field* fd = find_field(f);
            line += (line.empty() ? "" : " ") + pad(field_text(row, f), fd->width, fd->numeric);
        }
        text += "\n" + line;
        // WARNING> once, ERROR> as long as the task is in ERROR; not subject to `status set`.
        if (!row.warning.empty()) text += "\nWARNING> " + row.rmod + ": " + row.warning;
        if (row.state == State::ERROR)
            text += "\nERROR> " + row.rmod + ": " + (row.error.empty() ? "(no message)" : row.error);
        nlohmann::json j = nlohmann::json::object();
        for (const auto& f : status_field_names()) j[f] = field_value(row, f);
        j["warning"] = row.warning;
        j["error"] = row.error;
        if (const auto* p = profile_of(row)) j["clock"] = prof::to_string(p->cpu_clock);
        jtasks.push_back(std::move(j));
    }
    r.text = text;
    r.data = {{"subsystem", subsystem}, {"fields", fields}, {"tasks", jtasks}, {"time_unit", tools::kTimeUnit},
              {"reset", reset}};
    return r;
}

void Interpreter::detach() {
    std::lock_guard lock(mutex_);
    table_.reset();
    prof_.reset();
}

svar::Table* Interpreter::table() {
    if (!table_) {
        svar::TableOptions opt;
        opt.attach.prefault = false;
        table_ = svar::Table::attach(ipc::segment_name(sbs_.name(), "svar"), opt);
    }
    return &*table_;
}

Reply Interpreter::cmd_display(const Words& w) {
    svar::Table& t = *table();
    std::vector<VarItem> items;
    std::size_t k = 1;
    std::string who;
    const bool whole = w.size() > 1 && w[1] == "all";
    if (whole) {
        k = 2;
    } else if (w.size() > 1 && is_task(w[1])) {
        who = w[1];
        k = 2;
    } else if (w.size() == 1 && !default_rmod_.empty() && is_task(default_rmod_)) {
        who = default_rmod_;
    }
    if (!who.empty()) {
        task_of(who);
        const auto it = rmods_.find(who);
        if (it == rmods_.end()) throw CommandError("display: no .rmod recorded for task " + who);
        const RmodFile& f = it->second;
        // A combined task's objects may share a port (NDOF for each): once each.
        auto add = [&](const char* dir, const std::string& v) {
            if (std::none_of(items.begin(), items.end(), [&](const VarItem& x) { return x.name == v && x.dir == dir; }))
                items.push_back({dir, v});
        };
        for (const auto& v : f.global_in_consts()) add("in-const", v);
        for (const auto& v : f.global_out_consts()) add("out-const", v);
        for (const auto& v : f.global_in_vars()) add("in", v);
        for (const auto& v : f.global_out_vars()) add("out", v);
    } else {
        for (std::size_t i = 0; i < t.size(); ++i) items.push_back({"", std::string(t.var(i).name())});
    }
    const std::vector<std::string> patterns(w.begin() + static_cast<std::ptrdiff_t>(k), w.end());
    if (!patterns.empty()) {
        std::vector<VarItem> kept;
        for (const auto& p : patterns) {
            bool any = false;
            for (const auto& it : items) {
                if (!glob_match(p, it.name)) continue;
                any = true;
                const bool dup = std::any_of(kept.begin(), kept.end(),
                                             [&](const VarItem& x) { return x.name == it.name && x.dir == it.dir; });
                if (!dup) kept.push_back(it);
            }
            if (!any)
                throw CommandError("display: no variable matches " + p +
                                   (who.empty() ? " in table " + t.name() : " among the ports of " + who));
        }
        items = std::move(kept);
    }

    return values_reply(t, items, who);
}

Reply values_reply(svar::Table& t, const std::vector<VarItem>& items, const std::string& who) {
    Reply r;
    std::string text = who.empty() ? "SVAR table " + t.name() : who + ":";
    nlohmann::json vars = nlohmann::json::array();
    for (const auto& it : items) {
        const auto ix = t.find(it.name);
        if (!ix) throw CommandError("display: variable " + it.name + " is not in table " + t.name());
        const auto info = t.var(*ix);
        std::vector<unsigned char> buf(info.bytes());
        const auto st = t.read(*ix, buf.data());
        if (!svar::transferred(st))
            throw CommandError("display: reading " + it.name + ": " + svar::to_string(st));
        nlohmann::json jv = {{"name", it.name}, {"type", svar::type_name(info.type())}, {"nelem", info.nelem()},
                             {"units", std::string(info.units())}, {"desc", std::string(info.desc())}};
        if (!it.dir.empty()) jv["dir"] = it.dir;
        std::string values;
        if (info.type() == svar::Type::struct_) {
            values = "(" + std::to_string(info.bytes()) + " bytes)";
            jv["values"] = nullptr;
        } else {
            const auto nums = numbers_of(info, buf.data());
            for (double x : nums) values += (values.empty() ? "" : " ") + fmt("%.6g", x);
            jv["values"] = nums;
        }
        text += "\n  " + (it.dir.empty() ? std::string() : pad(it.dir, 10)) + pad(it.name, 16) + " " +
                pad(type_text(info), 12) + " " + values + (info.units().empty() ? "" : "  " + std::string(info.units()));
        vars.push_back(std::move(jv));
    }
    if (items.empty()) text += "\n  (no variables)";
    r.text = text;
    r.data = {{"rmod", who}, {"vars", vars}};
    return r;
}

// ----------------------------------------------------------------- show, setvar

// The live tasks that write (out-var, out-const) and read (in-var, in-const)
// the global variable `name`.
// ----------------------------------------------------------------- sample

namespace {

double positive_number(const std::string& option, const std::string& text) {
    char* end = nullptr;
    const double v = std::strtod(text.c_str(), &end);
    if (end == text.c_str() || *end != '\0' || !(v > 0) || !std::isfinite(v))
        throw CommandError("sample: " + option + " " + text + " is not a positive number");
    return v;
}

}  // namespace

// Spawns a task from an .rmod made here and turns it on; when `on` is
// refused (verification), the task is killed again and the refusal thrown.
sbs::TaskId Interpreter::spawn_on(const RmodFile& f, const std::string& rtpu) {
    const sbs::TaskId id = sbs_.spawn_parsed({f}, rtpu);
    rmods_[f.name] = f;
    rtpu_of_[f.name] = sbs_.status(id).rtpu;
    try {
        sbs_.control(id, sbs::Control::on);
    } catch (...) {
        try {
            sbs_.control(id, sbs::Control::kill);
        } catch (const std::exception&) {  // the refusal is what the caller needs to see
        }
        rmods_.erase(f.name);
        rtpu_of_.erase(f.name);
        throw;
    }
    return id;
}

// At a task's rate: by default the fastest producer's, so no value it writes is missed.
double Interpreter::producers_rate(const std::vector<std::string>& vars, std::string& why) const {
    double rate = 0;
    for (const auto& v : vars)
        for (const auto& p : users_of(v.substr(0, v.find('['))).producers)
            if (const auto id = sbs_.find(p); id && sbs_.freq_get(*id) > rate) {
                rate = sbs_.freq_get(*id);
                why = "the rate of " + p;
            }
    if (rate > 0) return rate;
    why = "no task produces them";
    return 100;
}

// sample.N for the first N naming neither a task nor a ring (a crashed master's stale ring is removed).
std::string Interpreter::free_sampler_name() {
    for (;;) {
        const std::string name = "sample." + std::to_string(++samplers_made_);
        const std::string ring = ipc::segment_name(sbs_.name(), name);
        if (ipc::Segment::exists(ring) && ipc::Segment::is_stale(ring)) ipc::Segment::unlink(ring);
        if (!is_task(name) && !ipc::Segment::exists(ring)) return name;
    }
}

// The RTPU named by --rtpu, or the MASTER one.
const RtpuSpec& Interpreter::sampler_rtpu(const std::string& name) const {
    const SbsFile& f = sbs_.file();
    const RtpuSpec* spec = f.find_rtpu(name.empty() ? f.master : name);
    if (spec == nullptr && name.empty() && !f.rtpus.empty()) spec = &f.rtpus.front();
    if (spec != nullptr) return *spec;
    std::vector<std::string> names;
    for (const auto& r : f.rtpus) names.push_back(r.name);
    throw CommandError("sample: no RTPU " + name + " in " + f.path + " (RTPUs: " + join(names) + ")");
}

std::set<std::string> Interpreter::tasks_on() const {
    std::set<std::string> on;
    for (const auto& [name, f] : rmods_)
        if (const auto id = sbs_.find(name); id && sbs_.state(*id) == State::ON) on.insert(name);
    return on;
}

// What the RTPU's scheduler counts in its analysis: its ON periodic tasks and
// servers, at their current rates (a task not ON is never released).
std::vector<muf::TaskSpec> Interpreter::analysed_tasks(const std::string& rtpu) const {
    return analysed_tasks(rtpu, tasks_on());
}

// The same with `on` standing for the tasks ON (a reconfig's state part-way).
std::vector<muf::TaskSpec> Interpreter::analysed_tasks(const std::string& rtpu, const std::set<std::string>& on) const {
    std::vector<muf::TaskSpec> out;
    for (const auto& [name, f] : rmods_) {
        const auto where = rtpu_of_.find(name);
        if (!on.count(name) || where == rtpu_of_.end() || where->second != rtpu) continue;
        if (auto t = analysed_spec(name, f)) out.push_back(std::move(*t));
    }
    return out;
}

// Issue #29.2: what a client can start is admitted like a sampler; the owner
// (prompt, -c, the .sbs) may run a task outside it, as the thesis lets the
// operator do (an RTPU's MINFREQ..MAXFREQ only scales criticality, §4.5.1),
// and is told so (docs/permissions.md).
std::string Interpreter::admit(const std::string& what, const std::string& rtpu, const muf::TaskSpec& task, double hz,
                               const std::vector<muf::TaskSpec>* running, const std::string& hint) const {
    const RtpuSpec* spec = sbs_.file().find_rtpu(rtpu);
    if (spec == nullptr) return {};
    const std::string why = running ? admission_problem(*spec, hz, *running, task) : rate_problem(*spec, hz);
    if (why.empty()) return {};
    if (origin_ != Origin::local) throw CommandError(what + " refused: " + why + (hint.empty() ? "" : "; " + hint));
    return "WARNING> " + what + ": " + why + " (run as the owner asked; a client would be refused)";
}

std::string Interpreter::admit_on(const std::string& what, const std::string& name, const std::set<std::string>& on) const {
    const auto f = rmods_.find(name);
    const auto where = rtpu_of_.find(name);
    if (f == rmods_.end() || where == rtpu_of_.end() || on.count(name)) return {};  // ON already: the runtime says so
    const auto task = analysed_spec(name, f->second);
    if (!task) return {};
    const auto running = analysed_tasks(where->second, on);
    return admit(what + " " + name, where->second, *task, f->second.freq, &running);
}

// Each `on` is judged with the items before it applied, so `off a, on b` may
// swap b for a; the first refusal stops the list before anything is sent.
std::string Interpreter::admit_reconfig(const std::vector<std::vector<std::string>>& groups) const {
    std::set<std::string> on = tasks_on();
    std::string warnings;
    for (const auto& g : groups) {
        if (g[0] == "on") {
            const std::string w = admit_on("reconfig on", g[1], on);
            if (!w.empty()) warnings += "\n" + w;
            on.insert(g[1]);
        } else if (g[0] == "off" || g[0] == "kill") {
            on.erase(g[1]);
        }
    }
    return warnings;
}

// A sampler is a task (issue #29.2): its rate within the RTPU's MINFREQ and
// MAXFREQ, and the RTPU's analysis still guaranteeing its critical set with it.
// A refusal names the numbers and the RTPUs that would take it.
void Interpreter::admit_sampler(const RtpuSpec& spec, const std::string& name, double rate, std::size_t channels) const {
    muf::TaskSpec candidate;
    candidate.name = name;
    candidate.period = 1.0 / rate;
    candidate.wcet = sampler_cycle_cost(channels);
    const auto problem = [&](const RtpuSpec& r) { return admission_problem(r, rate, analysed_tasks(r.name), candidate); };
    const std::string why = problem(spec);
    if (why.empty()) return;
    std::vector<std::string> others;
    for (const RtpuSpec& r : sbs_.file().rtpus)
        if (r.name != spec.name && problem(r).empty()) others.push_back(r.name);
    throw CommandError("sample refused: " + why + "; " +
                       (others.empty() ? "no RTPU takes it at " + cfg::number_text(rate) + " Hz: choose another --rate"
                                       : "--rtpu " + join(others, " or --rtpu ") + " takes it"));
}

// The ring's entries as the sampler module makes them: CAPACITY rounded up to
// a power of two, or 10 s at the rate (modules/sampler/sampler.cpp).
std::size_t Interpreter::ring_entries(const std::string& capacity, double rate) {
    if (capacity.empty()) return sampler::capacity_for(rate, 10.0);
    const double wanted = std::strtod(capacity.c_str(), nullptr);
    std::size_t entries = 2;
    while (static_cast<double>(entries) < wanted && entries < sampler::kMaxCapacity) entries *= 2;
    return entries;
}

// What clients (network peers, web pages) may make the master allocate in
// sampler rings, per ring and in all (docs/permissions.md): past a bound the
// request is refused, never shrunk.
void Interpreter::bound_client_rings(std::size_t bytes) {
    for (auto it = client_rings_.begin(); it != client_rings_.end();)
        it = is_task(it->first) ? std::next(it) : client_rings_.erase(it);  // killed since
    std::size_t total = 0;
    for (const auto& [name, b] : client_rings_) total += b;
    const auto mib = [](std::size_t b) { return fmt("%.1f MiB", static_cast<double>(b) / (1 << 20)); };
    if (bytes > kMaxClientRingBytes)
        throw CommandError("sample refused: its ring would take " + mib(bytes) + ", over the " + mib(kMaxClientRingBytes) +
                           " a client's ring may have (fewer channels, a lower --rate or a smaller --capacity)");
    if (client_rings_.size() >= kMaxClientSamplers)
        throw CommandError("sample refused: clients already run " + std::to_string(client_rings_.size()) +
                           " samplers, the most they may (kill one first)");
    if (total + bytes > kMaxClientRingsBytes)
        throw CommandError("sample refused: clients' rings already take " + mib(total) + "; with " + mib(bytes) +
                           " more they would pass the " + mib(kMaxClientRingsBytes) + " all clients' rings may have");
}

Reply Interpreter::cmd_sample(const Words& w) {
    std::vector<std::string> vars;
    std::string rtpu, capacity;
    double rate = 0;
    for (std::size_t i = 1; i < w.size(); ++i) {
        const bool has_value = i + 1 < w.size();
        if (w[i] == "--rate" && has_value) rate = positive_number("--rate", w[++i]);
        else if (w[i] == "--rtpu" && has_value) rtpu = w[++i];
        else if (w[i] == "--capacity" && has_value) capacity = std::to_string(static_cast<long>(positive_number("--capacity", w[++i])));
        else if (w[i].rfind("--", 0) == 0) throw CommandError("sample: unknown option " + w[i] + " (--rate HZ, --rtpu RTPU, --capacity N)");
        else vars.push_back(w[i]);
    }
    if (vars.empty()) throw CommandError("usage: sample VAR[IDX]... [--rate HZ] [--rtpu RTPU] [--capacity N]");
    const std::vector<sampler::Channel> channels = sampler::parse_channels(*table(), vars);
    std::string rate_from = "given";
    if (rate == 0) rate = producers_rate(vars, rate_from);
    if (const std::string why = frequency_problem(rate); !why.empty()) throw CommandError("sample: " + why);
    const RtpuSpec& spec = sampler_rtpu(rtpu);
    const std::size_t ring_bytes = sampler::required_size(channels.size(), ring_entries(capacity, rate));
    if (origin_ != Origin::local) bound_client_rings(ring_bytes);
    const std::string name = free_sampler_name();
    admit_sampler(spec, name, rate, channels.size());
    RmodFile f;
    f.name = name;
    f.module = "sampler";
    f.desc = "sampler (the sample command)";
    f.type = TaskType::periodic;
    f.freq = rate;
    f.period = 1.0 / rate;
    f.local.file = "sample command";
    f.local.set("CHANNELS", vars);
    f.local.set("RING", {name});
    if (!capacity.empty()) f.local.set("CAPACITY", {capacity});
    const auto s = sbs_.status(spawn_on(f, spec.name));
    // Counted from now on as it was admitted: the .rmod the runtime got has no WCET.
    rmods_[name].wcet = sampler_cycle_cost(channels.size());
    if (origin_ != Origin::local) client_rings_[name] = ring_bytes;
    const std::string ring = ipc::segment_name(sbs_.name(), name);
    const sampler::RingReader reader = sampler::RingReader::attach(ring);
    std::vector<std::string> names;
    for (const auto& c : channels) names.push_back(c.name);
    Reply r;
    r.text = name + ": sampling " + std::to_string(names.size()) + " channel(s) (" + join(names) + ") at " +
             cfg::number_text(rate) + " Hz (" + rate_from + ") on RTPU " + s.rtpu + " into " + ring + " (" +
             std::to_string(reader.capacity()) + " entries); `kill " + name + "` stops it";
    r.data = {{"rmod", name}, {"ring", ring}, {"channels", names}, {"rate", rate},
              {"capacity", reader.capacity()}, {"rtpu", s.rtpu}};
    return r;
}

// ----------------------------------------------------------------- peer

Reply Interpreter::cmd_peer(const Words& w) {
    constexpr const char* kUsage = "usage: peer NAME --pid PID [--out VAR...] [--in VAR...] [--program TEXT...]";
    if (w.size() < 2 || w[1].rfind("--", 0) == 0) throw CommandError(kUsage);
    const std::string name = w[1];
    std::vector<std::string> out, in, program, pid;
    std::vector<std::string>* list = nullptr;
    for (std::size_t i = 2; i < w.size(); ++i) {
        if (w[i] == "--out") list = &out;
        else if (w[i] == "--in") list = &in;
        else if (w[i] == "--pid") list = &pid;
        else if (w[i] == "--program") list = &program;
        else if (!list || (list != &program && w[i].rfind("--", 0) == 0)) throw CommandError(kUsage);
        else list->push_back(w[i]);
    }
    if (pid.size() != 1) throw CommandError(kUsage);
    if (out.empty() && in.empty()) throw CommandError("peer " + name + ": it produces (--out) or consumes (--in) nothing");
    if (is_task(name)) throw CommandError("peer: task " + name + " already exists (kill it first)");
    if (name.find_first_of("+/ ") != std::string::npos) throw CommandError("peer: NAME " + name + " may not hold + / or blanks");
    RmodFile f;
    f.name = name;
    f.module = std::string(sbs::kPeerModule);
    f.desc = "peer process " + pid[0];
    f.type = TaskType::background;
    f.in_vars = in;
    f.out_vars = out;
    f.local.file = "peer command";
    f.local.set("PID", pid);
    if (!program.empty()) f.local.set("PROGRAM", program);
    (void)spawn_on(f, {});  // §3.3.1: refused when another task produces one of `out`
    Reply r;
    r.text = name + ": peer process " + pid[0] + " ON, producing " + (out.empty() ? "nothing" : join(out)) +
             ", consuming " + (in.empty() ? "nothing" : join(in));
    r.data = {{"rmod", name}, {"state", "ON"}, {"pid", std::stol(pid[0])}, {"produces", out}, {"consumes", in}};
    return r;
}

void Interpreter::check_peers() {
    for (const auto& [name, f] : rmods_) {
        if (f.module != sbs::kPeerModule) continue;
        const long pid = static_cast<long>(f.local.number("PID", 0));
        if (pid <= 0 || ::kill(static_cast<pid_t>(pid), 0) == 0 || errno == EPERM) continue;
        const auto id = sbs_.find(name);
        if (!id || sbs_.state(*id) != State::ON) continue;
        sbs_.event(*id);  // its cycle finds the process gone: ERROR
        for (int i = 0; i < 200 && sbs_.state(*id) == State::ON; ++i)
            std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
}

Interpreter::Users Interpreter::users_of(const std::string& name) const {
    Users u;
    for (const auto& [task, f] : rmods_) {
        auto has = [&](const std::vector<std::string>& v) { return std::find(v.begin(), v.end(), name) != v.end(); };
        if (has(f.global_out_vars()) || has(f.global_out_consts())) u.producers.push_back(task);
        if (has(f.global_in_vars()) || has(f.global_in_consts())) u.consumers.push_back(task);
    }
    return u;
}

namespace {

// What `show` shows: its parser, `show` alone and TAB completion read this table.
struct ShowTopic {
    const char* name;
    const char* usage;
    const char* what;
};
constexpr ShowTopic kShowTopics[] = {
    {"rtpu", "show rtpu [NAME...]", "the RTPUs: CPU, scheduler, backend, tasks, planned utilisation"},
    {"svar", "show svar [VAR...]", "the variables with the tasks producing and consuming them"},
    {"graph", "show graph", "the port graph and the problems of the tasks ON"},
};

bool is_show_topic(const std::string& word) {
    return std::any_of(std::begin(kShowTopics), std::end(kShowTopics), [&](const ShowTopic& t) { return word == t.name; });
}

// `show` alone: what it can show, one line each.
Reply show_topics_reply() {
    Reply r;
    r.text = "show what:";
    std::vector<std::string> names;
    for (const auto& t : kShowTopics) {
        r.text += "\n  " + pad(t.usage, 22) + " " + t.what;
        names.push_back(t.name);
    }
    r.data = {{"topics", names}};
    return r;
}

}  // namespace

Reply Interpreter::cmd_show(const Words& w) {
    if (w.size() == 1) return show_topics_reply();
    if (!is_show_topic(w[1]) || (w[1] == "graph" && w.size() > 2))
        throw CommandError("usage: show rtpu|svar|graph [NAME...] (show alone lists them)");
    if (w[1] == "graph") return show_graph();
    const std::vector<std::string> names(w.begin() + 2, w.end());
    auto wanted = [&](const std::string& n) {
        return names.empty() || std::any_of(names.begin(), names.end(), [&](const std::string& p) { return glob_match(p, n); });
    };
    Reply r;
    if (w[1] == "rtpu") {
        static constexpr const char* kSched[] = {"RM", "EDF", "MUF"};
        static constexpr const char* kBackend[] = {"fifo", "deadline", "other"};
        std::string text = "RTPU         CPU  SCHED BACKEND  USAGE      U(plan)  RANKING              TASKS";
        nlohmann::json rtpus = nlohmann::json::array();
        const std::vector<sbs::RtpuRanking> rankings = sbs_.rtpu_ranking();
        for (std::size_t ri = 0; ri < sbs_.file().rtpus.size(); ++ri) {
            const RtpuSpec& spec = sbs_.file().rtpus[ri];
            if (!wanted(spec.name)) continue;
            const sbs::RtpuRanking& rk = rankings.at(ri);
            // Static: each task keeps one priority. Dynamic: re-ranked at each
            // release; "prio N" counts the priority changes that needed.
            const std::string ranking =
                rk.mode == "dynamic" ? fmt("dynamic prio %llu", static_cast<unsigned long long>(rk.priority_changes))
                                     : rk.mode;
            std::vector<std::string> tasks;
            double planned = 0;  // sum of WCET x frequency: the analysis's C/T (0 for a task without WCET)
            for (const auto& [task, rtpu] : rtpu_of_) {
                if (rtpu != spec.name || !rmods_.count(task)) continue;
                tasks.push_back(task);
                const RmodFile& f = rmods_.at(task);
                planned += f.wcet * f.freq;
            }
            const std::string sched = kSched[static_cast<int>(spec.scheduler)];
            const std::string backend = kBackend[static_cast<int>(spec.backend)];
            const std::string usage = spec.usage == Usage::exclusive ? "exclusive" : "shared";
            text += "\n" + pad(spec.name, 12) + " " + pad(std::to_string(spec.cpu), 4) + " " + pad(sched, 5) + " " +
                    pad(backend, 8) + " " + pad(usage, 10) + " " + pad(fmt("%.1f%%", planned * 100), 8) + " " +
                    pad(ranking, 20) + " " + (tasks.empty() ? std::string("-") : join(tasks));
            rtpus.push_back({{"name", spec.name}, {"cpu", spec.cpu}, {"scheduler", sched}, {"backend", backend},
                             {"usage", usage}, {"minfreq", spec.minfreq}, {"maxfreq", spec.maxfreq},
                             {"master", spec.name == sbs_.file().master}, {"tasks", tasks},
                             {"planned_utilisation", planned},
                             {"ranking", rk.mode},
                             {"reschedules", rk.reschedules}, {"priority_changes", rk.priority_changes}});
        }
        text += "\n(U(plan): sum of WCET x FREQ of the tasks' .rmod files; measured CPU times are in `status`."
                "\n RANKING: static, each task keeps one priority; dynamic, re-ranked at every release, with the"
                "\n priority changes that took so far; best-effort, no real-time priorities: docs/muf.md)";
        r.text = text;
        r.data = {{"rtpus", rtpus}};
        return r;
    }
    svar::Table& t = *table();
    std::string text = pad("VARIABLE", 16) + " " + pad("TYPE", 12) + " " + pad("PRODUCERS", 16) + " CONSUMERS";
    nlohmann::json vars = nlohmann::json::array();
    for (std::size_t i = 0; i < t.size(); ++i) {
        const auto info = t.var(i);
        const std::string name(info.name());
        if (!wanted(name)) continue;
        const Users u = users_of(name);
        text += "\n" + pad(name, 16) + " " + pad(type_text(info), 12) + " " +
                pad(u.producers.empty() ? std::string("(.svar INIT)") : join(u.producers), 16) + " " +
                (u.consumers.empty() ? std::string("-") : join(u.consumers));
        vars.push_back({{"name", name}, {"type", type_text(info)}, {"units", std::string(info.units())},
                        {"producers", u.producers}, {"consumers", u.consumers}});
    }
    r.text = text;
    r.data = {{"vars", vars}};
    return r;
}

// The port graph (§3.3, Fig 3.7): every live task with its RTPU, state and
// ports, every variable with its producers and consumers, and what §3.3.1
// verification says of the tasks ON now (the web console draws this).
Reply Interpreter::show_graph() {
    nlohmann::json tasks = nlohmann::json::array();
    std::vector<sbs::TaskId> on;
    std::string text;
    for (const auto& [name, f] : rmods_) {
        const auto id = sbs_.find(name);
        if (!id) continue;
        const State state = sbs_.state(*id);
        if (state == State::ON) on.push_back(*id);
        const auto rtpu = rtpu_of_.find(name);
        tasks.push_back({{"rmod", name}, {"module", f.module}, {"rtpu", rtpu == rtpu_of_.end() ? "" : rtpu->second},
                         {"state", std::string(chimera::to_string(state))}, {"freq", f.freq},
                         {"in", f.global_in_vars()}, {"in_const", f.global_in_consts()},
                         {"out", f.global_out_vars()}, {"out_const", f.global_out_consts()}});
        text += (text.empty() ? "" : "\n") + pad(name, 16) + " " + pad(std::string(chimera::to_string(state)), 11) + " " +
                join(f.global_in_vars()) + " -> " + join(f.global_out_vars());
    }
    svar::Table& t = *table();
    nlohmann::json vars = nlohmann::json::array();
    for (std::size_t i = 0; i < t.size(); ++i) {
        const std::string name(t.var(i).name());
        const Users u = users_of(name);
        vars.push_back({{"name", name}, {"type", type_text(t.var(i))}, {"producers", u.producers},
                        {"consumers", u.consumers}});
    }
    nlohmann::json problems = nlohmann::json::array();
    for (const auto& p : sbs_.verification_problems(on)) {
        problems.push_back({{"kind", p.kind == sbs::VerifyProblem::Kind::two_producers ? "two_producers" : "no_producer"},
                            {"var", p.variable}, {"tasks", p.tasks}, {"message", p.message}});
        text += "\n" + p.message;
    }
    nlohmann::json rtpus = nlohmann::json::array();
    for (const auto& spec : sbs_.file().rtpus) rtpus.push_back(spec.name);
    Reply r;
    r.text = text.empty() ? "no task spawned" : text;
    r.data = {{"subsystem", sbs_.name()}, {"master", sbs_.file().master}, {"rtpus", rtpus}, {"tasks", tasks},
              {"vars", vars}, {"problems", problems}, {"illegal_configuration", sbs_.illegal_configuration()}};
    return r;
}

Reply Interpreter::cmd_setvar(const Words& w) {
    std::vector<std::string> args(w.begin() + 1, w.end());
    const auto force_at = std::find(args.begin(), args.end(), "--force");
    const bool force = force_at != args.end();
    if (force) args.erase(force_at);
    if (args.size() < 2) throw CommandError("usage: setvar VAR[IDX] VALUE... [--force]");
    std::string name = args[0];
    std::optional<std::size_t> index;
    if (const auto open = name.find('['); open != std::string::npos) {
        char* end = nullptr;
        const unsigned long k = std::strtoul(name.c_str() + open + 1, &end, 10);
        if (end == name.c_str() + open + 1 || std::string_view(end) != "]")
            throw CommandError("setvar: '" + name + "' is not VAR or VAR[INDEX]");
        index = k;
        name.erase(open);
    }
    svar::Table& t = *table();
    const auto ix = t.find(name);
    if (!ix) throw CommandError("setvar: no variable " + name + " in table " + t.name());
    const auto info = t.var(*ix);
    if (info.type() == svar::Type::struct_) throw CommandError("setvar: " + name + " is a struct; it cannot be written from here");
    const std::size_t first = index.value_or(0);
    const std::size_t count = args.size() - 1;
    if (index && *index >= info.nelem())
        throw CommandError("setvar: " + name + " has " + std::to_string(info.nelem()) + " elements; index " +
                           std::to_string(*index) + " is out of range");
    if (first + count > info.nelem())
        throw CommandError("setvar: " + name + " has " + std::to_string(info.nelem()) + " elements; " +
                           std::to_string(count) + " values from index " + std::to_string(first) + " do not fit");
    if (!index && count != info.nelem() && count != 1)
        throw CommandError("setvar: " + name + " has " + std::to_string(info.nelem()) +
                           " elements: give one value for all, every value, or VAR[INDEX]");
    const Users u = users_of(name);
    if (!u.producers.empty() && !force)
        throw CommandError("setvar: " + name + " is produced by " + join(u.producers) +
                           ": its next cycle overwrites it (add --force to write it anyway)");
    std::vector<unsigned char> buf(info.bytes());
    if (!svar::transferred(t.read(*ix, buf.data()))) throw CommandError("setvar: reading " + name + " failed");
    const std::size_t n = (!index && count == 1) ? info.nelem() : count;
    for (std::size_t j = 0; j < n; ++j) {
        const std::string& text = args[1 + (count == 1 ? 0 : j)];
        const std::size_t k = first + j;
        char* end = nullptr;
        const double x = std::strtod(text.c_str(), &end);
        if (end == text.c_str() || *end != '\0' || !std::isfinite(x))
            throw CommandError("setvar: " + name + "[" + std::to_string(k) + "]: '" + text + "' is not a number");
        if (const std::string why = tools::value_refusal(info, k, x); !why.empty())
            throw CommandError("setvar: " + name + "[" + std::to_string(k) + "]: " + text + " " + why);
        tools::store_number(info, buf.data(), k, x);
    }
    if (!svar::transferred(t.write(*ix, buf.data()))) throw CommandError("setvar: writing " + name + " failed");
    const auto now = numbers_of(info, buf.data());
    std::string values;
    for (double x : now) values += (values.empty() ? "" : " ") + fmt("%.6g", x);
    Reply r;
    r.text = name + " = " + values + (u.producers.empty() ? "" : "  (forced; produced by " + join(u.producers) + ")");
    r.data = {{"name", name}, {"values", now}, {"forced", !u.producers.empty()}, {"producers", u.producers}};
    return r;
}

Reply Interpreter::module_load(const Words& w) {
    if (w.size() != 3) throw CommandError("usage: module load PATH");
    if (origin_ != Origin::local)
        throw CommandError("module load: over the network no library is loaded from a path; only the master's own "
                           "prompt or -c may (the module path it was started with serves the network)");
    const std::string name = sbs_.load_module(w[2]);
    const std::string dir = fs::absolute(w[2]).parent_path().string();
    if (std::find(extra_dirs_.begin(), extra_dirs_.end(), dir) == extra_dirs_.end()) extra_dirs_.push_back(dir);
    Reply r;
    r.text = "module " + name + " loaded from " + w[2] + "; " + dir + " is on the module path";
    r.data = {{"module", name}, {"path", w[2]}, {"dir", dir}};
    return r;
}

Reply Interpreter::cmd_module(const Words& w) {
    if (w.size() >= 2 && w[1] == "load") return module_load(w);
    if (w.size() > 2) throw CommandError("usage: module [NAME] | module load PATH");
    const auto dirs = module_path();
    std::map<std::string, std::string> modules, rmod_files;
    scan_dirs(dirs, modules, rmod_files);
    Reply r;
    if (w.size() == 1) {
        std::string text = "modules on the module path:";
        nlohmann::json jm = nlohmann::json::array(), jr = nlohmann::json::array();
        for (const auto& [name, path] : modules) {
            text += "\n  " + pad(name, 14) + " " + path;
            jm.push_back({{"name", name}, {"path", path}});
        }
        if (modules.empty()) text += "\n  (none)";
        text += "\nrmod files:";
        for (const auto& [name, path] : rmod_files) {
            std::string module, desc;
            try {
                const auto f = read_rmod(path);
                module = f.module;
                desc = f.desc;
            } catch (const std::exception& e) {
                desc = std::string("unreadable: ") + e.what();
            }
            text += "\n  " + pad(name, 14) + " MODULE " + pad(module, 10) + " " + desc;
            jr.push_back({{"name", name}, {"module", module}, {"desc", desc}, {"path", path}});
        }
        if (rmod_files.empty()) text += "\n  (none)";
        r.text = text;
        r.data = {{"path", dirs}, {"modules", jm}, {"rmods", jr}};
        return r;
    }

    // One name: an .rmod (its ports and LOCAL keys), or a module (every .rmod using it).
    const std::string& name = w[1];
    std::vector<std::string> files;
    if (const auto p = find_rmod_file(name)) {
        files.push_back(*p);
    } else {
        for (const auto& [n, path] : rmod_files) {
            try {
                if (read_rmod(path).module == name) files.push_back(path);
            } catch (const std::exception&) {
            }
        }
        if (files.empty() && !modules.count(name))
            throw CommandError("module: no module or .rmod named " + name + " on the module path (" +
                               join(dirs, ":") + ")");
    }
    std::string text;
    if (files.empty()) text = "module " + name + " (" + modules[name] + "): no .rmod file uses it";
    svar::Table* tbl = nullptr;
    try {
        tbl = table();
    } catch (const std::exception&) {
    }
    nlohmann::json jr = nlohmann::json::array();
    for (const auto& path : files) {
        const RmodFile f = read_rmod(path);
        if (!text.empty()) text += "\n";
        text += "rmod " + f.name + " (" + path + "): MODULE " + f.module + (modules.count(f.module) ? "" : " (no .so found)") +
                "\n  " + f.desc + "\n  " + std::string(to_string(f.type)) +
                (f.freq > 0 ? ", " + fmt("%g", f.freq) + " Hz" : std::string());
        nlohmann::json ports = nlohmann::json::object();
        auto list = [&](const char* label, const std::vector<std::string>& internal) {
            nlohmann::json jp = nlohmann::json::array();
            text += "\n  " + pad(label, 10);
            if (internal.empty()) text += "none";
            for (const auto& port : internal) {
                const std::string global = f.global_name(port);
                std::string desc = global == port ? port : port + "=" + global;
                nlohmann::json j = {{"port", port}, {"svar", global}};
                if (tbl) {
                    if (const auto ix = tbl->find(global)) {
                        const auto info = tbl->var(*ix);
                        desc += " (" + type_text(info) + (info.units().empty() ? "" : ", " + std::string(info.units())) + ")";
                        j["type"] = type_text(info);
                        j["units"] = std::string(info.units());
                    } else {
                        desc += " (not in the SVAR table)";
                    }
                }
                text += desc + " ";
                jp.push_back(std::move(j));
            }
            ports[label] = std::move(jp);
        };
        list("in-const", f.in_consts);
        list("out-const", f.out_consts);
        list("in-var", f.in_vars);
        list("out-var", f.out_vars);
        nlohmann::json local = nlohmann::json::object();
        text += "\n  LOCAL";
        if (f.local.entries().empty()) text += "    none";
        for (const auto& e : f.local.entries()) {
            text += "\n    " + pad(e.key, 12) + " " + join(e.values);
            local[e.key] = join(e.values);
        }
        jr.push_back({{"name", f.name}, {"path", path}, {"module", f.module}, {"desc", f.desc},
                      {"tasktype", std::string(to_string(f.type))}, {"freq", f.freq}, {"ports", ports},
                      {"local", local}});
    }
    r.text = text;
    r.data = {{"name", name}, {"rmods", jr}};
    return r;
}

Reply Interpreter::cmd_reconfig(const Words& w) {
    // reconfig on a, off b  |  reconfig on a , off b: commas separate items.
    // --check: verify the configuration the list would leave, send nothing
    // (the web console shows a refusal before anything changes).
    const bool check_only = w.size() > 1 && w[1] == "--check";
    std::vector<std::vector<std::string>> groups(1);
    for (std::size_t i = check_only ? 2 : 1; i < w.size(); ++i) {
        std::string word = w[i];
        while (!word.empty()) {
            const auto comma = word.find(',');
            const std::string part = word.substr(0, comma);
            if (!part.empty()) groups.back().push_back(part);
            if (comma == std::string::npos) break;
            groups.emplace_back();
            word.erase(0, comma + 1);
        }
    }
    if (groups.back().empty()) groups.pop_back();
    if (groups.empty()) throw CommandError("usage: reconfig SIG RMOD [, SIG RMOD ...]");
    std::vector<sbs::ReconfigItem> items;
    std::vector<std::string> names;
    for (std::size_t i = 0; i < groups.size(); ++i) {
        const auto& g = groups[i];
        if (g.size() != 2 || !is_signal_word(g[0]))
            throw CommandError("reconfig: item " + std::to_string(i) + " '" + join(g) +
                               "' is not SIG RMOD (SIG: on off kill clear); nothing was sent");
        const auto id = sbs_.find(g[1]);
        if (!id) throw CommandError("reconfig: item " + std::to_string(i) + ": no task " + g[1] + "; nothing was sent");
        if (g[0] == "on") refuse_file_writer("reconfig on", g[1], sbs_.local_keys(*id));
        items.emplace_back(*id, signal_of(g[0]));
        names.push_back(g[0] + " " + g[1]);
    }
    const std::string warnings = admit_reconfig(groups);
    if (check_only) return reconfig_check(items, names);
    make_default(groups.back()[1]);
    const auto res = sbs_.reconfig(std::span<const sbs::ReconfigItem>(items));
    for (std::size_t i = 0; i < items.size(); ++i)
        if (items[i].signal == sbs::Control::kill && sbs_.status(items[i].task).state == State::NOT_CREATED)
            forget_task(groups[i][1]);
    Reply r;
    nlohmann::json applied = nlohmann::json::array();
    for (std::size_t i = 0; i < res.processed; ++i) applied.push_back(names[i]);
    if (!res) {
        r = Reply::failure("reconfig", "reconfig stopped at " + res.message + " (" + std::to_string(res.processed) +
                                           " of " + std::to_string(items.size()) + " items applied)");
        r.data = {{"applied", applied}, {"failed", res.failed}};
        return r;
    }
    r.text = "reconfig: " + std::to_string(res.processed) + " items applied: " + join(names, ", ") + warnings;
    r.data = {{"applied", applied}};
    if (!warnings.empty()) r.data["admission"] = warnings.substr(1);
    return r;
}

Reply Interpreter::reconfig_check(const std::vector<sbs::ReconfigItem>& items, const std::vector<std::string>& names) {
    const auto problems = sbs_.reconfig_problems(std::span<const sbs::ReconfigItem>(items));
    nlohmann::json jp = nlohmann::json::array();
    for (const auto& p : problems)
        jp.push_back({{"kind", p.kind == sbs::VerifyProblem::Kind::two_producers ? "two_producers" : "no_producer"},
                      {"var", p.variable}, {"tasks", p.tasks}, {"message", p.message}});
    Reply r;
    if (!problems.empty()) {
        // The words reconfig itself would refuse with.
        r = Reply::failure("reconfig", "reconfig refused: verification before any item was sent: " +
                                           problems.front().message + " (nothing sent: --check)");
    } else {
        r.text = "reconfig --check: " + join(names, ", ") + " verifies (nothing sent)";
    }
    r.data = {{"items", names}, {"verifies", problems.empty()}, {"problems", jp}};
    return r;
}

// Events to aperiodic servers (Subsystem::event): refused, naming the task,
// for a task the runtime would not serve them to, so none is silently dropped.
Reply Interpreter::cmd_event(const Words& w) {
    if (w.size() > 3) throw CommandError("usage: event [RMOD] [COUNT]");
    std::string rmod;
    std::string count_text = "1";
    if (w.size() == 3) {
        rmod = w[1];
        count_text = w[2];
    } else if (w.size() == 2) {
        (is_task(w[1]) ? rmod : count_text) = w[1];
    }
    const sbs::TaskId id = task_of(rmod);
    char* end = nullptr;
    const long count = std::strtol(count_text.c_str(), &end, 10);
    if (end == count_text.c_str() || *end != '\0' || count < 1 || count > 1000)
        throw CommandError("event: '" + count_text + "' is not a count of events (1 to 1000)");
    const auto file = rmods_.find(default_rmod_);
    if (file != rmods_.end() && !is_aperiodic(file->second.type))
        throw CommandError("event refused for task " + default_rmod_ + ": it is " +
                           std::string(to_string(file->second.type)) +
                           "; events go to aperiodic tasks (TASKTYPE sporadic, deferrable or background)");
    if (const State st = sbs_.state(id); st != State::ON)
        throw CommandError("event refused for task " + default_rmod_ + ": it is not ON (state " +
                           std::string(to_string(st)) + ")");
    for (long k = 0; k < count; ++k) sbs_.event(id);
    Reply r;
    r.text = default_rmod_ + ": " + std::to_string(count) + (count == 1 ? " event" : " events");
    r.data = {{"rmod", default_rmod_}, {"events", count}};
    return r;
}

Reply Interpreter::cmd_freq(const Words& w) {
    if (w.size() > 3) throw CommandError("usage: freq [RMOD] [HZ]");
    std::string rmod;
    std::string hz;
    if (w.size() == 3) {
        rmod = w[1];
        hz = w[2];
    } else if (w.size() == 2) {
        (is_task(w[1]) ? rmod : hz) = w[1];
    }
    const sbs::TaskId id = task_of(rmod);
    std::string warning;
    if (!hz.empty()) {
        char* end = nullptr;
        const double v = std::strtod(hz.c_str(), &end);
        if (end == hz.c_str() || *end != '\0' || !(v > 0) || !std::isfinite(v))
            throw CommandError("freq: '" + hz + "' is not a frequency in Hz (a positive number)");
        if (frequency_problem(v).empty()) warning = admit_freq(default_rmod_, v);  // else freq_set says why
        sbs_.freq_set(id, v);
        if (auto f = rmods_.find(default_rmod_); f != rmods_.end()) {  // the rate the analysis counts from now
            f->second.freq = v;
            f->second.period = 1.0 / v;
        }
    }
    const double now = sbs_.freq_get(id);
    Reply r;
    r.text = default_rmod_ + " " + fmt("%g", now) + " Hz" + (warning.empty() ? "" : "\n" + warning);
    r.data = {{"rmod", default_rmod_}, {"freq", now}};
    if (!warning.empty()) r.data["admission"] = warning;
    return r;
}

// A task ON is judged at `hz` beside the others ON; one not ON only by its
// rate (its `on` runs the analysis).
std::string Interpreter::admit_freq(const std::string& name, double hz) const {
    const auto f = rmods_.find(name);
    const auto where = rtpu_of_.find(name);
    if (f == rmods_.end() || where == rtpu_of_.end()) return {};
    RmodFile at = f->second;
    at.freq = hz;
    const auto task = analysed_spec(name, at);
    if (!task) return {};
    std::set<std::string> on = tasks_on();
    if (!on.erase(name)) return admit("freq " + name, where->second, *task, hz, nullptr);
    const auto running = analysed_tasks(where->second, on);
    return admit("freq " + name, where->second, *task, hz, &running);
}

Reply Interpreter::cmd_help(const Words& w) {
    Reply r;
    if (w.size() > 1) {
        for (const auto& c : command_table()) {
            if (w[1] == c.name) {
                r.text = std::string(c.usage) + "\n  " + c.help;
                if (w[1] == "status") r.text += "\n  fields: " + join(status_field_names());
                return r;
            }
        }
        throw CommandError("help: unknown command '" + w[1] + "'");
    }
    std::string text = "commands (the RMOD defaults to the one named last, shown in the prompt):";
    for (const auto& c : command_table()) text += "\n  " + pad(c.usage, 34) + " " + c.help;
    r.text = text;
    return r;
}

// ----------------------------------------------------------------- completion

std::vector<std::string> Interpreter::complete(std::string_view line) {
    std::lock_guard lock(mutex_);
    return complete_locked(line);
}

std::vector<std::string> Interpreter::complete_locked(std::string_view line) {
    // Words so far; the last one is being typed (empty after a space).
    std::vector<std::string> words;
    {
        std::string cur;
        for (char c : line) {
            if (c == ' ' || c == '\t') {
                if (!cur.empty()) words.push_back(cur);
                cur.clear();
            } else if (c == ';') {
                words.clear();
                cur.clear();
            } else {
                cur += c;
            }
        }
        words.push_back(cur);
    }
    const std::string prefix = words.back();
    const std::size_t index = words.size() - 1;
    std::set<std::string> cand;
    auto add = [&](const std::vector<std::string>& v) { cand.insert(v.begin(), v.end()); };
    auto variables = [&] {
        try {
            svar::Table& t = *table();
            for (std::size_t i = 0; i < t.size(); ++i) cand.emplace(t.var(i).name());
        } catch (const std::exception&) {
        }
    };
    try {
        if (index == 0) {
            for (const auto& c : command_table()) cand.insert(c.name);
        } else {
            const std::string& c = words[0];
            if (c == "help" && index == 1) {
                for (const auto& x : command_table()) cand.insert(x.name);
            } else if ((c == "on" || c == "off" || c == "kill" || c == "clear" || c == "freq" || c == "event") && index == 1) {
                add(live_rmods());
            } else if (c == "status") {
                if (index == 1) {
                    add(live_rmods());
                    cand.insert({"all", "reset", "set"});
                } else if (words[1] == "set") {
                    add(status_field_names());
                    if (index == 2) cand.insert({"default", "all"});
                }
            } else if (c == "display") {
                if (index == 1) {
                    add(live_rmods());
                    cand.insert("all");
                }
                variables();
            } else if (c == "set") {
                if (index == 1) {
                    add(live_rmods());
                    add(local_keys(default_rmod_));
                } else if (index == 2 && is_task(words[1])) {
                    add(local_keys(words[1]));
                }
            } else if (c == "spawn" || c == "module") {
                if (index == 1) {
                    std::map<std::string, std::string> modules, rmod_files;
                    scan_dirs(module_path(), modules, rmod_files);
                    for (const auto& [n, p] : rmod_files) cand.insert(n);
                    if (c == "module")
                        for (const auto& [n, p] : modules) cand.insert(n);
                } else if (index == 2 && c == "spawn") {
                    for (const auto& r : sbs_.file().rtpus) cand.insert(r.name);
                }
            } else if (c == "show") {
                if (index == 1)
                    for (const auto& t : kShowTopics) cand.insert(t.name);
                else if (words[1] == "svar") variables();
                else if (words[1] == "rtpu") for (const auto& r : sbs_.file().rtpus) cand.insert(r.name);
            } else if (c == "setvar") {
                if (index == 1) variables();
                else cand.insert("--force");
            } else if (c == "sample" || c == "record" || c == "peer") {
                if (index >= 2 && words[index - 1] == "--rtpu") {
                    for (const auto& r : sbs_.file().rtpus) cand.insert(r.name);
                } else if (c != "peer" || index >= 2) {
                    variables();
                    if (c == "sample") cand.insert({"--rate", "--rtpu", "--capacity"});
                    if (c == "record") cand.insert({"--rate", "--rtpu"});
                    if (c == "peer") cand.insert({"--pid", "--out", "--in", "--program"});
                }
            } else if (c == "reconfig") {
                // Alternating SIG RMOD; a comma starts a new item.
                std::size_t pos = 0;
                for (std::size_t i = 1; i < index; ++i) {
                    for (char ch : words[i])
                        if (ch == ',') pos = 0;
                    if (!words[i].empty() && words[i] != ",") pos = words[i].back() == ',' ? 0 : pos + 1;
                }
                if (pos % 2 == 0) {
                    cand.insert({"on", "off", "kill", "clear"});
                } else {
                    add(live_rmods());
                }
            }
        }
    } catch (const std::exception&) {
        // Completion never reports errors; it just offers nothing more.
    }
    std::vector<std::string> out;
    for (const auto& s : cand)
        if (s.compare(0, prefix.size(), prefix) == 0) out.push_back(s);
    return out;
}

}  // namespace chimera::cli

namespace chimera::cli {

// ----------------------------------------------------------------- save, TASK lines

Reply Interpreter::start_tasks() {
    const SbsFile& f = sbs_.file();
    std::vector<std::string> spawned, to_turn_on;
    std::string warnings;  // the owner's tasks admission would refuse a client (docs/permissions.md)
    const auto warned = [&](const Reply& r) {
        if (r.data.is_object() && r.data.contains("admission")) warnings += "\n" + r.data["admission"].get<std::string>();
    };
    auto fail = [&](int line, const std::string& why) {
        for (auto it = spawned.rbegin(); it != spawned.rend(); ++it) execute("kill " + *it);
        return Reply::failure("start", f.path + ":" + std::to_string(line) + ": " + why);
    };
    for (const TaskLine& t : f.tasks) {
        const std::string name = join(t.rmods, "+");
        Reply r = execute("spawn " + name + (t.rtpu.empty() ? "" : " " + t.rtpu));
        if (!r.ok) return fail(t.line, r.error);
        warned(r);
        const std::string rmod = r.data.value("rmod", name);
        spawned.push_back(rmod);
        for (const TaskLine::Set& set : t.local) {
            r = execute("set " + rmod + " " + set.key + " " + join(set.values));
            if (!r.ok) return fail(set.line, r.error);
        }
        if (t.on) to_turn_on.push_back(rmod);
    }
    if (!to_turn_on.empty()) {
        std::string items;
        for (const auto& rmod : to_turn_on) items += (items.empty() ? "" : ", ") + std::string("on ") + rmod;
        const Reply r = execute("reconfig " + items);
        if (!r.ok) return fail(f.tasks.front().line, r.error);
        warned(r);
    }
    Reply r;
    r.text = spawned.empty() ? "" : "started " + join(spawned) + (to_turn_on.empty() ? "" : "; on: " + join(to_turn_on));
    if (!warnings.empty()) r.text += r.text.empty() ? warnings.substr(1) : warnings;
    r.data = {{"spawned", spawned}, {"on", to_turn_on}};
    return r;
}

// The tasks `save` writes (those spawned from .rmod files), in the order
// spawn accepted them: a const's producer before its readers, unless it was
// killed and spawned again later (check_saved_starts refuses that).
std::vector<std::string> Interpreter::saved_tasks() const {
    std::vector<std::pair<int, std::string>> by_id;
    for (const auto& [name, file] : rmods_)
        if (const auto id = sbs_.find(name); id && files_of_.count(name)) by_id.emplace_back(id->value, name);
    std::sort(by_id.begin(), by_id.end());
    std::vector<std::string> names;
    for (auto& [id, name] : by_id) names.push_back(std::move(name));
    return names;
}

// Throws unless the saved TASK lines (of the tasks `names`) would start: each
// line's in-consts come from a line before it (or its own combined task) or a
// .svar INIT, as spawn demands, and the tasks marked ON pass the verification
// of the reconfig that turns them on (§3.3.1).
void Interpreter::check_saved_starts(const SbsFile& saved, const std::vector<std::string>& names) {
    svar::Table& t = *table();
    std::set<std::string> produced;
    for (const TaskLine& line : saved.tasks) {
        std::vector<RmodFile> files;
        for (const auto& p : line.rmods) files.push_back(read_rmod(p));
        for (const auto& f : files)
            for (const auto& v : f.global_out_consts()) produced.insert(v);
        for (const auto& f : files)
            for (const auto& v : f.global_in_consts()) {
                const auto ix = t.find(v);
                if (!produced.count(v) && !(ix && t.var(*ix).has_init()))
                    throw std::runtime_error("TASK line " + std::to_string(line.line) + ": in-const " + v + " of " +
                                             f.name + " is produced by no TASK line before it");
            }
    }
    std::vector<sbs::TaskId> on;
    for (std::size_t i = 0; i < saved.tasks.size() && i < names.size(); ++i)
        if (const auto id = sbs_.find(names[i]); saved.tasks[i].on && id) on.push_back(*id);
    if (const auto problems = sbs_.verification_problems(on); !problems.empty())
        throw std::runtime_error("the tasks marked ON would not be turned on: " + problems.front().message);
}

// The running configuration as .sbs text (see cmd_save).
std::string Interpreter::saved_sbs() const {
    const SbsFile& f = sbs_.file();
    std::string out = "# Saved by sbs `save` from subsystem " + f.subsystem + " (started from " + f.path + ").\n";
    out += "SUBSYSTEM " + f.subsystem + "\nSVARFILE  " + fs::absolute(f.svarfile).lexically_normal().string() +
           "\nMASTER    " + f.master + "\n";
    for (const RtpuSpec& r : f.rtpus) {
        out += "\nRTPU      " + r.name + " " + std::to_string(r.cpu) + "\nSCHEDULER " + std::string(to_string(r.scheduler)) +
               "\nUSAGE     " + std::string(to_string(r.usage)) + "\nERRPRINT  " + std::string(to_string(r.errprint)) +
               "\nMINFREQ   " + fmt("%.17g", r.minfreq) + "\nMAXFREQ   " + fmt("%.17g", r.maxfreq) +
               "\nBACKEND   " + std::string(to_string(r.backend)) + "\n";
        if (r.half_tick) out += "ACCOUNTING halftick " + fmt("%.17g", r.tick) + "\n";
    }
    for (const std::string& name : saved_tasks()) {
        const RmodFile& file = rmods_.at(name);
        const auto files = files_of_.find(name);
        std::vector<std::string> paths;
        for (const auto& p : files->second) paths.push_back(fs::absolute(p).lexically_normal().string());
        const auto id = sbs_.find(name);
        const bool on = id && sbs_.state(*id) == State::ON;
        const auto rtpu = rtpu_of_.find(name);
        out += "\nTASK " + join(paths, "+") + (rtpu == rtpu_of_.end() ? "" : " " + rtpu->second) + (on ? " ON" : " OFF") + "\n";
        for (const auto& e : file.local.entries())
            if (e.line == 0) out += "SET " + e.key + " " + join(e.values) + "\n";
    }
    return out + "EOF\n";
}

Reply Interpreter::cmd_save(const Words& w) {
    if (w.size() != 2) throw CommandError("usage: save FILE.sbs");
    if (origin_ != Origin::local)
        throw CommandError("save: over the network no file is written; save at the master's own prompt or with -c");
    const fs::path path(w[1]);
    if (path.extension() != ".sbs") throw CommandError("save: " + w[1] + ": the file name ends in .sbs");
    const std::string text = saved_sbs();
    // What is written must read back as a .sbs that starts: checked before it replaces anything.
    try {
        cfg::Reader reader = cfg::Reader::from_string(text, w[1]);
        check_saved_starts(parse_sbs(reader, ""), saved_tasks());
    } catch (const std::exception& e) {
        throw CommandError(std::string("save: the configuration does not read back and start (") + e.what() +
                           "); nothing written");
    }
    const fs::path tmp = path.string() + ".tmp";
    {
        std::ofstream out(tmp, std::ios::trunc);
        out << text;
        out.flush();
        if (!out) throw CommandError("save: cannot write " + tmp.string());
    }
    std::error_code ec;
    fs::rename(tmp, path, ec);
    if (ec) {
        fs::remove(tmp, ec);
        throw CommandError("save: cannot replace " + w[1]);
    }
    Reply r;
    r.text = "saved subsystem " + sbs_.name() + " to " + w[1] + " (" + std::to_string(saved_tasks().size()) + " task line(s))";
    r.data = {{"file", w[1]}, {"sbs", text}};
    return r;
}

}  // namespace chimera::cli
