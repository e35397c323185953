#include "generator.hpp"

#include <chimera/svar.hpp>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdlib>
#include <cstdio>
#include <cstring>
#include <set>
#include <sstream>

namespace chimera::chimgen {

namespace {

bool is_identifier(std::string_view s) {
    if (s.empty() || !(std::isalpha(static_cast<unsigned char>(s[0])) || s[0] == '_')) return false;
    for (char c : s) {
        if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_')) return false;
    }
    return true;
}

std::string format_number(double v) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%.17g", v);
    // Shortest text that reads back to the same double; no exponent for the
    // magnitudes people write plainly (FREQ 100, not FREQ 1e+02).
    const bool plain = std::fabs(v) >= 1e-4 && std::fabs(v) < 1e15;
    for (int prec = 1; prec <= 17; ++prec) {
        char shorter[64];
        std::snprintf(shorter, sizeof shorter, "%.*g", prec, v);
        if (plain && std::strchr(shorter, 'e') != nullptr) continue;
        if (std::strtod(shorter, nullptr) == v) return shorter;
    }
    return buf;
}

struct Port {
    std::string internal;  // the module's own name (what translate() takes)
    std::string global;    // after SVARALIAS
    std::string ident;     // C++ member name without the trailing underscore
    std::string cpp;       // element type
    PortType type;
    bool writes = false;   // an out-const or out-var: the module writes it
    std::vector<std::string> roles;
};

// Every distinct port in the order of Listing A-1's local structure: in-vars,
// out-vars, then the constants.
std::vector<Port> collect_ports(const ModuleSpec& spec) {
    std::vector<Port> ports;
    std::set<std::string> used_idents;
    auto add = [&](const std::vector<std::string>& list, const char* role, bool writes) {
        for (const auto& name : list) {
            Port* existing = nullptr;
            for (auto& p : ports) {
                if (p.internal == name) existing = &p;
            }
            if (existing != nullptr) {
                existing->writes = existing->writes || writes;
                existing->roles.emplace_back(role);
                continue;
            }
            Port p;
            p.internal = name;
            p.global = spec.rmod.global_name(name);
            const auto t = spec.types.find(p.global);
            if (t != spec.types.end()) {
                p.type = t->second;
            } else {
                p.type.svar = spec.default_type;
            }
            p.cpp = cpp_type(p.type.svar);
            std::string ident = port_identifier(name);
            std::string unique = ident;
            for (int n = 2; !used_idents.insert(unique).second; ++n) unique = ident + std::to_string(n);
            p.ident = unique;
            p.writes = writes;
            p.roles.emplace_back(role);
            ports.push_back(std::move(p));
        }
    };
    add(spec.rmod.in_vars, "in-var", false);
    add(spec.rmod.out_vars, "out-var", true);
    add(spec.rmod.in_consts, "in-const", false);
    add(spec.rmod.out_consts, "out-const", true);
    return ports;
}

std::string join(const std::vector<std::string>& v, std::string_view sep) {
    std::string out;
    for (std::size_t i = 0; i < v.size(); ++i) {
        if (i) out += sep;
        out += v[i];
    }
    return out;
}

std::string shape(const PortType& t) {
    std::string s = t.svar;
    if (t.nelem > 1) s += "[" + std::to_string(t.nelem) + "]";
    return s;
}

}  // namespace

std::string cpp_type(std::string_view t) {
    if (t == "byte") return "std::uint8_t";
    if (t == "char") return "char";
    if (t == "word") return "std::uint16_t";
    if (t == "short") return "std::int16_t";
    if (t == "unsigned") return "std::uint32_t";
    if (t == "int") return "std::int32_t";
    if (t == "float") return "float";
    if (t == "double") return "double";
    if (t.substr(0, 7) == "struct[" && t.size() > 8 && t.back() == ']') return "std::byte";
    throw GenError("unknown SVAR type '" + std::string(t) +
                   "' (byte char word short unsigned int float double struct[N])");
}

