// The end of a subsystem as its Python objects see it (issue #29.8): every
// call on a Table, Tbuf, StatusReader or Ring of a subsystem whose master has
// finished raises SubsystemGone, and the object unmaps its segments then.
#include "bindings.hpp"

#include <signal.h>

#include <cerrno>

namespace chimera::python {

namespace {

constexpr ipc::SegmentKind kStatusKind{ipc::ObjectType::prof_status, prof::kStatusLayoutVersion};

bool process_lives(int pid) { return pid > 0 && (::kill(pid, 0) == 0 || errno == EPERM); }

// The master's status segment, watched (read-only, no lock); invalid when
// none is published now or this user may not read it.
ipc::Segment watch_status(const std::string& subsystem) {
    try {
        ipc::AttachOptions o;
        o.prefault = false;
        o.ready_timeout_ns = 100'000'000;
        return ipc::Segment::watch(ipc::segment_name(subsystem, "status"), kStatusKind, o);
    } catch (const ipc::SegmentError&) {
        return {};
    }
}

bool finished(const ipc::Segment& status) {
    const auto& h = status.header();
    return h.state.load(std::memory_order_acquire) != static_cast<std::uint32_t>(ipc::SegmentState::ready) ||
           !process_lives(h.creator_pid);
}

}  // namespace

void Lifeline::watch(const std::string& subsystem, std::string object, std::function<void()> release) {
    subsystem_ = subsystem;
    object_ = std::move(object);
    release_ = std::move(release);
    if (subsystem.empty()) return;
    status_ = watch_status(subsystem);
    if (status_.valid()) pid_ = status_.header().creator_pid;
}

bool Lifeline::gone() {
    if (!gone_ && status_.valid() && finished(status_)) {
        gone_ = true;
        status_.detach();
    }
    if (gone_ && uses_ == 0) release_now();
    return gone_;
}

void Lifeline::check() {
    if (gone())
        throw SubsystemGone("subsystem " + subsystem_ + " has finished (its master, pid " + std::to_string(pid_) +
                            ", is gone): this " + object_ + " is closed; attach again once the subsystem runs");
}

void Lifeline::release_now() {
    if (released_) return;
    released_ = true;
    if (release_) release_();
}

std::string Lifeline::subsystem_of(const std::string& segment) {
    const std::string prefix = "/chimera.";
    if (segment.compare(0, prefix.size(), prefix) != 0) return "";
    const std::size_t dot = segment.find('.', prefix.size());
    return dot == std::string::npos ? "" : segment.substr(prefix.size(), dot - prefix.size());
}

bool Lifeline::master_alive(const std::string& subsystem) {
    try {
        ipc::AttachOptions o;
        o.prefault = false;
        o.ready_timeout_ns = 100'000'000;
        const ipc::Segment status = ipc::Segment::watch(ipc::segment_name(subsystem, "status"), kStatusKind, o);
        return !finished(status);
    } catch (const ipc::SegmentError& e) {
        return e.error_number() == EACCES;  // another user's, not ours to read: listed, as it exists
    }
}

}  // namespace chimera::python
