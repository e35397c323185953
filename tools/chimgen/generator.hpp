// tools/chimgen/generator.hpp — the module-framework generator of thesis §3.7:
// from a module's name and ports (an .rmod, or the same facts on the command
// line) it writes the C++ skeleton in the style of Listing A-1, the .rmod and a
// meson snippet, so the engineer only fills in the algorithm.
#pragma once

#include <chimera/sbs_files.hpp>

#include <map>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace chimera::chimgen {

class GenError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

/// The C++ type of one port (a .svar TYPE): its spelling in the generated
/// code and whether it is an untyped struct.
struct PortType {
    std::string svar = "double";  ///< as a .svar writes it: float, int, struct[16] ...
    std::size_t nelem = 0;        ///< 0: unknown (no .svar given)
    std::string units;            ///< from the .svar, for the comment
    std::string desc;
};

/// The C++ spelling of a .svar type: "float" -> "float", "int" -> "std::int32_t",
/// "struct[N]" -> "std::byte". Throws GenError for an unknown type.
std::string cpp_type(std::string_view svar_type);

/// A C++ identifier for a port name: lower case, `^` -> `d` (Q^_REF -> qd_ref,
/// the thesis's own spelling in Listing A-1), other non-identifier characters
/// -> `_`.
std::string port_identifier(std::string_view port);

/// The class name for a module name: `mysample` -> `Mysample`, `joint_pid` -> `JointPid`.
std::string class_name(std::string_view module);

/// Everything the generator needs.
struct ModuleSpec {
    RmodFile rmod;                         ///< MODULE, DESC, aliases, ports, type, FREQ, LOCAL
    std::map<std::string, PortType> types; ///< by GLOBAL port name; missing: `default_type`
    std::string default_type = "double";
    std::string class_name;                ///< empty: class_name(rmod.module)
    std::string svar_file;                 ///< where the types came from (comment only)
};

/// Checks the spec: a valid module identifier, no port in two lists of the
/// same direction, known types. Throws GenError naming the problem.
void validate(const ModuleSpec& spec);

/// Fills `types` from a .svar file for every port (global names); throws
/// GenError naming a port the table does not have.
void types_from_svar(ModuleSpec& spec, const std::string& svar_path);

/// The module source (MODULE.cpp).
std::string generate_source(const ModuleSpec& spec);
/// The .rmod text; parse_rmod() reads it back to the same RmodFile.
std::string generate_rmod(const ModuleSpec& spec);
/// A meson.build for the module's folder (works in-tree under modules/ and in
/// a project that finds chimera through pkg-config).
std::string generate_meson(const ModuleSpec& spec);
/// A Makefile that builds the module outside the tree through pkg-config
/// (installed library, or a build tree with PKG_CONFIG_PATH=BUILD/meson-uninstalled).
std::string generate_makefile(const ModuleSpec& spec);

}  // namespace chimera::chimgen
