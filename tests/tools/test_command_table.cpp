// Who may run what (issue #29.1): every command of the interpreter's table and
// of the web console's is classified, and a watcher (a web page without
// control, a watcher sbs) may run exactly the ones that only read or touch
// its own session. A command added to a table without a classification, or
// one whose classification changes, fails here until this list says so.
#include "command_line.hpp"
#include "command_table.hpp"

#include <gtest/gtest.h>

#include <map>
#include <set>
#include <string>

using namespace chimera::cli;

namespace {

std::vector<std::string> words(const std::string& command) { return split_words(command); }

// The bare command (its name alone) as a watcher sends it: may it run?
const std::map<std::string, bool> kWatcherMayRunBare = {
    {"clear", false},   {"complete", true}, {"display", true}, {"event", false},  {"finish", false},
    {"freq", true},     {"help", true},     {"kill", false},   {"module", true},  {"network", false},
    {"off", false},     {"on", false},      {"peer", false},   {"quit", true},    {"reconfig", false},
    {"record", false},  {"sample", false},  {"save", false},   {"set", true},     {"setvar", false},
    {"show", true},     {"sleep", false},   {"spawn", false},  {"status", true},  {"control", true},
    {"release", true},  {"scope", true},
};

}  // namespace

TEST(CommandTable, EveryCommandIsClassifiedAndAWatcherRunsOnlyTheOnesThatRead) {
    std::set<std::string> seen;
    for (const auto* table : {&command_table(), &console_command_table()}) {
        for (const CommandInfo& c : *table) {
            SCOPED_TRACE(c.name);
            EXPECT_NE(c.access, Access::unclassified) << "a new command needs an Access in its table entry";
            EXPECT_EQ(c.access == Access::acts, c.acts_by != nullptr) << "an acting command says what it does";
            EXPECT_TRUE(seen.insert(c.name).second) << "listed twice";
            const auto expected = kWatcherMayRunBare.find(c.name);
            ASSERT_NE(expected, kWatcherMayRunBare.end()) << "not in this test's list: decide who may run it";
            EXPECT_EQ(watcher_refusal({c.name}).empty(), expected->second) << watcher_refusal({c.name});
        }
    }
    EXPECT_EQ(seen.size(), kWatcherMayRunBare.size()) << "the test lists a command no table has";
}

// The forms of the commands that read in one form and act in another.
TEST(CommandTable, AWatcherIsToldWhatTheActingFormOfACommandDoes) {
    const std::map<std::string, std::string> acting = {
        {"scope start Q_MEZ --rate 100000 --rtpu ctrl", "scope start creates a task (a sampler) and its ring"},
        {"sample Q_MEZ", "sample creates a task (a sampler) and its ring"},
        {"status reset", "status reset restarts every reader's profile"},
        {"status set rmod cycle", "status set changes the fields every interface's status shows"},
        {"module load /tmp/x.so", "module load loads a shared object into the master"},
        {"reconfig off jpid", "reconfig sends signals to tasks"},
        {"freq jpid 500", "freq changes a task's frequency"},
        {"freq 500", "freq changes a task's frequency"},
        {"set jpid KP 1", "set changes a task's LOCAL configuration"},
        {"sleep 60", "sleep holds the master's one command thread for up to 60 s"},
        {"record X 5s x.csv", "record creates a task (a sampler) and writes a file"},
        {"save x.sbs", "save writes a file"},
        {"nosuchcommand", "nosuchcommand is not a command"},
    };
    for (const auto& [command, why] : acting) EXPECT_EQ(watcher_refusal(words(command)), why) << command;
    for (const std::string command : {"scope stop", "scope ack 3", "status", "status all", "status jpid", "status set",
                                      "module", "module jpid", "reconfig --check off jpid", "freq jpid", "set jpid",
                                      "show rtpu", "display Q_*", "help scope", "control", "release", "quit", ""})
        EXPECT_EQ(watcher_refusal(words(command)), "") << command;
}

TEST(CommandTable, TheAccessOfAFormIsNeverDepends) {
    EXPECT_EQ(command_access(words("scope stop")), Access::session);
    EXPECT_EQ(command_access(words("status jpid")), Access::reads);
    std::string why;
    EXPECT_EQ(command_access(words("spawn jpid"), &why), Access::acts);
    EXPECT_EQ(why, "creates a task");
}
