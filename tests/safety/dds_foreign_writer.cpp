// dds_foreign_writer — the safety suite's foreign publisher (issue #29.9): a
// participant of its own on the arm's torque topic, built only from Cyclone
// DDS's C API and the types idlc compiles from modules/ddsbridge/idl/
// ros2_msgs.idl (no line of the bridge), as a misbehaving ROS 2 node would be.
// It reads the controller's torque commands on the topic and, for SECONDS,
// writes in turn, from the newest one read and with its header.stamp:
//   reversed   the six joints named in reverse order, each with its own torque
//              (the same command by name: taken by position it would swap
//              joint 1's torque with joint 6's, and so on);
//   partial    joint2 and joint5 only;
//   oversized  joint1 .. joint64 (58 names the arm does not have);
//   huge       the six names with 100000 efforts (800 kB);
//   unnamed    six efforts without names;
// and, from the first command it read, with that command's stamp:
//   replayed   the old command again (older than the newest the robot took:
//              taken, it would send the arm back to it).
// Prints one line at the end: "sent reversed=N partial=N oversized=N huge=N
// unnamed=N replayed=N read=N" (read: the controller's commands it read).
//
//   dds_foreign_writer DOMAIN CONFIG_FILE TOPIC SECONDS
//
// Exit 0 when it read a command and wrote, 1 when it never read one, 2 on bad use.
#include <dds/dds.h>

#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "ros2_msgs.h"

