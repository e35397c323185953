// .rmod (§3.8) and .sbs (§4.5.1) readers.
#include "chimera/sbs_files.hpp"

#include <gtest/gtest.h>

#include <string>

using chimera::cfg::ParseError;
using chimera::cfg::Reader;

namespace {

chimera::RmodFile rmod(const std::string& text, const std::string& path = "qmdiff.rmod") {
    auto r = Reader::from_string(text, path);
    return chimera::parse_rmod(r, path);
}
chimera::SbsFile sbs(const std::string& text, const std::string& dir = "/cfg") {
    auto r = Reader::from_string(text, "sub.sbs");
    return chimera::parse_sbs(r, dir);
}
template <typename F>
std::string error_of(F&& body) {
    try {
        body();
    } catch (const ParseError& e) {
        return e.what();
    }
    return "";
}

}  // namespace

TEST(RmodFile, ThesisQmdiffExample) {
    auto f = rmod(
        "MODULE    diff\n"
        "DESC      measured joint position differentiator\n"
        "SVARALIAS Z=Q_MEZ\n"
        "SVARALIAS Z^=Q^_MEZ\n"
        "INCONST   NDOF\n"
        "OUTCONST  none\n"
        "INVAR     Z\n"
        "OUTVAR    Z^\n"
        "TASKTYPE  periodic\n"
        "FREQ      100\n"
        "EOF\n",
        "lib/qmdiff.rmod");
    EXPECT_EQ(f.name, "qmdiff");
    EXPECT_EQ(f.module, "diff");
    EXPECT_EQ(f.desc, "measured joint position differentiator");
    EXPECT_EQ(f.in_consts, std::vector<std::string>{"NDOF"});
    EXPECT_TRUE(f.out_consts.empty());
    EXPECT_EQ(f.in_vars, std::vector<std::string>{"Z"});
    EXPECT_EQ(f.global_in_vars(), std::vector<std::string>{"Q_MEZ"});
    EXPECT_EQ(f.global_out_vars(), std::vector<std::string>{"Q^_MEZ"});
    EXPECT_EQ(f.global_name("NDOF"), "NDOF");
    EXPECT_EQ(f.type, chimera::TaskType::periodic);
    EXPECT_DOUBLE_EQ(f.freq, 100.0);
    EXPECT_DOUBLE_EQ(f.period, 0.01);
}

TEST(RmodFile, PeriodAndLocalSection) {
    auto f = rmod(
        "DEFINE G 2.5\n"
        "MODULE invdyn\nDESC inverse dynamics\nINCONST LINKS COGLINKS MASS\nOUTCONST none\n"
        "INVAR A B\nOUTVAR C\nTASKTYPE synchronous\nPERIOD 0.005\n\n"
        "LOCAL\nFC 0.0 400.0 G\nMODE linear\nEOF\n",
        "invdyn.rmod");
    EXPECT_DOUBLE_EQ(f.freq, 200.0);
    EXPECT_EQ(f.type, chimera::TaskType::synchronous);
    EXPECT_EQ(f.in_consts.size(), 3u);
    EXPECT_EQ(f.local.numbers("FC"), (std::vector<double>{0.0, 400.0, 2.5}));
    EXPECT_EQ(f.local.text("MODE"), "linear");
    EXPECT_EQ(f.local.find("FC")->line, 12);
    EXPECT_DOUBLE_EQ(f.local.number("ABSENT", 7.0), 7.0);
    EXPECT_THROW(f.local.number("FC", 0), std::invalid_argument);
    EXPECT_THROW(f.local.numbers("MODE"), std::invalid_argument);
}

TEST(RmodFile, AperiodicMayOmitFrequency) {
    auto f = rmod("MODULE log\nDESC logger\nINVAR X\nTASKTYPE sporadic\nEOF\n");
    EXPECT_EQ(f.type, chimera::TaskType::sporadic);
    EXPECT_EQ(f.freq, 0.0);
    EXPECT_TRUE(f.out_vars.empty());
}

