// fuzz/fuzz_msg.cpp — msg::validate_geometry() and msg::validate() over
// arbitrary message-queue images.
//
// Invariants: no crash or read outside the image, one verdict per image, a
// fault named by segment and field; validate() implies validate_geometry().
// validate() checks bounds (every link and chain inside the queue), not every
// invariant check() adds (ownership, states, order), so on a queue it
// accepts: Queue::bind() succeeds and receive and send never crash or block;
// and a queue check() finds consistent is never refused as corrupt and stays
// consistent (check() and validate() accept it after).
#include <vector>

#include "chimera/msg.hpp"
#include "harness.hpp"

using namespace chimera;
using fuzz::require;

namespace {

void use_queue(const fuzz::Image& image) {
    auto* q = static_cast<msg::layout::QueueHeader*>(image.data());
    // Nobody holds the lock of a copy: one a dead or live holder left in the
    // image would only make this process wait for it.
    new (&q->mutex) ipc::LockWord{};
    msg::Queue queue;
    try {
        queue = msg::Queue::bind(image.data(), image.size());
    } catch (const std::exception& e) {
        fuzz::broken(std::string("msg::validate accepted what bind refuses: ") + e.what());
    }
    const bool consistent = queue.check().empty();
    std::vector<std::byte> buffer(std::size_t{q->blknum} * q->blksize);
    for (std::uint32_t i = 0; i <= q->blknum; ++i) {
        const xm::Status s = queue.receive(buffer.data(), buffer.size(), nullptr, 0);
        require(!consistent || s != xm::Status::corrupt, "a consistent queue's receive refused as corrupt");
        if (s != xm::Status::ok) break;
    }
    const xm::Status sent = queue.send("fuzz", 4, 1, 1, 0);
    require(!consistent || sent != xm::Status::corrupt, "a consistent queue's send refused as corrupt");
    // An inconsistent queue may be left with a link the next operation
    // refuses (every operation checks each link it follows); the sanitizers
    // say whether anything was read or written outside the image meanwhile.
    if (!consistent) return;
    if (const ipc::Fault f = msg::validate(image.data(), image.size()))
        fuzz::broken("receive and send left a consistent queue refused by validate(): " + ipc::describe("image", f));
    const std::string after = queue.check();
    require(after.empty(), "receive and send broke a consistent queue: " + after);
    queue.detach();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const fuzz::Image image(data, size);
    const bool geometry_ok = !fuzz::checked_fault("msg::validate_geometry", image, msg::validate_geometry);
    const bool queue_ok = !fuzz::checked_fault("msg::validate", image, msg::validate);
    require(geometry_ok || !queue_ok, "msg::validate accepted a geometry validate_geometry refuses");
    if (queue_ok) use_queue(image);
    return 0;
}
