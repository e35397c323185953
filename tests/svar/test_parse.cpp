// The .svar parser (thesis §5.5.2).
#include <gtest/gtest.h>

#include <cstdlib>
#include <fstream>
#include <sstream>

#include "chimera/cfg.hpp"
#include "chimera/svar.hpp"

using chimera::cfg::ParseError;
using namespace chimera::svar;

namespace {

std::string data_file(const std::string& name) {
    const char* root = std::getenv("CHIMERA_SOURCE_ROOT");
    return std::string(root ? root : "..") + "/tests/svar/data/" + name;
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

std::string parse_error(const std::string& text) {
    return error_of([&] { parse_svar_string(text, "t.svar"); });
}

const char* kHead = "NAME X\nTYPE float\nDESC d\nUNITS u\nNELEM 3\n";

}  // namespace

TEST(SvarParse, ThesisSampleFailsAtTheAmeLine) {
    const std::string path = data_file("thesis_sample.svar");
    EXPECT_EQ(error_of([&] { parse_svar_file(path); }), path + ":23: expected NAME, found AME");
}

TEST(SvarParse, ThesisSampleFixedIsAccepted) {
    const TableSpec spec = parse_svar_file(data_file("thesis_sample_fixed.svar"));
    ASSERT_EQ(spec.vars.size(), 4u);
    const VarSpec& q = spec.vars[0];
    EXPECT_EQ(q.name, "Q_REF");
    EXPECT_EQ(q.type, Type::double_);
    EXPECT_EQ(q.elem_size, 8u);
    EXPECT_EQ(q.nelem, 7u);
    EXPECT_EQ(q.desc, "reference joint position");
    EXPECT_EQ(q.units, "radians");
    EXPECT_EQ(q.line, 5);
    ASSERT_TRUE(q.has_init);
    EXPECT_DOUBLE_EQ(q.init[0], -3.141592653589793);
    EXPECT_DOUBLE_EQ(q.init[2], 6.283185307179586);
    ASSERT_TRUE(q.has_range);
    EXPECT_DOUBLE_EQ(q.min[2], -6.283185307179586);
    EXPECT_DOUBLE_EQ(q.max[1], 0.0);
    EXPECT_EQ(spec.vars[1].name, "Q^_REF");
    EXPECT_EQ(spec.vars[1].units, "radians/seconds");
    const VarSpec& sg = spec.vars[2];
    EXPECT_EQ(sg.name, "SG_MEZ");
    EXPECT_EQ(sg.type, Type::int_);
    EXPECT_EQ(sg.nelem, 8u);
    EXPECT_FALSE(sg.has_init);
    EXPECT_TRUE(sg.init.empty());  // no INIT: zeros
    EXPECT_EQ(sg.init_at(7), 0.0);
    EXPECT_EQ(sg.min, std::vector<double>(8, -1000.0));
    EXPECT_EQ(sg.max, std::vector<double>(8, 1000.0));
    const VarSpec& traj = spec.vars[3];
    EXPECT_EQ(traj.type, Type::struct_);
    EXPECT_EQ(traj.elem_size, 32u);
    EXPECT_EQ(traj.nelem, 4u);
    EXPECT_EQ(traj.bytes(), 128u);
    EXPECT_TRUE(traj.init.empty());
    EXPECT_FALSE(traj.has_range);
    EXPECT_EQ(spec.find("SG_MEZ"), 2u);
    EXPECT_FALSE(spec.find("NOPE"));
}

TEST(SvarParse, EveryTypeHasItsCSize) {
    const TableSpec spec = parse_svar_string(
        "NAME a\nTYPE byte\nDESC\nUNITS\nNELEM 1\n"
        "NAME b\nTYPE char\nDESC\nUNITS\nNELEM 1\n"
        "NAME c\nTYPE word\nDESC\nUNITS\nNELEM 1\n"
        "NAME d\nTYPE short\nDESC\nUNITS\nNELEM 1\n"
        "NAME e\nTYPE unsigned\nDESC\nUNITS\nNELEM 1\n"
        "NAME f\nTYPE int\nDESC\nUNITS\nNELEM 1\n"
        "NAME g\nTYPE float\nDESC\nUNITS\nNELEM 1\n"
        "NAME h\nTYPE double\nDESC\nUNITS\nNELEM 1\n"
        "NAME i\nTYPE struct[5]\nDESC\nUNITS\nNELEM 1\nEOF\n",
        "t.svar");
    const std::size_t sizes[] = {1, 1, 2, 2, 4, 4, 4, 8, 5};
    const Type types[] = {Type::byte_, Type::char_, Type::word, Type::short_, Type::unsigned_,
                          Type::int_, Type::float_, Type::double_, Type::struct_};
    ASSERT_EQ(spec.vars.size(), 9u);
    for (std::size_t i = 0; i < 9; ++i) {
        EXPECT_EQ(spec.vars[i].elem_size, sizes[i]) << i;
        EXPECT_EQ(spec.vars[i].type, types[i]) << i;
    }
    EXPECT_EQ(type_spelling(Type::struct_, 32), "struct[32]");
    EXPECT_EQ(type_spelling(Type::unsigned_, 4), "unsigned");
}

TEST(SvarParse, ShortInitLeavesTheOthersZero) {
    const TableSpec s = parse_svar_string(std::string(kHead) + "INIT 1.5\nEOF\n", "t.svar");
    EXPECT_EQ(s.vars[0].init, (std::vector<double>{1.5}));
    EXPECT_EQ(s.vars[0].init_at(1), 0.0);
    EXPECT_EQ(s.vars[0].init_at(2), 0.0);
}

// Found by fuzz/fuzz_svar: the INIT values were padded with zeros to NELEM,
// so this 52-byte file took 2 GB and tens of seconds to parse.
// (fuzz/corpus/svar/nelem-at-the-table-limit.svar)
TEST(SvarParse, ALargeNelemCostsNoMemoryPerElement) {
    const TableSpec s =
        parse_svar_string("NAME A\nTYPE byte\nDESC d\nUNITS u\nNELEM 268435456\nEOF\n", "big.svar");
    EXPECT_EQ(s.vars[0].nelem, kMaxTableDataBytes);
    EXPECT_EQ(s.vars[0].init.capacity(), 0u);
    EXPECT_EQ(s.vars[0].init_at(kMaxTableDataBytes - 1), 0.0);
}

TEST(SvarParse, KeywordOrderIsEnforced) {
    EXPECT_EQ(parse_error("NAME X\nDESC d\nTYPE float\nUNITS u\nNELEM 1\nEOF\n"),
              "t.svar:2: expected TYPE, found DESC");
    EXPECT_EQ(parse_error("NAME X\nTYPE float\nDESC d\nNELEM 1\nEOF\n"),
              "t.svar:4: expected UNITS, found NELEM");
    EXPECT_EQ(parse_error(std::string(kHead) + "MIN 0 0 0\nMAX 1 1 1\nINIT 1\nEOF\n"),
              "t.svar:8: INIT out of order in X: the order is NAME, TYPE, DESC, UNITS, NELEM, "
              "[INIT], [MIN, MAX]");
    EXPECT_EQ(parse_error(std::string(kHead) + "EOF\n" ),
              "");
}

TEST(SvarParse, MinAndMaxBothOrNeitherWithAllElements) {
    EXPECT_EQ(parse_error(std::string(kHead) + "MIN 0 0 0\nEOF\n"),
              "t.svar:7: MIN of X must be followed by MAX, found EOF");
    EXPECT_EQ(parse_error(std::string(kHead) + "MAX 0 0 0\nEOF\n"),
              "t.svar:6: MAX of X without MIN (both or neither)");
    EXPECT_EQ(parse_error(std::string(kHead) + "MIN 0 0\nMAX 1 1 1\nEOF\n"),
              "t.svar:6: MIN of X needs all 3 values, found 2");
    EXPECT_EQ(parse_error(std::string(kHead) + "MIN 0 0 0\nMAX 1 1 1 1\nEOF\n"),
              "t.svar:7: MAX of X needs all 3 values, found 4");
    EXPECT_EQ(parse_error(std::string(kHead) + "MIN 0 2 0\nMAX 1 1 1\nEOF\n"),
              "t.svar:7: MAX value 2 of X (1) is below MIN (2)");
}

TEST(SvarParse, InitChecks) {
    EXPECT_EQ(parse_error(std::string(kHead) + "INIT 1 2 3 4\nEOF\n"),
              "t.svar:6: INIT of X has 4 values, NELEM is 3");
    EXPECT_EQ(parse_error(std::string(kHead) + "INIT\nEOF\n"), "t.svar:6: INIT of X has no values");
    EXPECT_EQ(parse_error(std::string(kHead) + "INIT 1 abc\nEOF\n"),
              "t.svar:6: expected a number for INIT value 2 of X, found 'abc'");
    EXPECT_EQ(parse_error("NAME B\nTYPE byte\nDESC\nUNITS\nNELEM 2\nINIT 1 256\nEOF\n"),
              "t.svar:6: INIT value 2 of B is 256, outside the range of byte");
    EXPECT_EQ(parse_error("NAME I\nTYPE int\nDESC\nUNITS\nNELEM 1\nINIT 1.5\nEOF\n"),
              "t.svar:6: expected an integer for INIT value 1 of I, found '1.5'");
}

TEST(SvarParse, StructsTakeNoInitOrRange) {
    EXPECT_EQ(parse_error("NAME S\nTYPE struct[8]\nDESC\nUNITS\nNELEM 1\nINIT 0\nEOF\n"),
              "t.svar:6: struct variable S cannot have INIT");
    EXPECT_EQ(parse_error("NAME S\nTYPE struct[8]\nDESC\nUNITS\nNELEM 1\nMIN 0\nMAX 0\nEOF\n"),
              "t.svar:6: struct variable S cannot have MIN/MAX");
    EXPECT_EQ(parse_error("NAME S\nTYPE struct[0]\nDESC\nUNITS\nNELEM 1\nEOF\n"),
              "t.svar:2: struct size must be a positive integer, found struct[0]");
    EXPECT_EQ(parse_error("NAME S\nTYPE struct[x]\nDESC\nUNITS\nNELEM 1\nEOF\n"),
              "t.svar:2: struct size must be a positive integer, found struct[x]");
}

TEST(SvarParse, NamesTypesAndCounts) {
    EXPECT_EQ(parse_error("NAME ABCDEFGHIJKLMNOP\nTYPE int\nDESC\nUNITS\nNELEM 1\nEOF\n"),
              "t.svar:1: variable name ABCDEFGHIJKLMNOP has 16 characters, at most 15 are allowed");
    EXPECT_EQ(parse_error("NAME ABCDEFGHIJKLMNO\nTYPE int\nDESC\nUNITS\nNELEM 1\nEOF\n"), "");
    EXPECT_EQ(parse_error("NAME X\nTYPE long\nDESC\nUNITS\nNELEM 1\nEOF\n"),
              "t.svar:2: unknown type long for X (valid: byte, char, word, short, unsigned, int, "
              "float, double, struct[N])");
    EXPECT_EQ(parse_error("NAME X\nTYPE int\nDESC\nUNITS\nNELEM 0\nEOF\n"),
              "t.svar:5: NELEM of X must be at least 1, found 0");
    EXPECT_EQ(parse_error("NAME X\nTYPE int\nDESC\nUNITS\nNELEM 1\n"
                          "NAME Y\nTYPE int\nDESC\nUNITS\nNELEM 1\n"
                          "NAME X\nTYPE int\nDESC\nUNITS\nNELEM 1\nEOF\n"),
              "t.svar:11: duplicate variable X (first defined at line 1)");
    EXPECT_EQ(parse_error("EOF\n"), "t.svar:1: no variables defined (expected NAME before EOF)");
}

TEST(SvarParse, TruncatedFileIsReported) {
    EXPECT_EQ(parse_error(std::string(kHead)),
              "t.svar:5: truncated file: expected EOF as the last line, found end of file");
}

TEST(SvarParse, MissingFileNamesIt) {
    EXPECT_EQ(error_of([] { parse_svar_file("/nonexistent/x.svar"); }),
              "/nonexistent/x.svar: cannot open file: No such file or directory");
}

// A table's size is bounded (kMaxTableDataBytes, 256 MiB) and computed without
// overflow: 64 variables of struct[1073741824] once summed to "0 bytes of
// data" and were created; one NELEM 268435456 of double cost 2 GB and 7 s.
TEST(SvarParse, TableSizeIsBoundedWithoutOverflow) {
    std::string wraps;
    for (int i = 0; i < 64; ++i)
        wraps += "NAME S" + std::to_string(i) + "\nTYPE struct[1073741824]\nDESC d\nUNITS none\nNELEM 268435456\n";
    EXPECT_EQ(parse_error(wraps + "EOF\n"),
              "t.svar:5: NELEM 268435456 of S0 (struct[1073741824]) needs more than the 256 MiB a table may hold");
    EXPECT_EQ(parse_error("NAME BIG\nTYPE double\nDESC d\nUNITS none\nNELEM 268435456\nEOF\n"),
              "t.svar:5: NELEM 268435456 of BIG (double) needs more than the 256 MiB a table may hold");
    // Each fits; together they do not: named at the variable that passes the limit.
    std::string three;
    for (int i = 0; i < 3; ++i)
        three += "NAME V" + std::to_string(i) + "\nTYPE struct[1048576]\nDESC d\nUNITS none\nNELEM 100\n";
    EXPECT_EQ(parse_error(three + "EOF\n"),
              "t.svar:11: variable V2 takes the table's data past the 256 MiB a table may hold");
    // At the limit exactly: accepted.
    EXPECT_EQ(parse_error("NAME ALL\nTYPE struct[1048576]\nDESC d\nUNITS none\nNELEM 256\nEOF\n"), "");
}