TEST(RmodFile, Errors) {
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 10\nPERIOD 0.1\nEOF\n"); }),
              "qmdiff.rmod:5: FREQ and PERIOD are exclusive: FREQ already given at line 4");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nEOF\n"); }),
              "qmdiff.rmod:4: a periodic task needs FREQ or PERIOD, found EOF");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE cyclic\nFREQ 1\nEOF\n"); }),
              "qmdiff.rmod:3: TASKTYPE must be periodic, synchronous, sporadic, deferrable or background, "
              "found 'cyclic'");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nSVARALIAS Z\nTASKTYPE periodic\nFREQ 1\nEOF\n"); }),
              "qmdiff.rmod:3: SVARALIAS expects internal=GLOBAL, found 'Z'");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nINVAR X none\nTASKTYPE periodic\nFREQ 1\nEOF\n"); }),
              "qmdiff.rmod:3: INVAR: 'none' cannot be mixed with port names");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nINVAR X\nOUTVAR X\nTASKTYPE periodic\nFREQ 1\nEOF\n"); }),
              "");  // reading and writing the same name are different ports
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nINCONST X\nINVAR X\nTASKTYPE periodic\nFREQ 1\nEOF\n"); }),
              "qmdiff.rmod:4: port 'X' is listed twice");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ -3\nEOF\n"); }),
              "qmdiff.rmod:4: FREQ must be a positive number");
    // Keyword order is the thesis's: INVAR before INCONST is out of place.
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nINVAR X\nINCONST Y\nTASKTYPE periodic\nFREQ 1\nEOF\n"); }),
              "qmdiff.rmod:4: expected TASKTYPE, found INCONST");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 1\nLOCAL\nK 1\nK 2\nEOF\n"); }),
              "qmdiff.rmod:7: LOCAL key 'K' given twice");
    EXPECT_EQ(error_of([] { rmod("MODULE a-b\nDESC d\nTASKTYPE periodic\nFREQ 1\nEOF\n"); }),
              "qmdiff.rmod:1: MODULE name 'a-b' must be an identifier (letters, digits, _)");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 1\n"); }),
              "qmdiff.rmod:4: truncated file: expected EOF as the last line, found end of file");
    // One frequency range for the file, spawn and `freq` (1e-6 .. 1e6 Hz).
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 99999999999999999999999\nEOF\n"); }),
              "qmdiff.rmod:4: FREQ 99999999999999999999999: 1e+23 Hz is above the highest task frequency, 1e+06 Hz "
              "(a period of 1 us)");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nPERIOD 1e-9\nEOF\n"); }),
              "qmdiff.rmod:4: PERIOD 1e-9: 1e+09 Hz is above the highest task frequency, 1e+06 Hz (a period of 1 us)");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nPERIOD 1e7\nEOF\n"); }),
              "qmdiff.rmod:4: PERIOD 1e7: 1e-07 Hz is below the lowest task frequency, 1e-06 Hz (a period of 10^6 s)");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 1000000\nEOF\n"); }), "");
    EXPECT_EQ(chimera::frequency_problem(1e308),
              "1e+308 Hz is above the highest task frequency, 1e+06 Hz (a period of 1 us)");
}

TEST(SbsFile, FullFile) {
    auto f = sbs(
        "SUBSYSTEM pidctl\nSVARFILE pid.svar\nMASTER control\n"
        "RTPU cpu0\nSCHEDULER RM\nERRPRINT errors\n"
        "RTPU control 1\nMAXFREQ 2000\nMINFREQ 10\nUSAGE shared\nBACKEND deadline\nSCHEDULER EDF\nEOF\n",
        "/opt/x");
    EXPECT_EQ(f.subsystem, "pidctl");
    EXPECT_EQ(f.svarfile, "/opt/x/pid.svar");
    ASSERT_EQ(f.rtpus.size(), 2u);
    EXPECT_EQ(f.rtpus[0].cpu, 0);
    EXPECT_EQ(f.rtpus[0].scheduler, chimera::Scheduler::RM);
    EXPECT_EQ(f.rtpus[0].errprint, chimera::ErrPrint::errors);
    EXPECT_EQ(f.rtpus[0].backend, chimera::Backend::fifo);
    EXPECT_EQ(f.rtpus[1].name, "control");
    EXPECT_EQ(f.rtpus[1].cpu, 1);
    EXPECT_EQ(f.rtpus[1].usage, chimera::Usage::shared);
    EXPECT_EQ(f.rtpus[1].backend, chimera::Backend::deadline);
    EXPECT_EQ(f.rtpus[1].scheduler, chimera::Scheduler::EDF);
    EXPECT_DOUBLE_EQ(f.rtpus[1].minfreq, 10);
    EXPECT_DOUBLE_EQ(f.rtpus[1].maxfreq, 2000);
    EXPECT_EQ(f.master, "control");
    EXPECT_EQ(f.find_rtpu("control")->line, 7);
}

