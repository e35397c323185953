// tools/sbs/command_line.hpp — splitting what the operator types into commands
// and words. Shared by the prompt, `-c` scripts and the network server so the
// three read a command exactly the same way.
#pragma once

#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace chimera::cli {

/// A line that cannot be split (an unterminated quote, a stray escape).
class SyntaxError : public std::runtime_error {
public:
    using std::runtime_error::runtime_error;
};

/// Splits a script into single commands at `;` and newlines outside quotes.
/// Empty commands and `#` comments (a word starting with #) are dropped.
std::vector<std::string> split_commands(std::string_view script);

/// Splits one command into words: whitespace separates, '...' is literal,
/// "..." allows \" and \\, a word starting with # ends the command.
/// Throws SyntaxError on an unterminated quote.
std::vector<std::string> split_words(std::string_view command);

/// Quotes a word so split_words() gives it back unchanged.
std::string quote_word(std::string_view word);

/// True when `pattern` (with * and ? wildcards) matches the whole of `name`.
bool glob_match(std::string_view pattern, std::string_view name) noexcept;

}  // namespace chimera::cli
