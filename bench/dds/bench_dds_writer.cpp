// bench_dds_writer — a second peer for bench/dds/bench_dds.sh: Cyclone DDS's
// own one-way path for the bridge's exact sample, with no bridge in it. A
// plain thread writes, on a 1 kHz timer, the JointState the bridge would send
// (6 names "jointN", 6 positions, element 0 the CLOCK_MONOTONIC time of the
// write), with the bridge's QoS (best effort, keep last 1, volatile, XCDR1),
// straight from where it decides to send — as ddsperf's ping does.
// bench_dds_consumer reads it exactly as it reads the bridge, so its "dds"
// leg is Cyclone's one-way time measured on one clock, not half a round trip.
//   bench_dds_writer DOMAIN TOPIC DURATION
#include <dds/dds.h>

#include <time.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <string>

#include "ros2_msgs.h"

namespace {

std::int64_t now_ns(clockid_t id) {
    timespec ts{};
    clock_gettime(id, &ts);
    return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc != 4) {
        std::fprintf(stderr, "usage: bench_dds_writer DOMAIN TOPIC DURATION\n");
        return 2;
    }
    const dds_entity_t participant = dds_create_participant(static_cast<dds_domainid_t>(std::atoi(argv[1])), nullptr, nullptr);
    if (participant < 0) {
        std::fprintf(stderr, "bench_dds_writer: participant: %s\n", dds_strretcode(participant));
        return 1;
    }
    const std::string topic_name = std::string("rt/") + argv[2];
    const dds_entity_t topic =
        dds_create_topic(participant, &sensor_msgs_msg_dds__JointState__desc, topic_name.c_str(), nullptr, nullptr);
    dds_qos_t* qos = dds_create_qos();
    dds_qset_reliability(qos, DDS_RELIABILITY_BEST_EFFORT, 0);
    dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, 1);
    dds_qset_durability(qos, DDS_DURABILITY_VOLATILE);
    const dds_data_representation_id_t xcdr1 = DDS_DATA_REPRESENTATION_XCDR1;
    dds_qset_data_representation(qos, 1, &xcdr1);
    const dds_entity_t writer = dds_create_writer(participant, topic, qos, nullptr);
    dds_delete_qos(qos);
    if (topic < 0 || writer < 0) {
        std::fprintf(stderr, "bench_dds_writer: topic or writer: %s\n", dds_strretcode(topic < 0 ? topic : writer));
        return 1;
    }
    char names_text[6][8] = {"joint1", "joint2", "joint3", "joint4", "joint5", "joint6"};
    char* names[6];
    for (int j = 0; j < 6; ++j) names[j] = names_text[j];
    char empty[1] = {'\0'};
    double q[6] = {};
    sensor_msgs_msg_dds__JointState_ sample{};
    const std::int64_t end = now_ns(CLOCK_MONOTONIC) + static_cast<std::int64_t>(std::atof(argv[3]) * 1e9);
    std::int64_t next = now_ns(CLOCK_MONOTONIC);
    std::uint64_t written = 0;
    while (next < end) {
        next += 1'000'000;
        const timespec ts{static_cast<time_t>(next / 1'000'000'000), static_cast<long>(next % 1'000'000'000)};
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
        for (int j = 1; j < 6; ++j) q[j] = 1e-3 * static_cast<double>(written % 1000) * j;
        q[0] = static_cast<double>(now_ns(CLOCK_MONOTONIC));
        const std::int64_t realtime = now_ns(CLOCK_REALTIME);
        sample = sensor_msgs_msg_dds__JointState_{};
        sample.header.frame_id = empty;
        sample.header.stamp.sec = static_cast<int32_t>(realtime / 1'000'000'000);
        sample.header.stamp.nanosec = static_cast<uint32_t>(realtime % 1'000'000'000);
        sample.name = {6, 6, names, false};
        sample.position = {6, 6, q, false};
        if (dds_write(writer, &sample) == DDS_RETCODE_OK) ++written;
    }
    std::printf("writer samples %llu\n", static_cast<unsigned long long>(written));
    dds_delete(participant);
    return 0;
}
