// Counting global allocator for the no-allocation tests: arm it around the
// calls that must not touch the heap.
#pragma once

#include <atomic>

namespace chimera::test {
extern std::atomic<bool> alloc_counting;
extern std::atomic<long> alloc_count;
}  // namespace chimera::test
