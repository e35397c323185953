// chimcfg — checks Chimera configuration files and shows .svar tables.
//
//   chimcfg check FILE...   one summary line per good file (exit 0), or the
//                           FILE:LINE: errors of the bad ones (exit 1)
//
// check runs the checks spawn and sbs run, through the same functions (the
// readers of src/cfg, src/svar, src/sbs and check_local_section()), so what it
// accepts starts and what it refuses never starts. For a .rmod that includes
// the LOCAL values against the keys its module declares: the module is loaded
// as spawn loads it (CHIMERA_MODULE_PATH, --module-path, the .rmod's folder,
// the install folder), so its constructors run; --no-modules checks the file
// alone, and the summary says when LOCAL was not checked.
//   chimcfg dump FILE.svar  each variable: name, type, nelem, units, init,
//                           min, max, description
//
// The kind of file is taken from its extension: .svar (§5.5.2), .rmod (§3.8),
// .sbs (§4.5.1).
#include "tool_cli.hpp"

#include <CLI/CLI.hpp>

#include <charconv>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <optional>
#include <set>
#include <string>
#include <vector>

#include "chimera/cfg.hpp"
#include "chimera/module.hpp"
#include "chimera/sbs.hpp"
#include "chimera/sbs_files.hpp"
#include "chimera/svar.hpp"

