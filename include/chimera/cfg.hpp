// chimera/cfg.hpp — the configuration-file reader shared by .svar, .rmod, .sbs
// and every other file in the project's style (thesis §5.5.2, §3.8, §4.5.1).
//
// The file format, as the thesis writes it:
//   - one keyword per line, followed by whitespace-separated arguments;
//   - `DEFINE NAME VALUE` makes NAME usable as a value anywhere after it
//     (also negated: `-NAME`);
//   - `#` starts a comment (at the start of a line or after whitespace);
//     blank lines are ignored;
//   - the last line is `EOF`, a safety check: a file that ends without it is
//     reported as truncated, and text after it is an error.
// Every error is a ParseError whose what() reads `FILE:LINE: message`.
#pragma once

#include "chimera/export.hpp"

#include <cstdint>
#include <initializer_list>
#include <map>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace chimera::cfg {

/// An error in a configuration file; what() is "FILE:LINE: message".
class CHIMERA_API ParseError : public std::runtime_error {
public:
    ParseError(std::string file, int line, std::string message);
    const std::string& file() const noexcept { return file_; }
    int line() const noexcept { return line_; }
    /// The message without the FILE:LINE: prefix.
    const std::string& message() const noexcept { return message_; }

private:
    std::string file_;
    int line_;
    std::string message_;
};

/// One meaningful line: keyword plus arguments, DEFINE names already substituted.
struct Line {
    int number = 0;                 ///< 1-based line number in the file
    std::string keyword;            ///< first token, exactly as written
    std::vector<std::string> args;  ///< remaining tokens, DEFINEs substituted
    std::string text;               ///< everything after the keyword, trimmed, comments removed
                                    ///< (for free-text fields such as DESC)
};

/// The largest configuration file read: a .svar, .rmod or .sbs is text a
/// person writes; anything larger is refused before it is read.
inline constexpr std::uintmax_t kMaxFileBytes = 4u << 20;

/// Reads a file line by line. Usage: a parser calls expect()/accept() in the
/// order the format fixes, and finishes with expect_end().
class CHIMERA_API Reader {
public:
    /// Reads the whole file; throws ParseError("FILE:0: cannot open ...").
    /// Only a regular file of at most kMaxFileBytes (a FIFO, a device such
    /// as /dev/zero or a directory is refused without reading it).
    static Reader from_file(const std::string& path);
    /// For tests and generated text; `name` is used as FILE in errors.
    static Reader from_string(std::string_view text, std::string name);

    const std::string& file() const noexcept { return file_; }

    /// The next meaningful line without consuming it; nullptr when the EOF
    /// line has been reached. Throws if the file ends without EOF.
    const Line* peek();
    /// Consumes and returns the next line; nullopt at EOF.
    [[nodiscard]] std::optional<Line> next();
    /// True when the next line's keyword is `keyword` (case-sensitive).
    bool next_is(std::string_view keyword);
    /// Consumes a line with this keyword, or fails: "expected NAME, found AME".
    Line expect(std::string_view keyword);
    /// Consumes a line whose keyword is one of `keywords`, or fails naming them all.
    Line expect_one_of(std::initializer_list<std::string_view> keywords);
    /// Consumes the line if its keyword matches.
    [[nodiscard]] std::optional<Line> accept(std::string_view keyword);
    /// Requires that the EOF line is next: "expected EOF, found X".
    void expect_end();
    /// Line number of the EOF line (or of the last line when truncated).
    int end_line() const noexcept { return eof_line_; }

    [[noreturn]] void fail(int line, const std::string& message) const;
    [[noreturn]] void fail(const Line& line, const std::string& message) const {
        fail(line.number, message);
    }

    /// Argument count checks: "KEYWORD takes N arguments, found M".
    void require_args(const Line& line, std::size_t count) const;
    void require_args(const Line& line, std::size_t min, std::size_t max) const;

    /// Numeric conversion of a whole token, with a FILE:LINE: error naming
    /// `what` when it is not a number.
    double to_double(const Line& line, std::size_t arg, std::string_view what) const;
    std::int64_t to_int(const Line& line, std::size_t arg, std::string_view what) const;

    const std::map<std::string, std::string, std::less<>>& defines() const noexcept {
        return defines_;
    }

private:
    Reader(std::string file, std::vector<std::string> raw_lines);
    void fill();

    std::string file_;
    std::vector<std::string> raw_;
    std::size_t pos_ = 0;        // next raw line to tokenize
    std::optional<Line> pending_;
    bool at_eof_ = false;
    int eof_line_ = 0;
    std::map<std::string, std::string, std::less<>> defines_;
};

/// The words of `s`, split at blanks and tabs (the tokens of a line).
CHIMERA_API std::vector<std::string> split_words(std::string_view s);

/// Whole-token number parsing shared by every reader; nullopt when malformed.
[[nodiscard]] CHIMERA_API std::optional<double> parse_double(std::string_view token) noexcept;
[[nodiscard]] CHIMERA_API std::optional<std::int64_t> parse_int(std::string_view token) noexcept;
/// A number as the readers' messages and written files show it (printf's %g).
CHIMERA_API std::string number_text(double v);

}  // namespace chimera::cfg
