// chimsched, run as a user would: the binary, its text and JSON output, its errors.
#include <gtest/gtest.h>
#include <nlohmann/json.hpp>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <string>
#include <utility>
#include <vector>

#include "chimera/muf.hpp"

using nlohmann::json;

namespace {

struct Outcome {
    int status = -1;
    std::string out;
    std::string err;
};

std::string env(const char* name) {
    const char* v = std::getenv(name);
    return v ? v : "";
}

std::string slurp(const std::string& path) {
    std::ifstream in(path);
    return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

Outcome run(const std::string& args) {
    static int n = 0;
    const std::string base = "/tmp/chimsched_test." + std::to_string(getpid()) + "." + std::to_string(n++);
    const std::string cmd = env("CHIMSCHED") + " " + args + " >" + base + ".out 2>" + base + ".err";
    Outcome r;
    const int rc = std::system(cmd.c_str());
    r.status = WIFEXITED(rc) ? WEXITSTATUS(rc) : -1;
    r.out = slurp(base + ".out");
    r.err = slurp(base + ".err");
    std::remove((base + ".out").c_str());
    std::remove((base + ".err").c_str());
    return r;
}

std::string fig6_1() { return env("CHIMERA_SOURCE_ROOT") + "/tools/chimsched/examples/fig6_1.tasks"; }

std::string write_file(const std::string& name, const std::string& text) {
    const std::string path = "/tmp/chimsched_test." + std::to_string(getpid()) + "." + name;
    std::ofstream(path) << text;
    return path;
}

}  // namespace

TEST(Chimsched, ShippedExampleIsFigure6_1) {
    const auto set = chimera::muf::read_task_set(fig6_1());
    ASSERT_EQ(set.tasks.size(), 4u);
    EXPECT_EQ(set.tasks[0].period, 6);
    EXPECT_EQ(set.tasks[1].wcet, 4);
    EXPECT_EQ(set.tasks[2].period, 12);
    EXPECT_EQ(set.tasks[3].wcet, 4);
}

TEST(Chimsched, AnalyzeText) {
    const Outcome r = run("analyze " + fig6_1());
    ASSERT_EQ(r.status, 0) << r.err;
    EXPECT_NE(r.out.find("U = 1.2500"), std::string::npos) << r.out;
    EXPECT_NE(r.out.find("critical set RM:  tau1 tau2  (U = 0.7333 <= W = 0.8284)"), std::string::npos)
        << r.out;
    EXPECT_NE(r.out.find("critical set MUF: tau1 tau2 tau3  (U = 0.9833 <= 1)"), std::string::npos);
    EXPECT_NE(r.out.find("tau1=5/0 tau2=5/0 tau3=5/0 tau4=3/0"), std::string::npos);
}

TEST(Chimsched, AnalyzeJson) {
    for (const char* policy : {"muf", "rm", "edf"}) {
        const Outcome r = run(std::string("analyze --json --policy ") + policy + " " + fig6_1());
        ASSERT_EQ(r.status, 0) << r.err;
        const json j = json::parse(r.out);
        EXPECT_DOUBLE_EQ(j["utilisation"].get<double>(), 1.25);
        ASSERT_EQ(j["tasks"].size(), 4u);
        std::vector<bool> critical;
        for (const auto& t : j["tasks"]) critical.push_back(t["critical"].get<bool>());
        const std::string p = policy;
        const std::vector<bool> want = p == "muf"  ? std::vector<bool>{true, true, true, false}
                                       : p == "rm" ? std::vector<bool>{true, true, false, false}
                                                   : std::vector<bool>{false, false, false, false};
        EXPECT_EQ(critical, want) << p;
        EXPECT_EQ(j["tasks"][0]["name"], "tau1");
        EXPECT_EQ(j["critical_sets"]["muf"]["tasks"], json({"tau1", "tau2", "tau3"}));
    }
}

TEST(Chimsched, SimulateJsonMissesAsInFigure6_1) {
    const std::vector<std::pair<const char*, std::vector<int>>> want = {
        {"rm", {0, 0, 2, 2}}, {"edf", {2, 2, 0, 0}}, {"muf", {0, 0, 0, 2}}};
    for (const auto& [policy, misses] : want) {
        const Outcome r = run(std::string("simulate ") + fig6_1() + " --policy " + policy + " --until 30 --json");
        ASSERT_EQ(r.status, 0) << r.err;
        const json j = json::parse(r.out);
        std::vector<int> got;
        for (const auto& t : j["tasks"]) got.push_back(t["misses"].get<int>());
        EXPECT_EQ(got, misses) << policy;
        EXPECT_EQ(j["tasks"][3]["name"], "tau4");
    }
}

// Issue #20.6: with no options, simulate draws Figure 6.1: RM, EDF and MUF over
// one hyperperiod (60), a late job aborted at its deadline. The misses are the
// figure's: RM tau3 and tau4, EDF tau1 and tau2 (tasks of the critical set),
// MUF only tau4 (outside it).
const std::vector<std::pair<const char*, std::vector<int>>> kFigure6_1Misses = {
    {"rm", {0, 0, 2, 4}}, {"edf", {4, 4, 0, 0}}, {"muf", {0, 0, 0, 4}}};

TEST(Chimsched, SimulateDefaultsDrawFigure6_1) {
    const Outcome r = run("simulate --json " + fig6_1());
    ASSERT_EQ(r.status, 0) << r.err;
    const json all = json::parse(r.out);
    ASSERT_EQ(all.size(), 3u) << r.out;
    for (std::size_t p = 0; p < 3; ++p) {
        const json& j = all[p];
        EXPECT_EQ(j["policy"], kFigure6_1Misses[p].first);
        EXPECT_EQ(j["until"], 60.0);
        EXPECT_EQ(j["late"], "abort");
        std::vector<int> got;
        for (const auto& t : j["tasks"]) got.push_back(t["misses"].get<int>());
        EXPECT_EQ(got, kFigure6_1Misses[p].second) << j["policy"];
    }
    const Outcome text = run("simulate " + fig6_1());
    ASSERT_EQ(text.status, 0) << text.err;
    for (const char* policy : {"rm schedule", "edf schedule", "muf schedule"})
        EXPECT_NE(text.out.find(std::string(policy) + " of " + fig6_1() + " over [0, 60), late jobs aborted at their "
                                "deadline (as Figure 6.1; --late finish: run on)"),
                  std::string::npos)
            << text.out;
    // --late finish says which option draws the figure; under EDF the overload
    // then spreads to every task (the domino Figure 6.1 does not draw).
    const Outcome finish = run("simulate --json --policy edf --late finish " + fig6_1());
    ASSERT_EQ(finish.status, 0) << finish.err;
    const json finish_json = json::parse(finish.out);
    for (const auto& t : finish_json["tasks"]) EXPECT_GT(t["misses"].get<int>(), 0) << t;
    EXPECT_NE(run("simulate --policy edf --late finish " + fig6_1()).out.find("Figure 6.1 aborts them: --late abort"),
              std::string::npos);
}

TEST(Chimsched, SimulateWithoutAHyperperiodAsksForUntil) {
    const std::string f = write_file("nohyper.tasks",
                                     "TASK A PERIOD 999.983 WCET 1\n"
                                     "TASK B PERIOD 1000.003 WCET 1\n"
                                     "EOF\n");
    const Outcome r = run("simulate --policy rm " + f);
    EXPECT_EQ(r.status, 1);
    EXPECT_NE(r.err.find(f + ": the periods have no hyperperiod of at most a million ticks; give --until"),
              std::string::npos)
        << r.err;
    EXPECT_EQ(run("simulate --policy rm --until 3000 " + f).status, 0);
    std::remove(f.c_str());
}

TEST(Chimsched, SimulateTextGantt) {
    const std::string f = write_file("g.tasks",
                                     "TASK A PERIOD 4 WCET 1\n"
                                     "TASK B PERIOD 10 WCET 5\n"
                                     "EOF\n");
    const Outcome r = run("simulate " + f + " --policy rm --until 10");
    ASSERT_EQ(r.status, 0) << r.err;
    EXPECT_NE(r.out.find("A    |#...#...#.\n"
                         "B    |-###-##...\n"),
              std::string::npos)
        << r.out;
    EXPECT_NE(r.out.find("B      61     0        1         1       0       0           1"), std::string::npos) << r.out;
    std::remove(f.c_str());
}

TEST(Chimsched, FractionalTimesAreScaledToTicks) {
    const std::string f = write_file("f.tasks",
                                     "DEFINE T 0.5\n"
                                     "TASK a PERIOD T WCET 0.25\n"
                                     "TASK b PERIOD 1.5 WCET 0.5 DEADLINE 1.0\n"
                                     "EOF\n");
    const Outcome r = run("simulate " + f + " --policy muf --until 3 --json");
    ASSERT_EQ(r.status, 0) << r.err;
    const json j = json::parse(r.out);
    EXPECT_EQ(j["tasks"][0]["released"], 6);
    EXPECT_EQ(j["tasks"][1]["released"], 2);
    EXPECT_EQ(j["tasks"][1]["misses"], 0);
    EXPECT_DOUBLE_EQ(j["jobs"][1]["finish"].get<double>(), 0.75);
    std::remove(f.c_str());
}

TEST(Chimsched, ErrorsNameFileAndLine) {
    const std::vector<std::pair<std::string, std::string>> cases = {
        {"TASK a PERIOD 10 WCET 1\nTASK b PERIOD x WCET 1\nEOF\n", ":2: "},
        {"TASK a PERIOD 10 WCET 1\n", "truncated"},
        {"# comment\nTASK a WCET 1\nEOF\n", ":2: task a has no PERIOD"},
        {"TASK a PERIOD 10 WCET 1 CRIT 63\nEOF\n", ":1: task a CRIT must be 1..62"},
        {"TASK a PERIOD 10 WCET 1 COLOUR red\nEOF\n", ":1: task a: unknown option COLOUR"},
        {"TASK a PERIOD 10 WCET 1\nTASK a PERIOD 5 WCET 1\nEOF\n", ":2: task a is defined twice"},
        {"TASK a PERIOD 10 WCET 1\nFLOW a z\nEOF\n", ":2: FLOW names unknown task z"},
        {"TASK a PERIOD 10 WCET 1\nPERIOD 4\nEOF\n", ":2: expected TASK or FLOW"},
        {"TASK a PERIOD 0 WCET 1\nEOF\n", ":1: task a PERIOD must be > 0"},
        {"TASK a PERIOD 10 WCET\nEOF\n", ":1: task a: WCET needs a value"},
    };
    int k = 0;
    for (const auto& [text, message] : cases) {
        const std::string f = write_file("bad" + std::to_string(k++) + ".tasks", text);
        const Outcome r = run("analyze " + f);
        EXPECT_EQ(r.status, 1) << text;
        EXPECT_EQ(r.err.rfind(f + ":", 0), 0u) << r.err;  // starts with FILE:
        EXPECT_NE(r.err.find(message), std::string::npos) << "want " << message << ", got " << r.err;
        EXPECT_TRUE(r.out.empty());
        std::remove(f.c_str());
    }
    const Outcome missing = run("analyze /nonexistent/x.tasks");
    EXPECT_EQ(missing.status, 1);
    EXPECT_NE(missing.err.find("/nonexistent/x.tasks: cannot open file: No such file or directory"), std::string::npos)
        << missing.err;
}

TEST(Chimsched, UsageErrors) {
    EXPECT_NE(run("simulate " + fig6_1() + " --policy lifo --until 10").status, 0);
    EXPECT_NE(run("simulate " + fig6_1() + " --policy rm --late sometimes").status, 0);
    EXPECT_NE(run("").status, 0);
}
