// The live view of chimtop (ncurses), as an htop user expects it: a help
// screen (h, ?, F1), a field picker listing every field (f, F2), search (/,
// F3, n) and filter (\, F4), a summary line per RTPU, sorting, the SVAR pane,
// and — when started without a subsystem — the list of running subsystems to
// choose from.
#pragma once

#include <csignal>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "chimera/prof.hpp"
#include "source.hpp"

namespace chimtop {

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
    std::int64_t half_tick_ns() const;
};

/// Set by SIGINT/SIGTERM: the view ends at its next redraw.
extern volatile std::sig_atomic_t g_stop;

class Ui {
public:
    Ui(Options o, std::vector<std::string> fields);
    int run();

private:
    enum class Mode { table, help, fields, search, filter, chooser };

    bool key(int ch);  // false: quit
    bool table_key(int ch);
    void picker_key(int ch);
    std::vector<std::string> picker_order() const;
    void prompt_key(int ch);
    bool chooser_key(int ch);
    void watch(const std::string& subsystem);
    void set_sort(int column);
    void search_next(bool from_current);

    void draw();
    void draw_table();
    int draw_title(int y);
    int draw_rows(int y, int last_row);
    void draw_pane(const chimera::prof::TaskStatus& t, int pane_rows);
    void draw_help();
    void draw_picker();
    void draw_chooser();
    void footer();

    Options o_;
    std::vector<std::string> fields_;
    std::optional<Attachment> attach_;
    Mode mode_ = Mode::table;
    int sort_col_ = 0;
    int selected_ = 0;
    std::string message_;
    std::string filter_, search_;
    std::vector<chimera::prof::TaskStatus> shown_;  // the rows on screen, in order
    int picker_cursor_ = 0;
    std::vector<SubsystemEntry> running_;
    int chooser_cursor_ = 0;
};

}  // namespace chimtop