std::string port_identifier(std::string_view port) {
    std::string out;
    for (char c : port) {
        const auto u = static_cast<unsigned char>(c);
        if (c == '^') {
            out += 'd';
        } else if (std::isalnum(u)) {
            out += static_cast<char>(std::tolower(u));
        } else {
            out += '_';
        }
    }
    if (out.empty() || std::isdigit(static_cast<unsigned char>(out[0]))) out.insert(0, "p_");
    return out;
}

std::string class_name(std::string_view module) {
    std::string out;
    bool upper = true;
    for (char c : module) {
        if (c == '_') {
            upper = true;
            continue;
        }
        const auto u = static_cast<unsigned char>(c);
        out += upper ? static_cast<char>(std::toupper(u)) : c;
        upper = false;
    }
    if (out.empty()) out = "Module";
    if (std::isdigit(static_cast<unsigned char>(out[0]))) out.insert(0, "M");
    return out;
}

void validate(const ModuleSpec& spec) {
    const RmodFile& r = spec.rmod;
    if (!is_identifier(r.module)) {
        throw GenError("module name '" + r.module +
                       "' must be a C identifier (it names the CHIMERA_MODULE symbol)");
    }
    if (!spec.class_name.empty() && !is_identifier(spec.class_name)) {
        throw GenError("class name '" + spec.class_name + "' is not a C++ identifier");
    }
    auto check_list = [](const std::vector<std::string>& list, const char* what) {
        std::set<std::string> seen;
        for (const auto& n : list) {
            if (n.empty() || n == "none") throw GenError(std::string(what) + ": bad port name '" + n + "'");
            for (char c : n) {
                if (std::isspace(static_cast<unsigned char>(c)) || c == '#' || c == '=' || c == ',' ||
                    c == '"' || c == '\\') {
                    throw GenError(std::string(what) + ": port name '" + n +
                                   "' may not contain spaces, '#', '=', ',', '\"' or '\\'");
                }
            }
            if (!seen.insert(n).second) throw GenError(std::string(what) + ": port '" + n + "' given twice");
        }
    };
    check_list(r.in_consts, "in-consts");
    check_list(r.out_consts, "out-consts");
    check_list(r.in_vars, "in-vars");
    check_list(r.out_vars, "out-vars");
    for (const auto& n : r.out_vars) {
        for (const auto& m : r.in_vars) {
            if (n == m) throw GenError("port '" + n + "' is both an in-var and an out-var");
        }
    }
    const bool aperiodic = is_aperiodic(r.type);
    if (!aperiodic && !(r.freq > 0.0)) {
        throw GenError(std::string(to_string(r.type)) + " task needs a frequency (--freq or --period)");
    }
    for (const auto& [global, type] : spec.types) cpp_type(type.svar);
    cpp_type(spec.default_type);
    if (r.desc.empty()) throw GenError("the module needs a description (DESC)");
    if (r.desc.find('#') != std::string::npos) throw GenError("DESC may not contain '#' (a comment)");
}

void types_from_svar(ModuleSpec& spec, const std::string& svar_path) {
    svar::TableSpec table;
    try {
        table = svar::parse_svar_file(svar_path);
    } catch (const std::exception& e) {
        throw GenError(e.what());
    }
    spec.svar_file = svar_path;
    const RmodFile& r = spec.rmod;
    for (const auto* list : {&r.in_consts, &r.out_consts, &r.in_vars, &r.out_vars}) {
        for (const auto& internal : *list) {
            const std::string global = r.global_name(internal);
            const auto ix = table.find(global);
            if (!ix) {
                throw GenError(svar_path + ": no variable " + global + " (port " + internal +
                               " of module " + r.module + ")");
            }
            const svar::VarSpec& v = table.vars[*ix];
            PortType t;
            t.svar = svar::type_spelling(v.type, v.elem_size);
            t.nelem = v.nelem;
            t.units = v.units;
            t.desc = v.desc;
            spec.types[global] = t;
        }
    }
}

