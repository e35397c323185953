// dds_foreign_writer — the safety suite's foreign publisher (issue #29.9): a
// participant of its own on the arm's torque topic, built only from Cyclone
// DDS's C API and the types idlc compiles from modules/ddsbridge/idl/
// ros2_msgs.idl (no line of the bridge), as a misbehaving ROS 2 node would be.
// It reads the controller's torque commands on the topic and, for SECONDS,
// writes in turn, from the newest one read:
//   reordered  the six joints named in reverse order, each with its own torque
//              (the same command by name: taken by position it would swap
//              joint 1's torque with joint 6's, and so on);
//   partial    joint2 and joint5 only;
//   oversized  joint1 .. joint64 (58 names the arm does not have);
//   huge       the six names with 100000 efforts (800 kB);
//   unnamed    six efforts without names.
// Prints one line at the end: "sent reordered=N partial=N oversized=N huge=N
// unnamed=N read=N" (read: the controller's commands it read).
//
//   dds_foreign_writer DOMAIN CONFIG_FILE TOPIC SECONDS
//
// Exit 0 when it read a command and wrote, 1 when it never read one, 2 on bad use.
#include <dds/dds.h>

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
};

void write(dds_entity_t w, const Message& m) {
    std::vector<char*> n;
    for (const std::string& s : m.names) n.push_back(const_cast<char*>(s.c_str()));
    std::vector<double> e = m.efforts;
    char empty[] = "";
    sensor_msgs_msg_dds__JointState_ s{};
    s.header.frame_id = empty;
    s.name = {static_cast<uint32_t>(n.size()), static_cast<uint32_t>(n.size()), n.data(), false};
    s.effort = {static_cast<uint32_t>(e.size()), static_cast<uint32_t>(e.size()), e.data(), false};
    (void)dds_write(w, &s);
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
    std::vector<double> last;  // the newest command read, joint1 .. joint6
    long read = 0, sent[5] = {0, 0, 0, 0, 0};
    for (unsigned i = 0; dds_time() < end; ++i) {
        // About 200 writes a second, each kind 40; the newest command is read
        // right before each write, so a reordered one is as new as it can be.
        dds_sleepfor(DDS_MSECS(5));
        void* samples[1] = {nullptr};
        dds_sample_info_t info;
        while (dds_take(reader, samples, &info, 1, 1) > 0) {
            const auto* s = static_cast<const sensor_msgs_msg_dds__JointState_*>(samples[0]);
            if (info.valid_data && s->name._length == 6 && s->effort._length == 6) {
                std::vector<double> by_name(6, 0.0);  // joint1 .. joint6, whatever order they came in
                int named = 0;
                for (int k = 0; k < 6; ++k) {
                    const int j = std::atoi(s->name._buffer[k] + (std::strncmp(s->name._buffer[k], "joint", 5) ? 0 : 5));
                    if (j >= 1 && j <= 6) {
                        by_name[j - 1] = s->effort._buffer[k];
                        ++named;
                    }
                }
                if (named == 6) {
                    last = by_name;
                    ++read;
                }
            }
            dds_return_loan(reader, samples, 1);
        }
        if (last.empty()) continue;
        Message m;
        const unsigned kind = i % 5;
        if (kind == 0) {
            for (int j = 6; j >= 1; --j) {
                m.names.push_back("joint" + std::to_string(j));
                m.efforts.push_back(last[j - 1]);
            }
        } else if (kind == 1) {
            m.names = {"joint2", "joint5"};
            m.efforts = {last[1], last[4]};
        } else if (kind == 2) {
            for (int j = 1; j <= 64; ++j) {
                m.names.push_back("joint" + std::to_string(j));
                m.efforts.push_back(j <= 6 ? last[j - 1] : 0.0);
            }
        } else if (kind == 3) {
            if (i % 25 != 3) continue;  // 8 a second: 6.4 MB/s on the link is plenty
            for (int j = 1; j <= 6; ++j) m.names.push_back("joint" + std::to_string(j));
            m.efforts.assign(100000, 0.0);
            for (int j = 0; j < 6; ++j) m.efforts[j] = last[j];
        } else {
            m.efforts = last;
        }
        write(writer, m);
        ++sent[kind];
    }
    std::printf("sent reordered=%ld partial=%ld oversized=%ld huge=%ld unnamed=%ld read=%ld\n", sent[0], sent[1],
                sent[2], sent[3], sent[4], read);
    dds_delete(dom);
    return read > 0 ? 0 : 1;
}