namespace {

struct Message {
    std::vector<std::string> names;
    std::vector<double> efforts;
    std::int64_t stamp_ns = 0;  // header.stamp
};

// A command read: joint1 .. joint6's torques, whatever order they came in, and its stamp.
struct Command {
    std::vector<double> efforts;
    std::int64_t stamp_ns = 0;
};

void write(dds_entity_t w, const Message& m) {
    std::vector<char*> n;
    for (const std::string& s : m.names) n.push_back(const_cast<char*>(s.c_str()));
    std::vector<double> e = m.efforts;
    char empty[] = "";
    sensor_msgs_msg_dds__JointState_ s{};
    s.header.frame_id = empty;
    s.header.stamp.sec = static_cast<int32_t>(m.stamp_ns / 1'000'000'000);
    s.header.stamp.nanosec = static_cast<uint32_t>(m.stamp_ns % 1'000'000'000);
    s.name = {static_cast<uint32_t>(n.size()), static_cast<uint32_t>(n.size()), n.data(), false};
    s.effort = {static_cast<uint32_t>(e.size()), static_cast<uint32_t>(e.size()), e.data(), false};
    (void)dds_write(w, &s);
}

// Takes the controller's commands read since the last call: the newest one
// naming joint1 .. joint6 into `last`; how many.
long take_commands(dds_entity_t reader, Command& last) {
    long read = 0;
    void* samples[1] = {nullptr};
    dds_sample_info_t info;
    while (dds_take(reader, samples, &info, 1, 1) > 0) {
        const auto* s = static_cast<const sensor_msgs_msg_dds__JointState_*>(samples[0]);
        if (info.valid_data && s->name._length == 6 && s->effort._length == 6) {
            std::vector<double> by_name(6, 0.0);
            int named = 0;
            for (int k = 0; k < 6; ++k) {
                const int j = std::atoi(s->name._buffer[k] + (std::strncmp(s->name._buffer[k], "joint", 5) ? 0 : 5));
                if (j >= 1 && j <= 6) {
                    by_name[j - 1] = s->effort._buffer[k];
                    ++named;
                }
            }
            if (named == 6) {
                last = {by_name, static_cast<std::int64_t>(s->header.stamp.sec) * 1'000'000'000 + s->header.stamp.nanosec};
                ++read;
            }
        }
        dds_return_loan(reader, samples, 1);
    }
    return read;
}

// The message of `kind` (the order of the header's list) from the newest
// command read, or (replayed) the first.
Message make(unsigned kind, const Command& last, const Command& first) {
    Message m;
    m.stamp_ns = last.stamp_ns;
    if (kind == 0) {
        for (int j = 6; j >= 1; --j) {
            m.names.push_back("joint" + std::to_string(j));
            m.efforts.push_back(last.efforts[j - 1]);
        }
    } else if (kind == 1) {
        m.names = {"joint2", "joint5"};
        m.efforts = {last.efforts[1], last.efforts[4]};
    } else if (kind == 2) {
        for (int j = 1; j <= 64; ++j) {
            m.names.push_back("joint" + std::to_string(j));
            m.efforts.push_back(j <= 6 ? last.efforts[j - 1] : 0.0);
        }
    } else if (kind == 3) {
        for (int j = 1; j <= 6; ++j) m.names.push_back("joint" + std::to_string(j));
        m.efforts.assign(100000, 0.0);
        for (int j = 0; j < 6; ++j) m.efforts[j] = last.efforts[j];
    } else if (kind == 4) {
        m.efforts = last.efforts;
    } else {
        for (int j = 1; j <= 6; ++j) m.names.push_back("joint" + std::to_string(j));
        m.efforts = first.efforts;
        m.stamp_ns = first.stamp_ns;
    }
    return m;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc != 5) {
        std::fprintf(stderr, "usage: dds_foreign_writer DOMAIN CONFIG_FILE TOPIC SECONDS\n");
        return 2;
    }
    const int domain = std::atoi(argv[1]);
    const std::string config = std::string("file://") + argv[2];
    const dds_time_t end = dds_time() + static_cast<dds_time_t>(std::atof(argv[4]) * 1e9);
    const dds_entity_t dom = dds_create_domain(domain, config.c_str());
    const dds_entity_t pp = dds_create_participant(domain, nullptr, nullptr);
    if (dom < 0 || pp < 0) {
        std::fprintf(stderr, "dds_foreign_writer: cannot join domain %d with %s\n", domain, argv[2]);
        return 2;
    }
    const dds_entity_t topic = dds_create_topic(pp, &sensor_msgs_msg_dds__JointState__desc, argv[3], nullptr, nullptr);
    // The bridge's command QoS (reliable, keep last 1); the reader ignores this
    // participant's own writes: it wants the controller's commands only.
    dds_qos_t* q = dds_create_qos();
    dds_qset_reliability(q, DDS_RELIABILITY_RELIABLE, DDS_SECS(1));
    dds_qset_history(q, DDS_HISTORY_KEEP_LAST, 1);
    const dds_entity_t writer = dds_create_writer(pp, topic, q, nullptr);
    dds_qset_ignorelocal(q, DDS_IGNORELOCAL_PARTICIPANT);
    const dds_entity_t reader = dds_create_reader(pp, topic, q, nullptr);
    dds_delete_qos(q);
    if (topic < 0 || writer < 0 || reader < 0) {
        std::fprintf(stderr, "dds_foreign_writer: cannot use topic %s\n", argv[3]);
        return 2;
    }
    Command last, first;
    long read = 0, sent[6] = {0, 0, 0, 0, 0, 0};
    for (unsigned i = 0; dds_time() < end; ++i) {
        // About 200 writes a second, each kind 33; the newest command is read
        // right before each write, so a reversed one is as new as it can be.
        dds_sleepfor(DDS_MSECS(5));
        read += take_commands(reader, last);
        if (last.efforts.empty()) continue;
        if (first.efforts.empty()) first = last;
        const unsigned kind = i % 6;
        if (kind == 3 && i % 30 != 3) continue;  // huge: under 7 a second, 5.3 MB/s on the link is plenty
        write(writer, make(kind, last, first));
        ++sent[kind];
    }
    std::printf("sent reversed=%ld partial=%ld oversized=%ld huge=%ld unnamed=%ld replayed=%ld read=%ld\n", sent[0],
                sent[1], sent[2], sent[3], sent[4], sent[5], read);
    dds_delete(dom);
    return read > 0 ? 0 : 1;
}