std::string generate_source(const ModuleSpec& spec) {
    validate(spec);
    const RmodFile& r = spec.rmod;
    const std::string cls = spec.class_name.empty() ? class_name(r.module) : spec.class_name;
    const auto ports = collect_ports(spec);
    std::ostringstream o;

    o << "// " << r.module << ".cpp — control module `" << r.module << "`: " << r.desc << ".\n";
    o << "// Framework generated by chimgen (thesis §3.7, Listing A-1)";
    if (!r.path.empty()) o << " from " << r.path;
    o << ".\n";
    o << "// Only the algorithm is left to write. The ports are translated once, in\n"
         "// init(), into pointers to the task's local table: the runtime copies the\n"
         "// in-vars into it before every cycle() and the out-vars out of it after.\n";
    if (!ports.empty()) {
        o << "//\n";
        std::size_t w_name = 4, w_type = 4;
        for (const auto& p : ports) {
            w_name = std::max(w_name, p.internal.size());
            w_type = std::max(w_type, shape(p.type).size());
        }
        for (const auto& p : ports) {
            std::string line = "//   " + join(p.roles, ",");
            line.resize(std::max<std::size_t>(line.size(), 24), ' ');
            std::string name = p.internal;
            name.resize(w_name, ' ');
            std::string type = shape(p.type);
            type.resize(w_type, ' ');
            line += " " + name + "  " + type;
            if (p.global != p.internal) line += "  = " + p.global;
            if (!p.type.units.empty()) line += "  [" + p.type.units + "]";
            if (!p.type.desc.empty()) line += "  " + p.type.desc;
            while (!line.empty() && line.back() == ' ') line.pop_back();
            o << line << "\n";
        }
        if (spec.svar_file.empty()) {
            o << "// (Port types: no .svar was given to chimgen; ports not typed on its command\n"
                 "// line are " << spec.default_type
              << ". init() fails with a clear message if the table disagrees.)\n";
        }
    }
    o << "//\n"
         "// Every method below returns its documented default (chimera/module.hpp);\n"
         "// delete the ones the module does not need.\n";
    o << "#include <chimera/module.hpp>\n"
         "#include <chimera/svar.hpp>\n\n"
         "#include <cstddef>\n"
         "#include <cstdint>\n\n"
         "namespace {\n\n";
    o << "class " << cls << " final : public chimera::Module {\n"
         "public:\n";

    // init
    o << "    chimera::Result init(chimera::Task& " << (ports.empty() ? "/*task*/" : "task")
      << ") override {\n";
    for (const auto& p : ports) {
        o << "        " << p.ident << "_ = task.translate<" << p.cpp << ">(\"" << p.internal << "\");\n";
    }
    if (!ports.empty()) o << "\n";
    o << "        // Module-dependent initialization code goes here. The .rmod's LOCAL\n"
         "        // section is task.local(), e.g. task.local().number(\"GAIN\", 1.0).\n";
    if (!r.out_consts.empty()) {
        o << "        // Set the out-consts (";
        std::vector<std::string> oc;
        for (const auto& p : ports) {
            if (std::find(r.out_consts.begin(), r.out_consts.end(), p.internal) != r.out_consts.end()) {
                oc.push_back(p.ident + "_");
            }
        }
        o << join(oc, ", ") << ") here: they are published when init returns.\n";
    }
    o << "        return chimera::Result::OK;\n"
         "    }\n\n";

    o << "    chimera::Result reinit(chimera::Task& /*task*/) override {\n"
         "        // Module-dependent re-initialization code goes here: an in-const has\n"
         "        // changed value (the pointers stay valid).\n"
         "        return chimera::Result::OK;\n"
         "    }\n\n";

    o << "    chimera::Result on(chimera::Task& /*task*/) override {\n"
         "        // Module-dependent 'on' code goes here (in-vars and out-vars are fresh).\n"
         "        return chimera::Result::OK;\n"
         "    }\n\n";

    o << "    chimera::Result cycle(chimera::Task& /*task*/) override {\n"
         "        // Module-dependent 'cycle' code goes here:";
    {
        std::vector<std::string> in, out;
        for (const auto& p : ports) {
            const std::string ref = p.ident + "_" + (p.type.nelem > 1 ? "[i]" : "[0]");
            (p.writes ? out : in).push_back(ref);
        }
        if (!in.empty()) o << " read " << join(in, ", ") << ";";
        if (!out.empty()) o << (in.empty() ? "" : "\n        //") << " write " << join(out, ", ") << ".";
        o << "\n";
    }
    o << "        // Real-time path: no allocation, no blocking calls, no locks.\n"
         "        return chimera::Result::OK;\n"
         "    }\n\n";

    o << "    chimera::Result sync(chimera::Task& /*task*/) override {\n";
    if (r.type == TaskType::synchronous) {
        o << "        // Module-dependent 'sync' code goes here: block until the external\n"
             "        // event, then return (the cycle follows). Return early when\n"
             "        // task.command_pending() so a signal can be applied.\n";
    } else {
        o << "        // Module-dependent 'sync' code: used by synchronous tasks only; this\n"
             "        // one is " << to_string(r.type) << ".\n";
    }
    o << "        return chimera::Result::OK;\n"
         "    }\n\n";

    o << "    chimera::Result off(chimera::Task& /*task*/) override {\n"
         "        // Module-dependent 'off' code goes here (the out-vars are written after it).\n"
         "        return chimera::Result::OK;\n"
         "    }\n\n";

    o << "    chimera::Result kill(chimera::Task& /*task*/) override {\n"
         "        // Module-dependent 'kill' code goes here: release what init() acquired.\n"
         "        return chimera::Result::OK;\n"
         "    }\n\n";

    o << "    chimera::Result error(chimera::Task& /*task*/, const chimera::err::Error& /*err*/) override {\n"
         "        // Module-dependent 'error' code goes here. If the error is handled,\n"
         "        // return CONTINUE (carry on) or OFF; ERROR waits for the operator's clear.\n"
         "        return chimera::Result::ERROR;\n"
         "    }\n\n";

    o << "    chimera::Result clear(chimera::Task& /*task*/, const chimera::err::Error& /*err*/) override {\n"
         "        // Module-dependent 'clear' code goes here: check that the problem is\n"
         "        // fixed; return ERROR if it is not.\n"
         "        return chimera::Result::OFF;\n"
         "    }\n\n";

    o << "    chimera::Result set(chimera::Task& /*task*/) override {\n"
         "        // Module-dependent 'set' code goes here (optional): task.arg() is\n"
         "        // \"KEY value...\" and task.local() already holds the new value.\n"
         "        return chimera::Result::OK;\n"
         "    }\n\n";

    o << "    chimera::Result get(chimera::Task& /*task*/) override {\n"
         "        // Module-dependent 'get' code goes here (optional): task.arg() is the\n"
         "        // key; answer with task.reply(...) (default: the LOCAL value).\n"
         "        return chimera::Result::OK;\n"
         "    }\n";

    if (!ports.empty()) {
        o << "\nprivate:\n";
        for (const auto& p : ports) {
            o << "    " << (p.writes ? "" : "const ") << p.cpp << "* " << p.ident << "_ = nullptr;";
            o << "  // " << join(p.roles, ", ") << " " << p.internal;
            if (p.type.nelem > 1) o << "[" << p.type.nelem << "]";
            if (!p.type.units.empty()) o << " (" << p.type.units << ")";
            o << "\n";
        }
    }
    o << "};\n\n"
         "}  // namespace\n\n";
    o << "CHIMERA_MODULE(" << r.module << ", " << cls << ")\n";
    return o.str();
}

