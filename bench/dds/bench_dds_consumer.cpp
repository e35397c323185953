// bench_dds_consumer — the receiving side of bench/dds/bench_dds.sh: the
// bridge's own receiving code (ddsbridge::Link, the listener that fills the
// port's TBUF), read by a 1 kHz loop as a consumer task would. For each new
// value:
//   transfer = its arrival in the TBUF (the TBUF's stamp, CLOCK_MONOTONIC)
//              - the producer's table write (element 0, CLOCK_MONOTONIC: the
//              namespaces share the machine's clock);
//   wait     = the consumer loop's read - the arrival (reported apart).
// and, from the listener's probe (every value received in the window), the
// transfer's legs (CLOCK_REALTIME stamps moved to CLOCK_MONOTONIC here):
//   write    = the bridge's TBUF write (header.stamp) - the table write;
//   handoff  = the bridge thread's dds_write (DDS source timestamp) - its TBUF write;
//   dds      = the listener's entry - dds_write: Cyclone, the network, the receive thread;
//   store    = the TBUF write - the listener's entry: take and copy.
// Prints "NAME n N p50 US p99 US max US" for transfer, wait and each leg.
//   bench_dds_consumer DOMAIN CONFIG TOPIC WARMUP DURATION [JointState|StateVar]
#include "dds_link.hpp"

#include <chimera/ipc/clock.hpp>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <string>
#include <vector>

namespace {

void print(const char* what, std::vector<double> v) {
    if (v.empty()) {
        std::printf("%s n 0\n", what);
        return;
    }
    std::sort(v.begin(), v.end());
    auto at = [&](double q) { return v[static_cast<std::size_t>(q * static_cast<double>(v.size() - 1))]; };
    std::printf("%s n %zu p50 %.1f p99 %.1f max %.1f us\n", what, v.size(), at(0.5) / 1e3, at(0.99) / 1e3, v.back() / 1e3);
}

// The listener's probes, recorded on Cyclone's receive thread into room
// reserved before the run; read once the window has ended.
struct Legs {
    struct Seen {
        std::int64_t table_ns, header_ns, written_ns, entered_ns, stored_ns;
    };
    std::vector<Seen> seen = std::vector<Seen>(200000);
    std::atomic<std::size_t> n{0};
    std::int64_t from_ns = 0, until_ns = 0;  // the window, CLOCK_MONOTONIC

    static void record(void* self, const ddsbridge::ReceiveProbe& p) {
        auto& legs = *static_cast<Legs*>(self);
        const std::size_t i = legs.n.load(std::memory_order_relaxed);
        if (i == legs.seen.size() || p.stored_ns < legs.from_ns || p.stored_ns >= legs.until_ns) return;
        legs.seen[i] = {static_cast<std::int64_t>(p.values[0]), p.header_stamp_ns, p.written_ns, p.entered_ns, p.stored_ns};
        legs.n.store(i + 1, std::memory_order_release);
    }

    void print(std::int64_t realtime_minus_monotonic) const {
        std::vector<double> write, handoff, dds, store;
        for (std::size_t i = 0; i < n.load(std::memory_order_acquire); ++i) {
            const Seen& s = seen[i];
            const std::int64_t header = s.header_ns - realtime_minus_monotonic;
            const std::int64_t written = s.written_ns - realtime_minus_monotonic;
            write.push_back(static_cast<double>(header - s.table_ns));
            handoff.push_back(static_cast<double>(written - header));
            dds.push_back(static_cast<double>(s.entered_ns - written));
            store.push_back(static_cast<double>(s.stored_ns - s.entered_ns));
        }
        ::print("leg_write", write);
        ::print("leg_handoff", handoff);
        ::print("leg_dds", dds);
        ::print("leg_store", store);
    }
};

std::int64_t realtime_minus_monotonic() {
    timespec rt{}, mono{};
    clock_gettime(CLOCK_REALTIME, &rt);
    clock_gettime(CLOCK_MONOTONIC, &mono);
    return (static_cast<std::int64_t>(rt.tv_sec) - mono.tv_sec) * 1'000'000'000 + (rt.tv_nsec - mono.tv_nsec);
}

}  // namespace

int main(int argc, char** argv) {
    if (argc != 6 && argc != 7) {
        std::fprintf(stderr, "usage: bench_dds_consumer DOMAIN CONFIG TOPIC WARMUP DURATION [JointState|StateVar]\n");
        return 2;
    }
    using namespace ddsbridge;
    BridgeConfig config;
    config.domain = std::atoi(argv[1]);
    config.config_file = argv[2];
    Port port;
    port.spec.port = "Q";
    port.spec.ros_name = argv[3];
    port.spec.direction = Direction::sub;
    port.spec.message = argc == 7 && std::string(argv[6]) == "StateVar" ? Message::state_var : Message::joint_position;
    port.spec.qos = Qos::state;
    port.spec.age_limit = 1;
    port.global_name = "Q";
    port.nelem = 6;
    config.topics = {port.spec};
    Link link(config, {port});
    const std::int64_t period = 1'000'000;
    const std::int64_t warm_until = chimera::ipc::now_ns() + static_cast<std::int64_t>(std::atof(argv[4]) * 1e9);
    const std::int64_t end = warm_until + static_cast<std::int64_t>(std::atof(argv[5]) * 1e9);
    Legs legs;
    legs.from_ns = warm_until;
    legs.until_ns = end;
    link.set_receive_probe(0, &Legs::record, &legs);
    const std::int64_t offset_before = realtime_minus_monotonic();
    std::vector<double> transfer, wait;
    transfer.reserve(100000);
    wait.reserve(100000);
    std::int64_t next = chimera::ipc::now_ns();
    for (;;) {
        next += period;
        const timespec ts{static_cast<time_t>(next / 1'000'000'000), static_cast<long>(next % 1'000'000'000)};
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
        const std::int64_t now = chimera::ipc::now_ns();
        if (now >= end) break;
        chimera::tbuf::ReadResult r;
        const auto* item = static_cast<const unsigned char*>(link.buffer(0).read_view(r));
        if (r.status != chimera::tbuf::ReadStatus::fresh || now < warm_until) continue;
        double written = 0;
        std::copy_n(item + sizeof(ReceivedHeader), sizeof written, reinterpret_cast<unsigned char*>(&written));
        transfer.push_back(static_cast<double>(r.time_ns) - written);
        wait.push_back(static_cast<double>(now - r.time_ns));
    }
    link.set_receive_probe(0, nullptr, nullptr);
    print("transfer", transfer);
    print("wait", wait);
    legs.print((offset_before + realtime_minus_monotonic()) / 2);
    std::printf("received %llu rejected %llu\n", static_cast<unsigned long long>(link.counts(0).received.load()),
                static_cast<unsigned long long>(link.counts(0).rejected.load()));
    return 0;
}
