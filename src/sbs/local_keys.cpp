// The LOCAL keys a module declares (module.hpp, LocalKey) and the run-time
// check of a `set` against them (issue #16.2).
#include <chimera/cfg.hpp>
#include <chimera/module.hpp>

#include <cmath>
#include <cstdio>

namespace chimera {

std::string_view to_string(LocalType t) noexcept {
    switch (t) {
        case LocalType::number: return "number";
        case LocalType::numbers: return "numbers";
        case LocalType::integer: return "integer";
        case LocalType::word: return "word";
        case LocalType::text: return "text";
        case LocalType::output_file: return "output-file";
    }
    return "?";
}

const LocalKey* find_local_key(std::span<const LocalKey> keys, std::string_view key) noexcept {
    const LocalKey* best = nullptr;
    std::size_t best_len = 0;
    for (const LocalKey& k : keys) {
        const std::string_view name = k.name;
        if (name == key) return &k;
        if (!name.empty() && name.back() == '*') {
            const std::string_view prefix = name.substr(0, name.size() - 1);
            if (key.substr(0, prefix.size()) == prefix && (best == nullptr || prefix.size() > best_len)) {
                best = &k;
                best_len = prefix.size();
            }
        }
    }
    return best;
}

namespace {

bool numeric(LocalType t) { return t == LocalType::number || t == LocalType::numbers || t == LocalType::integer; }

std::string range_text(const LocalKey& k) {
    if (!numeric(k.type) || k.min > k.max || (std::isinf(k.min) && std::isinf(k.max))) return "";
    return "[" + cfg::number_text(k.min) + ", " + cfg::number_text(k.max) + "]";
}

// Why a value does not fit the declared type and range ("" when it does).
std::string value_problem(const LocalKey& k, const std::vector<std::string>& values) {
    const bool one = k.type == LocalType::number || k.type == LocalType::integer || k.type == LocalType::word ||
                     k.type == LocalType::output_file;
    if (values.empty()) return "a value is needed (" + std::string(to_string(k.type)) + ")";
    if (one && values.size() != 1)
        return "takes one " + std::string(to_string(k.type)) + ", given " + std::to_string(values.size()) + " words";
    if (!numeric(k.type)) return "";
    for (const auto& v : values) {
        const auto d = cfg::parse_double(v);
        if (!d) return "'" + v + "' is not a number";
        if (k.type == LocalType::integer && *d != std::floor(*d)) return "'" + v + "' is not an integer";
        if (k.min <= k.max && (*d < k.min || *d > k.max))
            return v + " is out of range " + range_text(k);
    }
    return "";
}

}  // namespace

std::string describe(const LocalKey& k) {
    std::string s = std::string(k.name) + " " + std::string(to_string(k.type));
    if (const auto r = range_text(k); !r.empty()) s += " " + r;
    s += k.live ? " live" : " spawn-only";
    if (k.fallback != nullptr && *k.fallback != '\0') s += " (default " + std::string(k.fallback) + ")";
    if (k.help != nullptr && *k.help != '\0') s += " - " + std::string(k.help);
    return s;
}

std::string check_local_set(std::span<const LocalKey> keys, std::string_view module, std::string_view key,
                            const std::vector<std::string>& values) {
    const std::string who = "module " + std::string(module);
    if (keys.empty()) return who + " declares no LOCAL keys: nothing can be set at run time";
    const LocalKey* k = find_local_key(keys, key);
    if (k == nullptr) {
        std::string names;
        for (const auto& d : keys) names += (names.empty() ? "" : " ") + std::string(d.name);
        return "no LOCAL key " + std::string(key) + " in " + who + " (it takes " + names + ")";
    }
    if (!k->live)
        return "LOCAL " + std::string(key) + " of " + who +
               " is read only at spawn: edit the .rmod and respawn (kill, spawn)";
    if (const auto p = value_problem(*k, values); !p.empty()) return "LOCAL " + std::string(key) + ": " + p;
    return "";
}

void check_local_section(std::span<const LocalKey> keys, std::string_view module, const LocalConfig& local) {
    if (keys.empty()) return;
    for (const auto& e : local.entries()) {
        const LocalKey* k = find_local_key(keys, e.key);
        std::string why;
        if (k == nullptr) {
            std::string names;
            for (const auto& d : keys) names += (names.empty() ? "" : ", ") + std::string(d.name);
            why = "not a key of " + std::string(module) + " (" + names + ")";
        } else {
            why = value_problem(*k, e.values);
        }
        if (!why.empty()) throw cfg::ParseError(local.file, e.line, "LOCAL " + e.key + ": " + why);
    }
}

}  // namespace chimera