TEST(SbsFile, Defaults) {
    auto f = sbs("SUBSYSTEM s\nSVARFILE /abs/t.svar\nRTPU cpu3\nEOF\n");
    EXPECT_EQ(f.svarfile, "/abs/t.svar");
    EXPECT_EQ(f.master, "cpu3");
    EXPECT_EQ(f.rtpus[0].cpu, 3);
    EXPECT_EQ(f.rtpus[0].scheduler, chimera::Scheduler::MUF);
    EXPECT_EQ(f.rtpus[0].usage, chimera::Usage::exclusive);
    EXPECT_EQ(f.rtpus[0].errprint, chimera::ErrPrint::warnings);
}

TEST(SbsFile, Accounting) {
    auto f = sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nACCOUNTING halftick 0.004\n"
                 "RTPU cpu1\nACCOUNTING nanoseconds\nRTPU cpu2\nEOF\n");
    EXPECT_TRUE(f.rtpus[0].half_tick);
    EXPECT_DOUBLE_EQ(f.rtpus[0].tick, 0.004);
    EXPECT_FALSE(f.rtpus[1].half_tick);
    EXPECT_FALSE(f.rtpus[2].half_tick);  // the default
}

// Found by fuzz/fuzz_sbs: a combined task naming one rmod twice was accepted
// (the same rmod on two TASK lines is refused). fuzz/corpus/sbs/rmod-twice-in-a-task.sbs
TEST(SbsFile, ACombinedTaskNamesEachRmodOnce) {
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nTASK a+b+a\nEOF\n"); }),
              "sub.sbs:4: TASK a+b+a: rmod a is named twice");
    EXPECT_EQ(sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nTASK a+b\nEOF\n").tasks.at(0).rmods.size(), 2u);
}

// Found by fuzz/fuzz_sbs (CI): a cpuN name with a number past int wrapped to a negative CPU.
// fuzz/corpus/sbs/cpu-number-overflow.sbs
TEST(SbsFile, ACpuNumberPastTheKernelsCpuSetsIsRefused) {
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu4294967296\nEOF\n"); }),
              "sub.sbs:3: RTPU cpu4294967296: give the CPU it runs on (RTPU name CPU), or name it cpuN");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU main 4096\nEOF\n"); }),
              "sub.sbs:3: RTPU main: expected a CPU number 0..4095, found '4096'");
    EXPECT_EQ(sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu4095\nEOF\n").rtpus.at(0).cpu, 4095);
}

