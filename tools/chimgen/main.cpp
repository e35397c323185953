// chimgen — generates the framework of a control module (thesis §3.7).
//
//   chimgen mysample --out-const DH,NDOF --in-var Q_REF,Q^_REF,T_GRAV
//           --out-var Q_MEZ,Q^_MEZ --freq 100 --svar robot.svar --desc "sample module"
//   chimgen --from qmdiff.rmod --svar robot.svar -o modules/diff
//
// Writes MODULE.cpp (Listing A-1 style, C++), RMOD.rmod and meson.build into
// the output folder (default: ./MODULE).
#include "generator.hpp"

#include "tool_cli.hpp"

#include <CLI/CLI.hpp>

#include <filesystem>
#include <fstream>
#include <iostream>

namespace fs = std::filesystem;
using namespace chimera;
using namespace chimera::chimgen;

namespace {

// "A,B" and "A B" and repeated options all add ports; NAME:TYPE types a port.
void add_ports(const std::vector<std::string>& args, std::vector<std::string>& list,
               std::map<std::string, PortType>& typed_internal) {
    for (const auto& arg : args) {
        std::string item;
        auto flush = [&] {
            if (item.empty() || item == "none") {
                item.clear();
                return;
            }
            // A colon types the port; `^` and `_` are legal in names, ':' is not.
            const auto colon = item.find(':');
            std::string name = item.substr(0, colon);
            if (colon != std::string::npos) {
                PortType t;
                t.svar = item.substr(colon + 1);
                cpp_type(t.svar);
                typed_internal[name] = t;
            }
            list.push_back(name);
            item.clear();
        };
        for (char c : arg) {
            if (c == ',' || c == ' ' || c == '\t') {
                flush();
            } else {
                item += c;
            }
        }
        flush();
    }
}

void write_file(const fs::path& path, const std::string& text, bool force) {
    if (fs::exists(path) && !force) {
        throw GenError(path.string() + " exists (use --force to overwrite)");
    }
    std::ofstream out(path);
    out << text;
    if (!out) throw GenError("cannot write " + path.string());
}

TaskType parse_tasktype(const std::string& s) {
    for (auto t : {TaskType::periodic, TaskType::synchronous, TaskType::sporadic, TaskType::deferrable,
                   TaskType::background}) {
        if (to_string(t) == s) return t;
    }
    throw GenError("unknown task type '" + s + "' (periodic synchronous sporadic deferrable background)");
}

}  // namespace

