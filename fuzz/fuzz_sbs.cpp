// fuzz/fuzz_sbs.cpp — the .sbs reader (thesis §4.5.1) on arbitrary text.
//
// Invariants: only cfg::ParseError escapes, with FILE:LINE; what the reader
// accepts is a subsystem the master can build: a name of letters, digits, _
// and -, an SVARFILE resolved against the file's folder, at least one RTPU,
// RTPU names unique, a MASTER that is one of them, CPU numbers >= 0,
// 0 < MINFREQ < MAXFREQ (finite), a half-tick in (0, 1] s; TASK lines
// naming each rmod once, on an RTPU of the file, their SET lines with a key
// and a value.
#include <cctype>
#include <cmath>
#include <set>

#include "chimera/cfg.hpp"
#include "chimera/sbs_files.hpp"
#include "harness.hpp"

using namespace chimera;
using fuzz::require;

namespace {

void check_rtpu(const RtpuSpec& r) {
    require(!r.name.empty() && r.cpu >= 0, "RTPU " + r.name + ": no name or a negative CPU");
    require(std::isfinite(r.minfreq) && std::isfinite(r.maxfreq) && r.minfreq > 0 && r.minfreq < r.maxfreq,
            "RTPU " + r.name + ": MINFREQ/MAXFREQ not 0 < min < max");
    require(!r.half_tick || (r.tick > 0 && r.tick <= 1), "RTPU " + r.name + ": half-tick outside (0, 1] s");
    require(r.line > 0, "RTPU " + r.name + " without its line");
}

void check_sbs(const SbsFile& f) {
    require(!f.subsystem.empty(), "empty SUBSYSTEM accepted");
    for (char c : f.subsystem)
        require(std::isalnum(static_cast<unsigned char>(c)) || c == '_' || c == '-',
                "SUBSYSTEM name accepted: " + f.subsystem);
    require(!f.svarfile.empty() && f.svarfile.front() == '/', "SVARFILE not resolved: " + f.svarfile);
    require(!f.rtpus.empty(), "a subsystem without RTPU accepted");
    std::set<std::string> names;
    for (const RtpuSpec& r : f.rtpus) {
        require(names.insert(r.name).second, "RTPU " + r.name + " twice");
        check_rtpu(r);
    }
    require(f.find_rtpu(f.master) != nullptr, "MASTER " + f.master + " is no RTPU of the file");
    std::set<std::string> rmods;
    for (const TaskLine& t : f.tasks) {
        require(!t.rmods.empty() && t.line > 0, "a TASK without rmod or line");
        for (const std::string& rmod : t.rmods)
            require(!rmod.empty() && rmod.find('+') == std::string::npos && rmods.insert(rmod).second,
                    "TASK line " + std::to_string(t.line) + ": rmod '" + rmod + "' empty, combined or a task twice");
        require(t.rtpu.empty() || f.find_rtpu(t.rtpu) != nullptr, "TASK on RTPU " + t.rtpu + ", not in the file");
        for (const TaskLine::Set& set : t.local)
            require(!set.key.empty() && !set.values.empty() && set.line > t.line, "a SET without key or value");
    }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const std::string file = "/fuzz/fuzz.sbs";
    SbsFile f;
    if (fuzz::accepted<cfg::ParseError>(file, [&] {
            cfg::Reader reader = cfg::Reader::from_string(fuzz::text_of(data, size), file);
            f = parse_sbs(reader, "/fuzz");
        }))
        check_sbs(f);
    return 0;
}
