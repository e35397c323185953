// Helpers for the multi-process ipc tests.
#pragma once

#include <unistd.h>

#include <atomic>
#include <string>

#include "chimera/ipc/segment.hpp"
#include "process.hpp"

namespace chimera::ipc::test {

/// A unique segment name for this process and test.
inline std::string unique_name(const std::string& what) {
    return "/chimera.test" + std::to_string(getpid()) + "." + what;
}

/// What the segment tests put in their segments.
inline constexpr SegmentKind kKind{ObjectType::test, 2};
struct Body {
    SegmentHeader header;
    std::uint64_t value;
};

/// Creates and publishes a segment holding a Body.
inline Segment make(const std::string& name, std::uint64_t value = 42, mode_t mode = 0600) {
    CreateOptions o;
    o.mode = mode;
    Segment s = Segment::create(name, sizeof(Body), kKind, o);
    s.at_bytes<Body>(0)->value = value;
    s.publish();
    return s;
}

using chimera::test::fork_child;
using chimera::test::shared_anon;
using chimera::test::wait_child;
using chimera::test::wait_for;

}  // namespace chimera::ipc::test