int main(int argc, char** argv) {
    CLI::App app{"chimgen: generate the framework of a Chimera control module (thesis §3.7)"};
    std::string name, from, svar_file, desc, tasktype = "periodic", out_dir, cls, default_type = "double";
    std::string rmod_name;
    std::vector<std::string> in_consts, out_consts, in_vars, out_vars, aliases, locals;
    double freq = 0, period = 0;
    bool force = false, print = false;
    app.add_option("name", name, "module name (a C identifier; the .rmod's MODULE)");
    app.add_option("--from", from, "read name, ports, type and frequency from this .rmod")
        ->check(CLI::ExistingFile);
    app.add_option("--in-const", in_consts, "in-const ports: NAME[:TYPE], comma-separated or repeated");
    app.add_option("--out-const", out_consts, "out-const ports");
    app.add_option("--in-var", in_vars, "in-var ports");
    app.add_option("--out-var", out_vars, "out-var ports");
    app.add_option("--svar", svar_file, "take port types, units and descriptions from this .svar")
        ->check(CLI::ExistingFile);
    app.add_option("--type", default_type, "type of ports typed nowhere else (default double)");
    app.add_option("--alias", aliases, "SVARALIAS internal=GLOBAL (repeatable)");
    app.add_option("--local", locals, "a LOCAL line \"KEY value...\" (repeatable)");
    app.add_option("--tasktype", tasktype, "periodic synchronous sporadic deferrable background");
    auto* f = app.add_option("--freq", freq, "frequency in Hz");
    app.add_option("--period", period, "period in seconds")->excludes(f);
    app.add_option("--desc", desc, "one-line description (DESC)");
    app.add_option("--rmod", rmod_name, "name of the generated .rmod (default: the module name)");
    app.add_option("--class", cls, "C++ class name (default: the module name in CamelCase)");
    app.add_option("-o,--output", out_dir, "output folder (default: ./NAME)");
    app.add_flag("--force", force, "overwrite existing files");
    app.add_flag("--print", print, "print the source on stdout and write nothing");
    chimera::tools::add_version(app, "chimgen");
    if (const int status = chimera::tools::parse(app, argc, argv); status >= 0) return status;

    try {
        ModuleSpec spec;
        spec.default_type = default_type;
        spec.class_name = cls;
        std::map<std::string, PortType> typed;  // by internal name
        if (!from.empty()) {
            if (!in_consts.empty() || !out_consts.empty() || !in_vars.empty() || !out_vars.empty() ||
                !aliases.empty() || !locals.empty()) {
                throw GenError("--from takes the ports from the .rmod; do not give them as well");
            }
            spec.rmod = read_rmod(from);
            if (!name.empty() && name != spec.rmod.module) {
                throw GenError(from + " is module " + spec.rmod.module + ", not " + name);
            }
            if (!desc.empty()) spec.rmod.desc = desc;
        } else {
            if (name.empty()) throw GenError("give a module name or --from FILE.rmod (see --help)");
            RmodFile& r = spec.rmod;
            r.module = name;
            r.name = rmod_name.empty() ? name : rmod_name;
            r.desc = desc.empty() ? name + " control module" : desc;
            r.type = parse_tasktype(tasktype);
            add_ports(in_consts, r.in_consts, typed);
            add_ports(out_consts, r.out_consts, typed);
            add_ports(in_vars, r.in_vars, typed);
            add_ports(out_vars, r.out_vars, typed);
            for (const auto& a : aliases) {
                const auto eq = a.find('=');
                if (eq == std::string::npos || eq == 0 || eq + 1 == a.size()) {
                    throw GenError("--alias takes internal=GLOBAL, found '" + a + "'");
                }
                r.aliases.emplace_back(a.substr(0, eq), a.substr(eq + 1));
            }
            for (const auto& l : locals) {
                std::vector<std::string> words;
                std::string w;
                for (char c : l + " ") {
                    if (c == ' ' || c == '\t') {
                        if (!w.empty()) words.push_back(w);
                        w.clear();
                    } else {
                        w += c;
                    }
                }
                if (words.size() < 2) throw GenError("--local takes \"KEY value...\", found '" + l + "'");
                const std::string key = words.front();
                words.erase(words.begin());
                r.local.set(key, words);
            }
            if (period > 0) {
                r.freq = 1.0 / period;
                r.period = period;
            } else if (freq > 0) {
                r.freq = freq;
                r.period = 1.0 / freq;
            }
            r.path = r.name + ".rmod";
        }
        if (!svar_file.empty()) types_from_svar(spec, svar_file);
        for (const auto& [internal, t] : typed) spec.types[spec.rmod.global_name(internal)] = t;

        const std::string source = generate_source(spec);
        if (print) {
            std::cout << source;
            return 0;
        }
        const std::string rmod_text = generate_rmod(spec);
        // The .rmod written must be one the runtime reads back unchanged.
        {
            auto reader = cfg::Reader::from_string(rmod_text, spec.rmod.name + ".rmod");
            parse_rmod(reader, spec.rmod.name + ".rmod");
        }
        const fs::path dir = out_dir.empty() ? fs::path(spec.rmod.module) : fs::path(out_dir);
        fs::create_directories(dir);
        const fs::path rmod_path = dir / ((spec.rmod.name.empty() ? spec.rmod.module : spec.rmod.name) + ".rmod");
        write_file(dir / (spec.rmod.module + ".cpp"), source, force);
        if (!from.empty() && fs::exists(rmod_path) && fs::equivalent(rmod_path, from)) {
            // Generating next to the .rmod it came from: keep the original.
        } else if (!from.empty()) {
            write_file(rmod_path, [&] {
                std::ifstream in(from);
                return std::string(std::istreambuf_iterator<char>(in), {});
            }(), force);
        } else {
            write_file(rmod_path, rmod_text, force);
        }
        write_file(dir / "meson.build", generate_meson(spec), force);
        write_file(dir / "Makefile", generate_makefile(spec), force);
        std::cout << "chimgen: wrote " << (dir / (spec.rmod.module + ".cpp")).string() << ", "
                  << rmod_path.string() << ", " << (dir / "meson.build").string() << ", "
                  << (dir / "Makefile").string() << "\n";
        if (svar_file.empty() && typed.size() < static_cast<std::size_t>(
                                                    spec.rmod.in_consts.size() + spec.rmod.out_consts.size() +
                                                    spec.rmod.in_vars.size() + spec.rmod.out_vars.size())) {
            std::cout << "chimgen: no --svar: untyped ports are " << default_type
                      << " (init() reports a mismatch with the table by name)\n";
        }
        return 0;
    } catch (const std::exception& e) {
        std::cerr << "chimgen: " << e.what() << "\n";
        return 1;
    }
}
