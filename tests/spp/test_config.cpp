// The SPP entries of the hardware configuration file (§7.4.1), the library
// downloaded at init, and translate: every set-up error names FILE:LINE, the
// SPP or the symbol, as spp.hpp promises.
#include <gtest/gtest.h>

#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <string>

#include "spp_test_util.hpp"

using namespace spp_test;
namespace spp = chimera::spp;

namespace {

// The message of the Error `f` throws; a failure when it throws nothing.
template <typename F>
std::string error_of(F&& f) {
    try {
        f();
    } catch (const spp::Error& e) {
        return e.what();
    }
    ADD_FAILURE() << "no spp::Error thrown";
    return {};
}

std::string parse_error(const std::string& text) {
    return error_of([&] { spp::parse_config(text, "lab.spp"); });
}

}  // namespace

TEST(SppConfig, ReadsEveryKeywordAndKeepsDefaultsForTheOptionalOnes) {
    const auto configs = spp::parse_config(
        "# the lab's SPPs\n"
        "DEFINE FPA_MEM 65536\n"
        "SPP fpa0\n"
        "  DRIVER thread\n"
        "  MEMSIZE FPA_MEM\n"
        "  QUEUE 16      # per task\n"
        "  TASKS 3\n"
        "  CPU 1\n"
        "  PRIORITY 40\n"
        "END\n"
        "\n"
        "SPP dsp\n"
        "  MEMSIZE 1024\n"
        "END\n"
        "EOF\n",
        "lab.spp");
    ASSERT_EQ(configs.size(), 2u);
    const spp::Config& a = configs[0];
    EXPECT_EQ(a.name, "fpa0");
    EXPECT_EQ(a.driver, "thread");
    EXPECT_EQ(a.memsize, 65536u);
    EXPECT_EQ(a.queue, 16);
    EXPECT_EQ(a.tasks, 3);
    EXPECT_EQ(a.cpu, 1);
    EXPECT_EQ(a.priority, 40);
    EXPECT_EQ(a.file, "lab.spp");
    EXPECT_EQ(a.line, 3);
    const spp::Config& b = spp::find_config(configs, "dsp");
    EXPECT_EQ(b.memsize, 1024u);
    EXPECT_EQ(b.driver, "thread");
    EXPECT_EQ(b.queue, 64);
    EXPECT_EQ(b.tasks, 8);
    EXPECT_EQ(b.cpu, -1);       // not pinned
    EXPECT_EQ(b.priority, 0);   // SCHED_OTHER
    EXPECT_EQ(b.line, 12);
}

TEST(SppConfig, AFileWithoutItsEofLineIsReportedTruncatedAtItsLastLine) {
    EXPECT_EQ(parse_error("SPP fpa0\n  MEMSIZE 64\nEND\n"),
              "lab.spp:3: truncated file: expected EOF as the last line, found end of file");
    EXPECT_EQ(parse_error("SPP fpa0\nEOF\nMEMSIZE 64\n"), "lab.spp:3: expected nothing after EOF, found 'MEMSIZE 64'");
}

TEST(SppConfig, AnUnknownKeywordIsNamedWithItsLineAndSpp) {
    EXPECT_EQ(parse_error("SPP fpa0\n  MEMSIZE 64\n  ADDRESS 0xe0000000\nEND\nEOF\n"),
              "lab.spp:3: unknown keyword ADDRESS in SPP fpa0");
    EXPECT_EQ(parse_error("MEMSIZE 64\nEOF\n"), "lab.spp:1: expected SPP, found MEMSIZE");
}

