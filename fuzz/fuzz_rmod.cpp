// fuzz/fuzz_rmod.cpp — the .rmod reader (thesis §3.8) on arbitrary text.
//
// Invariants: only cfg::ParseError escapes, with FILE:LINE; what the reader
// accepts is a module spawn can start: an identifier as MODULE, a task
// frequency frequency_problem() accepts (and 1/period), FREQ/PERIOD for
// every periodic or synchronous task, a WCET within the period and EFFECTIVE
// within the WCET, CRIT 1..62, port names and LOCAL keys unique, SVARALIAS
// applied without error.
#include <cctype>
#include <cmath>
#include <set>

#include "chimera/cfg.hpp"
#include "chimera/sbs_files.hpp"
#include "harness.hpp"

using namespace chimera;
using fuzz::require;

namespace {

void check_ports(const std::vector<std::string>& ports, const char* list) {
    std::set<std::string> seen;
    for (const auto& p : ports) {
        require(!p.empty() && p != "none", std::string(list) + ": port '" + p + "' accepted");
        require(seen.insert(p).second, std::string(list) + ": port " + p + " listed twice");
    }
}

void check_timing(const RmodFile& f) {
    require(!(f.freq > 0) || frequency_problem(f.freq).empty(), "FREQ accepted that spawn refuses: " +
                                                                     frequency_problem(f.freq));
    require(f.freq == 0 || (f.freq > 0 && std::fabs(f.period * f.freq - 1) < 1e-9),
            "period is not 1/freq");
    require(is_aperiodic(f.type) || f.freq > 0, "a periodic task without FREQ or PERIOD");
    require(std::isfinite(f.wcet) && f.wcet >= 0, "WCET not a finite non-negative time");
    require(f.freq == 0 || f.wcet <= f.period, "WCET exceeds the period");
    require(std::isfinite(f.effective) && f.effective >= 0 && (f.effective == 0 || f.effective <= f.wcet),
            "EFFECTIVE not within WCET");
    require(!f.crit || (*f.crit >= 1 && *f.crit <= 62), "CRIT outside 1..62");
}

void check_rmod(const RmodFile& f) {
    require(f.name == "fuzz", "rmod name is not the file's stem: " + f.name);
    require(!f.module.empty(), "empty MODULE accepted");
    for (char c : f.module)
        require(std::isalnum(static_cast<unsigned char>(c)) || c == '_', "MODULE not an identifier: " + f.module);
    check_ports(f.in_consts, "INCONST");
    check_ports(f.out_consts, "OUTCONST");
    check_ports(f.in_vars, "INVAR");
    check_ports(f.out_vars, "OUTVAR");
    std::set<std::string> aliased;
    for (const auto& [from, to] : f.aliases)
        require(aliased.insert(from).second && !to.empty(), "SVARALIAS " + from + " twice or to nothing");
    // The names spawn looks up in the table.
    require(f.global_in_vars().size() == f.in_vars.size() && f.global_out_vars().size() == f.out_vars.size() &&
                f.global_in_consts().size() == f.in_consts.size() &&
                f.global_out_consts().size() == f.out_consts.size(),
            "SVARALIAS changed a port list's length");
    check_timing(f);
    std::set<std::string> keys;
    for (const auto& e : f.local.entries()) {
        require(keys.insert(e.key).second, "LOCAL key " + e.key + " twice");
        require(f.local.find(e.key) == &e, "LOCAL key " + e.key + " not found");
        try {
            (void)f.local.number(e.key, 0.0);  // documented: std::invalid_argument when not one number
        } catch (const std::invalid_argument& err) {
            require(std::string(err.what()).rfind("fuzz.rmod:" + std::to_string(e.line) + ":", 0) == 0,
                    std::string("a LOCAL error without FILE:LINE: ") + err.what());
        }
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string file = "fuzz.rmod";
    RmodFile f;
    if (fuzz::accepted<cfg::ParseError>(file, [&] {
            cfg::Reader reader = cfg::Reader::from_string(fuzz::text_of(data, size), file);
            f = parse_rmod(reader, file);
        }))
        check_rmod(f);
    return 0;
}
