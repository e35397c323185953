// Splitting commands and words: the prompt, `-c` and the network read a
// command line the same way through these functions.
#include "command_line.hpp"

#include <gtest/gtest.h>

using namespace chimera::cli;
using V = std::vector<std::string>;

TEST(CommandLine, SplitsScriptAtSemicolonsAndNewlines) {
    EXPECT_EQ(split_commands("spawn pid; on pid;status"), (V{"spawn pid", "on pid", "status"}));
    EXPECT_EQ(split_commands("spawn a\non a\n\n  ;; status  "), (V{"spawn a", "on a", "status"}));
    EXPECT_TRUE(split_commands("  ; ;\n").empty());
}

TEST(CommandLine, SemicolonInsideQuotesDoesNotSplit) {
    EXPECT_EQ(split_commands("set pid NAME 'a;b'; status"), (V{"set pid NAME 'a;b'", "status"}));
    EXPECT_EQ(split_commands("set x \"q\\\";r\"; on"), (V{"set x \"q\\\";r\"", "on"}));
}

TEST(CommandLine, CommentsRunToTheEndOfTheLine) {
    EXPECT_EQ(split_commands("# setup\nspawn a # the source; on a\non a"), (V{"spawn a", "on a"}));
    // '#' inside a word is not a comment.
    EXPECT_EQ(split_commands("set a KEY x#y"), (V{"set a KEY x#y"}));
}

TEST(CommandLine, UnterminatedQuoteIsAnError) {
    EXPECT_THROW(split_commands("set a 'oops"), SyntaxError);
    EXPECT_THROW(split_words("set a \"oops"), SyntaxError);
    EXPECT_THROW(split_words("set a 'oops"), SyntaxError);
}

TEST(CommandLine, SplitsWords) {
    EXPECT_EQ(split_words("  spawn\tpid  cpu0 "), (V{"spawn", "pid", "cpu0"}));
    EXPECT_EQ(split_words("set 'a b' \"c \\\"d\\\" \\\\\" e'f'g"),
              (V{"set", "a b", "c \"d\" \\", "efg"}));
    EXPECT_EQ(split_words("display # comment"), (V{"display"}));
    EXPECT_EQ(split_words("''"), (V{""}));
    EXPECT_TRUE(split_words("   ").empty());
}

TEST(CommandLine, QuoteWordRoundTrips) {
    for (std::string w : {"plain", "two words", "semi;colon", "q\"uote", "back\\slash", "#hash", "",
                          "it's"}) {
        const auto words = split_words(quote_word(w));
        ASSERT_EQ(words.size(), 1u) << w;
        EXPECT_EQ(words[0], w);
    }
    EXPECT_EQ(quote_word("plain"), "plain");
}

TEST(CommandLine, GlobMatch) {
    EXPECT_TRUE(glob_match("Q_*", "Q_MEZ"));
    EXPECT_TRUE(glob_match("*", ""));
    EXPECT_TRUE(glob_match("?_REF", "Q_REF"));
    EXPECT_TRUE(glob_match("*MEZ", "QD_MEZ"));
    EXPECT_TRUE(glob_match("Q*_*Z", "QD_MEZ"));
    EXPECT_FALSE(glob_match("Q_*", "QD_MEZ"));
    EXPECT_FALSE(glob_match("?", ""));
    EXPECT_FALSE(glob_match("Q_REF", "Q_REFX"));
    EXPECT_TRUE(glob_match("a*b*c", "aXXbYYbc"));
}
