// Replaces global operator new/delete (own translation unit, so the compiler
// does not pair the malloc/free inside them with the callers' new/delete).
#include "alloc_counter.hpp"

#include <cstdlib>
#include <new>

namespace chimera::test {
std::atomic<bool> alloc_counting{false};
std::atomic<long> alloc_count{0};
}  // namespace chimera::test

namespace {
void* counted_alloc(std::size_t n) {
    if (chimera::test::alloc_counting.load(std::memory_order_relaxed)) {
        chimera::test::alloc_count.fetch_add(1, std::memory_order_relaxed);
    }
    if (void* p = std::malloc(n ? n : 1)) return p;
    throw std::bad_alloc();
}
}  // namespace

void* operator new(std::size_t n) { return counted_alloc(n); }
void* operator new[](std::size_t n) { return counted_alloc(n); }
void operator delete(void* p) noexcept { std::free(p); }
void operator delete[](void* p) noexcept { std::free(p); }
void operator delete(void* p, std::size_t) noexcept { std::free(p); }
void operator delete[](void* p, std::size_t) noexcept { std::free(p); }