std::string generate_rmod(const ModuleSpec& spec) {
    validate(spec);
    const RmodFile& r = spec.rmod;
    std::ostringstream o;
    o << "# " << (r.name.empty() ? r.module : r.name) << ".rmod — generated by chimgen\n";
    o << "MODULE    " << r.module << "\n";
    o << "DESC      " << r.desc << "\n";
    for (const auto& [internal, global] : r.aliases) o << "SVARALIAS " << internal << "=" << global << "\n";
    auto list = [&](const char* key, const std::vector<std::string>& v) {
        std::string k = key;
        k.resize(10, ' ');
        o << k << (v.empty() ? "none" : join(v, " ")) << "\n";
    };
    list("INCONST", r.in_consts);
    list("OUTCONST", r.out_consts);
    list("INVAR", r.in_vars);
    list("OUTVAR", r.out_vars);
    o << "TASKTYPE  " << to_string(r.type) << "\n";
    if (r.freq > 0.0) o << "FREQ      " << format_number(r.freq) << "\n";
    if (!r.local.entries().empty()) {
        o << "\nLOCAL\n";
        for (const auto& e : r.local.entries()) {
            std::string k = e.key;
            k.resize(std::max<std::size_t>(k.size() + 1, 10), ' ');
            o << k << join(e.values, " ") << "\n";
        }
    }
    o << "EOF\n";
    return o.str();
}

