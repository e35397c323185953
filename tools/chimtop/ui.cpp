#include "ui.hpp"

#include <ncurses.h>

#include <algorithm>
#include <clocale>
#include <cmath>

#include "chimera/ipc/segment.hpp"
#include "fields.hpp"
#include "status_text.hpp"
#include "svar_pane.hpp"

namespace chimtop {

volatile std::sig_atomic_t g_stop = 0;

std::int64_t Options::half_tick_ns() const {
    return half_tick_ms < 0 ? -1 : static_cast<std::int64_t>(std::llround(half_tick_ms * 1e6));
}

namespace {

constexpr int kEscape = 27;
constexpr short kWarnColour = 1, kErrorColour = 2, kHeaderColour = 3;

const char* const kHelp[] = {
    "chimtop - live status of a Chimera subsystem's tasks (the status fields of thesis section 4.4.1)",
    "",
    "  h ? F1      this help (any key: back)",
    "  f F2        choose the fields: every field listed, space shows/hides, [ ] move",
    "  / F3        search: select the next task matching (rmod, RTPU, state, policy); n: next",
    "  \\ F4        filter: show only the tasks matching; Esc clears",
    "  < > s       sort by the previous / next column        r   reverse the order",
    "  up down j k select a task                            v   SVAR pane of the selected task",
    "  z           restart THIS chimtop's window (nobody else's counts change)",
    "  + -         faster / slower refresh                   q   quit",
    "",
    "Every time is in microseconds (us). Counts, averages and percentiles are over this",
    "chimtop's window: since you last pressed z, or since the RTPU's last reset (`status reset`",
    "at the sbs prompt, or a task turned on). minC/maxC/minU/maxU are since that reset.",
    "cycP50/cycP99: cycle time, wake-up to end of cycle (wall clock), median and 99th percentile;",
    "latP50/latP99: release lateness, wake-up minus release instant (periodic tasks).",
    "One line per RTPU: its tasks, CPU use (sum of avgU), misses, the worst task's p99s.",
    "Rows: yellow = missed cycles, red = ERROR. --list-fields explains every field.",
};

bool is_help_key(int ch) { return ch == 'h' || ch == '?' || ch == KEY_F(1); }

}  // namespace

Ui::Ui(Options o, std::vector<std::string> fields) : o_(std::move(o)), fields_(std::move(fields)) {
    auto it = std::find(fields_.begin(), fields_.end(), o_.sort);
    sort_col_ = it == fields_.end() ? 0 : static_cast<int>(it - fields_.begin());
    if (it == fields_.end()) o_.sort = fields_[0];
    if (o_.subsystem.empty()) mode_ = Mode::chooser;
    else attach_.emplace(o_.subsystem, o_.half_tick_ns());
}

int Ui::run() {
    std::setlocale(LC_ALL, "");  // the terminal's character set; chimtop itself prints ASCII
    initscr();
    cbreak();
    noecho();
    keypad(stdscr, TRUE);
    set_escdelay(25);
    curs_set(0);
    if (has_colors()) {
        start_color();
        use_default_colors();
        init_pair(kWarnColour, COLOR_YELLOW, -1);  // missed cycles, warnings
        init_pair(kErrorColour, COLOR_RED, -1);    // ERROR, permission denied
        init_pair(kHeaderColour, COLOR_CYAN, -1);
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

// ------------------------------------------------------------------ keys

bool Ui::key(int ch) {
    switch (mode_) {
        case Mode::help: mode_ = attach_ ? Mode::table : Mode::chooser; return true;
        case Mode::fields: picker_key(ch); return true;
        case Mode::search:
        case Mode::filter: prompt_key(ch); return true;
        case Mode::chooser: return chooser_key(ch);
        case Mode::table: return table_key(ch);
    }
    return true;
}

bool Ui::table_key(int ch) {
    const int n = static_cast<int>(fields_.size());
    if (is_help_key(ch)) mode_ = Mode::help;
    else if (ch == 'q' || ch == 'Q') return false;
    else if (ch == 'f' || ch == KEY_F(2)) {
        mode_ = Mode::fields;
        picker_cursor_ = 0;
    } else if (ch == '/' || ch == KEY_F(3)) {
        mode_ = Mode::search;
        search_.clear();
    } else if (ch == '\\' || ch == KEY_F(4)) mode_ = Mode::filter;
    else if (ch == 'n') search_next(false);
    else if (ch == kEscape) filter_.clear();
    else if (ch == '<' || ch == KEY_LEFT) set_sort((sort_col_ + n - 1) % n);
    else if (ch == '>' || ch == KEY_RIGHT || ch == 's') set_sort((sort_col_ + 1) % n);
    else if (ch == 'r') o_.descending = !o_.descending;
    else if (ch == KEY_UP || ch == 'k') selected_ = std::max(selected_ - 1, 0);
    else if (ch == KEY_DOWN || ch == 'j') ++selected_;
    else if (ch == '+') o_.rate_hz = std::min(o_.rate_hz * 2, 50.0);
    else if (ch == '-') o_.rate_hz = std::max(o_.rate_hz / 2, 0.125);
    else if (ch == 'v') o_.svar_pane = !o_.svar_pane;
    else if (ch == 'z' && attach_) {
        attach_->restart_window();
        message_ = "window restarted: counts from now on (other readers are not affected)";
    }
    return true;
}

void Ui::set_sort(int column) {
    sort_col_ = column;
    o_.sort = fields_[static_cast<std::size_t>(sort_col_)];
}

// Moves the selection to the next row matching the search text (the
// selected one itself when `from_current`, as the text is typed).
void Ui::search_next(bool from_current) {
    const int n = static_cast<int>(shown_.size());
    for (int k = from_current ? 0 : 1; k <= n; ++k) {
        const int i = (selected_ + k) % std::max(n, 1);
        if (i < n && matches(shown_[static_cast<std::size_t>(i)], search_)) {
            selected_ = i;
            message_.clear();
            return;
        }
    }
    message_ = "no task matches '" + search_ + "'";
}

void Ui::prompt_key(int ch) {
    std::string& text = mode_ == Mode::search ? search_ : filter_;
    if (ch == '\n' || ch == KEY_ENTER) {
        mode_ = Mode::table;
        return;
    }
    if (ch == kEscape) {
        text.clear();
        mode_ = Mode::table;
        return;
    }
    if ((ch == KEY_BACKSPACE || ch == 127 || ch == 8) && !text.empty()) text.pop_back();
    else if (ch >= 32 && ch < 127) text += static_cast<char>(ch);
    if (mode_ == Mode::search) search_next(true);
}

// The picker lists the shown fields first, in display order, then the others.
std::vector<std::string> Ui::picker_order() const {
    std::vector<std::string> order = fields_;
    for (const auto& f : all_fields())
        if (std::find(order.begin(), order.end(), f.name) == order.end()) order.emplace_back(f.name);
    return order;
}

void Ui::picker_key(int ch) {
    const std::vector<std::string> order = picker_order();
    const int n = static_cast<int>(order.size());
    const std::string current = order[static_cast<std::size_t>(picker_cursor_)];
    const auto shown = std::find(fields_.begin(), fields_.end(), current);
    if (ch == KEY_UP || ch == 'k') picker_cursor_ = std::max(picker_cursor_ - 1, 0);
    else if (ch == KEY_DOWN || ch == 'j') picker_cursor_ = std::min(picker_cursor_ + 1, n - 1);
    else if (ch == ' ') {
        if (shown == fields_.end()) fields_.push_back(current);  // shown last: the cursor follows it
        else if (fields_.size() > 1) fields_.erase(shown);
        else message_ = "at least one field stays shown";
        const std::vector<std::string> now = picker_order();  // the cursor stays on the field
        picker_cursor_ = static_cast<int>(std::find(now.begin(), now.end(), current) - now.begin());
    } else if ((ch == '[' || ch == ']') && shown != fields_.end()) {
        const auto i = shown - fields_.begin();
        const auto j = ch == '[' ? i - 1 : i + 1;
        if (j >= 0 && j < static_cast<long>(fields_.size())) {
            std::swap(fields_[static_cast<std::size_t>(i)], fields_[static_cast<std::size_t>(j)]);
            picker_cursor_ = static_cast<int>(j);
        }
    } else if (ch == '\n' || ch == KEY_ENTER || ch == kEscape || ch == 'f' || ch == 'q' || ch == KEY_F(2)) {
        mode_ = Mode::table;
    }
    const auto s = std::find(fields_.begin(), fields_.end(), o_.sort);
    if (s == fields_.end()) set_sort(0);
    else sort_col_ = static_cast<int>(s - fields_.begin());
}

bool Ui::chooser_key(int ch) {
    const int n = static_cast<int>(running_.size());
    if (ch == 'q' || ch == 'Q') return false;
    if (is_help_key(ch)) mode_ = Mode::help;
    else if (ch == KEY_UP || ch == 'k') chooser_cursor_ = std::max(chooser_cursor_ - 1, 0);
    else if (ch == KEY_DOWN || ch == 'j') chooser_cursor_ = std::min(chooser_cursor_ + 1, std::max(n - 1, 0));
    else if ((ch == '\n' || ch == KEY_ENTER) && chooser_cursor_ < n) watch(running_[static_cast<std::size_t>(chooser_cursor_)].name);
    return true;
}

void Ui::watch(const std::string& subsystem) {
    o_.subsystem = subsystem;
    o_.svar_segment = chimera::ipc::segment_name(subsystem, "svar");
    attach_.emplace(subsystem, o_.half_tick_ns());
    mode_ = Mode::table;
    message_.clear();
}

// ------------------------------------------------------------------ drawing

void Ui::draw() {
    erase();
    if (mode_ == Mode::chooser) draw_chooser();
    else if (mode_ == Mode::help) draw_help();
    else if (mode_ == Mode::fields) draw_picker();
    else draw_table();
    refresh();
}

int Ui::draw_title(int y) {
    const bool up = attach_->refresh();
    std::string title = "chimtop  subsystem " + o_.subsystem;
    if (const auto w = attach_->window_seconds()) {
        char buf[64];
        std::snprintf(buf, sizeof buf, "  window %.1f s", *w);
        title += buf;
    } else {
        title += "  window: since the last reset";
    }
    title += "  sort " + o_.sort + (o_.descending ? " desc" : " asc") + "  times in " + chimera::tools::kTimeUnit;
    if (!filter_.empty()) title += "  filter '" + filter_ + "'";
    if (up && attach_->restarts()) title += "  (re-attached)";
    attron(A_BOLD);
    mvaddnstr(y++, 0, title.c_str(), COLS);
    attroff(A_BOLD);
    if (up) return y;
    const bool denied = attach_->denied();
    attron(COLOR_PAIR(denied ? kErrorColour : kWarnColour) | A_BOLD);
    const std::string what = denied ? attach_->problem()
                                    : "waiting for subsystem '" + o_.subsystem + "' (" + attach_->problem() + ") ...";
    mvaddnstr(y + 1, 0, what.c_str(), COLS);
    attroff(COLOR_PAIR(denied ? kErrorColour : kWarnColour) | A_BOLD);
    return -1;
}

void Ui::draw_table() {
    int y = draw_title(0);
    if (y < 0) {
        footer();
        return;
    }
    std::vector<chimera::prof::TaskStatus> tasks = attach_->snapshot();
    for (const auto& s : summarise(attach_->rtpus(), tasks)) mvaddnstr(y++, 0, summary_line(s).c_str(), COLS);
    const std::size_t all = tasks.size();
    std::erase_if(tasks, [&](const auto& t) { return !matches(t, filter_); });
    sort_tasks(tasks, o_.sort, o_.descending);
    shown_ = std::move(tasks);
    selected_ = std::clamp(selected_, 0, std::max(static_cast<int>(shown_.size()) - 1, 0));

    attron(COLOR_PAIR(kHeaderColour) | A_BOLD | A_UNDERLINE);
    mvaddnstr(y++, 0, header_line(fields_).c_str(), COLS);
    attroff(COLOR_PAIR(kHeaderColour) | A_BOLD | A_UNDERLINE);
    const int pane_rows = o_.svar_pane ? std::max(LINES / 3, 4) : 0;
    y = draw_rows(y, LINES - 2 - pane_rows);
    if (shown_.empty())
        mvaddstr(y++, 0, all == 0 ? "(no tasks)" : ("(none of the " + std::to_string(all) + " tasks matches the filter)").c_str());
    if (o_.svar_pane && !shown_.empty()) draw_pane(shown_[static_cast<std::size_t>(selected_)], pane_rows);
    footer();
}

int Ui::draw_rows(int y, int last_row) {
    for (std::size_t i = 0; i < shown_.size() && y <= last_row; ++i) {
        const auto& t = shown_[i];
        attr_t a = A_NORMAL;
        if (t.state == chimera::prof::TaskState::error) a |= COLOR_PAIR(kErrorColour) | A_BOLD;
        else if (t.miss > 0) a |= COLOR_PAIR(kWarnColour) | A_BOLD;
        if (static_cast<int>(i) == selected_) a |= A_REVERSE;
        attron(a);
        mvaddnstr(y++, 0, task_line(t, fields_).c_str(), COLS);
        attroff(a);
        for (const auto& m : message_lines(t)) {
            if (y > last_row) break;
            const short colour = m.rfind("ERROR>", 0) == 0 ? kErrorColour : kWarnColour;
            attron(COLOR_PAIR(colour));
            mvaddnstr(y++, 2, m.c_str(), COLS - 2);
            attroff(COLOR_PAIR(colour));
        }
    }
    return y;
}

void Ui::draw_pane(const chimera::prof::TaskStatus& t, int pane_rows) {
    int py = LINES - 1 - pane_rows;
    attron(A_BOLD);
    mvprintw(py++, 0, "SVAR of %s  (in: %s  out: %s)", t.rmod.c_str(), t.inputs.c_str(), t.outputs.c_str());
    attroff(A_BOLD);
    for (const auto& l : svar_lines(o_.svar_segment, t.inputs, t.outputs)) {
        if (py >= LINES - 1) break;
        mvaddnstr(py++, 2, l.c_str(), COLS - 2);
    }
}

void Ui::draw_help() {
    int y = 0;
    for (const char* line : kHelp) {
        if (y == 0) attron(A_BOLD);
        mvaddnstr(y++, 0, line, COLS);
        attroff(A_BOLD);
    }
    attron(A_REVERSE);
    mvaddnstr(LINES - 1, 0, "any key: back", COLS);
    attroff(A_REVERSE);
}

void Ui::draw_picker() {
    const std::vector<std::string> order = picker_order();
    attron(A_BOLD);
    mvaddnstr(0, 0, "Fields (every one listed)   up/down: move   space: show/hide   [ ]: earlier/later   Enter: done", COLS);
    attroff(A_BOLD);
    const int top = std::max(0, picker_cursor_ - (LINES - 4));
    for (int i = top, y = 2; i < static_cast<int>(order.size()) && y < LINES - 1; ++i, ++y) {
        const std::string& name = order[static_cast<std::size_t>(i)];
        const bool shown = std::find(fields_.begin(), fields_.end(), name) != fields_.end();
        char line[200];
        std::snprintf(line, sizeof line, "[%c] %-12s %s", shown ? 'x' : ' ', field_header(name).c_str(), find_field(name)->help);
        if (i == picker_cursor_) attron(A_REVERSE);
        mvaddnstr(y, 0, line, COLS);
        if (i == picker_cursor_) attroff(A_REVERSE);
    }
    footer();
}

void Ui::draw_chooser() {
    running_ = running_subsystems();
    chooser_cursor_ = std::clamp(chooser_cursor_, 0, std::max(static_cast<int>(running_.size()) - 1, 0));
    attron(A_BOLD);
    mvaddnstr(0, 0, "chimtop - Chimera subsystems on this machine   up/down: choose   Enter: watch   h: help   q: quit", COLS);
    attroff(A_BOLD);
    if (running_.empty()) mvaddnstr(2, 0, "no Chimera subsystem is running (no /dev/shm/chimera.*.status); waiting ...", COLS);
    for (std::size_t i = 0; i < running_.size() && static_cast<int>(i) + 2 < LINES - 1; ++i) {
        const attr_t a = (static_cast<int>(i) == chooser_cursor_ ? A_REVERSE : A_NORMAL) |
                         (running_[i].readable ? A_NORMAL : COLOR_PAIR(kErrorColour));
        attron(a);
        mvaddnstr(static_cast<int>(i) + 2, 0, entry_line(running_[i]).c_str(), COLS);
        attroff(a);
    }
    footer();
}

void Ui::footer() {
    if (attach_ && !attach_->error().empty()) message_ = attach_->error();
    std::string line = message_;
    if (mode_ == Mode::search) line = "search: " + search_ + "_   (Enter: keep, Esc: clear, n: next)";
    else if (mode_ == Mode::filter) line = "filter: " + filter_ + "_   (Enter: keep, Esc: clear)";
    else if (line.empty() && mode_ == Mode::table)
        line = "h help  f fields  / search  \\ filter  < > sort  z restart window  v SVAR  q quit";
    mvaddnstr(LINES - 1, 0, line.c_str(), COLS);
}

}  // namespace chimtop
