// The configuration-file reader (see include/chimera/cfg.hpp for the format).
#include "chimera/cfg.hpp"

#include <sys/stat.h>

#include <cerrno>
#include <charconv>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>

namespace chimera::cfg {

namespace {

// Line 0 is the file as a whole (it cannot be opened or read): no line number.
std::string make_what(const std::string& file, int line, const std::string& message) {
    return line > 0 ? file + ":" + std::to_string(line) + ": " + message : file + ": " + message;
}

// Removes a comment: '#' at the start of the line or after whitespace.
std::string_view strip_comment(std::string_view s) {
    for (std::size_t i = 0; i < s.size(); ++i) {
        if (s[i] == '#' && (i == 0 || s[i - 1] == ' ' || s[i - 1] == '\t')) return s.substr(0, i);
    }
    return s;
}

std::string_view trim(std::string_view s) {
    const auto first = s.find_first_not_of(" \t\r\n");
    if (first == std::string_view::npos) return {};
    const auto last = s.find_last_not_of(" \t\r\n");
    return s.substr(first, last - first + 1);
}

std::string quote(std::string_view s) { return "'" + std::string(s) + "'"; }

}  // namespace

std::vector<std::string> split_words(std::string_view s) {
    std::vector<std::string> out;
    std::size_t i = 0;
    while (i < s.size()) {
        while (i < s.size() && (s[i] == ' ' || s[i] == '\t')) ++i;
        std::size_t j = i;
        while (j < s.size() && s[j] != ' ' && s[j] != '\t') ++j;
        if (j > i) out.emplace_back(s.substr(i, j - i));
        i = j;
    }
    return out;
}

ParseError::ParseError(std::string file, int line, std::string message)
    : std::runtime_error(make_what(file, line, message)),
      file_(std::move(file)),
      line_(line),
      message_(std::move(message)) {}

std::optional<double> parse_double(std::string_view token) noexcept {
    if (token.empty()) return std::nullopt;
    // strtod accepts hex, inf and nan; the format wants plain decimal numbers.
    for (char c : token) {
        if (!((c >= '0' && c <= '9') || c == '.' || c == '-' || c == '+' || c == 'e' || c == 'E'))
            return std::nullopt;
    }
    std::string copy(token);
    char* end = nullptr;
    errno = 0;
    const double v = std::strtod(copy.c_str(), &end);
    if (end != copy.c_str() + copy.size() || errno == ERANGE) return std::nullopt;
    return v;
}

std::string number_text(double v) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%g", v);
    return buf;
}

std::optional<std::int64_t> parse_int(std::string_view token) noexcept {
    if (!token.empty() && token.front() == '+') token.remove_prefix(1);
    std::int64_t v = 0;
    int base = 10;
    bool negative = false;
    std::string_view digits = token;
    if (!digits.empty() && digits.front() == '-') {
        negative = true;
        digits.remove_prefix(1);
    }
    if (digits.size() > 2 && digits[0] == '0' && (digits[1] == 'x' || digits[1] == 'X')) {
        base = 16;
        digits.remove_prefix(2);
    }
    if (digits.empty()) return std::nullopt;
    auto [ptr, ec] = std::from_chars(digits.data(), digits.data() + digits.size(), v, base);
    if (ec != std::errc() || ptr != digits.data() + digits.size()) return std::nullopt;
    return negative ? -v : v;
}

Reader::Reader(std::string file, std::vector<std::string> raw_lines)
    : file_(std::move(file)), raw_(std::move(raw_lines)) {}

Reader Reader::from_file(const std::string& path) {
    // stat, not open: opening a FIFO would block until a writer comes.
    struct stat st {};
    if (::stat(path.c_str(), &st) != 0)
        throw ParseError(path, 0, std::string("cannot open file: ") + std::strerror(errno));
    if (S_ISDIR(st.st_mode)) throw ParseError(path, 0, "cannot read file: it is a directory");
    if (!S_ISREG(st.st_mode)) {
        const char* kind = S_ISFIFO(st.st_mode)  ? "a FIFO"
                           : S_ISCHR(st.st_mode) ? "a character device"
                           : S_ISBLK(st.st_mode) ? "a block device"
                           : S_ISSOCK(st.st_mode) ? "a socket"
                                                  : "not a regular file";
        throw ParseError(path, 0, std::string("cannot read file: it is ") + kind + ", not a regular file");
    }
    if (static_cast<std::uintmax_t>(st.st_size) > kMaxFileBytes)
        throw ParseError(path, 0, "cannot read file: " + std::to_string(st.st_size) + " bytes, more than the " +
                                      std::to_string(kMaxFileBytes >> 20) + " MiB a configuration file may have");
    errno = 0;
    std::ifstream in(path);
    if (!in) {
        const int e = errno;
        throw ParseError(path, 0, std::string("cannot open file: ") + (e ? std::strerror(e) : "reason unknown"));
    }
    std::vector<std::string> lines;
    std::string line;
    std::uintmax_t bytes = 0;
    while (std::getline(in, line)) {
        bytes += line.size() + 1;
        // The file may have grown since stat: the bound holds while reading.
        if (bytes > kMaxFileBytes)
            throw ParseError(path, 0, "cannot read file: more than the " + std::to_string(kMaxFileBytes >> 20) +
                                          " MiB a configuration file may have");
        lines.push_back(line);
    }
    if (in.bad()) {
        const int e = errno;
        throw ParseError(path, 0, std::string("cannot read file: ") + (e ? std::strerror(e) : "reason unknown"));
    }
    return Reader(path, std::move(lines));
}