namespace {

using chimera::svar::TableSpec;
using chimera::svar::Type;
using chimera::svar::VarSpec;

std::string extension(const std::string& path) {
    return std::filesystem::path(path).extension().string();
}

std::string plural(std::size_t n, const char* word) {
    return std::to_string(n) + " " + word + (n == 1 ? "" : "s");
}

std::size_t data_bytes(const TableSpec& spec) {
    std::size_t total = 0;
    for (const VarSpec& v : spec.vars) total += v.bytes();
    return total;
}

std::string summary_svar(const std::string& path) {
    const TableSpec spec = chimera::svar::parse_svar_file(path);
    return path + ": ok, svar, " + plural(spec.vars.size(), "variable") + ", " +
           std::to_string(data_bytes(spec)) + " bytes of data";
}

std::string list_summary(const char* what, const std::vector<std::string>& names) {
    std::string s = std::string(what) + " ";
    if (names.empty()) return s + "none";
    for (std::size_t i = 0; i < names.size(); ++i) s += (i ? "," : "") + names[i];
    return s;
}

/// Where to find modules, or none: --no-modules.
struct ModuleLookup {
    bool load = true;
    std::vector<std::string> dirs;  // --module-path
};

// The LOCAL section against the module's declarations, as spawn checks it.
std::string local_check(const chimera::RmodFile& r, const ModuleLookup& modules) {
    if (!modules.load) return "LOCAL not checked (--no-modules)";
    try {
        const auto keys = chimera::sbs::module_local_keys(r, modules.dirs);
        chimera::check_local_section(keys, r.module, r.local);
        return keys.empty() ? "LOCAL free (module " + r.module + " declares no keys)"
                            : "LOCAL checked against module " + r.module;
    } catch (const chimera::sbs::ModuleNotFound&) {
        return "LOCAL not checked (module " + r.module +
               " not on the module path: --module-path DIR or CHIMERA_MODULE_PATH)";
    }
}

/// The table the .rmod files given are checked against: that of the first
/// .sbs given (its SVARFILE), else the first .svar given.
struct PortTable {
    std::string svarfile;  // "" : none given
    std::set<std::string> names;
};

PortTable port_table(const std::vector<std::string>& files) {
    PortTable t;
    for (const char* kind : {".sbs", ".svar"}) {
        for (const std::string& path : files) {
            if (extension(path) != kind) continue;
            try {
                t.svarfile = kind == std::string(".sbs") ? chimera::read_sbs(path).svarfile : path;
                for (const auto& v : chimera::svar::parse_svar_file(t.svarfile).vars) t.names.insert(v.name);
                return t;
            } catch (const std::exception&) {
                t = {};  // reported on its own line; the ports stay unchecked
            }
        }
    }
    return t;
}

// The ports against the table, as spawn checks them.
std::string port_check(const chimera::RmodFile& r, const PortTable& table) {
    if (table.svarfile.empty()) return "ports not checked (give the .sbs or .svar too)";
    const std::string why = chimera::port_problem(
        r, [&](const std::string& g) { return table.names.count(g) != 0; }, table.svarfile);
    if (!why.empty()) throw std::runtime_error(why);
    return "ports checked against " + table.svarfile;
}

std::string summary_rmod(const std::string& path, const ModuleLookup& modules, const PortTable& table) {
    const chimera::RmodFile r = chimera::read_rmod(path);
    const std::string ports = port_check(r, table);
    const std::string local = local_check(r, modules);
    std::string s = path + ": ok, rmod " + r.name + ", module " + r.module + ", " +
                    std::string(chimera::to_string(r.type));
    if (r.freq > 0) {
        char buf[64];
        std::snprintf(buf, sizeof buf, " at %g Hz", r.freq);
        s += buf;
    }
    s += "; " + list_summary("in-consts", r.global_in_consts()) + "; " +
         list_summary("out-consts", r.global_out_consts()) + "; " +
         list_summary("in-vars", r.global_in_vars()) + "; " +
         list_summary("out-vars", r.global_out_vars()) + "; " + ports + "; " + local;
    return s;
}

// The .rmod of a TASK line as sbs finds it: the path given, beside the
// .sbs, or NAME[.rmod] in the module path folders.
std::optional<std::string> task_rmod_file(const std::string& name, const std::string& sbs_path,
                                          const ModuleLookup& modules) {
    std::vector<std::string> dirs = {"", std::filesystem::path(sbs_path).parent_path().string()};
    if (const char* env = std::getenv("CHIMERA_MODULE_PATH")) {
        std::string rest = env;
        for (std::size_t colon; (colon = rest.find(':')) != std::string::npos; rest.erase(0, colon + 1))
            if (colon > 0) dirs.push_back(rest.substr(0, colon));
        if (!rest.empty()) dirs.push_back(rest);
    }
    dirs.insert(dirs.end(), modules.dirs.begin(), modules.dirs.end());
    for (const auto& d : dirs)
        for (const std::string& file : {name, name + ".rmod"}) {
            const auto p = d.empty() ? std::filesystem::path(file) : std::filesystem::path(d) / file;
            std::error_code ec;
            if (p.extension() == ".rmod" && std::filesystem::is_regular_file(p, ec)) return p.string();
        }
    return std::nullopt;
}

std::string summary_sbs(const std::string& path, const ModuleLookup& modules) {
    const chimera::SbsFile f = chimera::read_sbs(path);
    chimera::check_rtpu_cpus(f);
    // The table it names must be a good .svar too.
    const TableSpec spec = chimera::svar::parse_svar_file(f.svarfile);
    // Each TASK line's .rmod files as spawn reads them, their ports against that table.
    std::set<std::string> names;
    for (const auto& v : spec.vars) names.insert(v.name);
    for (const chimera::TaskLine& t : f.tasks) {
        std::vector<chimera::RmodFile> objects;
        for (const std::string& rmod : t.rmods) {
            const auto file = task_rmod_file(rmod, path, modules);
            if (!file)
                throw std::runtime_error(path + ":" + std::to_string(t.line) + ": TASK " + rmod + ": no file " + rmod +
                                         "[.rmod] here, beside the .sbs or on the module path");
            const chimera::RmodFile r = chimera::read_rmod(*file);
            const std::string why =
                chimera::port_problem(r, [&](const std::string& g) { return names.count(g) != 0; }, f.svarfile);
            if (!why.empty()) throw std::runtime_error(path + ":" + std::to_string(t.line) + ": " + why);
            objects.push_back(r);
        }
        if (const std::string why = chimera::combined_problem(objects); !why.empty())
            throw std::runtime_error(path + ":" + std::to_string(t.line) + ": " + why);
    }
    return path + ": ok, subsystem " + f.subsystem + ", " + plural(f.rtpus.size(), "RTPU") +
           ", master " + f.master + ", svar " + f.svarfile + " (" +
           plural(spec.vars.size(), "variable") + ")" +
           (f.tasks.empty() ? "" : ", " + plural(f.tasks.size(), "TASK line") + " (rmod files, ports and rates checked)");
}

int check(const std::vector<std::string>& files, const ModuleLookup& modules) {
    const PortTable table = port_table(files);
    int bad = 0;
    for (const std::string& path : files) {
        try {
            const std::string ext = extension(path);
            std::string line;
            if (ext == ".svar")
                line = summary_svar(path);
            else if (ext == ".rmod")
                line = summary_rmod(path, modules, table);
            else if (ext == ".sbs")
                line = summary_sbs(path, modules);
            else
                throw std::runtime_error(path + ": unknown kind of file '" + ext +
                                         "' (expected .svar, .rmod or .sbs)");
            std::cout << line << '\n';
        } catch (const std::exception& e) {
            std::cout.flush();
            std::cerr << e.what() << '\n';
            ++bad;
        }
    }
    return bad == 0 ? 0 : 1;
}

std::string number(double x, Type t) {
    char buf[64];
    if (t == Type::float_ || t == Type::double_) {
        const auto r = std::to_chars(buf, buf + sizeof buf, x);
        return std::string(buf, r.ptr);
    }
    std::snprintf(buf, sizeof buf, "%lld", static_cast<long long>(x));
    return buf;
}

std::string values(const std::vector<double>& v, Type t) {
    std::string s;
    for (std::size_t i = 0; i < v.size(); ++i) s += (i ? " " : "") + number(v[i], t);
    return s;
}

int dump(const std::string& path) {
    if (extension(path) != ".svar") {
        std::cerr << path << ": dump reads .svar files\n";
        return 1;
    }
    TableSpec spec;
    try {
        spec = chimera::svar::parse_svar_file(path);
    } catch (const std::exception& e) {
        std::cerr << e.what() << '\n';
        return 1;
    }
    std::cout << path << ": " << plural(spec.vars.size(), "variable") << ", "
              << data_bytes(spec) << " bytes of data\n";
    for (std::size_t i = 0; i < spec.vars.size(); ++i) {
        const VarSpec& v = spec.vars[i];
        std::cout << '\n'
                  << "[" << i << "] " << v.name << "  "
                  << chimera::svar::type_spelling(v.type, v.elem_size) << "  nelem " << v.nelem
                  << "  units " << (v.units.empty() ? "-" : v.units) << '\n';
        if (!v.desc.empty()) std::cout << "    desc  " << v.desc << '\n';
        if (v.type == Type::struct_) {
            std::cout << "    init  (struct: zero, set by the application)\n";
        } else {
            std::vector<double> init(v.nelem);
            for (std::size_t k = 0; k < v.nelem; ++k) init[k] = v.init_at(k);
            std::cout << "    init  " << values(init, v.type)
                      << (v.has_init ? "" : "  (no INIT: zeros)") << '\n';
            if (v.has_range) {
                std::cout << "    min   " << values(v.min, v.type) << '\n';
                std::cout << "    max   " << values(v.max, v.type) << '\n';
            } else {
                std::cout << "    min   -\n    max   -\n";
            }
        }
    }
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    CLI::App app{"chimcfg: check Chimera configuration files (.svar, .rmod, .sbs)"};
    app.require_subcommand(1);
    std::vector<std::string> files;
    auto* c = app.add_subcommand("check", "validate files; one summary line each, or FILE:LINE: errors");
    c->add_option("files", files, "files to check (.svar, .rmod, .sbs)")->required();
    ModuleLookup modules;
    c->add_option("--module-path", modules.dirs,
                  "a folder with modules, searched as sbs --module-path (repeatable)")
        ->allow_extra_args(false);  // one folder each: the files follow
    bool no_modules = false;
    c->add_flag("--no-modules", no_modules,
                "do not load the module a .rmod names (its LOCAL values then go unchecked)");
    std::string svar;
    auto* d = app.add_subcommand("dump", "print each variable of a .svar file");
    d->add_option("file", svar, "the .svar file")->required();
    chimera::tools::add_version(app, "chimcfg");
    if (const int status = chimera::tools::parse(app, argc, argv); status >= 0) return status;
    modules.load = !no_modules;
    if (c->parsed()) return check(files, modules);
    return dump(svar);
}
