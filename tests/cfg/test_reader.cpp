#include "chimera/cfg.hpp"

#include <gtest/gtest.h>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sys/stat.h>

using chimera::cfg::Line;
using chimera::cfg::ParseError;
using chimera::cfg::Reader;

namespace {

// Runs `body` and returns the ParseError's what(), or "" when nothing was thrown.
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

TEST(CfgReader, DefinesAreSubstitutedAndNegated) {
    auto r = Reader::from_string(
        "DEFINE DOF 7\nDEFINE PI 3.5\nDEFINE NEG -2\nINIT DOF -PI PI -NEG x\nEOF\n", "t.svar");
    Line l = r.expect("INIT");
    ASSERT_EQ(l.args.size(), 5u);
    EXPECT_EQ(l.args[0], "7");
    EXPECT_EQ(l.args[1], "-3.5");
    EXPECT_EQ(l.args[2], "3.5");
    EXPECT_EQ(l.args[3], "2");
    EXPECT_EQ(l.args[4], "x");
    EXPECT_EQ(l.number, 4);
    r.expect_end();
}

TEST(CfgReader, CommentsAndBlankLinesAreIgnored) {
    auto r = Reader::from_string("# header\n\n  NAME  A   # trailing\n\t\nDESC a b#c\nEOF\n", "f");
    Line name = r.expect("NAME");
    EXPECT_EQ(name.number, 3);
    EXPECT_EQ(name.args, std::vector<std::string>{"A"});
    Line desc = r.expect("DESC");
    EXPECT_EQ(desc.text, "a b#c");  // '#' inside a word is not a comment
    r.expect_end();
}

TEST(CfgReader, MissingEofIsTruncation) {
    auto r = Reader::from_string("NAME A\nTYPE int\n", "cut.svar");
    r.expect("NAME");
    r.expect("TYPE");
    EXPECT_EQ(error_of([&] { r.expect_end(); }),
              "cut.svar:2: truncated file: expected EOF as the last line, found end of file");
}

TEST(CfgReader, TextAfterEofIsAnError) {
    auto r = Reader::from_string("NAME A\nEOF\n# fine\nNAME B\n", "x");
    r.expect("NAME");
    EXPECT_EQ(error_of([&] { r.expect_end(); }), "x:4: expected nothing after EOF, found 'NAME B'");
}

TEST(CfgReader, ExpectNamesWhatWasFound) {
    auto r = Reader::from_string("AME SG_MEZ\nEOF\n", "s.svar");
    EXPECT_EQ(error_of([&] { r.expect("NAME"); }), "s.svar:1: expected NAME, found AME");
    EXPECT_EQ(error_of([&] { r.expect_one_of({"FREQ", "PERIOD"}); }),
              "s.svar:1: expected FREQ or PERIOD, found AME");
}

TEST(CfgReader, ExpectAtEofSaysEof) {
    auto r = Reader::from_string("EOF\n", "e");
    EXPECT_EQ(error_of([&] { r.expect("NAME"); }), "e:1: expected NAME, found EOF");
    EXPECT_FALSE(r.next().has_value());
}

TEST(CfgReader, NumbersAreWholeTokens) {
    auto r = Reader::from_string("V 1.5 2x 0x10 -3\nEOF\n", "n");
    Line l = r.expect("V");
    EXPECT_DOUBLE_EQ(r.to_double(l, 0, "V"), 1.5);
    EXPECT_EQ(error_of([&] { r.to_double(l, 1, "V element 2"); }),
              "n:1: expected a number for V element 2, found '2x'");
    EXPECT_EQ(r.to_int(l, 2, "V"), 16);
    EXPECT_EQ(r.to_int(l, 3, "V"), -3);
    EXPECT_EQ(error_of([&] { r.to_int(l, 0, "V"); }), "n:1: expected an integer for V, found '1.5'");
}

TEST(CfgReader, ArgumentCounts) {
    auto r = Reader::from_string("FREQ 1 2\nEOF\n", "a");
    Line l = r.expect("FREQ");
    EXPECT_EQ(error_of([&] { r.require_args(l, 1); }), "a:1: FREQ takes 1 argument, found 2");
    EXPECT_EQ(error_of([&] { r.require_args(l, 2); }), "");
}

TEST(CfgReader, DuplicateDefineIsRefused) {
    auto r = Reader::from_string("DEFINE A 1\nDEFINE A 2\nEOF\n", "d");
    EXPECT_EQ(error_of([&] { r.peek(); }), "d:2: DEFINE A is already defined");
}

TEST(CfgReader, OnlyRegularFilesOfABoundedSizeAreRead) {
    // A FIFO would block the reader until a writer came; /dev/zero would be
    // read until memory ran out: both are refused before anything is read.
    char dir[] = "/tmp/cfg_reader_XXXXXX";
    ASSERT_NE(::mkdtemp(dir), nullptr);
    const std::string fifo = std::string(dir) + "/fifo.svar";
    ASSERT_EQ(::mkfifo(fifo.c_str(), 0600), 0);
    EXPECT_EQ(error_of([&] { Reader::from_file(fifo); }), fifo + ": cannot read file: it is a FIFO, not a regular file");
    EXPECT_EQ(error_of([] { Reader::from_file("/dev/zero"); }),
              "/dev/zero: cannot read file: it is a character device, not a regular file");
    const std::string big = std::string(dir) + "/big.svar";
    {
        std::ofstream f(big);
        const std::string line(1023, '#');
        for (int i = 0; i < 4097; ++i) f << line << '\n';
    }
    EXPECT_EQ(error_of([&] { Reader::from_file(big); }),
              big + ": cannot read file: 4195328 bytes, more than the 4 MiB a configuration file may have");
    // An empty file is named with a line, like every other error.
    const std::string empty = std::string(dir) + "/empty.rmod";
    { std::ofstream f(empty); }
    EXPECT_EQ(error_of([&] { Reader::from_file(empty).peek(); }),
              empty + ":1: empty file: expected the file's content and EOF as the last line");
    std::filesystem::remove_all(dir);
}

TEST(CfgReader, UnreadableFile) {
    EXPECT_EQ(error_of([] { Reader::from_file("/nonexistent/x.svar"); }),
              "/nonexistent/x.svar: cannot open file: No such file or directory");
    // A directory opens as a stream but reads nothing: said as such, not as a truncated file.
    EXPECT_EQ(error_of([] { Reader::from_file("/tmp"); }), "/tmp: cannot read file: it is a directory");
}
