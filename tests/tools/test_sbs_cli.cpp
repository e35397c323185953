// The `sbs` program driven one-shot with -c (thesis §4.4.1): every command's
// happy path and its errors, the default RMOD, --json replies, exit status.
#include "sbs_harness.hpp"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <set>

using sbs_test::json_lines;
using sbs_test::Outcome;
using sbs_test::Workspace;

namespace {

// Runs a script that must succeed, and returns its JSON replies.
std::vector<nlohmann::json> ok_json(const Workspace& ws, const std::string& script) {
    const Outcome r = ws.sbs_run({"-c", script, "--json"});
    EXPECT_EQ(r.status, 0) << r.out << r.err;
    auto replies = json_lines(r.out);
    for (const auto& j : replies) EXPECT_TRUE(j.value("ok", false)) << j.dump();
    return replies;
}

// Runs a script whose LAST command must fail; returns that reply's error.
std::string failing(const Workspace& ws, const std::string& script) {
    const Outcome r = ws.sbs_run({"-c", script, "--json"});
    EXPECT_EQ(r.status, 1) << r.out << r.err;
    const auto replies = json_lines(r.out);
    if (replies.empty()) {
        ADD_FAILURE() << "no reply: " << r.err;
        return {};
    }
    EXPECT_FALSE(replies.back().value("ok", true)) << replies.back().dump();
    for (std::size_t i = 0; i + 1 < replies.size(); ++i) EXPECT_TRUE(replies[i].value("ok", false)) << replies[i].dump();
    return replies.back().value("error", "");
}

const nlohmann::json* task(const nlohmann::json& status_reply, const std::string& rmod) {
    for (const auto& t : status_reply["data"]["tasks"])
        if (t["rmod"] == rmod) return &t;
    return nullptr;
}

}  // namespace

TEST(SbsCli, SpawnOnStatusDisplayWithJson) {
    Workspace ws;
    const auto r = ok_json(ws, "spawn ramp; on; spawn follow; on follow; sleep 0.3; status; display ramp; display follow Y");
    ASSERT_EQ(r.size(), 8u);
    EXPECT_EQ(r[0]["cmd"], "spawn");
    EXPECT_EQ(r[0]["data"]["state"], "OFF");
    EXPECT_EQ(r[0]["data"]["module"], "ramp");
    EXPECT_EQ(r[0]["rmod"], "ramp");
    // `on` with no RMOD goes to the default one: the last addressed.
    EXPECT_EQ(r[1]["data"]["rmod"], "ramp");
    EXPECT_EQ(r[1]["data"]["state"], "ON");
    EXPECT_EQ(r[3]["rmod"], "follow");

    const auto& status = r[5];
    EXPECT_EQ(status["data"]["subsystem"], ws.subsystem());
    ASSERT_EQ(status["data"]["tasks"].size(), 2u);
    const auto* ramp = task(status, "ramp");
    ASSERT_NE(ramp, nullptr);
    EXPECT_EQ((*ramp)["state"], "ON");
    EXPECT_EQ((*ramp)["S"], "P");
    EXPECT_EQ((*ramp)["rtpu"], "cpu0");
    EXPECT_DOUBLE_EQ((*ramp)["refF"].get<double>(), 200.0);
    EXPECT_DOUBLE_EQ((*ramp)["refT"].get<double>(), 5000.0);  // every time in µs
    EXPECT_EQ(status["data"]["time_unit"], "us");
    EXPECT_GT((*ramp)["cycle"].get<std::uint64_t>(), 5u);
    EXPECT_GT((*ramp)["tid"].get<long>(), 0);
    // The text form has the header of the chosen fields and one line per task.
    const std::string text = status["text"];
    EXPECT_NE(text.find("rmod"), std::string::npos);
    EXPECT_NE(text.find("refF"), std::string::npos);
    EXPECT_NE(text.find("(times in us)"), std::string::npos) << text;
    EXPECT_NE(text.find("maxC[us]"), std::string::npos) << text;

    // display: the SVARs a task reads and writes, with units; values move.
    const auto& d = r[6]["data"]["vars"];
    ASSERT_EQ(d.size(), 1u);
    EXPECT_EQ(d[0]["name"], "X");
    EXPECT_EQ(d[0]["dir"], "out");
    EXPECT_EQ(d[0]["units"], "m");
    EXPECT_GT(d[0]["values"][0].get<double>(), 5.0);
    const auto& f = r[7]["data"]["vars"];
    ASSERT_EQ(f.size(), 1u);  // the pattern keeps Y only (not the in-var X)
    EXPECT_EQ(f[0]["name"], "Y");
    EXPECT_EQ(f[0]["units"], "m/s");
    EXPECT_NE(r[7]["text"].get<std::string>().find("m/s"), std::string::npos);
}

TEST(SbsCli, FollowerComputesFromTheRamp) {
    Workspace ws;
    const auto r = ok_json(ws, "spawn ramp; spawn follow; reconfig on ramp, on follow; sleep 0.3; "
                               "reconfig off ramp, off follow; display all X Y");
    const auto& vars = r.back()["data"]["vars"];
    ASSERT_EQ(vars.size(), 2u);
    const double x = vars[0]["values"][0], y = vars[1]["values"][0];
    EXPECT_GT(x, 5.0);
    // follow ran after ramp's last cycle with GAIN 2: Y is twice some X it read.
    EXPECT_GT(y, 0.0);
    EXPECT_LE(y, 2 * x);
    EXPECT_EQ(static_cast<long>(y) % 2, 0);
}

TEST(SbsCli, DisplayWholeTableAndArrays) {
    Workspace ws;
    const auto r = ok_json(ws, "display; display all LIM*");
    EXPECT_EQ(r[0]["data"]["vars"].size(), 3u);  // no task yet: the whole table
    const auto& lim = r[1]["data"]["vars"][0];
    EXPECT_EQ(lim["type"], "float");
    EXPECT_EQ(lim["nelem"], 3);
    EXPECT_EQ(lim["values"], nlohmann::json::parse("[0.5,1.5,2.5]"));
    EXPECT_EQ(lim["units"], "rad");
}

TEST(SbsCli, TextOutputAndExitStatus) {
    Workspace ws;
    const Outcome ok = ws.sbs_run({"-c", "spawn ramp; on; status"});
    EXPECT_EQ(ok.status, 0) << ok.err;
    EXPECT_NE(ok.out.find("spawned ramp (module ramp) on RTPU cpu0"), std::string::npos) << ok.out;
    EXPECT_NE(ok.out.find("ramp: ON"), std::string::npos);
    EXPECT_NE(ok.out.find("subsystem " + ws.subsystem() + ": 1 task"), std::string::npos);

    // The first failure stops the script, names the problem on stderr, exits 1.
    const Outcome bad = ws.sbs_run({"-c", "spawn ramp; bogus; on ramp"});
    EXPECT_EQ(bad.status, 1);
    EXPECT_NE(bad.err.find("error: unknown command 'bogus'"), std::string::npos) << bad.err;
    EXPECT_EQ(bad.out.find("ramp: ON"), std::string::npos) << "ran past the failure: " << bad.out;
}

