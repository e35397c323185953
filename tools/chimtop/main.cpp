// chimtop — a top-like live view of a running Chimera subsystem (issue 5,
// ARCHITECTURE §8). It attaches to /chimera.<subsystem>.status by name,
// shows one row per task with the chosen §4.4.1 fields, and only ever READS
// the status segment (seqlocked snapshots: the tasks are never blocked). The
// optional SVAR pane reads the selected task's variables through the table's
// own locked read, once per refresh. `z` asks for a profiling reset, the
// status command's "since last status" semantics; nothing else writes.
#include <ncurses.h>
#include <signal.h>
#include <sys/stat.h>
#include <unistd.h>

#include "tool_cli.hpp"

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "chimera/ipc/segment.hpp"
#include "chimera/prof.hpp"
#include "fields.hpp"
#include "svar_pane.hpp"

namespace {

using chimera::prof::StatusReader;
using chimera::prof::TaskStatus;

/// Attachment that survives the subsystem stopping and restarting: a reader
/// is dropped when its creator is gone or the name now names a new segment.
class Attachment {
public:
    /// `half_tick_ns` >= 0: on every (re-)attachment, switch each RTPU to
    /// half-tick accounting with that tick (0: back to nanoseconds).
    Attachment(std::string subsystem, std::int64_t half_tick_ns)
        : subsystem_(std::move(subsystem)),
          path_("/dev/shm" + chimera::ipc::segment_name(subsystem_, "status")),
          half_tick_ns_(half_tick_ns) {}

