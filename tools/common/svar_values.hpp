// svar_values.hpp — the numbers of a state variable as the interfaces see
// them: elements read as doubles, a value checked against the variable's type
// and its .svar MIN/MAX, and stored in its type. One definition for every
// interface that writes the table from outside a task (the `sbs` setvar
// command, the Python bindings), so the same value is accepted or refused the
// same way, with the same words, wherever it is typed.
#pragma once

#include <chimera/svar.hpp>

#include <cstddef>
#include <string>
#include <utility>
#include <vector>

namespace chimera::tools {

/// The elements of `v` in `buf` (v.bytes() bytes) as doubles; empty for a struct.
std::vector<double> numbers_of(const svar::VarInfo& v, const unsigned char* buf);
/// Stores `x` as element k of `buf` in the variable's type (integers rounded
/// half away from zero, as std::llround). `x` must have passed value_refusal().
void store_number(const svar::VarInfo& v, unsigned char* buf, std::size_t k, double x);
/// "double", "float[6]", "struct[32][2]": the type as the tools print it.
std::string type_text(const svar::VarInfo& v);
/// Why `x` may not be element k of `v` — "is not a finite number", "does not
/// fit type int", "is outside the .svar range [-1, 1]" — or "" when it may.
std::string value_refusal(const svar::VarInfo& v, std::size_t k, double x);

}  // namespace chimera::tools
