// A Processor with the test library and its tasks, torn down safely: the
// gates are opened before the tasks finish, so a failed assertion while the
// executive is held does not leave finish() waiting forever.
#pragma once

#include <gtest/gtest.h>

#include <memory>
#include <vector>

#include "spp_test_util.hpp"

namespace spp_test {

class ExecutiveTest : public ::testing::Test {
protected:
    void SetUp() override { reset_fixtures(); }
    void TearDown() override {
        for (Gate& g : gates) g.open();
        tasks_.clear();
        proc_.reset();
    }

    void start(int queue = 64, int tasks = 8) { proc_ = spp::Processor::init(make_config(queue, tasks), make_library()); }
    spp::Processor& proc() { return *proc_; }

    /// A task's SPP object, finished at tear-down.
    spp::Spp& task(int priority) {
        tasks_.push_back(spp::Spp::init(*proc_, priority));
        return *tasks_.back();
    }

    /// Has `holder` issue hold(tag, gate) and returns once the executive is
    /// inside it: until the gate opens, commands only queue up.
    void hold_executive(spp::Spp& holder, std::int64_t tag, int gate = 0) {
        ASSERT_EQ(holder.call(holder.translate("hold"), tag_gate(tag, gate)), 0);
        gates[static_cast<std::size_t>(gate)].await_entered();
    }

    /// record(t) for each tag, all accepted.
    static void record_all(spp::Spp& s, std::initializer_list<std::int64_t> tags) {
        const spp::Handle rec = s.translate("record");
        for (std::int64_t t : tags) ASSERT_EQ(s.call(rec, tag(t)), 0) << "record(" << t << ")";
    }

private:
    std::unique_ptr<spp::Processor> proc_;
    std::vector<std::unique_ptr<spp::Spp>> tasks_;
};

}  // namespace spp_test