std::string generate_meson(const ModuleSpec& spec) {
    validate(spec);
    const RmodFile& r = spec.rmod;
    const std::string rmod_file = (r.name.empty() ? r.module : r.name) + ".rmod";
    std::ostringstream o;
    o << "# Module `" << r.module << "` (generated by chimgen). In this tree: put the folder\n"
         "# under modules/ and add it to the list in modules/meson.build. Elsewhere:\n"
         "# subdir() it from a project that has chimera installed (pkg-config).\n";
    o << "chimgen_" << r.module << "_dep = is_variable('chimera_dep') ? chimera_dep : dependency('chimera')\n";
    o << "chimgen_" << r.module << "_dir = is_variable('module_install_dir') ? module_install_dir : "
         "get_option('libdir') / 'chimera' / 'modules'\n";
    o << "shared_module('" << r.module << "', files('" << r.module << ".cpp'),\n"
         "  name_prefix : '',  # " << r.module << ".so: the name the module path looks for\n"
         "  dependencies : chimgen_" << r.module << "_dep,\n"
         "  install : true,\n"
         "  install_dir : chimgen_" << r.module << "_dir)\n";
    o << "install_data('" << rmod_file << "', install_dir : chimgen_" << r.module << "_dir)\n";
    return o.str();
}

std::string generate_makefile(const ModuleSpec& spec) {
    validate(spec);
    const std::string& m = spec.rmod.module;
    std::ostringstream o;
    o << "# Module `" << m << "` (generated by chimgen), built outside the Chimera tree:\n"
         "#   make                                           against the installed library\n"
         "#   PKG_CONFIG_PATH=BUILD/meson-uninstalled make   against a Chimera build tree BUILD\n"
         "# Then put this folder on the module path (CHIMERA_MODULE_PATH, sbs --module-path)\n"
         "# or load it at the sbs prompt: module load ./" << m << ".so\n"
         "CXX ?= c++\n"
         "CXXFLAGS ?= -O2 -g\n"
         "CHIMERA = $(shell pkg-config --cflags --libs chimera)\n\n"
         << m << ".so: " << m << ".cpp\n"
         "\t$(CXX) $(CXXFLAGS) -Wall -Wextra -fPIC -shared -o $@ $< $(CHIMERA)\n\n"
         "clean:\n\trm -f " << m << ".so\n"
         ".PHONY: clean\n";
    return o.str();
}

}  // namespace chimera::chimgen
