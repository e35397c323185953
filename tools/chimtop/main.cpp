// chimtop — a top-like live view of a running Chimera subsystem (issue 5,
// docs/architecture.md §15). It attaches to /chimera.<subsystem>.status by
// name, shows a summary line per RTPU and one row per task with the chosen
// §4.4.1 fields, and only READS the task groups of the status segment
// (seqlocked snapshots: the tasks are never blocked). Counts are over this
// chimtop's own window (`z` restarts it, nobody else's: issue 16.4). Started
// without a subsystem it lists the running ones. The optional SVAR pane reads
// the selected task's variables as a watcher (Table::watch: no table lock),
// once per refresh. chimtop maps both segments read-only, so a member of the
// watch group may run it (docs/permissions.md). The live view is in ui.cpp.
#include <cerrno>
#include <csignal>

#include "tool_cli.hpp"

#include <CLI/CLI.hpp>
#include <chrono>
#include <cstdio>
#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include "chimera/ipc/segment.hpp"
#include "fields.hpp"
#include "source.hpp"
#include "svar_pane.hpp"
#include "ui.hpp"

namespace {

using chimtop::Options;

void on_signal(int) { chimtop::g_stop = 1; }

/// `chimtop --once` / `--json` without a subsystem: the running ones.
int list_subsystems(bool json) {
    const auto entries = chimtop::running_subsystems();
    if (json) {
        nlohmann::json arr = nlohmann::json::array();
        for (const auto& e : entries)
            arr.push_back({{"name", e.name}, {"readable", e.readable}, {"alive", e.alive}, {"pid", e.creator_pid},
                           {"tasks", e.tasks}, {"problem", e.problem}});
        std::cout << nlohmann::json{{"subsystems", arr}}.dump(2) << "\n";
    } else if (entries.empty()) {
        std::cout << "no Chimera subsystem is running (no /dev/shm/chimera.*.status)\n";
    } else {
        for (const auto& e : entries) std::cout << chimtop::entry_line(e) << "\n";
    }
    return entries.empty() ? 1 : 0;
}

// Attaches, waiting up to --wait seconds; 0 when attached, else the exit status.
int attach_once(chimtop::Attachment& a, const Options& o) {
    const auto give_up = std::chrono::steady_clock::now() + std::chrono::duration<double>(o.wait_s);
    while (!a.refresh()) {
        if (a.denied() || std::chrono::steady_clock::now() >= give_up) {
            std::cerr << "chimtop: " << (a.denied() ? a.problem() : "no subsystem '" + o.subsystem + "' (" + a.problem() + ")")
                      << "\n";
            return 1;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    if (!a.error().empty()) {
        std::cerr << "chimtop: " << a.error() << "\n";
        return 1;
    }
    return 0;
}

int run_once(const Options& o, const std::vector<std::string>& fields) {
    chimtop::Attachment a(o.subsystem, o.half_tick_ns());
    if (const int status = attach_once(a, o); status != 0) return status;
    if (o.sample_s > 0) {
        // A profile of exactly this window (this chimtop's: nobody else's counts move).
        a.restart_window();
        std::this_thread::sleep_for(std::chrono::duration<double>(o.sample_s));
    }
    auto tasks = a.snapshot();
    chimtop::sort_tasks(tasks, o.sort, o.descending);
    if (o.json) {
        auto j = chimtop::to_json(o.subsystem, a.rtpus(), tasks);
        if (o.svar_pane) {
            for (auto& t : j["tasks"])
                t["svar"] = chimtop::svar_values_json(o.svar_segment, t["inputs"].get<std::string>(),
                                                       t["outputs"].get<std::string>());
        }
        std::cout << j.dump(2) << "\n";
        return 0;
    }
    std::cout << chimtop::plain_text(o.subsystem, a.rtpus(), tasks, fields);
    if (o.svar_pane)
        for (const auto& t : tasks) {
            std::cout << "SVAR of " << t.rmod << ":\n";
            for (const auto& l : chimtop::svar_lines(o.svar_segment, t.inputs, t.outputs)) std::cout << "  " << l << "\n";
        }
    return 0;
}

void add_options(CLI::App& app, Options& o) {
    app.add_option("subsystem", o.subsystem,
                   "subsystem name (segment /chimera.<name>.status); without it, the running subsystems are listed");
    app.add_option("-f,--fields", o.fields_text,
                   "comma-separated fields, in display order (like `status set`); --list-fields shows them");
    app.add_option("-s,--sort", o.sort, "field to sort by");
    app.add_flag("-r,--reverse", o.descending, "sort descending");
    app.add_option("-n,--rate", o.rate_hz, "redraws per second")->check(CLI::Range(0.1, 50.0));
    app.add_flag("--once", o.once, "print one snapshot as plain text and exit (times in us)");
    app.add_flag("--json", o.json, "print one snapshot as JSON and exit (times in us)");
    app.add_flag("--svar", o.svar_pane, "show the SVAR values each task reads and writes");
    app.add_option("--svar-segment", o.svar_segment, "SVAR table segment (default /chimera.<subsystem>.svar)");
    app.add_option("--wait", o.wait_s, "with --once/--json: seconds to wait for the subsystem");
    app.add_option("--sample", o.sample_s,
                   "with --once/--json: start this chimtop's window, wait this many seconds, then print "
                   "(a profile of exactly that window; other readers are not affected)")
        ->check(CLI::Range(0.0, 3600.0));
    app.add_option("--half-tick", o.half_tick_ms,
                   "switch every RTPU to the thesis's half-tick accounting with this tick in ms "
                   "(0: back to nanoseconds); resets profiling for every reader, re-applied after a restart")
        ->check(CLI::Range(0.0, 1000.0));
}

}  // namespace

int main(int argc, char** argv) {
    Options o;
    CLI::App app{"chimtop: live status of a Chimera subsystem's tasks (thesis §4.4.1 fields; times in us). "
                 "In the live view, h or F1 shows the keys."};
    add_options(app, o);
    bool list = false;
    app.add_flag("--list-fields", list, "list the status fields and exit");
    chimera::tools::add_version(app, "chimtop");
    if (const int status = chimera::tools::parse(app, argc, argv); status >= 0) return status;

    if (list) {
        for (const auto& f : chimtop::all_fields())
            std::printf("%-7s %s\n", f.name, f.help);
        return 0;
    }
    if (o.subsystem.empty() && (o.once || o.json)) return list_subsystems(o.json);
    std::vector<std::string> fields;
    try {
        fields = o.fields_text.empty() ? chimtop::default_fields() : chimtop::parse_fields(o.fields_text);
        if (!chimtop::find_field(o.sort)) throw std::invalid_argument("unknown sort field '" + o.sort + "'");
        if (o.svar_segment.empty() && !o.subsystem.empty())
            o.svar_segment = chimera::ipc::segment_name(o.subsystem, "svar");
    } catch (const std::exception& e) {
        std::cerr << "chimtop: " << e.what() << "\n";
        return 2;
    }
    if (o.once || o.json) return run_once(o, fields);

    std::signal(SIGINT, on_signal);
    std::signal(SIGTERM, on_signal);
    return chimtop::Ui(o, fields).run();
}