Reader Reader::from_string(std::string_view text, std::string name) {
    std::vector<std::string> lines;
    std::istringstream in{std::string(text)};
    std::string line;
    while (std::getline(in, line)) lines.push_back(line);
    return Reader(std::move(name), std::move(lines));
}

void Reader::fail(int line, const std::string& message) const {
    throw ParseError(file_, line, message);
}

void Reader::fill() {
    if (pending_ || at_eof_) return;
    while (pos_ < raw_.size()) {
        const int number = static_cast<int>(pos_) + 1;
        const std::string_view content = trim(strip_comment(raw_[pos_++]));
        if (content.empty()) continue;
        std::vector<std::string> tokens = split_words(content);
        Line line;
        line.number = number;
        line.keyword = tokens.front();
        const auto after_keyword = content.substr(content.find(line.keyword) + line.keyword.size());
        line.text = std::string(trim(after_keyword));

        if (line.keyword == "EOF") {
            if (tokens.size() != 1) fail(number, "EOF takes no arguments, found " + quote(line.text));
            // Only comments and blank lines may follow the safety line.
            for (std::size_t i = pos_; i < raw_.size(); ++i) {
                if (!trim(strip_comment(raw_[i])).empty())
                    fail(static_cast<int>(i) + 1,
                         "expected nothing after EOF, found " + quote(trim(raw_[i])));
            }
            at_eof_ = true;
            eof_line_ = number;
            return;
        }
        if (line.keyword == "DEFINE") {
            if (tokens.size() != 3)
                fail(number, "DEFINE takes a name and a value, found " + quote(line.text));
            if (defines_.count(tokens[1]))
                fail(number, "DEFINE " + tokens[1] + " is already defined");
            std::string value = tokens[2];
            if (auto it = defines_.find(value); it != defines_.end()) value = it->second;
            defines_[tokens[1]] = value;
            continue;
        }
        for (std::size_t i = 1; i < tokens.size(); ++i) {
            std::string& t = tokens[i];
            if (auto it = defines_.find(t); it != defines_.end()) {
                t = it->second;
            } else if (t.size() > 1 && t[0] == '-') {
                if (auto neg = defines_.find(std::string_view(t).substr(1)); neg != defines_.end()) {
                    const std::string& v = neg->second;
                    t = (!v.empty() && v[0] == '-') ? v.substr(1) : "-" + v;
                }
            }
            line.args.push_back(std::move(t));
        }
        pending_ = std::move(line);
        return;
    }
    const int last = static_cast<int>(raw_.size());
    eof_line_ = last;
    if (last == 0) fail(1, "empty file: expected the file's content and EOF as the last line");
    fail(last, "truncated file: expected EOF as the last line, found end of file");
}

const Line* Reader::peek() {
    fill();
    return pending_ ? &*pending_ : nullptr;
}

std::optional<Line> Reader::next() {
    fill();
    std::optional<Line> out = std::move(pending_);
    pending_.reset();
    return out;
}

bool Reader::next_is(std::string_view keyword) {
    const Line* l = peek();
    return l && l->keyword == keyword;
}

Line Reader::expect(std::string_view keyword) { return expect_one_of({keyword}); }

Line Reader::expect_one_of(std::initializer_list<std::string_view> keywords) {
    std::string wanted;
    for (auto k : keywords) {
        if (!wanted.empty()) wanted += " or ";
        wanted += k;
    }
    const Line* l = peek();
    if (!l) fail(eof_line_, "expected " + wanted + ", found EOF");
    for (auto k : keywords) {
        if (l->keyword == k) return *next();
    }
    fail(*l, "expected " + wanted + ", found " + l->keyword);
}

std::optional<Line> Reader::accept(std::string_view keyword) {
    if (next_is(keyword)) return next();
    return std::nullopt;
}

void Reader::expect_end() {
    if (const Line* l = peek()) fail(*l, "expected EOF, found " + l->keyword);
}

void Reader::require_args(const Line& line, std::size_t count) const {
    require_args(line, count, count);
}

void Reader::require_args(const Line& line, std::size_t min, std::size_t max) const {
    const std::size_t n = line.args.size();
    if (n >= min && n <= max) return;
    std::string expected = std::to_string(min);
    if (max != min) expected += max == SIZE_MAX ? " or more" : " to " + std::to_string(max);
    fail(line, line.keyword + " takes " + expected + " argument" + (max == 1 && min == 1 ? "" : "s") +
                   ", found " + std::to_string(n));
}

double Reader::to_double(const Line& line, std::size_t arg, std::string_view what) const {
    if (arg >= line.args.size())
        fail(line, "expected a number for " + std::string(what) + ", found nothing");
    if (auto v = parse_double(line.args[arg])) return *v;
    fail(line, "expected a number for " + std::string(what) + ", found " + quote(line.args[arg]));
}

std::int64_t Reader::to_int(const Line& line, std::size_t arg, std::string_view what) const {
    if (arg >= line.args.size())
        fail(line, "expected an integer for " + std::string(what) + ", found nothing");
    if (auto v = parse_int(line.args[arg])) return *v;
    fail(line, "expected an integer for " + std::string(what) + ", found " + quote(line.args[arg]));
}

}  // namespace chimera::cfg