    bool refresh() {
        if (reader_ && (!reader_->alive() || inode() != inode_)) {
            reader_.reset();
            ++restarts_;
        }
        if (!reader_) {
            const ino_t before = inode();
            reader_ = StatusReader::try_attach(subsystem_);
            if (reader_ && inode() != before) reader_.reset();  // replaced while attaching
            if (reader_) {
                inode_ = before;
                apply_accounting();
            }
        }
        return reader_.has_value();
    }
    /// Why the last accounting change failed ("" if it did not).
    const std::string& error() const { return error_; }
    StatusReader* reader() { return reader_ ? &*reader_ : nullptr; }
    const std::string& subsystem() const { return subsystem_; }
    int restarts() const { return restarts_; }

private:
    void apply_accounting() {
        if (half_tick_ns_ < 0) return;
        using chimera::prof::Accounting;
        try {
            for (std::uint32_t r = 0; r < reader_->rtpus(); ++r)
                reader_->set_accounting(static_cast<int>(r),
                                        half_tick_ns_ > 0 ? Accounting::half_tick : Accounting::nanoseconds,
                                        half_tick_ns_);
            error_.clear();
        } catch (const std::exception& e) {
            error_ = e.what();
        }
    }
    ino_t inode() const {
        struct stat st;
        return ::stat(path_.c_str(), &st) == 0 ? st.st_ino : 0;
    }
    std::string subsystem_;
    std::string path_;
    std::optional<StatusReader> reader_;
    ino_t inode_ = 0;
    int restarts_ = 0;
    std::int64_t half_tick_ns_ = -1;
    std::string error_;
};

struct Options {
    std::string subsystem;
    std::string fields_text;
    std::string sort = "rtpu";
    bool descending = false;
    double rate_hz = 2.0;
    bool once = false;
    bool json = false;
    bool svar_pane = false;
    std::string svar_segment;
    double wait_s = 0;
    double sample_s = 0;
    double half_tick_ms = -1;  ///< < 0: leave the accounting as it is
    std::int64_t half_tick_ns() const {
        return half_tick_ms < 0 ? -1 : static_cast<std::int64_t>(std::llround(half_tick_ms * 1e6));
    }
};

volatile sig_atomic_t g_stop = 0;
void on_signal(int) { g_stop = 1; }

int run_once(const Options& o, const std::vector<std::string>& fields) {
    Attachment a(o.subsystem, o.half_tick_ns());
    const auto give_up = std::chrono::steady_clock::now() + std::chrono::duration<double>(o.wait_s);
    while (!a.refresh()) {
        if (std::chrono::steady_clock::now() >= give_up) {
            std::cerr << "chimtop: no subsystem '" << o.subsystem << "' (segment "
                      << chimera::ipc::segment_name(o.subsystem, "status") << " not found)\n";
            return 1;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    if (!a.error().empty()) {
        std::cerr << "chimtop: " << a.error() << "\n";
        return 1;
    }
    if (o.sample_s > 0) {
        // A profile of exactly this window: reset every RTPU, wait, look.
        a.reader()->reset_all();
        std::this_thread::sleep_for(std::chrono::duration<double>(o.sample_s));
    }
    auto tasks = a.reader()->snapshot();
    chimtop::sort_tasks(tasks, o.sort, o.descending);
    if (o.json) {
        auto j = chimtop::to_json(o.subsystem, tasks);
        if (o.svar_pane) {
            for (auto& t : j["tasks"])
                t["svar"] = chimtop::svar_values_json(o.svar_segment, t["inputs"].get<std::string>(),
                                                       t["outputs"].get<std::string>());
        }
        std::cout << j.dump(2) << "\n";
    } else {
        std::cout << chimtop::plain_text(o.subsystem, tasks, fields);
        if (o.svar_pane)
            for (const auto& t : tasks) {
                std::cout << "SVAR of " << t.rmod << ":\n";
                for (const auto& l : chimtop::svar_lines(o.svar_segment, t.inputs, t.outputs))
                    std::cout << "  " << l << "\n";
            }
    }
    return 0;
}

class Ui {
public:
    Ui(Options o, std::vector<std::string> fields)
        : o_(std::move(o)), fields_(std::move(fields)), attach_(o_.subsystem, o_.half_tick_ns()) {
        auto it = std::find(fields_.begin(), fields_.end(), o_.sort);
        sort_col_ = it == fields_.end() ? 0 : static_cast<int>(it - fields_.begin());
        if (it == fields_.end()) o_.sort = fields_[0];
    }

    int run() {
        initscr();
        cbreak();
        noecho();
        keypad(stdscr, TRUE);
        curs_set(0);
        if (has_colors()) {
            start_color();
            use_default_colors();
            init_pair(1, COLOR_YELLOW, -1);  // missed cycles, warnings
            init_pair(2, COLOR_RED, -1);     // ERROR
            init_pair(3, COLOR_CYAN, -1);    // header
        }
        while (!g_stop) {
            draw();
            timeout(static_cast<int>(std::lround(1000.0 / o_.rate_hz)));
            const int ch = getch();
            if (ch == ERR) continue;
            if (!key(ch)) break;
        }
        endwin();
        return 0;
    }

private:
    bool key(int ch) {
        switch (ch) {
            case 'q':
            case 'Q':
                return false;
            case '<':
            case KEY_LEFT:
                sort_col_ = (sort_col_ + static_cast<int>(fields_.size()) - 1) % static_cast<int>(fields_.size());
                o_.sort = fields_[static_cast<std::size_t>(sort_col_)];
                break;
            case '>':
            case KEY_RIGHT:
            case 's':
                sort_col_ = (sort_col_ + 1) % static_cast<int>(fields_.size());
                o_.sort = fields_[static_cast<std::size_t>(sort_col_)];
                break;
            case 'r':
                o_.descending = !o_.descending;
                break;
            case KEY_UP:
            case 'k':
                if (selected_ > 0) --selected_;
                break;
            case KEY_DOWN:
            case 'j':
                ++selected_;
                break;
            case '+':
                o_.rate_hz = std::min(o_.rate_hz * 2, 50.0);
                break;
            case '-':
                o_.rate_hz = std::max(o_.rate_hz / 2, 0.125);
                break;
            case 'v':
                o_.svar_pane = !o_.svar_pane;
                break;
            case 'z':
                if (auto* r = attach_.reader()) {
                    try {
                        r->reset_all();
                        message_ = "profiling reset on every RTPU";
                    } catch (const std::exception& e) {
                        message_ = e.what();
                    }
                }
                break;
            case 'f':
                prompt_fields();
                break;
            default:
                break;
        }
        return true;
    }

    void prompt_fields() {
        const int rows = LINES;
        move(rows - 1, 0);
        clrtoeol();
        attron(A_BOLD);
        printw("fields: ");
        attroff(A_BOLD);
        echo();
        curs_set(1);
        timeout(-1);
        char buf[512] = {};
        getnstr(buf, sizeof buf - 1);
        noecho();
        curs_set(0);
        try {
            fields_ = chimtop::parse_fields(buf);
            auto it = std::find(fields_.begin(), fields_.end(), o_.sort);
            sort_col_ = it == fields_.end() ? 0 : static_cast<int>(it - fields_.begin());
            o_.sort = fields_[static_cast<std::size_t>(sort_col_)];
            message_.clear();
        } catch (const std::exception& e) {
            message_ = e.what();
        }
    }

    void draw() {
        erase();
        const bool up = attach_.refresh();
        int y = 0;
        attron(A_BOLD);
        mvprintw(y++, 0, "chimtop  subsystem %s  refresh %.3g Hz  sort %s %s%s", o_.subsystem.c_str(),
                 o_.rate_hz, o_.sort.c_str(), o_.descending ? "desc" : "asc",
                 up && attach_.restarts() ? "  (re-attached)" : "");
        attroff(A_BOLD);
        mvprintw(y++, 0, "q quit  </> sort column  r reverse  f fields  +/- rate  up/down select  v SVAR pane  z reset");
        if (!up) {
            attron(COLOR_PAIR(1) | A_BOLD);
            mvprintw(y + 1, 0, "waiting for subsystem '%s' (segment %s not found) ...", o_.subsystem.c_str(),
                     chimera::ipc::segment_name(o_.subsystem, "status").c_str());
            attroff(COLOR_PAIR(1) | A_BOLD);
            footer();
            refresh();
            return;
        }
        auto tasks = attach_.reader()->snapshot();
        chimtop::sort_tasks(tasks, o_.sort, o_.descending);
        if (selected_ >= static_cast<int>(tasks.size())) selected_ = static_cast<int>(tasks.size()) - 1;
        if (selected_ < 0) selected_ = 0;

        attron(COLOR_PAIR(3) | A_BOLD | A_UNDERLINE);
        mvaddnstr(y++, 0, chimtop::header_line(fields_).c_str(), COLS);
        attroff(COLOR_PAIR(3) | A_BOLD | A_UNDERLINE);
        const int pane_rows = o_.svar_pane ? std::max(LINES / 3, 4) : 0;
        const int last_row = LINES - 2 - pane_rows;
        for (std::size_t i = 0; i < tasks.size() && y <= last_row; ++i) {
            const auto& t = tasks[i];
            attr_t a = A_NORMAL;
            if (t.state == chimera::prof::TaskState::error) a |= COLOR_PAIR(2) | A_BOLD;
            else if (t.miss > 0) a |= COLOR_PAIR(1) | A_BOLD;
            if (static_cast<int>(i) == selected_) a |= A_REVERSE;
            attron(a);
            mvaddnstr(y++, 0, chimtop::task_line(t, fields_).c_str(), COLS);
            attroff(a);
            for (const auto& m : chimtop::message_lines(t)) {
                if (y > last_row) break;
                const bool err = m.rfind("ERROR>", 0) == 0;
                attron(COLOR_PAIR(err ? 2 : 1));
                mvaddnstr(y++, 2, m.c_str(), COLS - 2);
                attroff(COLOR_PAIR(err ? 2 : 1));
            }
        }
        if (tasks.empty()) mvprintw(y++, 0, "(no tasks)");
        if (o_.svar_pane && !tasks.empty()) {
            const auto& t = tasks[static_cast<std::size_t>(selected_)];
            int py = LINES - 1 - pane_rows;
            attron(A_BOLD);
            mvprintw(py++, 0, "SVAR of %s  (in: %s  out: %s)", t.rmod.c_str(), t.inputs.c_str(),
                     t.outputs.c_str());
            attroff(A_BOLD);
            for (const auto& l : chimtop::svar_lines(o_.svar_segment, t.inputs, t.outputs)) {
                if (py >= LINES - 1) break;
                mvaddnstr(py++, 2, l.c_str(), COLS - 2);
            }
        }
        footer();
        refresh();
    }

    void footer() {
        if (!attach_.error().empty()) message_ = attach_.error();
        if (!message_.empty()) mvaddnstr(LINES - 1, 0, message_.c_str(), COLS);
    }

    Options o_;
    std::vector<std::string> fields_;
    Attachment attach_;
    int sort_col_ = 0;
    int selected_ = 0;
    std::string message_;
};

}  // namespace

int main(int argc, char** argv) {
    Options o;
    CLI::App app{"chimtop: live status of a Chimera subsystem's tasks (thesis §4.4.1 fields)"};
    app.add_option("subsystem", o.subsystem, "subsystem name (segment /chimera.<name>.status)");
    app.add_option("-f,--fields", o.fields_text,
                   "comma-separated fields, in display order (like `status set`); --list-fields shows them");
    app.add_option("-s,--sort", o.sort, "field to sort by");
    app.add_flag("-r,--reverse", o.descending, "sort descending");
    app.add_option("-n,--rate", o.rate_hz, "redraws per second")->check(CLI::Range(0.1, 50.0));
    app.add_flag("--once", o.once, "print one snapshot as plain text and exit");
    app.add_flag("--json", o.json, "print one snapshot as JSON and exit");
    app.add_flag("--svar", o.svar_pane, "show the SVAR values each task reads and writes");
    app.add_option("--svar-segment", o.svar_segment,
                   "SVAR table segment (default /chimera.<subsystem>.svar)");
    app.add_option("--wait", o.wait_s, "with --once/--json: seconds to wait for the subsystem");
    app.add_option("--sample", o.sample_s,
                   "with --once/--json: reset profiling, wait this many seconds, then print "
                   "(a profile of exactly that window)")
        ->check(CLI::Range(0.0, 3600.0));
    app.add_option("--half-tick", o.half_tick_ms,
                   "switch every RTPU to the thesis's half-tick accounting with this tick in ms "
                   "(0: back to nanoseconds); resets profiling, re-applied after a restart")
        ->check(CLI::Range(0.0, 1000.0));
    bool list = false;
    app.add_flag("--list-fields", list, "list the status fields and exit");
    chimera::tools::add_version(app, "chimtop");
    if (const int status = chimera::tools::parse(app, argc, argv); status >= 0) return status;

    if (list) {
        for (const auto& f : chimtop::all_fields()) std::printf("%-7s %s\n", f.name, f.help);
        return 0;
    }
    if (o.subsystem.empty()) {
        std::cerr << "chimtop: which subsystem? (chimtop SUBSYSTEM; --help for the options)\n";
        return 2;
    }
    std::vector<std::string> fields;
    try {
        fields = o.fields_text.empty() ? chimtop::default_fields() : chimtop::parse_fields(o.fields_text);
        if (!chimtop::find_field(o.sort)) throw std::invalid_argument("unknown sort field '" + o.sort + "'");
        if (o.svar_segment.empty()) o.svar_segment = chimera::ipc::segment_name(o.subsystem, "svar");
    } catch (const std::exception& e) {
        std::cerr << "chimtop: " << e.what() << "\n";
        return 2;
    }
    if (o.once || o.json) return run_once(o, fields);

    signal(SIGINT, on_signal);
    signal(SIGTERM, on_signal);
    return Ui(o, fields).run();
}
