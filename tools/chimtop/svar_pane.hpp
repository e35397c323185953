// The SVAR pane: current values of the variables a task reads and writes
// (the task's in/out lists come from its status slot).
#pragma once

#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace chimtop {

/// "in  Q_REF  double[6]  0.1 0.2 ... radians" lines; one line explaining
/// why when the table cannot be read.
std::vector<std::string> svar_lines(const std::string& segment, const std::string& inputs,
                                    const std::string& outputs);
/// {"in": {"Q_REF": [..]}, "out": {...}} or {"error": "..."}.
nlohmann::json svar_values_json(const std::string& segment, const std::string& inputs,
                                const std::string& outputs);

}  // namespace chimtop