TEST(SppConfig, BadValuesNameTheirLine) {
    const std::string head = "SPP fpa0\n  MEMSIZE 64\n";
    EXPECT_EQ(parse_error(head + "  QUEUE 1\nEND\nEOF\n"), "lab.spp:3: QUEUE must be 2..65536, found 1");
    EXPECT_EQ(parse_error(head + "  TASKS 0\nEND\nEOF\n"), "lab.spp:3: TASKS must be 1..256, found 0");
    EXPECT_EQ(parse_error(head + "  CPU -1\nEND\nEOF\n"), "lab.spp:3: CPU must be 0..4095, found -1");
    EXPECT_EQ(parse_error(head + "  PRIORITY 0\nEND\nEOF\n"), "lab.spp:3: PRIORITY must be 1..99, found 0");
    EXPECT_EQ(parse_error(head + "  PRIORITY 100\nEND\nEOF\n"), "lab.spp:3: PRIORITY must be 1..99, found 100");
    EXPECT_EQ(parse_error(head + "  PRIORITY high\nEND\nEOF\n"),
              "lab.spp:3: expected an integer for PRIORITY, found 'high'");
    EXPECT_EQ(parse_error(head + "  QUEUE\nEND\nEOF\n"), "lab.spp:3: QUEUE takes 1 argument, found 0");
    EXPECT_EQ(parse_error(head + "  DRIVER mercury\nEND\nEOF\n"),
              "lab.spp:3: SPP fpa0: unknown driver mercury (thread)");
    EXPECT_EQ(parse_error("SPP fpa0\n  MEMSIZE 0\nEND\nEOF\n"), "lab.spp:2: MEMSIZE must be 1..16G bytes");
    EXPECT_EQ(parse_error("SPP fpa0\n  MEMSIZE 4k\nEND\nEOF\n"),
              "lab.spp:2: expected an integer for MEMSIZE, found '4k'");
    EXPECT_EQ(parse_error(head + "END now\nEOF\n"), "lab.spp:3: END takes 0 arguments, found 1");
}

TEST(SppConfig, StructuralErrorsNameTheLineOfTheSpp) {
    EXPECT_EQ(parse_error("SPP fpa0\n  QUEUE 8\nEND\nEOF\n"), "lab.spp:1: SPP fpa0: MEMSIZE missing");
    EXPECT_EQ(parse_error("SPP fpa0\n  MEMSIZE 64\nEOF\n"), "lab.spp:3: SPP fpa0: missing END");
    EXPECT_EQ(parse_error("SPP a\n MEMSIZE 8\nEND\nSPP a\n MEMSIZE 8\nEND\nEOF\n"),
              "lab.spp:4: SPP a is defined twice (first at line 1)");
    EXPECT_EQ(parse_error("SPP\n MEMSIZE 8\nEND\nEOF\n"), "lab.spp:1: SPP takes 1 argument, found 0");
}

TEST(SppConfig, LoadConfigNamesTheFileItRead) {
    char path[] = "/tmp/chimera-spp-test-XXXXXX";
    const int fd = mkstemp(path);
    ASSERT_GE(fd, 0);
    close(fd);
    {
        std::ofstream f(path);
        f << "SPP fpa0\n  MEMSIZE 128\n  BOGUS 1\nEND\nEOF\n";
    }
    EXPECT_EQ(error_of([&] { spp::load_config(path); }),
              std::string(path) + ":3: unknown keyword BOGUS in SPP fpa0");
    {
        std::ofstream f(path);
        f << "SPP fpa0\n  MEMSIZE 128\nEND\nEOF\n";
    }
    const auto configs = spp::load_config(path);
    ASSERT_EQ(configs.size(), 1u);
    EXPECT_EQ(configs[0].file, path);
    std::remove(path);
    EXPECT_EQ(error_of([&] { spp::load_config(path); }), std::string(path) + ": cannot open file: No such file or directory");
}

TEST(SppConfig, FindConfigNamesTheMissingSpp) {
    const auto configs = spp::parse_config("SPP fpa0\n MEMSIZE 8\nEND\nEOF\n", "lab.spp");
    EXPECT_EQ(error_of([&] { spp::find_config(configs, "fpa1"); }), "spp: no SPP named fpa1 in the configuration");
}

// --- the library --------------------------------------------------------------

TEST(SppLibrary, RefusesDuplicateNamesEmptyRoutinesAndBadVariables) {
    spp::Library lib;
    lib.add_routine("scale", scale);
    lib.add_variable("x", 8);
    EXPECT_EQ(error_of([&] { lib.add_routine("scale", record); }), "spp library: scale is defined twice");
    EXPECT_EQ(error_of([&] { lib.add_variable("scale", 8); }), "spp library: scale is defined twice");
    EXPECT_EQ(error_of([&] { lib.add_routine("x", record); }), "spp library: x is defined twice");
    EXPECT_EQ(error_of([&] { lib.add_routine("nothing", nullptr); }), "spp library: routine nothing has no code");
    EXPECT_EQ(error_of([&] { lib.add_variable("empty", 0); }), "spp library: variable empty has no size");
    EXPECT_EQ(error_of([&] { lib.add_variable("odd", 8, 12); }),
              "spp library: variable odd: alignment must be a power of two");
    EXPECT_EQ(lib.routines().size(), 1u);
    EXPECT_EQ(lib.variables().size(), 1u);
}

