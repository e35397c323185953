// bench_dds_consumer — the receiving side of bench/dds/bench_dds.sh: the
// bridge's own receiving code (ddsbridge::Link, the listener that fills the
// port's TBUF), read by a 1 kHz loop as a consumer task would. For each new
// value:
//   transfer = its arrival in the TBUF (the TBUF's stamp, CLOCK_MONOTONIC)
//              - the producer's table write (element 0, CLOCK_MONOTONIC: the
//              namespaces share the machine's clock);
//   wait     = the consumer loop's read - the arrival (reported apart).
// Prints "transfer n N p50 US p99 US" and "wait n N p50 US p99 US".
//   bench_dds_consumer DOMAIN CONFIG TOPIC WARMUP DURATION
#include "dds_link.hpp"

#include <chimera/ipc/clock.hpp>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <ctime>
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

}  // namespace

int main(int argc, char** argv) {
    if (argc != 6) {
        std::fprintf(stderr, "usage: bench_dds_consumer DOMAIN CONFIG TOPIC WARMUP DURATION\n");
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
    port.spec.message = Message::joint_position;
    port.spec.qos = Qos::state;
    port.spec.age_limit = 1;
    port.global_name = "Q";
    port.nelem = 6;
    config.topics = {port.spec};
    Link link(config, {port});
    const std::int64_t period = 1'000'000;
    const std::int64_t warm_until = chimera::ipc::now_ns() + static_cast<std::int64_t>(std::atof(argv[4]) * 1e9);
    const std::int64_t end = warm_until + static_cast<std::int64_t>(std::atof(argv[5]) * 1e9);
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
    print("transfer", transfer);
    print("wait", wait);
    std::printf("received %llu rejected %llu\n", static_cast<unsigned long long>(link.counts(0).received.load()),
                static_cast<unsigned long long>(link.counts(0).rejected.load()));
    return 0;
}
