// fuzz/fuzz_mailbox.cpp — xm::validate_mailbox() over arbitrary mailbox
// images (what a sender checks on attach, and every ring's positions and
// records). Invariants: no crash or read outside the image, one verdict per
// image, a fault named by segment and field.
#include "chimera/xmail.hpp"
#include "harness.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const chimera::fuzz::Image image(data, size);
    (void)chimera::fuzz::checked_fault("xm::validate_mailbox", image, chimera::xm::validate_mailbox);  // its checks are the harness; the fault itself is not needed here
    return 0;
}