TEST(SppLibrary, AVariableThatDoesNotFitInMemsizeIsAnInitErrorNamingItAndTheFileLine) {
    spp::Library lib;
    lib.add_variable("a", 64);
    lib.add_variable("b", 40);
    spp::Config c = make_config();
    c.memsize = 100;  // a fits; b starts at 64 and ends at 104
    c.file = "lab.spp";
    c.line = 7;
    EXPECT_EQ(error_of([&] { spp::Processor::init(c, lib); }),
              "SPP fpa0 (lab.spp:7): library variable b does not fit in MEMSIZE 100");
    c.memsize = 104;
    EXPECT_NO_THROW(spp::Processor::init(c, lib));
}

// A size near SIZE_MAX must not wrap the layout's running offset around to
// "fits": size_of() would then allow XFERs far outside the SPP's memory.
TEST(SppLibrary, AHugeVariableDoesNotFitEvenWhenTheSumWrapsAround) {
    spp::Library lib;
    lib.add_variable("a", 16);
    lib.add_variable("huge", std::numeric_limits<std::size_t>::max() - 8);
    EXPECT_EQ(error_of([&] { spp::Processor::init(make_config(), lib); }),
              "SPP fpa0 (test.spp:1): library variable huge does not fit in MEMSIZE 4096");
    spp::Library aligned;
    aligned.add_variable("a", 16);
    aligned.add_variable("far", 8, std::size_t{1} << 63);
    EXPECT_EQ(error_of([&] { spp::Processor::init(make_config(), aligned); }),
              "SPP fpa0 (test.spp:1): library variable far does not fit in MEMSIZE 4096");
    spp::Library aligned_first;
    aligned_first.add_variable("far", 8, std::size_t{1} << 63);
    EXPECT_EQ(error_of([&] { spp::Processor::init(make_config(), aligned_first); }),
              "SPP fpa0 (test.spp:1): library variable far does not fit in MEMSIZE 4096");
}

// A Config written in code gets the checks a file gets: a PRIORITY of 100
// must not surface later as "no real-time privilege (Invalid argument)".
TEST(SppLibrary, AConfigMadeInCodeIsCheckedAsAFileIsAtInit) {
    const auto init_error = [](auto&& change) {
        spp::Config c = make_config();
        change(c);
        return error_of([&] { spp::Processor::init(c, make_library()); });
    };
    EXPECT_EQ(init_error([](spp::Config& c) { c.priority = 100; }),
              "SPP fpa0 (test.spp:1): PRIORITY must be 1..99 (0: not real-time), found 100");
    EXPECT_EQ(init_error([](spp::Config& c) { c.priority = -1; }),
              "SPP fpa0 (test.spp:1): PRIORITY must be 1..99 (0: not real-time), found -1");
    EXPECT_EQ(init_error([](spp::Config& c) { c.queue = 0; }),
              "SPP fpa0 (test.spp:1): QUEUE must be 2..65536, found 0");
    EXPECT_EQ(init_error([](spp::Config& c) { c.tasks = 0; }),
              "SPP fpa0 (test.spp:1): TASKS must be 1..256, found 0");
    EXPECT_EQ(init_error([](spp::Config& c) { c.cpu = -2; }),
              "SPP fpa0 (test.spp:1): CPU must be 0..4095 (-1: not pinned), found -2");
    EXPECT_EQ(init_error([](spp::Config& c) { c.memsize = 0; }),
              "SPP fpa0 (test.spp:1): MEMSIZE must be 1..16G bytes, found 0");
}

TEST(SppLibrary, AnUnknownDriverIsAnInitErrorNamingTheSpp) {
    spp::Config c = make_config();
    c.driver = "mercury";
    EXPECT_EQ(error_of([&] { spp::Processor::init(c, make_library()); }), "SPP fpa0: unknown driver mercury");
}

