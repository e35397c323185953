// fuzz/fuzz_sem.cpp — sem::validate() over arbitrary semaphore images.
//
// Invariants: no crash or read outside the image, one verdict per image, a
// fault named by segment and field; and what the validator accepts,
// Semaphore::bind() (the checks of semAttach) accepts too.
#include "chimera/sem.hpp"
#include "harness.hpp"

using namespace chimera;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const fuzz::Image image(data, size);
    if (fuzz::checked_fault("sem::validate", image, sem::validate)) return 0;
    fuzz::require(image.size() >= sem::Semaphore::memory_size(), "sem::validate accepted a short image");
    if (image.size() != sem::Semaphore::memory_size()) return 0;  // bind() takes memory of exactly that size
    try {
        const sem::Semaphore s = sem::Semaphore::bind(image.data());
        fuzz::require(s.valid(), "bind gave no semaphore");
    } catch (const std::exception& e) {
        fuzz::broken(std::string("sem::validate accepted what bind refuses: ") + e.what());
    }
    return 0;
}
