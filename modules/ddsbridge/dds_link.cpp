// dds_link.cpp — the bridge thread, its DDS entities and the listeners (dds_link.hpp).
#include "dds_link.hpp"

#include <chimera/ipc/clock.hpp>
#include <chimera/ipc/seqlock.hpp>

#include <dds/dds.h>
#include <sched.h>
#include <sys/prctl.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <map>
#include <stdexcept>

#include "ros2_msgs.h"

namespace ddsbridge {

struct Link::Slot {
    std::unique_ptr<std::byte[], void (*)(void*)> memory{nullptr, &std::free};
    chimera::tbuf::Tbuf tbuf;
    SubCounts counts;
    dds_entity_t topic = 0, endpoint = 0;
    std::mutex listener_mu;  // one writer of the TBUF at a time, whichever Cyclone thread delivers
    std::vector<std::byte> item;  // the listener's staging item
    std::vector<char*> names;     // JointState.name (pub)
    std::unique_ptr<JointMap> joints;  // JointState (sub): the names matched, and the joints' values so far
    SampleOrder order;                 // sub: the newest sample taken (a reordered one is refused)
    Notice notices[kRefusals];         // refusals to tell the task (index: Refusal)
    const Port* port = nullptr;
    ReceiveProbeFn probe = nullptr;  // set and called under listener_mu
    void* probe_context = nullptr;
};

namespace {

using Clock = std::int64_t;

Clock clock_ns(clockid_t id) noexcept {
    timespec ts{};
    clock_gettime(id, &ts);  // vDSO
    return static_cast<Clock>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

// A domain created with a configuration file is shared by the bridges of one
// process that name the same domain and file, and deleted with the last one.
struct DomainUse {
    dds_entity_t entity = 0;
    std::string config;
    int users = 0;
};
std::mutex g_domains_mu;
std::map<int, DomainUse> g_domains;

void acquire_domain(int id, const std::string& file) {
    if (file.empty()) return;  // Cyclone's defaults: the participant creates the domain
    std::lock_guard<std::mutex> lock(g_domains_mu);
    auto it = g_domains.find(id);
    if (it != g_domains.end()) {
        if (it->second.config != file)
            throw std::runtime_error("DDS domain " + std::to_string(id) + " already runs in this process with CONFIG " +
                                     it->second.config + ", not " + file);
        ++it->second.users;
        return;
    }
    const std::string uri = "file://" + file;
    const dds_entity_t d = dds_create_domain(static_cast<dds_domainid_t>(id), uri.c_str());
    if (d < 0)
        throw std::runtime_error("CONFIG " + file + ": Cyclone DDS refused domain " + std::to_string(id) + ": " +
                                 dds_strretcode(d) + " (an unreadable file, bad XML, or the domain already "
                                 "running in this process without a CONFIG)");
    g_domains[id] = DomainUse{d, file, 1};
}

void release_domain(int id, const std::string& file) noexcept {
    if (file.empty()) return;
    std::lock_guard<std::mutex> lock(g_domains_mu);
    auto it = g_domains.find(id);
    if (it != g_domains.end() && --it->second.users == 0) {
        dds_delete(it->second.entity);
        g_domains.erase(it);
    }
}

dds_qos_t* make_qos(Qos profile) {
    dds_qos_t* q = dds_create_qos();
    if (profile == Qos::command)
        dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_MSECS(100));
    else
        dds_qset_reliability(q, DDS_RELIABILITY_BEST_EFFORT, 0);
    dds_qset_history(q, DDS_HISTORY_KEEP_LAST, 1);
    dds_qset_durability(q, DDS_DURABILITY_VOLATILE);
    const dds_data_representation_id_t xcdr1 = DDS_DATA_REPRESENTATION_XCDR1;
    dds_qset_data_representation(q, 1, &xcdr1);
    return q;
}

const dds_topic_descriptor_t* descriptor(Message m) noexcept {
    return m == Message::state_var ? &chimera_msgs_msg_dds__StateVar__desc : &sensor_msgs_msg_dds__JointState__desc;
}

dds_sequence_double* joint_field(sensor_msgs_msg_dds__JointState_& s, Message m) noexcept {
    switch (m) {
        case Message::joint_position: return &s.position;
        case Message::joint_velocity: return &s.velocity;
        case Message::joint_effort: return &s.effort;
        case Message::state_var: break;
    }
    return nullptr;
}

void set_stamp(std_msgs_msg_dds__Header_& h, Clock realtime_ns) noexcept {
    h.stamp.sec = static_cast<int32_t>(realtime_ns / 1'000'000'000);
    h.stamp.nanosec = static_cast<uint32_t>(realtime_ns % 1'000'000'000);
}

Clock stamp_ns(const std_msgs_msg_dds__Header_& h) noexcept {
    return static_cast<Clock>(h.stamp.sec) * 1'000'000'000 + h.stamp.nanosec;
}

// Who sent a sample: its writer's GUID (prefix: the participant), as Cyclone prints GUIDs; discovery
// data asked for only when a refusal is told (rate-limited), never per sample.
void publisher_of(dds_entity_t reader, const dds_sample_info_t& info, char* out, std::size_t size) noexcept {
    dds_builtintopic_endpoint_t* ep = dds_get_matched_publication_data(reader, info.publication_handle);
    if (ep == nullptr) {
        std::snprintf(out, size, "unknown");
        return;
    }
    const unsigned char* k = ep->key.v;
    std::snprintf(out, size, "%02x%02x%02x%02x:%02x%02x%02x%02x:%02x%02x%02x%02x:%02x%02x%02x%02x", k[0], k[1],
                  k[2], k[3], k[4], k[5], k[6], k[7], k[8], k[9], k[10], k[11], k[12], k[13], k[14], k[15]);
    dds_builtintopic_free_endpoint(ep);
}

// A header.stamp as seconds.nanoseconds (ROS time).
void stamp_text(Clock ns, char* out, std::size_t size) noexcept {
    const Clock sec = ns / 1'000'000'000, nsec = ns % 1'000'000'000;
    std::snprintf(out, size, "%s%lld.%09lld", ns < 0 && sec == 0 ? "-" : "", static_cast<long long>(sec),
                  static_cast<long long>(nsec < 0 ? -nsec : nsec));
}

// A reordered sample: its stamp (or, from the newest's writer, counter) and the newest taken's.
void describe_reordered(const Link::Slot& slot, const SampleStamp& got, char* out, std::size_t size) noexcept {
    const SampleStamp& newest = slot.order.newest();
    char was[24], now[24];
    stamp_text(got.source_ns, was, sizeof was);
    stamp_text(newest.source_ns, now, sizeof now);
    if (slot.order.by_counter(got))
        std::snprintf(out, size, "counter %llu older than %llu (stamps %s, %s)",
                      static_cast<unsigned long long>(got.counter), static_cast<unsigned long long>(newest.counter),
                      was, now);
    else
        std::snprintf(out, size, "stamp %s older than %s", was, now);
}

// What was wrong with a refused sample, in words naming the joint, the count or the stamps.
void describe_refusal(const Link::Slot& slot, const Applied& a, const SampleStamp& got,
                      std::span<const char* const> names, std::size_t values, char* out, std::size_t size) noexcept {
    const Port& port = *slot.port;
    const char* field = port.spec.message == Message::joint_position ? "position"
                        : port.spec.message == Message::joint_velocity ? "velocity"
                        : port.spec.message == Message::joint_effort   ? "effort"
                                                                       : "data";
    switch (a.refusal) {
        case Refusal::length:
            if (port.spec.message == Message::state_var)
                std::snprintf(out, size, "%zu values for %zu elements", values, port.nelem);
            else if (names.empty())
                std::snprintf(out, size, "no names and %zu %s values for %zu joints", values, field, port.nelem);
            else
                std::snprintf(out, size, "%zu %s values for %zu names", values, field, names.size());
            return;
        case Refusal::unnamed:
            std::snprintf(out, size, "no joint names (UNNAMED refuse)");
            return;
        case Refusal::unknown:
            std::snprintf(out, size, "unknown joint '%s'", names[a.offender] ? names[a.offender] : "");
            return;
        case Refusal::duplicate:
            std::snprintf(out, size, "joint '%s' named twice", names[a.offender] ? names[a.offender] : "");
            return;
        case Refusal::partial:
            std::snprintf(out, size, "%zu of %zu joints named (JOINT_SUBSET refuse)", names.size(), port.nelem);
            return;
        case Refusal::reordered:
            describe_reordered(slot, got, out, size);
            return;
        case Refusal::none: break;
    }
    std::snprintf(out, size, "?");
}

// A refused sample: counted, and told to the task (a warning naming the port,
// the topic and the publisher) the first time for its reason and then at most
// once every Notice::kNoticeInterval.
void refuse(Link::Slot& slot, dds_entity_t reader, const dds_sample_info_t& info, const Applied& a,
            const SampleStamp& got, std::span<const char* const> names, std::size_t values, Clock now) noexcept {
    const auto reason = static_cast<std::size_t>(a.refusal);
    slot.counts.rejected.fetch_add(1, std::memory_order_relaxed);
    const std::uint64_t n = slot.counts.refused[reason].fetch_add(1, std::memory_order_relaxed) + 1;
    Notice& notice = slot.notices[reason];
    if (notice.pending.load(std::memory_order_acquire)) return;  // the task has not told the last one yet
    if (notice.last_ns != 0 && now - notice.last_ns < Notice::kNoticeInterval) return;
    char who[64], what[160];
    publisher_of(reader, info, who, sizeof who);
    describe_refusal(slot, a, got, names, values, what, sizeof what);
    const TopicSpec& t = slot.port->spec;
    // Most telling first: a task's warning keeps its first 159 characters;
    // a reordered sample's two stamps leave room for the topic only before
    // the publisher.
    const auto count = static_cast<unsigned long long>(n);
    if (a.refusal == Refusal::reordered)
        std::snprintf(notice.text, sizeof notice.text, "%s refused a sample: %s (%llu %s so far), topic rt/%s, publisher %s",
                      t.port.c_str(), what, count, to_string(a.refusal), t.ros_name.c_str(), who);
    else
        std::snprintf(notice.text, sizeof notice.text, "%s refused a sample: %s (%llu %s so far), publisher %s, topic rt/%s",
                      t.port.c_str(), what, count, to_string(a.refusal), who, t.ros_name.c_str());
    notice.last_ns = now;
    notice.pending.store(true, std::memory_order_release);
}

// One sample into the port's TBUF, stamped with its arrival: a StateVar of the
// port's length, or a JointState matched by name (JointMap), not older than
// the newest taken (SampleOrder). A refused sample changes nothing but the
// counts; a JointState that leaves a joint without any value yet is
// held (its values kept for the next) and counted.
void receive(Link::Slot& slot, dds_entity_t reader, const void* sample, const dds_sample_info_t& info,
             Clock entered) noexcept {
    const Port& port = *slot.port;
    const bool state_var = port.spec.message == Message::state_var;
    auto* joints = reinterpret_cast<double*>(slot.item.data() + sizeof(ReceivedHeader));
    const dds_sequence_double* data = nullptr;
    std::span<const char* const> names;
    SampleStamp got{info.publication_handle, 0, 0};
    Applied a;
    if (state_var) {
        const auto* s = static_cast<const chimera_msgs_msg_dds__StateVar_*>(sample);
        data = &s->data;
        got.counter = s->counter;
        got.source_ns = stamp_ns(s->header);
        if (data->_length != port.nelem) a.refusal = Refusal::length;
    } else {
        auto* s = static_cast<sensor_msgs_msg_dds__JointState_*>(const_cast<void*>(sample));
        data = joint_field(*s, port.spec.message);
        got.source_ns = stamp_ns(s->header);
        names = {const_cast<const char* const*>(s->name._buffer), s->name._length};
        a = slot.joints->check(names, {data->_buffer, data->_length});
    }
    // What is wrong with the sample itself first; then its order.
    if (a.refusal == Refusal::none && slot.order.older(got)) a.refusal = Refusal::reordered;
    if (a.refusal != Refusal::none) {
        refuse(slot, reader, info, a, got, names, data->_length, entered);
        return;
    }
    slot.order.taken(got);  // a held JointState too: its values are the port's next
    if (state_var) {
        std::memcpy(joints, data->_buffer, port.nelem * sizeof(double));
        a.complete = true;
    } else {
        a = slot.joints->commit(names, {data->_buffer, data->_length}, joints);
    }
    if (!a.complete) {
        slot.counts.held.fetch_add(1, std::memory_order_relaxed);
        return;
    }
    const ReceivedHeader head{got.source_ns, state_var ? got.counter : slot.counts.received.load(std::memory_order_relaxed)};
    std::memcpy(slot.item.data(), &head, sizeof head);
    const Clock stored = chimera::ipc::now_ns();
    (void)slot.tbuf.write(slot.item.data(), stored);
    slot.counts.received.fetch_add(1, std::memory_order_relaxed);
    if (slot.probe)
        slot.probe(slot.probe_context, {joints, port.nelem, head.source_ns, info.source_timestamp, entered, stored});
}

// The listener: every sample taken, on whichever Cyclone thread delivers it.
void on_data_available(dds_entity_t reader, void* arg) {
    const Clock entered = chimera::ipc::now_ns();
    auto& slot = *static_cast<Link::Slot*>(arg);
    std::lock_guard<std::mutex> lock(slot.listener_mu);
    void* samples[1] = {nullptr};
    dds_sample_info_t info;
    while (dds_take(reader, samples, &info, 1, 1) > 0) {
        if (info.valid_data) receive(slot, reader, samples[0], info, entered);
        dds_return_loan(reader, samples, 1);
        samples[0] = nullptr;
    }
}

std::string dds_error(const std::string& what, dds_return_t rc) {
    return what + ": " + dds_strretcode(rc);
}

}  // namespace

Link::Link(const BridgeConfig& config, std::vector<Port> ports) : config_(config), ports_(std::move(ports)) {
    for (const Port& p : ports_) {
        auto s = std::make_unique<Slot>();
        s->port = &p;
        const std::size_t item = p.nelem * sizeof(double) + (p.spec.direction == Direction::sub ? sizeof(ReceivedHeader) : 0);
        const std::size_t size = (chimera::tbuf::required_size(item) + 63) / 64 * 64;
        s->memory.reset(static_cast<std::byte*>(std::aligned_alloc(64, size)));
        if (!s->memory) throw std::bad_alloc();
        s->tbuf = chimera::tbuf::Tbuf::create_in(s->memory.get(), size, item);
        s->item.assign(item, std::byte{0});
        if (p.spec.message != Message::state_var && p.spec.direction == Direction::pub)
            for (const std::string& n : p.joint_names) s->names.push_back(const_cast<char*>(n.c_str()));
        s->order = SampleOrder(p.spec.message == Message::state_var);
        if (p.spec.message != Message::state_var && p.spec.direction == Direction::sub)
            s->joints = std::make_unique<JointMap>(p.joint_names, JointOptions{config_.refuse_subset, config_.accept_unnamed});
        slots_.push_back(std::move(s));
    }
    // Not the task's policy, priority or CPU: SCHED_OTHER on every CPU the process may use.
    pthread_attr_t attr;
    pthread_attr_init(&attr);
    pthread_attr_setinheritsched(&attr, PTHREAD_EXPLICIT_SCHED);
    pthread_attr_setschedpolicy(&attr, SCHED_OTHER);
    sched_param sp{};
    pthread_attr_setschedparam(&attr, &sp);
    cpu_set_t cpus;
    if (sched_getaffinity(::getpid(), sizeof cpus, &cpus) == 0) pthread_attr_setaffinity_np(&attr, sizeof cpus, &cpus);
    const int rc = pthread_create(&thread_, &attr, &Link::thread_main, this);
    pthread_attr_destroy(&attr);
    if (rc != 0) throw std::runtime_error(std::string("cannot start the bridge thread: ") + std::strerror(rc));
    std::unique_lock<std::mutex> lock(mu_);
    cv_.wait(lock, [this] { return opened_; });
    if (!open_error_.empty()) {
        lock.unlock();
        pthread_join(thread_, nullptr);
        throw std::runtime_error(open_error_);
    }
}

chimera::tbuf::Tbuf& Link::buffer(std::size_t i) noexcept { return slots_[i]->tbuf; }
const SubCounts& Link::counts(std::size_t i) const noexcept { return slots_[i]->counts; }

const char* Link::pending_notice(std::size_t i, Refusal reason) const noexcept {
    const Notice& n = slots_[i]->notices[static_cast<std::size_t>(reason)];
    return n.pending.load(std::memory_order_acquire) ? n.text : nullptr;
}

void Link::notice_told(std::size_t i, Refusal reason) noexcept {
    slots_[i]->notices[static_cast<std::size_t>(reason)].pending.store(false, std::memory_order_release);
}

void Link::set_receive_probe(std::size_t i, ReceiveProbeFn fn, void* context) noexcept {
    std::lock_guard<std::mutex> lock(slots_[i]->listener_mu);
    slots_[i]->probe = fn;
    slots_[i]->probe_context = context;
}

Link::~Link() {
    stop_.store(true);
    pthread_join(thread_, nullptr);
}

void* Link::thread_main(void* self) noexcept {
    pthread_setname_np(pthread_self(), "ddsbridge");
    static_cast<Link*>(self)->run();
    return nullptr;
}

void Link::run() noexcept {
    tid_.store(static_cast<long>(::syscall(SYS_gettid)));
    std::string error;
    try {
        open();
    } catch (const std::exception& e) {
        error = e.what();
        close();
    }
    {
        std::lock_guard<std::mutex> lock(mu_);
        open_error_ = error;
        opened_ = true;
    }
    cv_.notify_all();
    if (!error.empty()) return;
    publish_loop();
    close();
}

void Link::open() {
    acquire_domain(config_.domain, config_.config_file);
    participant_ = dds_create_participant(static_cast<dds_domainid_t>(config_.domain), nullptr, nullptr);
    if (participant_ < 0) {
        const dds_return_t rc = participant_;
        participant_ = 0;
        throw std::runtime_error(dds_error("cannot create a DDS participant on domain " + std::to_string(config_.domain), rc));
    }
    for (auto& s : slots_) {
        const TopicSpec& t = s->port->spec;
        s->topic = dds_create_topic(participant_, descriptor(t.message), t.dds_topic().c_str(), nullptr, nullptr);
        if (s->topic < 0)
            throw std::runtime_error(dds_error("topic " + t.dds_topic() + " (" + type_name(t.message) + ")", s->topic));
        dds_qos_t* q = make_qos(t.qos);
        if (t.direction == Direction::pub) {
            s->endpoint = dds_create_writer(participant_, s->topic, q, nullptr);
        } else {
            dds_listener_t* l = dds_create_listener(s.get());
            dds_lset_data_available(l, &on_data_available);
            s->endpoint = dds_create_reader(participant_, s->topic, q, l);
            dds_delete_listener(l);
        }
        dds_delete_qos(q);
        if (s->endpoint < 0)
            throw std::runtime_error(dds_error(std::string(t.direction == Direction::pub ? "writer" : "reader") +
                                                   " of " + t.dds_topic(), s->endpoint));
    }
}

void Link::close() noexcept {
    if (participant_ > 0) dds_delete(participant_);  // its topics, readers (listeners stopped) and writers
    participant_ = 0;
    release_domain(config_.domain, config_.config_file);
}

void WriteSchedule::seen(std::int64_t write_ns, std::int64_t period_ns) noexcept {
    if (period_ns <= 0) return;
    if (origin_ == 0 || period_ns != period_ || write_ns - last_ > 3 * period_ns || write_ns < last_) {
        origin_ = write_ns;  // a new grid
        earliest_ = 0;
        typical_ = 0;
    } else {
        // The phase on the grid, in [-period/2, period/2): the jitter is less than half a period.
        const std::int64_t half = period_ns / 2;
        const std::int64_t phase = ((write_ns - origin_ + half) % period_ns + period_ns) % period_ns - half;
        earliest_ = std::min(std::min(earliest_ + kRelax, std::int64_t{0}), phase);
        typical_ += (phase - typical_) / kAverage;
    }
    period_ = period_ns;
    last_ = write_ns;
}

std::int64_t WriteSchedule::next_due(std::int64_t write_ns) const noexcept {
    if (origin_ == 0) return 0;
    // The grid point this write belongs to (nearest), then the next one.
    const std::int64_t base = origin_ + earliest_;
    const std::int64_t since = write_ns - base + period_ / 2;
    const std::int64_t k = since >= 0 ? since / period_ : -((-since + period_ - 1) / period_);
    return base + (k + 1) * period_;
}

std::int64_t WriteSchedule::next_typical(std::int64_t write_ns) const noexcept {
    const std::int64_t due = next_due(write_ns);
    return due == 0 ? 0 : due + std::max(typical_ - earliest_, std::int64_t{0});
}

struct Link::Messages {
    sensor_msgs_msg_dds__JointState_ joint{};
    chimera_msgs_msg_dds__StateVar_ var{};
    char empty[1] = {'\0'};
};

std::int64_t Link::publish_fresh() noexcept {
    Messages& m = *messages_;
    Clock newest = 0;
    for (auto& s : slots_) {
        const Port& p = *s->port;
        if (p.spec.direction != Direction::pub) continue;
        chimera::tbuf::ReadResult r;
        const void* data = s->tbuf.read_view(r);
        if (r.status != chimera::tbuf::ReadStatus::fresh) continue;
        newest = std::max(newest, r.time_ns);
        // ROS time: the task's write, moved from CLOCK_MONOTONIC to CLOCK_REALTIME.
        const Clock realtime = clock_ns(CLOCK_REALTIME) - (clock_ns(CLOCK_MONOTONIC) - r.time_ns);
        dds_sequence_double seq{static_cast<uint32_t>(p.nelem), static_cast<uint32_t>(p.nelem),
                                static_cast<double*>(const_cast<void*>(data)), false};
        dds_return_t rc;
        if (p.spec.message == Message::state_var) {
            set_stamp(m.var.header, realtime);
            m.var.header.frame_id = const_cast<char*>(p.global_name.c_str());
            m.var.counter = r.counter;
            m.var.data = seq;
            rc = dds_write(s->endpoint, &m.var);
        } else {
            m.joint = sensor_msgs_msg_dds__JointState_{};
            m.joint.header.frame_id = m.empty;
            set_stamp(m.joint.header, realtime);
            m.joint.name = {static_cast<uint32_t>(s->names.size()), static_cast<uint32_t>(s->names.size()),
                            s->names.data(), false};
            *joint_field(m.joint, p.spec.message) = seq;
            rc = dds_write(s->endpoint, &m.joint);
        }
        if (rc == DDS_RETCODE_OK) published_.fetch_add(1, std::memory_order_relaxed);
    }
    return newest;
}

namespace {

void sleep_until(Clock t) noexcept {
    const timespec ts{static_cast<time_t>(t / 1'000'000'000), static_cast<long>(t % 1'000'000'000)};
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {}
}

}  // namespace

void Link::publish_loop() noexcept {
    // Its sleeps end when asked, not up to 50 µs later (the default timer
    // slack of a SCHED_OTHER thread); Cyclone's threads keep theirs.
    prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL);
    messages_ = std::make_unique<Messages>();
    WriteSchedule schedule;
    const bool publishes = std::any_of(slots_.begin(), slots_.end(),
                                       [](const auto& s) { return s->port->spec.direction == Direction::pub; });
    Clock newest = 0;  // stamp of the newest value the task wrote
    while (!stop_.load(std::memory_order_relaxed)) {
        // poll and spin look at the TBUFs without sleeping for a while each
        // period: never where the task would preempt the looks (and them).
        if (config_.notify != Notify::wake && publishes) keep_off_task_cpus();
        const std::uint32_t seen = wakeups_.load();  // before the look: a write after it ends the wait at once
        if (const Clock wrote = publish_fresh(); wrote != 0) {
            newest = wrote;
            schedule.seen(wrote, period_ns_.load(std::memory_order_relaxed));
        }
        if (config_.notify == Notify::wake) {
            // Until the task's notify(), at most 10 ms (to see stop_).
            sleeping_.store(true);
            if (wakeups_.load() == seen) chimera::ipc::futex_wait(wakeups_, seen, 10'000'000);
            sleeping_.store(false);
            continue;
        }
        wait_for_write(schedule, newest);
    }
}

void Link::keep_off_task_cpus() noexcept {
    const std::uint64_t task = task_cpus_.load(std::memory_order_relaxed);
    if (task == avoided_cpus_) return;
    avoided_cpus_ = task;
    cpu_set_t cpus;
    if (sched_getaffinity(::getpid(), sizeof cpus, &cpus) != 0) return;  // the process's CPUs
    cpu_set_t others = cpus;
    for (int c = 0; c < 64; ++c)
        if ((task >> c) & 1u) CPU_CLR(c, &others);
    (void)sched_setaffinity(0, sizeof cpus, CPU_COUNT(&others) > 0 ? &others : &cpus);
}

// NOTIFY poll and spin: until the task's next write is due (spin: until it
// appears; poll: until it appears near its typical time, or a poll step);
// every period while the task is OFF.
void Link::wait_for_write(const WriteSchedule& schedule, Clock newest) noexcept {
    const Clock period = period_ns_.load(std::memory_order_relaxed);
    const Clock now = chimera::ipc::now_ns();
    const Clock due = period > 0 ? schedule.next_due(newest) : 0;
    if (due == 0 || now - due > 2 * period + kPollWindow) {  // OFF, not yet written, or long silent
        sleep_until(now + (period > 0 ? period : 10'000'000));
        return;
    }
    if (config_.notify == Notify::spin && now < due + kSpinLimit) {
        if (due - kSpinLead > now) sleep_until(due - kSpinLead);
        look_until(due + kSpinLimit);
        return;
    }
    const Clock typical = schedule.next_typical(newest);
    const Clock window_end = typical + std::min(kPollWindow, period / 20);
    if (config_.notify == Notify::poll && now < window_end) {
        const Clock wake = typical - kPollMargin - lateness_.average();
        if (wake > now) {
            sleep_until(wake);
            lateness_.seen(chimera::ipc::now_ns() - wake);
        }
        if (look_until(window_end)) return;
    }
    sleep_until(chimera::ipc::now_ns() + kPollStep);  // late: a look every step
}

bool Link::look_until(Clock until) noexcept {
    // A look is one relaxed load per TBUF until the write appears (the TBUF
    // then takes it: publish_fresh publishes it next).
    for (;;) {
        for (auto& s : slots_)
            if (s->port->spec.direction == Direction::pub && s->tbuf.fresh_pending()) return true;
        if (stop_.load(std::memory_order_relaxed) || chimera::ipc::now_ns() > until) return false;
        chimera::ipc::seqlock::cpu_relax();
    }
}

}  // namespace ddsbridge