TEST(SbsCli, StatusSetPicksFields) {
    Workspace ws;
    const auto r = ok_json(ws, "spawn ramp; status set rmod,state cycle; status; status set; status set default; status set all");
    EXPECT_EQ(r[1]["data"]["fields"], nlohmann::json::parse(R"(["rmod","state","cycle"])"));
    const std::string text = r[2]["text"];
    EXPECT_NE(text.find("rmod         state          cycle"), std::string::npos) << text;
    EXPECT_EQ(text.find("refF"), std::string::npos) << text;
    EXPECT_EQ(r[3]["data"]["fields"], r[1]["data"]["fields"]);  // `status set` alone shows them
    EXPECT_EQ(r[4]["data"]["fields"][0], "rmod");
    EXPECT_GT(r[4]["data"]["fields"].size(), 5u);
    EXPECT_EQ(r[5]["data"]["fields"], r[5]["data"]["available"]);
    EXPECT_NE(failing(ws, "status set rmod bogus").find("unknown field 'bogus'"), std::string::npos);
}

TEST(SbsCli, SetAndGetLocalParameters) {
    Workspace ws;
    const auto r = ok_json(ws, "spawn ramp; set; set STEP 5; set ramp STEP; spawn follow; set ramp; set GAIN 3; "
                               "set follow GAIN");
    EXPECT_EQ(r[1]["data"]["local"]["STEP"], "1");
    EXPECT_EQ(r[2]["data"]["value"], "5");
    EXPECT_EQ(r[3]["data"]["value"], "5");
    EXPECT_EQ(r[5]["data"]["local"]["STEP"], "5");  // the view follows a set
    EXPECT_EQ(r[5]["rmod"], "ramp");                 // and makes ramp the default again
    EXPECT_EQ(r[6]["data"]["rmod"], "ramp");         // so GAIN went to ramp
    EXPECT_EQ(r[7]["data"]["value"], "2");           // follow still has its own

    // The new STEP drives the ramp.
    const auto m = ok_json(ws, "spawn ramp; set STEP 1000; on; sleep 0.2; off; display");
    EXPECT_GE(m.back()["data"]["vars"][0]["values"][0].get<double>(), 1000.0);
    EXPECT_EQ(static_cast<long>(m.back()["data"]["vars"][0]["values"][0].get<double>()) % 1000, 0);

    EXPECT_NE(failing(ws, "set STEP 2").find("no default RMOD"), std::string::npos);
}

// Issue #16.2: the view lists what the module declares (type, range, live,
// default), and set refuses what the module would not take, naming the key.
TEST(SbsCli, SetRefusesUndeclaredAndOutOfRange) {
    Workspace ws;
    const auto r = ok_json(ws, "spawn ramp; set");
    const auto& keys = r[1]["data"]["keys"];
    ASSERT_EQ(keys.size(), 5u) << r[1];
    EXPECT_EQ(keys[0]["name"], "STEP");
    EXPECT_EQ(keys[0]["type"], "number");
    EXPECT_EQ(keys[0]["live"], true);
    EXPECT_EQ(keys[0]["max"], 1e6);
    EXPECT_EQ(keys[3]["name"], "INITFAIL");
    EXPECT_EQ(keys[3]["live"], false);
    EXPECT_EQ(r[1]["data"]["local"]["GAIN"], "2");  // not in ramp.rmod: the declared default
    EXPECT_NE(r[1]["text"].get<std::string>().find("spawn-only"), std::string::npos) << r[1]["text"];

    EXPECT_NE(failing(ws, "spawn ramp; set NOKEY 1").find("no LOCAL key NOKEY in module ramp (it takes STEP GAIN"),
              std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; set STEP banana").find("LOCAL STEP: 'banana' is not a number"),
              std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; set STEP 2e6").find("LOCAL STEP: 2e6 is out of range [-1e+06, 1e+06]"),
              std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; set STEP 1 2").find("LOCAL STEP: takes one number, given 2 words"),
              std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; set INITFAIL 1").find("LOCAL INITFAIL of module ramp is read only at spawn"),
              std::string::npos);
}

// Issue #15.4, one validator: `chimcfg check` and spawn run the same checks
// of a .rmod's LOCAL section against its module's declarations, so each file
// chimcfg refuses fails to spawn with the same FILE:LINE message, and the file
// it accepts spawns.
TEST(SbsCli, ChimcfgRefusesWhatSpawnRefusesAtTheSameLine) {
    Workspace ws;
    auto ramp_with = [&](const std::string& name, const std::string& local) {
        return ws.write(name + ".rmod", "MODULE ramp\nDESC ramp\nINVAR none\nOUTVAR X\nTASKTYPE periodic\nFREQ 200\n"
                                        "LOCAL\n" + local + "\nEOF\n");
    };
    struct Case {
        std::string name, local, error;
    };
    for (const Case& c : {Case{"inf", "STEP inf", ":8: LOCAL STEP: 'inf' is not a number"},
                          Case{"nan", "GAIN nan", ":8: LOCAL GAIN: 'nan' is not a number"},
                          Case{"huge", "STEP 1e309", ":8: LOCAL STEP: '1e309' is not a number"},
                          Case{"range", "STEP 2e6", ":8: LOCAL STEP: 2e6 is out of range [-1e+06, 1e+06]"},
                          Case{"typo", "STPE 1", ":8: LOCAL STPE: not a key of ramp (STEP, GAIN, WARN, INITFAIL, FAIL)"}}) {
        const std::string path = ramp_with(c.name, c.local);
        const auto check = sbs_test::run(sbs_test::env("CHIMCFG_EXE"), {"check", path});
        EXPECT_EQ(check.status, 1) << c.name << ": " << check.out;
        EXPECT_EQ(check.err, path + c.error + "\n") << c.name;
        EXPECT_NE(failing(ws, "spawn " + path).find("spawn: " + path + c.error), std::string::npos) << c.name;
    }
    const std::string good = ramp_with("good", "STEP 2e5\nGAIN -3");
    const auto check = sbs_test::run(sbs_test::env("CHIMCFG_EXE"), {"check", good});
    EXPECT_EQ(check.status, 0) << check.err;
    EXPECT_NE(check.out.find("LOCAL checked against module ramp"), std::string::npos) << check.out;
    EXPECT_EQ(ok_json(ws, "spawn " + good + "; set STEP")[1]["data"]["value"], "2e5");
}

