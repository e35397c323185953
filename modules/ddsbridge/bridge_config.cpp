// bridge_config.cpp — the ddsbridge .rmod, read and checked (bridge_config.hpp).
#include "bridge_config.hpp"

#include <chimera/cfg.hpp>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <stdexcept>

namespace ddsbridge {
namespace {

constexpr std::string_view kTopicPrefix = "TOPIC_";
constexpr std::string_view kStampPrefix = "STAMP_";
constexpr std::string_view kVlimitPrefix = "VLIMIT_";
constexpr std::string_view kTratePrefix = "TRATE_";

[[noreturn]] void fail(const chimera::RmodFile& rmod, int line, const std::string& what) {
    throw std::invalid_argument(rmod.local.file + ":" + std::to_string(line) + ": " + what);
}

bool listed(const std::vector<std::string>& list, const std::string& port) {
    return std::find(list.begin(), list.end(), port) != list.end();
}

Message parse_message(const chimera::RmodFile& rmod, const chimera::LocalConfig::Entry& e, const std::string& w) {
    if (w == "JointState.position") return Message::joint_position;
    if (w == "JointState.velocity") return Message::joint_velocity;
    if (w == "JointState.effort") return Message::joint_effort;
    if (w == "StateVar") return Message::state_var;
    fail(rmod, e.line, e.key + ": message '" + w +
                           "': expected JointState.position, JointState.velocity, JointState.effort or StateVar");
}

StaleAction parse_stale(const chimera::RmodFile& rmod, const chimera::LocalConfig::Entry& e, const std::string& w) {
    if (w == "warn") return StaleAction::warn;
    if (w == "hold") return StaleAction::hold;
    if (w == "zero") return StaleAction::zero;
    if (w == "illegal") return StaleAction::illegal;
    if (w == "error") return StaleAction::error;
    fail(rmod, e.line, e.key + ": stale action '" + w + "': expected warn, hold, zero, illegal or error");
}

// TOPIC_<port> NAME pub|sub MESSAGE state|command [AGE_LIMIT ACTION]
TopicSpec parse_topic(const chimera::RmodFile& rmod, const chimera::LocalConfig::Entry& e) {
    TopicSpec t;
    t.port = e.key.substr(kTopicPrefix.size());
    t.line = e.line;
    const auto& v = e.values;
    if (v.size() < 4)
        fail(rmod, e.line, e.key + " takes TOPIC pub|sub MESSAGE state|command [AGE_LIMIT STALE_ACTION]");
    t.ros_name = v[0];
    if (const std::string p = ros_name_problem(t.ros_name); !p.empty())
        fail(rmod, e.line, e.key + ": topic '" + t.ros_name + "': " + p);
    if (v[1] == "pub") {
        t.direction = Direction::pub;
    } else if (v[1] == "sub") {
        t.direction = Direction::sub;
    } else {
        fail(rmod, e.line, e.key + ": direction '" + v[1] + "': expected pub or sub");
    }
    t.message = parse_message(rmod, e, v[2]);
    if (v[3] == "state") {
        t.qos = Qos::state;
    } else if (v[3] == "command") {
        t.qos = Qos::command;
    } else {
        fail(rmod, e.line, e.key + ": QoS profile '" + v[3] + "': expected state or command");
    }
    if (t.direction == Direction::pub) {
        if (v.size() != 4) fail(rmod, e.line, e.key + ": a published topic takes no age limit");
        if (!listed(rmod.in_vars, t.port))
            fail(rmod, e.line, e.key + ": pub needs " + t.port + " among the INVARs (what the bridge publishes)");
        return t;
    }
    if (v.size() != 6)
        fail(rmod, e.line, e.key + ": a subscribed topic needs AGE_LIMIT (seconds) and STALE_ACTION");
    t.age_limit = chimera::cfg::parse_double(v[4]).value_or(0.0);
    if (!std::isfinite(t.age_limit) || t.age_limit <= 0)
        fail(rmod, e.line, e.key + ": age limit '" + v[4] + "': expected seconds > 0");
    t.stale = parse_stale(rmod, e, v[5]);
    if (!listed(rmod.out_vars, t.port))
        fail(rmod, e.line, e.key + ": sub needs " + t.port + " among the OUTVARs (what the bridge subscribes)");
    return t;
}

// A word of two choices: `first` (false) or `second` (true); absent: false.
bool parse_choice(const chimera::RmodFile& rmod, const char* key, const char* first, const char* second) {
    const auto* e = rmod.local.find(key);
    if (!e) return false;
    if (e->values.size() == 1 && e->values[0] == first) return false;
    if (e->values.size() == 1 && e->values[0] == second) return true;
    fail(rmod, e->line, std::string(key) + " '" + (e->values.empty() ? "" : e->values[0]) + "': expected " + first +
                            " or " + second);
}

// VLIMIT_<port> / TRATE_<port>: positive numbers, on a subscribed JointState
// port of the field the limit is about.
void parse_limits(const chimera::RmodFile& rmod, std::vector<TopicSpec>& subs) {
    for (const auto& e : rmod.local.entries()) {
        const bool vlimit = e.key.rfind(kVlimitPrefix, 0) == 0, trate = e.key.rfind(kTratePrefix, 0) == 0;
        if (!vlimit && !trate) continue;
        const std::string port = e.key.substr((vlimit ? kVlimitPrefix : kTratePrefix).size());
        auto it = std::find_if(subs.begin(), subs.end(), [&](const TopicSpec& t) { return t.port == port; });
        if (it == subs.end()) fail(rmod, e.line, e.key + ": " + port + " has no subscribed TOPIC_" + port + " line");
        const bool fits = vlimit ? it->message == Message::joint_position || it->message == Message::joint_velocity
                                 : it->message == Message::joint_effort;
        if (!fits)
            fail(rmod, e.line, e.key + ": " +
                                   (vlimit ? "a velocity limit is for a JointState.position or JointState.velocity port"
                                           : "a torque-rate limit is for a JointState.effort port"));
        if (e.values.empty()) fail(rmod, e.line, e.key + " takes a limit per joint, or one for all");
        it->limits.clear();
        for (const std::string& w : e.values) {
            const double v = chimera::cfg::parse_double(w).value_or(0.0);
            if (!std::isfinite(v) || v <= 0)
                fail(rmod, e.line, e.key + ": limit '" + w + "': expected a number > 0 (" +
                                       (vlimit ? "units per second" : "N m per second") + ")");
            it->limits.push_back(v);
        }
        it->limits_line = e.line;
    }
}

}  // namespace

std::vector<std::string> joint_names_for(const BridgeConfig& c, const TopicSpec& spec, std::size_t nelem,
                                         const std::string& rmod_file) {
    if (c.joint_names.empty()) {
        std::vector<std::string> names;
        for (std::size_t j = 1; j <= nelem; ++j) names.push_back("joint" + std::to_string(j));
        return names;
    }
    if (c.joint_names.size() != nelem)
        throw std::invalid_argument(rmod_file + ": JOINT_NAMES has " + std::to_string(c.joint_names.size()) +
                                    " names, TOPIC_" + spec.port + " " + std::to_string(nelem) + " joints");
    return c.joint_names;
}

std::vector<double> limits_for(const TopicSpec& spec, std::size_t nelem, const std::string& rmod_file) {
    if (spec.limits.empty()) return {};
    if (spec.limits.size() == 1) return std::vector<double>(nelem, spec.limits[0]);
    if (spec.limits.size() != nelem)
        throw std::invalid_argument(rmod_file + ":" + std::to_string(spec.limits_line) + ": " +
                                    (spec.message == Message::joint_effort ? "TRATE_" : "VLIMIT_") + spec.port +
                                    " has " + std::to_string(spec.limits.size()) + " limits for " +
                                    std::to_string(nelem) + " joints (give one per joint, or one for all)");
    return spec.limits;
}

std::string ros_name_problem(const std::string& name) {
    if (name.empty()) return "empty";
    if (name.rfind("rt/", 0) == 0) return "give the ROS 2 name; the bridge adds the DDS prefix rt/";
    bool token_start = true;
    for (std::size_t i = 0; i < name.size(); ++i) {
        const char c = name[i];
        if (c == '/') {
            if (token_start) return "empty name token (leading, trailing or double '/')";
            token_start = true;
            continue;
        }
        if (!std::isalnum(static_cast<unsigned char>(c)) && c != '_')
            return std::string("character '") + c + "' (ROS 2 names take letters, digits, '_' and '/')";
        if (token_start && std::isdigit(static_cast<unsigned char>(c))) return "a name token starts with a digit";
        token_start = false;
    }
    if (token_start) return "empty name token (leading, trailing or double '/')";
    return "";
}

BridgeConfig parse_config(const chimera::RmodFile& rmod) {
    BridgeConfig c;
    const chimera::LocalConfig& lc = rmod.local;
    c.domain = static_cast<int>(lc.number("DOMAIN", 0));
    if (const auto* e = lc.find("CONFIG"); e && !e->values.empty()) {
        // A relative file is the .rmod's neighbour, wherever the program runs.
        const std::filesystem::path file = e->values.front();
        const std::filesystem::path dir = std::filesystem::path(rmod.path).parent_path();
        c.config_file = (file.is_relative() && !rmod.path.empty() ? dir / file : file).string();
    }
    if (const auto* e = lc.find("AGE_CLOCK"); e && !e->values.empty()) {
        if (e->values.front() == "receive") {
            c.age_clock = AgeClock::receive;
        } else if (e->values.front() == "source") {
            c.age_clock = AgeClock::source;
        } else {
            fail(rmod, e->line, "AGE_CLOCK '" + e->values.front() + "': expected receive or source");
        }
    }
    if (const auto* e = lc.find("NOTIFY"); e && !e->values.empty()) {
        if (e->values.front() == "poll") {
            c.notify = Notify::poll;
        } else if (e->values.front() == "spin") {
            c.notify = Notify::spin;
        } else if (e->values.front() == "wake") {
            c.notify = Notify::wake;
        } else {
            fail(rmod, e->line, "NOTIFY '" + e->values.front() + "': expected poll, spin or wake");
        }
    }
    if (const auto* e = lc.find("JOINT_NAMES")) {
        c.joint_names = e->values;
        for (std::size_t i = 0; i < c.joint_names.size(); ++i)
            for (std::size_t j = 0; j < i; ++j)
                if (c.joint_names[i] == c.joint_names[j])
                    fail(rmod, e->line, "JOINT_NAMES: '" + c.joint_names[i] + "' is given twice (a name is one joint)");
    }
    c.refuse_subset = parse_choice(rmod, "JOINT_SUBSET", "update", "refuse");
    c.accept_unnamed = parse_choice(rmod, "UNNAMED", "refuse", "positional");
    std::vector<TopicSpec> pubs, subs;
    for (const auto& e : lc.entries()) {
        if (e.key.rfind(kTopicPrefix, 0) != 0) continue;
        TopicSpec t = parse_topic(rmod, e);
        (t.direction == Direction::pub ? pubs : subs).push_back(std::move(t));
    }
    std::vector<std::string> stamp_ports;
    for (const auto& e : lc.entries()) {
        if (e.key.rfind(kStampPrefix, 0) != 0) continue;
        const std::string port = e.key.substr(kStampPrefix.size());
        auto it = std::find_if(subs.begin(), subs.end(), [&](const TopicSpec& t) { return t.port == port; });
        if (it == subs.end()) fail(rmod, e.line, e.key + ": " + port + " has no subscribed TOPIC_" + port + " line");
        if (e.values.size() != 1 || !listed(rmod.out_vars, e.values[0]))
            fail(rmod, e.line, e.key + " takes one OUTVAR (3 doubles: counter, age, new/repeat/stale)");
        it->stamp_port = e.values[0];
        stamp_ports.push_back(e.values[0]);
    }
    // `hold` asks the consumers to hold on the stamp: without one, none can.
    for (const TopicSpec& t : subs)
        if (t.stale == StaleAction::hold && t.stamp_port.empty())
            fail(rmod, t.line, "TOPIC_" + t.port + ": stale action hold needs a STAMP_" + t.port +
                                   " line (the consumers hold on the stamp's -1)");
    parse_limits(rmod, subs);
    auto has_topic = [](const std::vector<TopicSpec>& list, const std::string& port) {
        return std::any_of(list.begin(), list.end(), [&](const TopicSpec& t) { return t.port == port; });
    };
    for (const auto& port : rmod.in_vars)
        if (!has_topic(pubs, port))
            throw std::invalid_argument(lc.file + ": INVAR " + port + " has no TOPIC_" + port + " line in LOCAL");
    for (const auto& port : rmod.out_vars)
        if (!has_topic(subs, port) && !listed(stamp_ports, port))
            throw std::invalid_argument(lc.file + ": OUTVAR " + port + " has no TOPIC_" + port + " line in LOCAL");
    c.topics = std::move(pubs);
    c.topics.insert(c.topics.end(), subs.begin(), subs.end());
    for (std::size_t i = 0; i < c.topics.size(); ++i)
        for (std::size_t j = 0; j < i; ++j)
            if (c.topics[i].ros_name == c.topics[j].ros_name)
                fail(rmod, c.topics[i].line, "TOPIC_" + c.topics[i].port + ": topic " + c.topics[i].ros_name +
                                                 " is already TOPIC_" + c.topics[j].port + "'s (one variable per topic)");
    return c;
}

const char* type_name(Message m) noexcept {
    return m == Message::state_var ? "chimera_msgs::msg::dds_::StateVar_" : "sensor_msgs::msg::dds_::JointState_";
}

const char* to_string(StaleAction a) noexcept {
    switch (a) {
        case StaleAction::warn: return "warn";
        case StaleAction::hold: return "hold";
        case StaleAction::zero: return "zero";
        case StaleAction::illegal: return "illegal";
        case StaleAction::error: return "error";
    }
    return "?";
}

}  // namespace ddsbridge
