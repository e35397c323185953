// The sampler: channels parsed from the command line's words, and the writer
// bound to the state-variable table that a sampling task's cycle calls.
#include "chimera/sampler.hpp"

#include <algorithm>
#include <charconv>
#include <optional>
#include <utility>

namespace chimera::sampler {

namespace {

// "12" → 12; nullopt for anything else.
std::optional<std::size_t> index_text(std::string_view s) {
    std::size_t v = 0;
    const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
    if (ec != std::errc{} || end != s.data() + s.size() || s.empty()) return std::nullopt;
    return v;
}

std::string channel_name(const svar::VarInfo& info, std::size_t element) {
    const std::string var(info.name());
    return info.nelem() == 1 ? var : var + "[" + std::to_string(element) + "]";
}

}  // namespace

std::vector<Channel> parse_channels(const svar::Table& table, std::span<const std::string> words) {
    std::vector<Channel> out;
    for (const std::string& word : words) {
        const std::size_t bracket = word.find('[');
        const std::string var = word.substr(0, bracket);
        const auto ix = table.find(var);
        if (!ix) throw svar::Error("sample " + word + ": table " + table.name() + " has no variable " + var);
        const svar::VarInfo info = table.var(*ix);
        if (info.type() == svar::Type::struct_)
            throw svar::Error("sample " + word + ": " + var + " is a struct: it has no numbers to sample");
        std::size_t first = 0, last = info.nelem() - 1;
        if (bracket != std::string::npos) {
            if (word.back() != ']')
                throw svar::Error("sample " + word + ": write VAR, VAR[i] or VAR[i:j]");
            const std::string_view inside = std::string_view(word).substr(bracket + 1, word.size() - bracket - 2);
            const std::size_t colon = inside.find(':');
            const auto a = index_text(inside.substr(0, colon));
            const auto b = colon == std::string_view::npos ? a : index_text(inside.substr(colon + 1));
            if (!a || !b || *a > *b)
                throw svar::Error("sample " + word + ": write VAR, VAR[i] or VAR[i:j] with i <= j");
            if (*b >= info.nelem())
                throw svar::Error("sample " + word + ": element " + std::to_string(*b) + " is outside " + var + " (" +
                                  std::to_string(info.nelem()) + " elements: 0 to " +
                                  std::to_string(info.nelem() - 1) + ")");
            first = *a;
            last = *b;
        }
        for (std::size_t k = first; k <= last; ++k) {
            if (out.size() == kMaxChannels)
                throw svar::Error("sample: more than " + std::to_string(kMaxChannels) + " channels (at " + word + ")");
            out.push_back(Channel{var, k, channel_name(info, k)});
        }
    }
    if (out.empty()) throw svar::Error("sample: no variable named");
    return out;
}

namespace {

std::vector<std::string> distinct_vars(const std::vector<Channel>& channels) {
    std::vector<std::string> vars;
    for (const Channel& c : channels)
        if (std::find(vars.begin(), vars.end(), c.var) == vars.end()) vars.push_back(c.var);
    return vars;
}

std::vector<std::uint32_t> var_indices(const svar::Table& table, const std::vector<Channel>& channels) {
    std::vector<std::uint32_t> ix;
    for (const Channel& c : channels) ix.push_back(static_cast<std::uint32_t>(table.index_of(c.var)));
    return ix;
}

}  // namespace

Sampler::Sampler(svar::Table& table, std::vector<Channel> channels, const std::string& ring_name,
                 std::size_t capacity, double rate_hz, const ipc::CreateOptions& options)
    : channels_(std::move(channels)) {
    if (channels_.empty() || channels_.size() > kMaxChannels)
        throw Error("sampler " + ring_name + ": 1 to " + std::to_string(kMaxChannels) + " channels");
    const std::vector<std::string> vars = distinct_vars(channels_);
    local_ = std::make_unique<svar::LocalTable>(table, vars);
    set_ = local_->make_set(vars);
    for (const Channel& c : channels_) {
        const svar::VarInfo info = table.var(c.var);
        if (info.type() == svar::Type::struct_ || c.element >= info.nelem())
            throw Error("sampler " + ring_name + ": " + c.name + " is not a number of the table");
        const auto* first = static_cast<const std::byte*>(local_->translate_any(c.var));
        sources_.push_back(Source{first + c.element * svar::type_size(info.type()), info.type()});
    }
    ring_ = RingWriter::create(ring_name, channels_, var_indices(table, channels_), capacity, rate_hz, options);
}

Sampler::Sampler(Sampler&&) noexcept = default;
Sampler::~Sampler() = default;

svar::Status Sampler::sample(std::int64_t time_ns, std::uint64_t cycle) noexcept {
    const svar::Status s = local_->copy_from_global(set_);
    if (!svar::transferred(s)) return s;
    double row[kMaxChannels];
    for (std::size_t i = 0; i < sources_.size(); ++i)
        row[i] = svar::element_value(sources_[i].type, sources_[i].at);
    ring_.publish_row(time_ns, cycle, row);
    return s;
}

}  // namespace chimera::sampler
