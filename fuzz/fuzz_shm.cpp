// fuzz/fuzz_shm.cpp — shm::validate() over arbitrary segment images (what
// shmAttach checks). Invariants: no crash or read outside the image, one
// verdict per image, a fault named by segment and field.
#include "chimera/shm.hpp"
#include "harness.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const chimera::fuzz::Image image(data, size);
    (void)chimera::fuzz::checked_fault("shm::validate", image, chimera::shm::validate);  // its checks are the harness; the fault itself is not needed here
    return 0;
}