TEST(SppLibrary, MemoryStartsZeroed) {
    spp::Library lib;
    lib.add_variable("byte", 1, 1);
    lib.add_variable("vec", 32, 32);
    lib.add_variable("big", 256, 64);
    auto proc = spp::Processor::init(make_config(), lib);
    auto s = spp::Spp::init(*proc, 1);
    for (const auto& [name, bytes] : {std::pair{"byte", 1}, std::pair{"vec", 32}, std::pair{"big", 256}}) {
        std::vector<unsigned char> out(static_cast<std::size_t>(bytes), 0xff);
        ASSERT_EQ(s->read(s->translate(name), out.data(), out.size()), 0);
        ASSERT_EQ(s->wait(), 0);
        for (std::size_t k = 0; k < out.size(); ++k) ASSERT_EQ(out[k], 0) << name << "[" << k << "]";
    }
}

// misalignment(variable, alignment): journals the variable's address modulo
// the alignment, taken where the routine sees it.
void misalignment(spp::Memory& m, const spp::Args& a) {
    const auto address = reinterpret_cast<std::uintptr_t>(m.at(a.h(0)));
    journal.add(static_cast<std::int64_t>(address % static_cast<std::uintptr_t>(a.i(1))));
}

// add_variable takes any power-of-two alignment (a cache line, a page for
// DMA-style buffers): the address must have it, not just the offset.
TEST(SppLibrary, EveryVariableGetsTheAlignmentItAskedFor) {
    reset_fixtures();
    spp::Library lib;
    lib.add_variable("byte", 1, 1);
    lib.add_variable("line", 64, 128);
    lib.add_variable("page", 4096, 4096);
    lib.add_routine("misalignment", misalignment);
    spp::Config c = make_config();
    c.memsize = 3 * 4096;
    // Several SPPs: one base address could be page-aligned by chance.
    for (int instance = 0; instance < 4; ++instance) {
        auto proc = spp::Processor::init(c, lib);
        auto s = spp::Spp::init(*proc, 1);
        for (const auto& [name, align] : {std::pair{"byte", 1}, std::pair{"line", 128}, std::pair{"page", 4096}})
            ASSERT_EQ(s->call(s->translate("misalignment"), spp::Args{}.add(s->translate(name)).add(align)), 0);
        ASSERT_EQ(s->wait(), 0);
    }
    EXPECT_EQ(journal.entries(), std::vector<std::int64_t>(12, 0));
}

// --- translate -----------------------------------------------------------------

TEST(SppTranslate, GivesRoutineAndVariableHandlesAndNamesAnUnknownSymbol) {
    auto proc = spp::Processor::init(make_config(), make_library());
    auto s = spp::Spp::init(*proc, 1);
    const spp::Handle x = s->translate("x");
    const spp::Handle rec = s->translate("record");
    EXPECT_EQ(x.kind, spp::Handle::Kind::variable);
    EXPECT_EQ(x.index, 0u);
    EXPECT_EQ(rec.kind, spp::Handle::Kind::routine);
    EXPECT_EQ(rec.index, 0u);
    EXPECT_EQ(s->translate("where").index, 8u);
    EXPECT_EQ(error_of([&] { s->translate("sclae"); }), "SPP fpa0: no routine or variable named sclae");
    EXPECT_FALSE(proc->lookup("sclae"));
    EXPECT_EQ(proc->lookup("probe").kind, spp::Handle::Kind::variable);
}

TEST(SppTranslate, TasksBeyondTasksAreRefusedUntilOneFinishes) {
    auto proc = spp::Processor::init(make_config(64, 2), make_library());
    auto a = spp::Spp::init(*proc, 1);
    auto b = spp::Spp::init(*proc, 2);
    EXPECT_EQ(error_of([&] { spp::Spp::init(*proc, 3); }), "SPP fpa0: all 2 task slots are in use (TASKS)");
    a.reset();  // finish
    auto c = spp::Spp::init(*proc, 3);
    EXPECT_EQ(c->priority(), 3);
    EXPECT_EQ(b->priority(), 2);
}