// Issue #16.3: setvar (halcmd setp for a state variable), show svar (show
// sig: producers and consumers), show rtpu (show thread).
TEST(SbsCli, SetvarShowSvarShowRtpu) {
    Workspace ws;
    const auto r = ok_json(ws, "setvar LIMITS[1] 7; display all LIMITS; setvar LIMITS 2; display all LIMITS; "
                               "spawn ramp; spawn follow; show svar; show rtpu; setvar X 5 --force");
    EXPECT_EQ(r[0]["data"]["values"], nlohmann::json::array({0.5, 7.0, 2.5}));
    EXPECT_EQ(r[1]["data"]["vars"][0]["values"], nlohmann::json::array({0.5, 7.0, 2.5}));  // in the table
    EXPECT_EQ(r[3]["data"]["vars"][0]["values"], nlohmann::json::array({2.0, 2.0, 2.0}));
    const auto& vars = r[6]["data"]["vars"];
    ASSERT_EQ(vars.size(), 3u);
    EXPECT_EQ(vars[0]["name"], "X");
    EXPECT_EQ(vars[0]["producers"], nlohmann::json::array({"ramp"}));
    EXPECT_EQ(vars[0]["consumers"], nlohmann::json::array({"follow"}));
    EXPECT_EQ(vars[1]["producers"], nlohmann::json::array({"follow"}));
    EXPECT_EQ(vars[2]["producers"], nlohmann::json::array());
    const auto& rtpus = r[7]["data"]["rtpus"];
    ASSERT_EQ(rtpus.size(), 1u);
    EXPECT_EQ(rtpus[0]["name"], "cpu0");
    EXPECT_EQ(rtpus[0]["cpu"], 0);
    EXPECT_EQ(rtpus[0]["backend"], "other");
    EXPECT_EQ(rtpus[0]["scheduler"], "MUF");
    EXPECT_EQ(rtpus[0]["tasks"], nlohmann::json::array({"follow", "ramp"}));
    EXPECT_EQ(rtpus[0]["ranking"], "best-effort");  // backend other: no priorities
    EXPECT_EQ(r[8]["data"]["forced"], true);

    EXPECT_NE(failing(ws, "setvar LIMITS[2] 4").find("LIMITS[2]: 4 is outside the .svar range [0, 3]"), std::string::npos);
    EXPECT_NE(failing(ws, "setvar LIMITS[3] 1").find("index 3 is out of range"), std::string::npos);
    EXPECT_NE(failing(ws, "setvar LIMITS 1 2").find("give one value for all, every value, or VAR[INDEX]"),
              std::string::npos);
    EXPECT_NE(failing(ws, "setvar NOPE 1").find("no variable NOPE"), std::string::npos);
    EXPECT_NE(failing(ws, "setvar X pi").find("'pi' is not a number"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; setvar X 5").find("X is produced by ramp"), std::string::npos);
    EXPECT_NE(failing(ws, "show thread").find("usage: show rtpu|svar"), std::string::npos);
}

// Issue #35.4, #35.5: `show` alone lists what it shows; TAB after `show `
// offers every one of them (the same table the command reads its word from).
TEST(SbsCli, ShowAloneListsWhatItShowsAndCompletionOffersThem) {
    Workspace ws;
    const auto r = ok_json(ws, "show; complete show g; complete show r");
    ASSERT_EQ(r.size(), 3u);
    EXPECT_EQ(r[0]["data"]["topics"], nlohmann::json({"rtpu", "svar", "graph"})) << r[0].dump();
    EXPECT_NE(r[0]["text"].get<std::string>().find("show graph"), std::string::npos) << r[0].dump();
    EXPECT_EQ(r[1]["data"]["candidates"], nlohmann::json({"graph"})) << r[1].dump();
    EXPECT_EQ(r[2]["data"]["candidates"], nlohmann::json({"rtpu"})) << r[2].dump();
}

// Issue #35.3: killing the default task (as `record` does with its sampler)
// makes the previous default the default again, or none.
TEST(SbsCli, AKilledDefaultFallsBackToThePreviousOne) {
    Workspace ws;
    const auto r = ok_json(ws, "spawn ramp; spawn follow; kill; status; kill ramp; status");
    ASSERT_EQ(r.size(), 6u);
    EXPECT_EQ(r[3]["rmod"], "ramp");
    EXPECT_EQ(r[5]["rmod"], "");
}

// Issue #16.3: spawn a+b (§3.8.1): one task, the objects' methods in the
// order given; X passes from ramp to the follower inside the task and is never
// written to the global table.
TEST(SbsCli, SpawnCombinedTask) {
    Workspace ws;
    ws.write("follow200.rmod",
             "MODULE ramp\nDESC follower at the ramp's rate\nINVAR X\nOUTVAR Y\nTASKTYPE periodic\nFREQ 200\n"
             "LOCAL\nGAIN 2\nEOF\n");
    const auto r = ok_json(ws, "spawn ramp+follow200; on; sleep 0.3; off; show svar; display all X Y; status");
    EXPECT_EQ(r[0]["data"]["rmod"], "ramp+follow200");
    EXPECT_EQ(r[0]["data"]["files"].size(), 2u);
    EXPECT_EQ(r[1]["data"]["state"], "ON");
    const auto& vars = r[4]["data"]["vars"];
    EXPECT_EQ(vars[0]["name"], "X");
    EXPECT_EQ(vars[0]["producers"], nlohmann::json::array());  // internal to the task
    EXPECT_EQ(vars[1]["producers"], nlohmann::json::array({"ramp+follow200"}));
    const auto& values = r[5]["data"]["vars"];
    EXPECT_EQ(values[0]["values"][0], 0.0);  // X never left the task
    EXPECT_GT(values[1]["values"][0].get<double>(), 0.0);  // Y = 2 * X, written every cycle
    EXPECT_EQ(r[6]["data"]["tasks"][0]["rmod"], "ramp+follow200");
    EXPECT_NE(failing(ws, "spawn ramp+follow").find("follow"), std::string::npos);  // 200 Hz + 100 Hz
    EXPECT_NE(failing(ws, "spawn ramp+nosuch").find("no file nosuch"), std::string::npos);
}

// A combined task whose objects read one global variable: display lists it once.
TEST(SbsCli, DisplayOfACombinedTaskListsASharedPortOnce) {
    Workspace ws;
    ws.write("followa.rmod", "MODULE ramp\nDESC follower\nINVAR X\nOUTVAR Y\nTASKTYPE periodic\nFREQ 200\nEOF\n");
    ws.write("sinkb.rmod", "MODULE ramp\nDESC reader\nINVAR X\nOUTVAR none\nTASKTYPE periodic\nFREQ 200\nEOF\n");
    const auto r = ok_json(ws, "spawn ramp; spawn followa+sinkb; display followa+sinkb");
    const auto& vars = r[2]["data"]["vars"];
    ASSERT_EQ(vars.size(), 2u) << vars.dump();
    EXPECT_EQ(vars[0]["name"], "X");
    EXPECT_EQ(vars[1]["name"], "Y");
}

TEST(SbsCli, ControlSignalsAndTheirRefusals) {
    Workspace ws;
    EXPECT_NE(failing(ws, "on").find("no default RMOD"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; on nosuch").find("no task nosuch"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; on nosuch").find("tasks: ramp"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; on; on").find("already ON"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; off").find("already OFF"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; clear").find("not in ERROR"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; kill; kill ramp").find("NOT-CREATED"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; kill; kill").find("no default RMOD"), std::string::npos);  // gone with ramp
    EXPECT_NE(failing(ws, "spawn ramp; on ramp extra").find("usage: on [RMOD]"), std::string::npos);
    // Two producers of X may not be ON together (§3.3.1).
    const std::string two = failing(ws, "spawn ramp; spawn ramp2; on ramp; on ramp2");
    EXPECT_NE(two.find("X"), std::string::npos) << two;
    EXPECT_NE(two.find("ramp"), std::string::npos) << two;

    // kill from ON: off first, then gone from status; respawn works.
    const auto r = ok_json(ws, "spawn ramp; on; kill; status; spawn ramp; status");
    EXPECT_EQ(r[2]["data"]["state"], "NOT-CREATED");
    EXPECT_EQ(r[3]["data"]["tasks"].size(), 0u);
    EXPECT_EQ(r[5]["data"]["tasks"].size(), 1u);
    EXPECT_EQ(r[5]["data"]["tasks"][0]["state"], "OFF");
}

TEST(SbsCli, ErrorStateAndClear) {
    Workspace ws;
    const auto r = ok_json(ws, "spawn ramp; on; set FAIL 1; sleep 0.2; status ramp; set FAIL 0; clear; status; on; "
                               "sleep 0.1; status");
    const auto& err = r[4]["data"]["tasks"][0];
    EXPECT_EQ(err["state"], "ERROR");
    EXPECT_NE(err["error"].get<std::string>().find("FAIL is set"), std::string::npos) << err.dump();
    EXPECT_NE(r[4]["text"].get<std::string>().find("ERROR> ramp: "), std::string::npos) << r[4]["text"];
    EXPECT_EQ(r[6]["data"]["state"], "OFF");
    EXPECT_EQ(r[7]["data"]["tasks"][0]["state"], "OFF");
    EXPECT_EQ(r[7]["text"].get<std::string>().find("ERROR>"), std::string::npos);
    EXPECT_EQ(r[10]["data"]["tasks"][0]["state"], "ON");
}

TEST(SbsCli, WarningShownOnce) {
    Workspace ws;
    const Outcome r = ws.sbs_run({"-c", "spawn ramp; set WARN careful; on; status; status"});
    EXPECT_EQ(r.status, 0) << r.err;
    const auto first = r.out.find("WARNING> ramp: careful");
    ASSERT_NE(first, std::string::npos) << r.out;
    EXPECT_EQ(r.out.find("WARNING>", first + 1), std::string::npos) << r.out;
}

TEST(SbsCli, SpawnErrors) {
    Workspace ws;
    EXPECT_NE(failing(ws, "spawn").find("usage: spawn RMOD[+RMOD...] [RTPU]"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn nosuch").find("no file nosuch[.rmod]"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp cpu9").find("no RTPU cpu9"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; spawn ramp").find("already exists"), std::string::npos);
    const std::string ghost = failing(ws, "spawn ghost");
    EXPECT_NE(ghost.find("ghost"), std::string::npos) << ghost;
    // init fails: the task is not created and the error says why.
    const std::string path = ws.write("broken.rmod", "MODULE ramp\nDESC fails\nOUTVAR X\nTASKTYPE periodic\nFREQ 10\n"
                                                     "LOCAL\nINITFAIL 1\nEOF\n");
    const std::string init = failing(ws, "spawn " + path);
    EXPECT_NE(init.find("INITFAIL is set"), std::string::npos) << init;
    // A bad .rmod names file and line.
    const std::string bad = ws.write("bad.rmod", "MODULE ramp\nDESC x\nTASKTYPE sometimes\nEOF\n");
    const std::string parse = failing(ws, "spawn " + bad);
    EXPECT_NE(parse.find("bad.rmod:3"), std::string::npos) << parse;
}

TEST(SbsCli, Reconfig) {
    Workspace ws;
    const auto r = ok_json(ws, "spawn ramp; spawn follow; reconfig on ramp , on follow; status");
    EXPECT_EQ(r[2]["data"]["applied"], nlohmann::json::parse(R"(["on ramp","on follow"])"));
    for (const auto& t : r[3]["data"]["tasks"]) EXPECT_EQ(t["state"], "ON");
    EXPECT_EQ(r[2]["rmod"], "follow");

    // Stops at the first failure, says which, and what was applied.
    const Outcome stop = ws.sbs_run({"-c", "spawn ramp; spawn follow; reconfig on ramp, clear follow, on follow; status",
                                 "--json"});
    EXPECT_EQ(stop.status, 1);
    const auto s = json_lines(stop.out);
    ASSERT_EQ(s.size(), 3u);
    const std::string e = s[2]["error"];
    EXPECT_NE(e.find("item 1 (clear follow)"), std::string::npos) << e;
    EXPECT_NE(e.find("1 of 3 items applied"), std::string::npos) << e;
    EXPECT_EQ(s[2]["data"]["applied"], nlohmann::json::parse(R"(["on ramp"])"));

    // Verified before anything is sent.
    const std::string v = failing(ws, "spawn ramp; spawn ramp2; reconfig on ramp, on ramp2");
    EXPECT_NE(v.find("verification"), std::string::npos) << v;
    EXPECT_NE(failing(ws, "spawn ramp; reconfig on").find("is not SIG RMOD"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; reconfig jump ramp").find("is not SIG RMOD"), std::string::npos);
    EXPECT_NE(failing(ws, "reconfig on nobody").find("no task nobody"), std::string::npos);
    EXPECT_NE(failing(ws, "reconfig").find("usage: reconfig"), std::string::npos);
}

TEST(SbsCli, ModuleListsAndShows) {
    Workspace ws;
    const auto r = ok_json(ws, "module; module follow; module ramp2");
    bool have_ramp_so = false;
    for (const auto& m : r[0]["data"]["modules"]) have_ramp_so |= m["name"] == "ramp";
    EXPECT_TRUE(have_ramp_so) << r[0].dump();
    bool have_follow = false;
    for (const auto& m : r[0]["data"]["rmods"]) have_follow |= m["name"] == "follow" && m["module"] == "ramp";
    EXPECT_TRUE(have_follow);
    const auto& follow = r[1]["data"]["rmods"][0];
    EXPECT_EQ(follow["module"], "ramp");
    EXPECT_EQ(follow["ports"]["in-var"][0]["svar"], "X");
    EXPECT_EQ(follow["ports"]["out-var"][0]["units"], "m/s");
    EXPECT_EQ(follow["local"]["GAIN"], "2");
    EXPECT_DOUBLE_EQ(follow["freq"].get<double>(), 100.0);
    const std::string text = r[1]["text"];
    EXPECT_NE(text.find("GAIN"), std::string::npos);
    EXPECT_NE(failing(ws, "module nothing").find("no module or .rmod named nothing"), std::string::npos);
}

TEST(SbsCli, FreqHelpSyntaxAndQuit) {
    Workspace ws;
    const auto r = ok_json(ws, "spawn ramp; freq; freq 50; freq ramp; help; help status");
    EXPECT_DOUBLE_EQ(r[1]["data"]["freq"].get<double>(), 200.0);
    EXPECT_DOUBLE_EQ(r[3]["data"]["freq"].get<double>(), 50.0);
    EXPECT_NE(r[4]["text"].get<std::string>().find("reconfig SIG RMOD"), std::string::npos);
    EXPECT_NE(r[5]["text"].get<std::string>().find("mezT"), std::string::npos);
    EXPECT_NE(failing(ws, "spawn ramp; freq -3").find("not a frequency"), std::string::npos);
    // Positive but out of range: refused, not rounded to a period of 0 ("0 Hz").
    EXPECT_NE(failing(ws, "spawn ramp; freq ramp 1e308").find("above the highest task frequency"), std::string::npos);
    EXPECT_NE(failing(ws, "help nothing").find("unknown command 'nothing'"), std::string::npos);
    EXPECT_NE(failing(ws, "display 'unterminated").find("unterminated"), std::string::npos);
    EXPECT_NE(failing(ws, "display all NOPE*").find("no variable matches NOPE*"), std::string::npos);
    EXPECT_NE(failing(ws, "sleep forever").find("usage: sleep"), std::string::npos);

    // quit ends the script early and finishes the subsystem: nothing stays in /dev/shm.
    const Outcome q = ws.sbs_run({"-c", "spawn ramp; on; quit; status"});
    EXPECT_EQ(q.status, 0);
    EXPECT_EQ(q.out.find("subsystem "), std::string::npos) << q.out;
    EXPECT_FALSE(std::filesystem::exists("/dev/shm/chimera." + ws.subsystem() + ".svar"));
}

TEST(SbsCli, BadSbsFileNamesFileAndLine) {
    Workspace ws;
    const std::string bad = ws.write("bad.sbs", "SUBSYSTEM x\nSVARFILE nothere.svar\nRTPU\nEOF\n");
    const Outcome r = sbs_test::run(sbs_test::env("SBS_EXE"), {bad, "-c", "status"});
    EXPECT_EQ(r.status, 1);
    EXPECT_NE(r.err.find("bad.sbs:"), std::string::npos) << r.err;
}

// A .sbs of this workspace's subsystem with `tail` after its RTPU.
std::string sbs_with(const Workspace& ws, const std::string& name, const std::string& tail) {
    return ws.write(name, "SUBSYSTEM " + ws.subsystem() + "\nSVARFILE  " + sbs_test::env("SBS_TEST_DATA") +
                              "/tools.svar\nRTPU      cpu0\nBACKEND   other\n" + tail + "EOF\n");
}

Outcome run_sbs_file(const std::string& file, const std::string& script) {
    return sbs_test::run(sbs_test::env("SBS_EXE"),
                         {file, "--module-path", sbs_test::env("SBS_TEST_DATA"), "--no-attach", "-c", script, "--json"});
}

TEST(SbsCli, TaskLinesOfTheSbsStartTheirTasks) {
    Workspace ws;
    ws.write("follow200.rmod",
             "MODULE ramp\nDESC follower at the ramp's rate\nINVAR X\nOUTVAR Y\nTASKTYPE periodic\nFREQ 200\n"
             "LOCAL\nGAIN 2\nEOF\n");
    const std::string file = sbs_with(ws, "tasks.sbs", "TASK ramp+follow200 ON\nSET GAIN 4\nTASK follow\n");
    const Outcome r = run_sbs_file(file, "sleep 0.2; status; set ramp+follow200 GAIN; display all X Y");
    ASSERT_EQ(r.status, 0) << r.out << r.err;
    const auto replies = json_lines(r.out);
    ASSERT_EQ(replies.size(), 4u) << r.out;
    ASSERT_EQ(replies[1]["data"]["tasks"].size(), 2u);
    EXPECT_EQ(replies[1]["data"]["tasks"][0]["rmod"], "ramp+follow200");
    EXPECT_EQ(replies[1]["data"]["tasks"][0]["state"], "ON");
    EXPECT_EQ(replies[1]["data"]["tasks"][1]["rmod"], "follow");
    EXPECT_EQ(replies[1]["data"]["tasks"][1]["state"], "OFF");  // no ON: spawned and left OFF
    EXPECT_EQ(replies[2]["data"]["value"], "4");
    const auto& values = replies[3]["data"]["vars"];
    ASSERT_EQ(values.size(), 2u);
    EXPECT_GT(values[1]["values"][0].get<double>(), 0.0);
    // The SET line reached the module: Y = 4 * X of the same cycle, X internal to the task.
    const auto ok = sbs_test::run(sbs_test::env("CHIMCFG_EXE"), {"check", "--module-path", sbs_test::env("SBS_TEST_DATA"), file});
    EXPECT_EQ(ok.status, 0) << ok.out << ok.err;
}

TEST(SbsCli, ATaskLineThatFailsNamesItsLineAndStartsNothing) {
    Workspace ws;
    const std::string file = sbs_with(ws, "bad.sbs", "TASK ramp ON\nTASK follow ON\nSET NOKEY 1\n");
    const Outcome r = run_sbs_file(file, "status");
    EXPECT_EQ(r.status, 1) << r.out << r.err;
    EXPECT_NE(r.err.find("bad.sbs:7: "), std::string::npos) << r.err;  // the SET line
    EXPECT_NE(r.err.find("NOKEY"), std::string::npos) << r.err;
    EXPECT_FALSE(std::filesystem::exists("/dev/shm/chimera." + ws.subsystem() + ".svar"));
    const std::string missing = sbs_with(ws, "missing.sbs", "TASK nosuch\n");
    const Outcome m = run_sbs_file(missing, "status");
    EXPECT_EQ(m.status, 1);
    EXPECT_NE(m.err.find("missing.sbs:5: "), std::string::npos) << m.err;
    const auto check = sbs_test::run(sbs_test::env("CHIMCFG_EXE"), {"check", missing});
    EXPECT_EQ(check.status, 1);
    EXPECT_NE(check.err.find("missing.sbs:5: TASK nosuch: no file nosuch[.rmod]"), std::string::npos) << check.err;
    // TASK names an RTPU of the file; a rmod is one task only.
    const std::string rtpu = sbs_with(ws, "rtpu.sbs", "TASK ramp cpu9\n");
    EXPECT_NE(run_sbs_file(rtpu, "status").err.find("rtpu.sbs:5: TASK ramp: no RTPU cpu9 in this file"), std::string::npos);
    const std::string twice = sbs_with(ws, "twice.sbs", "TASK ramp\nTASK follow+ramp\n");
    EXPECT_NE(run_sbs_file(twice, "status").err.find("twice.sbs:6: TASK: rmod ramp is already a task of line 5"),
              std::string::npos);
}

TEST(SbsCli, SaveWritesASbsThatStartsTheSameSubsystem) {
    Workspace ws;
    const std::string saved = ws.dir() + "/saved.sbs";
    const auto r = ok_json(ws, "spawn ramp; set STEP 5; on; spawn follow; save " + saved);
    EXPECT_EQ(r.back()["data"]["file"], saved);
    const std::string text = r.back()["data"]["sbs"];
    EXPECT_NE(text.find("SET STEP 5\n"), std::string::npos) << text;
    EXPECT_EQ(text.find("SET GAIN"), std::string::npos) << text;  // unchanged LOCAL stays in the .rmod
    ASSERT_TRUE(std::filesystem::exists(saved));
    // It starts the same tasks, in the same states, with the same LOCAL.
    const Outcome again = run_sbs_file(saved, "status; set ramp STEP; set follow GAIN");
    ASSERT_EQ(again.status, 0) << again.out << again.err;
    const auto replies = json_lines(again.out);
    ASSERT_EQ(replies.size(), 3u);
    const auto* ramp = task(replies[0], "ramp");
    const auto* follow = task(replies[0], "follow");
    ASSERT_TRUE(ramp && follow) << replies[0].dump();
    EXPECT_EQ((*ramp)["state"], "ON");
    EXPECT_EQ((*follow)["state"], "OFF");
    EXPECT_EQ(replies[1]["data"]["value"], "5");
    EXPECT_EQ(replies[2]["data"]["value"], "2");
    EXPECT_EQ(sbs_test::run(sbs_test::env("CHIMCFG_EXE"), {"check", saved}).status, 0);
    // Only to a .sbs name, never over the network (tests/tools/test_sbs_network.cpp).
    EXPECT_NE(failing(ws, "save " + ws.dir() + "/x.txt").find("ends in .sbs"), std::string::npos);
}

namespace {

// Figure 3.7's table under this workspace's subsystem name, on its two RTPUs
// without real-time priority; "" when its modules are not built here.
std::string fig3_7_sbs(const Workspace& ws) {
    if (!std::filesystem::exists(sbs_test::env("CHIMERA_LIB_DIR") + "/modules/pid/pid.so")) return {};
    const std::string svar = sbs_test::env("CHIMERA_INCLUDE_DIR") + "/../examples/fig3_7_pid/fig3_7.svar";
    const std::string rtpu = "\nBACKEND   other\nMINFREQ   1\nMAXFREQ   1000\n";
    return ws.write(ws.subsystem() + ".sbs", "SUBSYSTEM " + ws.subsystem() + "\nSVARFILE  " + svar +
                                                 "\nMASTER    ctrl\nRTPU      ctrl 0" + rtpu + "RTPU      robot 1" + rtpu +
                                                 "EOF\n");
}

}  // namespace

// Issue #35.1: TASK lines in spawn order, so the consts a task reads are
// produced by a line before it (in name order jpid came before puma_torque).
TEST(SbsCli, SaveWritesTaskLinesInSpawnOrderSoFigure37Restarts) {
    Workspace ws;
    if (fig3_7_sbs(ws).empty()) GTEST_SKIP() << "the robotics modules are not built";
    const std::string saved = ws.dir() + "/saved.sbs";
    ok_json(ws, "spawn puma_torque robot; spawn jtraj; spawn jpid; reconfig on puma_torque, on jtraj, on jpid; save " + saved);
    const Outcome again = run_sbs_file(saved, "status");
    ASSERT_EQ(again.status, 0) << again.out << again.err;
    const auto replies = json_lines(again.out);
    ASSERT_EQ(replies.size(), 1u) << again.out;
    std::vector<std::string> tasks;
    for (const auto& t : replies[0]["data"]["tasks"]) tasks.push_back(t["rmod"].get<std::string>() + " " + t["state"].get<std::string>());
    EXPECT_EQ(tasks, (std::vector<std::string>{"puma_torque ON", "jtraj ON", "jpid ON"})) << again.out;
}

// A configuration that would not start again is refused, nothing written:
// the producer of NDOF killed and spawned after its consumer; a task ON whose
// input no task ON produces (`on` allows it, the starting reconfig does not).
TEST(SbsCli, SaveRefusesTaskLinesThatWouldNotStart) {
    Workspace ws;
    if (fig3_7_sbs(ws).empty()) GTEST_SKIP() << "the robotics modules are not built";
    const std::string saved = ws.dir() + "/saved.sbs";
    const std::string error =
        failing(ws, "spawn puma_torque robot; spawn jpid; kill puma_torque; spawn puma_torque robot; save " + saved);
    EXPECT_NE(error.find("in-const NDOF"), std::string::npos) << error;
    EXPECT_NE(error.find("nothing written"), std::string::npos) << error;
    EXPECT_FALSE(std::filesystem::exists(saved));
    const std::string unfed = failing(ws, "spawn puma_torque robot; spawn jpid; on puma_torque; save " + saved);
    EXPECT_NE(unfed.find("variable T_REF read by puma_torque is produced by no module"), std::string::npos) << unfed;
    EXPECT_FALSE(std::filesystem::exists(saved));
}

TEST(SbsCli, ModuleLoadFromAPathMakesItsRmodsSpawn) {
    Workspace ws;
    // A .rmod whose module is on no folder of the module path: its folder holds no library.
    const std::string rmod = ws.write("elsewhere.rmod", "MODULE ramp\nDESC ramp\nINVAR none\nOUTVAR X\n"
                                                       "TASKTYPE periodic\nFREQ 200\nEOF\n");
    const std::string so = sbs_test::env("RAMP_SO");
    const std::string module_path = sbs_test::env("CHIMERA_MODULE_PATH");
    ::unsetenv("CHIMERA_MODULE_PATH");  // the folder of ramp.so: off the path for this test
    const Outcome before = sbs_test::run(sbs_test::env("SBS_EXE"), {ws.sbs(), "--no-attach", "-c", "spawn " + rmod});
    const Outcome after = sbs_test::run(sbs_test::env("SBS_EXE"),
                                        {ws.sbs(), "--no-attach", "--json", "-c", "module load " + so + "; spawn " + rmod});
    ::setenv("CHIMERA_MODULE_PATH", module_path.c_str(), 1);
    EXPECT_EQ(before.status, 1) << before.out << before.err;
    EXPECT_NE(before.err.find("module ramp not found"), std::string::npos) << before.err;
    ASSERT_EQ(after.status, 0) << after.out << after.err;
    const auto replies = json_lines(after.out);
    EXPECT_EQ(replies[0]["data"]["module"], "ramp");
    EXPECT_EQ(replies[1]["data"]["module"], "ramp");
    EXPECT_NE(failing(ws, "module load " + ws.dir() + "/elsewhere.rmod").find("shared object"), std::string::npos);
    EXPECT_NE(failing(ws, "module load /nonexistent/x.so").find("not a regular file"), std::string::npos);
}

TEST(SbsCli, FromTheBuildTreeTheShippedModulesNeedNoFlag) {
    Workspace ws;
    const std::string module_path = sbs_test::env("CHIMERA_MODULE_PATH");
    ::unsetenv("CHIMERA_MODULE_PATH");
    const Outcome r = sbs_test::run(sbs_test::env("SBS_EXE"), {ws.sbs(), "--no-attach", "--json", "-c", "module"});
    ::setenv("CHIMERA_MODULE_PATH", module_path.c_str(), 1);
    ASSERT_EQ(r.status, 0) << r.out << r.err;
    const auto replies = json_lines(r.out);
    ASSERT_EQ(replies.size(), 1u);
    std::set<std::string> rmods;
    for (const auto& f : replies[0]["data"]["rmods"]) rmods.insert(f["name"].get<std::string>());
    EXPECT_TRUE(rmods.count("jpid") && rmods.count("jpidg")) << r.out;  // modules/pid of the source tree
    std::string pid_so;
    for (const auto& m : replies[0]["data"]["modules"])
        if (m["name"] == "pid") pid_so = m["path"];
    EXPECT_EQ(pid_so, sbs_test::env("CHIMERA_LIB_DIR") + "/modules/pid/pid.so") << r.out;  // built beside sbs
}

TEST(SbsCli, ScriptFromStdin) {
    Workspace ws;
    const Outcome r = ws.sbs_run({}, "spawn ramp\non\nbogus\nstatus\n");
    EXPECT_EQ(r.status, 1);  // a failed command makes the exit status non-zero
    EXPECT_NE(r.out.find("ramp: ON"), std::string::npos) << r.out;
    EXPECT_NE(r.out.find("error: unknown command 'bogus'"), std::string::npos) << r.out;
    EXPECT_NE(r.out.find("1 task"), std::string::npos) << "the prompt survives errors: " << r.out;
}

// ----------------------------------------------------------------- sample and record

namespace {

std::vector<std::vector<std::string>> csv_rows(const std::string& path, std::string& header) {
    std::ifstream in(path);
    std::getline(in, header);
    std::vector<std::vector<std::string>> rows;
    for (std::string line; std::getline(in, line);) {
        std::vector<std::string> cells;
        std::size_t at = 0;
        for (;;) {
            const auto comma = line.find(',', at);
            cells.push_back(line.substr(at, comma == std::string::npos ? std::string::npos : comma - at));
            if (comma == std::string::npos) break;
            at = comma + 1;
        }
        rows.push_back(cells);
    }
    return rows;
}

}  // namespace

// record: a sampler task at the producer's rate (ramp, 200 Hz), round(0.5 s x
// 200 Hz) rows, time and one column per element, nothing lost, the task and
// its ring gone afterwards.
TEST(SbsCli, RecordWritesOneRowPerSampleAtTheProducersRate) {
    Workspace ws;
    const std::string csv = ws.dir() + "/q.csv";
    const auto r = ok_json(ws, "spawn ramp; on; record X LIMITS 0.5s " + csv + "; status all");
    ASSERT_EQ(r.size(), 4u);
    EXPECT_EQ(r[2]["cmd"], "record");
    EXPECT_EQ(r[2]["data"]["samples"], 100);
    EXPECT_EQ(r[2]["data"]["lost"], 0);
    EXPECT_EQ(r[2]["data"]["rate"], 200.0);
    EXPECT_EQ(r[2]["data"]["channels"], 4);
    EXPECT_EQ(r[2]["text"], "recorded 100 samples of 4 channel(s) at 200 Hz to " + csv + ", 0 lost");
    ASSERT_EQ(r[3]["data"]["tasks"].size(), 1u) << "the sampler task is killed at the end";
    EXPECT_EQ(r[3]["rmod"], "ramp") << "the default RMOD is not left on the killed sampler";
    EXPECT_FALSE(std::filesystem::exists("/dev/shm/chimera." + ws.subsystem() + ".sample.1"));
    EXPECT_FALSE(std::filesystem::exists(csv + ".part"));
    std::string header;
    const auto rows = csv_rows(csv, header);
    EXPECT_EQ(header, "t,X,LIMITS[0],LIMITS[1],LIMITS[2]");
    ASSERT_EQ(rows.size(), 100u);
    double last_t = -1, last_x = -1;
    for (const auto& row : rows) {
        ASSERT_EQ(row.size(), 5u);
        const double t = std::stod(row[0]), x = std::stod(row[1]);
        EXPECT_GT(t, last_t);
        EXPECT_GE(x, last_x) << "X ramps up: a sample out of order";
        EXPECT_EQ(row[2], "0.5");
        EXPECT_EQ(row[3], "1.5");
        EXPECT_EQ(row[4], "2.5");
        last_t = t;
        last_x = x;
    }
    EXPECT_EQ(rows[0][0], "0");
    EXPECT_GT(last_x, 1.0);
}

TEST(SbsCli, SampleStartsARingThatKillStops) {
    Workspace ws;
    const auto r = ok_json(ws, "sample LIMITS[1:2] X --rate 50 --capacity 3000; status; kill sample.1; sample X");
    ASSERT_EQ(r.size(), 4u);
    const auto& d = r[0]["data"];
    EXPECT_EQ(d["rmod"], "sample.1");
    EXPECT_EQ(d["ring"], "/chimera." + ws.subsystem() + ".sample.1");
    EXPECT_EQ(d["channels"], nlohmann::json({"LIMITS[1]", "LIMITS[2]", "X"}));
    EXPECT_EQ(d["rate"], 50.0);
    EXPECT_EQ(d["capacity"], 4096);
    const auto* s = task(r[1], "sample.1");
    ASSERT_NE(s, nullptr);
    EXPECT_EQ((*s)["state"], "ON");
    EXPECT_EQ((*s)["module"], "sampler");
    EXPECT_EQ(r[2]["data"]["state"], "NOT-CREATED");
    // No task produces X: 100 Hz, and the reply says why.
    EXPECT_EQ(r[3]["data"]["rmod"], "sample.2");
    EXPECT_EQ(r[3]["data"]["rate"], 100.0);
    EXPECT_NE(r[3]["text"].get<std::string>().find("(no task produces them)"), std::string::npos) << r[3]["text"];
}

TEST(SbsCli, SampleAndRecordRefusals) {
    Workspace ws;
    const std::string table = "/chimera." + ws.subsystem() + ".svar";
    EXPECT_EQ(failing(ws, "sample NOPE"), "sample NOPE: table " + table + " has no variable NOPE");
    EXPECT_EQ(failing(ws, "sample LIMITS[3]"), "sample LIMITS[3]: element 3 is outside LIMITS (3 elements: 0 to 2)");
    EXPECT_EQ(failing(ws, "sample X --rate -5"), "sample: --rate -5 is not a positive number");
    EXPECT_EQ(failing(ws, "sample X --bogus 1"), "sample: unknown option --bogus (--rate HZ, --rtpu RTPU, --capacity N)");
    EXPECT_EQ(failing(ws, "sample"), "usage: sample VAR[IDX]... [--rate HZ] [--rtpu RTPU] [--capacity N]");
    EXPECT_EQ(failing(ws, "record X 2s"), "usage: record VAR[IDX]... DURATION FILE.csv [--rate HZ] [--rtpu RTPU]");
    EXPECT_EQ(failing(ws, "record X 0s q.csv"), "record: duration 0s is not a positive time (5s, 500ms, 2min, 1.5)");
    EXPECT_EQ(failing(ws, "record X 2h q.csv"), "record: duration 2h is not a positive time (5s, 500ms, 2min, 1.5)");
    EXPECT_EQ(failing(ws, "record NOPE 1s " + ws.dir() + "/n.csv"), "sample NOPE: table " + table + " has no variable NOPE");
    EXPECT_FALSE(std::filesystem::exists(ws.dir() + "/n.csv.part"));
    EXPECT_FALSE(std::filesystem::exists(ws.dir() + "/n.csv"));
}

TEST(SbsCli, SampleRecordAndPeerComplete) {
    Workspace ws;
    const auto r = ok_json(ws, "complete sample LI; complete record X --rtpu c; complete record --r; complete peer p --o");
    ASSERT_EQ(r.size(), 4u);
    EXPECT_EQ(r[0]["data"]["candidates"], nlohmann::json({"LIMITS"}));
    EXPECT_EQ(r[1]["data"]["candidates"], nlohmann::json({"cpu0"}));
    EXPECT_EQ(r[2]["data"]["candidates"], nlohmann::json({"--rate", "--rtpu"}));
    EXPECT_EQ(r[3]["data"]["candidates"], nlohmann::json({"--out"}));
}

// ----------------------------------------------------------------- sampler admission (issue #29.2)

namespace {

// Two RTPUs on CPU 0: cpu0 at the default 1..1000 Hz, fast up to 5 kHz.
void two_rtpus(const Workspace& ws) {
    ws.write(ws.subsystem() + ".sbs", "SUBSYSTEM " + ws.subsystem() + "\nSVARFILE  " + sbs_test::env("SBS_TEST_DATA") +
                                          "/tools.svar\nRTPU      cpu0\nBACKEND   other\n"
                                          "RTPU      fast 0\nMAXFREQ   5000\nBACKEND   other\nEOF\n");
}

}  // namespace

// A sampler is a task: a rate outside its RTPU's MINFREQ..MAXFREQ is refused
// with both bounds and the RTPU that would take it; one no RTPU can run
// (the issue's 100 kHz) is refused outright; nothing is left spawned.
TEST(SbsCli, ASamplersRateMustLieWithinItsRtpusRange) {
    Workspace ws;
    two_rtpus(ws);
    EXPECT_EQ(failing(ws, "sample X --rate 2000"),
              "sample refused: 2000 Hz is above RTPU cpu0's MAXFREQ (it runs tasks at 1 to 1000 Hz); --rtpu fast takes it");
    EXPECT_EQ(failing(ws, "sample X --rate 0.5 --rtpu fast"),
              "sample refused: 0.5 Hz is below RTPU fast's MINFREQ (it runs tasks at 1 to 5000 Hz); no RTPU takes it at "
              "0.5 Hz: choose another --rate");
    const std::string refused = failing(ws, "sample X --rate 100000 --rtpu fast");
    EXPECT_EQ(refused, "sample refused: 100000 Hz is above RTPU fast's MAXFREQ (it runs tasks at 1 to 5000 Hz); "
                       "no RTPU takes it at 100000 Hz: choose another --rate");
    const auto r = ok_json(ws, "sample X --rate 2000 --rtpu fast; status");
    ASSERT_EQ(r.size(), 2u);
    EXPECT_EQ(r[0]["data"]["rtpu"], "fast");
    EXPECT_EQ(r[1]["data"]["tasks"].size(), 1u) << "the refused samplers left no task";
}

// The RTPU's MUF analysis with the sampler added must still guarantee its
// critical set: heavy (C 4.95 ms every 5 ms, U 0.99) would leave it for a
// 1 kHz sampler, so that one is refused, naming heavy and offering fast; a
// 10 Hz sampler fits beside it and is admitted.
TEST(SbsCli, ASamplerThatWouldPushATaskOutOfTheCriticalSetIsRefused) {
    Workspace ws;
    two_rtpus(ws);
    ws.write("heavy.rmod", "MODULE ramp\nDESC a ramp that reserves 99% of its RTPU\nINVAR none\nOUTVAR X\n"
                           "TASKTYPE periodic\nFREQ 200\nWCET 0.00495\n\nLOCAL\nSTEP 1\nEOF\n");
    const std::string why = failing(ws, "spawn " + ws.dir() + "/heavy.rmod; on; sample X --rate 1000");
    EXPECT_EQ(why.rfind("sample refused: RTPU cpu0 (MUF) cannot take sample.1 at 1000 Hz (C ", 0), 0u) << why;
    EXPECT_NE(why.find("): the critical set would lose heavy (U 0.990) (utilisation with it 1.0"), std::string::npos) << why;
    EXPECT_NE(why.find(", bound 1.000); --rtpu fast takes it"), std::string::npos) << why;
    const auto r = ok_json(ws, "spawn " + ws.dir() + "/heavy.rmod; on; sample X --rate 10; sample X --rate 1000 --rtpu fast");
    ASSERT_EQ(r.size(), 4u);
    EXPECT_EQ(r[2]["data"]["rtpu"], "cpu0");
    EXPECT_EQ(r[3]["data"]["rtpu"], "fast");
}

// A running sampler counts in the next one's analysis with the cost it was
// admitted with (C 20.1 us, U 0.004 at 200 Hz): beside heavy (U 0.990) two
// fit, a third would not be guaranteed itself.
TEST(SbsCli, RunningSamplersCountInTheNextOnesAnalysis) {
    Workspace ws;
    two_rtpus(ws);
    ws.write("heavy.rmod", "MODULE ramp\nDESC a ramp that reserves 99% of its RTPU\nINVAR none\nOUTVAR X\n"
                           "TASKTYPE periodic\nFREQ 200\nWCET 0.00495\n\nLOCAL\nSTEP 1\nEOF\n");
    EXPECT_EQ(failing(ws, "spawn " + ws.dir() + "/heavy.rmod; on; sample X --rate 200; sample X --rate 200; "
                      "sample X --rate 200"),
              "sample refused: RTPU cpu0 (MUF) cannot take sample.3 at 200 Hz (C 20 us, U 0.004): it would not be in "
              "the critical set itself (utilisation with it 1.002, bound 1.000); --rtpu fast takes it");
}