TEST(SbsFile, Errors) {
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nMASTER cpu9\nRTPU cpu0\nEOF\n"); }),
              "sub.sbs:3: MASTER names RTPU 'cpu9', which is not defined in this file");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU main\nEOF\n"); }),
              "sub.sbs:3: RTPU main: give the CPU it runs on (RTPU name CPU), or name it cpuN");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nSCHEDULER FIFO\nEOF\n"); }),
              "sub.sbs:4: SCHEDULER must be RM, EDF or MUF, found 'FIFO'");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nUSAGE both\nEOF\n"); }),
              "sub.sbs:4: USAGE must be exclusive or shared, found 'both'");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nERRPRINT all\nEOF\n"); }),
              "sub.sbs:4: ERRPRINT must be errors, warnings or none, found 'all'");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nMINFREQ 10\nMAXFREQ 5\nEOF\n"); }),
              "sub.sbs:3: RTPU cpu0: MINFREQ must be below MAXFREQ");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nMAXFREQ 1e30\nEOF\n"); }),
              "sub.sbs:4: MAXFREQ: 1e+30 Hz is above the highest task frequency, 1e+06 Hz (a period of 1 us)");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nMINFREQ nan\nEOF\n"); }),
              "sub.sbs:4: expected a number for MINFREQ, found 'nan'");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nUSAGE shared\nUSAGE shared\nEOF\n"); }),
              "sub.sbs:5: USAGE given twice for RTPU cpu0");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nRTPU cpu0\nEOF\n"); }),
              "sub.sbs:4: RTPU 'cpu0' is defined twice");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nEOF\n"); }), "sub.sbs:3: expected RTPU, found EOF");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nPRIORITY 3\nEOF\n"); }),
              "sub.sbs:4: expected SCHEDULER or USAGE or ERRPRINT or MINFREQ or MAXFREQ or BACKEND or ACCOUNTING, "
              "found PRIORITY");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nACCOUNTING halftick\nEOF\n"); }),
              "sub.sbs:4: ACCOUNTING halftick takes the tick in seconds, e.g. halftick 0.001");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nACCOUNTING halftick 0\nEOF\n"); }),
              "sub.sbs:4: ACCOUNTING halftick: the tick must be more than 0 and at most 1 second");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU cpu0\nACCOUNTING ticks\nEOF\n"); }),
              "sub.sbs:4: ACCOUNTING must be nanoseconds or halftick TICK, found 'ticks'");
    EXPECT_EQ(error_of([] { sbs("SUBSYSTEM s\nSVARFILE t.svar\nRTPU x 1 2\nEOF\n"); }),
              "sub.sbs:3: RTPU takes 1 to 2 arguments, found 3");
}

TEST(RmodFile, SchedulingParameters) {
    auto f = rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 100\nCRIT 6\nWCET 0.004\nEFFECTIVE 0.002\nEOF\n");
    EXPECT_DOUBLE_EQ(f.wcet, 0.004);
    EXPECT_DOUBLE_EQ(f.effective, 0.002);
    EXPECT_EQ(f.crit, 6);
    auto g = rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 100\nLOCAL\nWCET_NOT 1\nEOF\n");
    EXPECT_EQ(g.wcet, 0.0);  // absent: C = 0 (every task in the critical set)
    EXPECT_FALSE(g.crit);
    auto s = rmod("MODULE a\nDESC d\nTASKTYPE deferrable\nPERIOD 0.1\nWCET 0.005\nEOF\n");
    EXPECT_DOUBLE_EQ(s.period, 0.1);
    EXPECT_DOUBLE_EQ(s.wcet, 0.005);
}

TEST(RmodFile, SchedulingParameterErrors) {
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 100\nWCET 0.02\nEOF\n"); }),
              "qmdiff.rmod:5: WCET 0.02 s exceeds the period 0.010000 s");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 10\nWCET 0.01\nWCET 0.02\nEOF\n"); }),
              "qmdiff.rmod:6: WCET given twice");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 10\nWCET 0.01\nEFFECTIVE 0.02\nEOF\n"); }),
              "qmdiff.rmod:6: EFFECTIVE (0.020000 s) exceeds WCET (0.010000 s): E is at most C (§6.4)");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 10\nCRIT 63\nEOF\n"); }),
              "qmdiff.rmod:5: CRIT must be 1..62 (0 and 63 are reserved), found 63");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE periodic\nFREQ 10\nWCET -1\nEOF\n"); }),
              "qmdiff.rmod:5: WCET must be a positive number of seconds");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE deferrable\nWCET 0.01\nEOF\n"); }),
              "qmdiff.rmod:5: a deferrable server needs both PERIOD (or FREQ) and WCET (its capacity), or "
              "neither (then it serves in the background)");
    EXPECT_EQ(error_of([] { rmod("MODULE a\nDESC d\nTASKTYPE sporadic\nPERIOD 0.1\nEFFECTIVE 0.01\nEOF\n"); }),
              "qmdiff.rmod:6: EFFECTIVE makes a soft real-time task, which must be periodic (TASKTYPE sporadic)");
}
