#include "command_line.hpp"

namespace chimera::cli {

namespace {

bool is_space(char c) noexcept { return c == ' ' || c == '\t' || c == '\r'; }

}  // namespace

std::vector<std::string> split_commands(std::string_view script) {
    std::vector<std::string> out;
    std::string current;
    char quote = 0;
    bool comment = false;
    bool word_start = true;
    auto flush = [&] {
        std::size_t b = 0;
        std::size_t e = current.size();
        while (b < e && is_space(current[b])) ++b;
        while (e > b && is_space(current[e - 1])) --e;
        if (e > b) out.emplace_back(current.substr(b, e - b));
        current.clear();
        comment = false;
        word_start = true;
    };
    for (std::size_t i = 0; i < script.size(); ++i) {
        const char c = script[i];
        if (comment) {
            if (c == '\n') flush();
            continue;
        }
        if (quote != 0) {
            current += c;
            if (c == '\\' && quote == '"' && i + 1 < script.size()) {
                current += script[++i];
            } else if (c == quote) {
                quote = 0;
            }
            continue;
        }
        if (c == ';' || c == '\n') {
            flush();
            continue;
        }
        if (c == '#' && word_start) {
            comment = true;
            continue;
        }
        if (c == '\'' || c == '"') quote = c;
        current += c;
        word_start = is_space(c);
    }
    if (quote != 0) throw SyntaxError(std::string("unterminated ") + quote + " quote");
    flush();
    return out;
}

std::vector<std::string> split_words(std::string_view command) {
    std::vector<std::string> words;
    std::string word;
    bool in_word = false;
    std::size_t i = 0;
    while (i < command.size()) {
        const char c = command[i];
        if (is_space(c) || c == '\n') {
            if (in_word) words.push_back(std::move(word));
            word.clear();
            in_word = false;
            ++i;
            continue;
        }
        if (c == '#' && !in_word) break;
        in_word = true;
        if (c == '\'') {
            const auto end = command.find('\'', i + 1);
            if (end == std::string_view::npos) throw SyntaxError("unterminated ' quote");
            word.append(command.substr(i + 1, end - i - 1));
            i = end + 1;
            continue;
        }
        if (c == '"') {
            ++i;
            bool closed = false;
            while (i < command.size()) {
                const char d = command[i++];
                if (d == '"') {
                    closed = true;
                    break;
                }
                if (d == '\\' && i < command.size() && (command[i] == '"' || command[i] == '\\')) {
                    word += command[i++];
                    continue;
                }
                word += d;
            }
            if (!closed) throw SyntaxError("unterminated \" quote");
            continue;
        }
        word += c;
        ++i;
    }
    if (in_word) words.push_back(std::move(word));
    return words;
}

std::string quote_word(std::string_view word) {
    bool plain = !word.empty();
    for (char c : word) {
        if (is_space(c) || c == '\n' || c == '\'' || c == '"' || c == ';' || c == '#' || c == '\\') {
            plain = false;
            break;
        }
    }
    if (plain) return std::string(word);
    std::string out = "\"";
    for (char c : word) {
        if (c == '"' || c == '\\') out += '\\';
        out += c;
    }
    out += '"';
    return out;
}

bool glob_match(std::string_view pattern, std::string_view name) noexcept {
    // Iterative matcher with one backtrack point: linear for the patterns
    // an operator types.
    std::size_t p = 0, n = 0, star = std::string_view::npos, mark = 0;
    while (n < name.size()) {
        if (p < pattern.size() && (pattern[p] == '?' || pattern[p] == name[n])) {
            ++p;
            ++n;
        } else if (p < pattern.size() && pattern[p] == '*') {
            star = p++;
            mark = n;
        } else if (star != std::string_view::npos) {
            p = star + 1;
            n = ++mark;
        } else {
            return false;
        }
    }
    while (p < pattern.size() && pattern[p] == '*') ++p;
    return p == pattern.size();
}

}  // namespace chimera::cli
