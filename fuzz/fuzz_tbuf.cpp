// fuzz/fuzz_tbuf.cpp — tbuf::validate() over arbitrary triple-buffer images.
//
// Invariants: no crash or read outside the image, one verdict per image, a
// fault named by segment and field; and a buffer the validator accepts is one
// attach_in() accepts and both sides can use: a read is not refused as
// corrupt, a write publishes or names what it refused (the newest item's
// counter-stamp is data the validator does not bound), and the buffer
// validates again afterwards.
#include <vector>

#include "chimera/tbuf.hpp"
#include "harness.hpp"

using namespace chimera;
using fuzz::require;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const fuzz::Image image(data, size);
    if (fuzz::checked_fault("tbuf::validate", image, tbuf::validate)) return 0;
    // The validator checks bounds; whether the buffer is published yet is the
    // segment's life cycle, which attach_in() waits for or refuses.
    const auto* segment = static_cast<const ipc::SegmentHeader*>(image.data());
    if (segment->state.load() != static_cast<std::uint32_t>(ipc::SegmentState::ready)) return 0;
    // Whether a role's owner or the role lock's holder lives is not in the
    // bytes (a live buffer may name any of them): the image's are taken as
    // gone, so that taking a role over neither waits for a stranger nor
    // blocks on a lock word the fuzzer made up (ipc::lock has its own tests).
    auto* header = static_cast<tbuf::detail::Header*>(image.data());
    header->roles.owner.store(0);
    header->writer.owner.store(0);
    header->reader.owner.store(0);
    tbuf::Tbuf t;
    try {
        t = tbuf::Tbuf::attach_in(image.data(), image.size());
    } catch (const std::exception& e) {
        fuzz::broken(std::string("tbuf::validate accepted what attach_in refuses: ") + e.what());
    }
    std::vector<std::byte> item(t.item_size(), std::byte{0x5a});
    const tbuf::ReadResult r = t.read(item.data());
    require(r.status != tbuf::ReadStatus::corrupt, "a validated buffer's read refused: " + t.fault_message());
    if (t.write(item.data(), 1) == tbuf::kCorrupt)
        require(!t.fault_message().empty(), "a validated buffer's write refused without saying why");
    require(!tbuf::validate(image.data(), image.size()), "a write and a read broke a validated buffer");
    return 0;
}
