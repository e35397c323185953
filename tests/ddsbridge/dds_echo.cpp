// dds_echo — an independent reader of what ddsbridge publishes: built only
// from Cyclone DDS's C API and the types idlc compiles from
// modules/ddsbridge/idl/ros2_msgs.idl (no line of the bridge), as a ROS 2
// node would see the topic. Prints each sample decoded, one line, and first
// what discovery says of the writer (type name, data representation).
//
//   dds_echo DOMAIN CONFIG_FILE TOPIC JointState|StateVar COUNT TIMEOUT_S
//
// Exit 0 when COUNT samples were read, 1 on a timeout, 2 on bad use.
#include <dds/dds.h>

#include <cinttypes>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>

#include "ros2_msgs.h"

namespace {

void print_doubles(const char* name, const dds_sequence_double& s) {
    std::printf(" %s=[", name);
    for (uint32_t i = 0; i < s._length; ++i) std::printf(i ? ",%.17g" : "%.17g", s._buffer[i]);
    std::printf("]");
}

void print_header(const std_msgs_msg_dds__Header_& h) {
    std::printf(" stamp=%" PRId32 ".%09" PRIu32 " frame_id=%s", h.stamp.sec, h.stamp.nanosec, h.frame_id);
}

// The writer as discovery describes it: its type name and data representation.
bool print_writer(dds_entity_t reader) {
    dds_instance_handle_t handles[4];
    const dds_return_t n = dds_get_matched_publications(reader, handles, 4);
    if (n <= 0) return false;
    dds_builtintopic_endpoint_t* ep = dds_get_matched_publication_data(reader, handles[0]);
    if (ep == nullptr) return false;
    uint32_t reps = 0;
    dds_data_representation_id_t* values = nullptr;
    std::printf("writer type=%s representation=", ep->type_name);
    if (dds_qget_data_representation(ep->qos, &reps, &values) && reps > 0) {
        for (uint32_t i = 0; i < reps; ++i)
            std::printf("%s%s", i ? "," : "", values[i] == DDS_DATA_REPRESENTATION_XCDR1 ? "XCDR1" : "XCDR2");
        dds_free(values);
    } else {
        std::printf("default(XCDR1)");
    }
    dds_reliability_kind_t rel;
    dds_duration_t block;
    if (dds_qget_reliability(ep->qos, &rel, &block))
        std::printf(" reliability=%s", rel == DDS_RELIABILITY_RELIABLE ? "reliable" : "best_effort");
    std::printf("\n");
    dds_builtintopic_free_endpoint(ep);
    return true;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc != 7) {
        std::fprintf(stderr, "usage: dds_echo DOMAIN CONFIG_FILE TOPIC JointState|StateVar COUNT TIMEOUT_S\n");
        return 2;
    }
    const int domain = std::atoi(argv[1]);
    const std::string config = std::string("file://") + argv[2];
    const bool joint = std::strcmp(argv[4], "JointState") == 0;
    const long count = std::atol(argv[5]);
    const dds_time_t deadline = dds_time() + static_cast<dds_time_t>(std::atof(argv[6]) * 1e9);
    const dds_entity_t dom = dds_create_domain(domain, config.c_str());
    const dds_entity_t pp = dds_create_participant(domain, nullptr, nullptr);
    if (dom < 0 || pp < 0) {
        std::fprintf(stderr, "dds_echo: cannot join domain %d with %s\n", domain, argv[2]);
        return 2;
    }
    const dds_topic_descriptor_t* desc = joint ? &sensor_msgs_msg_dds__JointState__desc : &chimera_msgs_msg_dds__StateVar__desc;
    const dds_entity_t topic = dds_create_topic(pp, desc, argv[3], nullptr, nullptr);
    // ROS 2's sensor-data profile: best effort, keep last 5, volatile.
    dds_qos_t* q = dds_create_qos();
    dds_qset_reliability(q, DDS_RELIABILITY_BEST_EFFORT, 0);
    dds_qset_history(q, DDS_HISTORY_KEEP_LAST, 5);
    const dds_entity_t reader = dds_create_reader(pp, topic, q, nullptr);
    dds_delete_qos(q);
    if (topic < 0 || reader < 0) {
        std::fprintf(stderr, "dds_echo: cannot read %s\n", argv[3]);
        return 2;
    }
    bool writer_seen = false;
    long got = 0;
    while (got < count && dds_time() < deadline) {
        if (!writer_seen) writer_seen = print_writer(reader);
        void* samples[1] = {nullptr};
        dds_sample_info_t info;
        if (dds_take(reader, samples, &info, 1, 1) <= 0) {
            dds_sleepfor(DDS_MSECS(1));
            continue;
        }
        if (info.valid_data) {
            if (joint) {
                const auto* s = static_cast<const sensor_msgs_msg_dds__JointState_*>(samples[0]);
                std::printf("JointState");
                print_header(s->header);
                std::printf(" name=[");
                for (uint32_t i = 0; i < s->name._length; ++i) std::printf(i ? ",%s" : "%s", s->name._buffer[i]);
                std::printf("]");
                print_doubles("position", s->position);
                print_doubles("velocity", s->velocity);
                print_doubles("effort", s->effort);
            } else {
                const auto* s = static_cast<const chimera_msgs_msg_dds__StateVar_*>(samples[0]);
                std::printf("StateVar");
                print_header(s->header);
                std::printf(" counter=%" PRIu64, s->counter);
                print_doubles("data", s->data);
            }
            std::printf("\n");
            std::fflush(stdout);
            ++got;
        }
        dds_return_loan(reader, samples, 1);
    }
    dds_delete(dom);
    return got >= count ? 0 : 1;
}
