// A watcher's table (issue 16.7, docs/permissions.md): read-only, never takes
// the table lock (so never delays a task), copies only what no write ran
// through, writes nothing, and is not a user of the segment.
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <thread>

#include "chimera/cfg.hpp"
#include "chimera/ipc/lock.hpp"
#include "chimera/svar.hpp"
#include "layout.hpp"  // the write sequence counter, to hold a write open
#include "svar_test_util.hpp"

using namespace chimera;
using namespace chimera::svar;
using namespace svar_test;

namespace {

const char* kVars =
    "NAME POS\nTYPE double\nDESC position\nUNITS m\nNELEM 8\nINIT 1 1 1 1 1 1 1 1\n"
    "NAME COUNT\nTYPE int\nDESC count\nUNITS none\nNELEM 1\nINIT 5\n"
    "EOF\n";

}  // namespace

TEST(SvarWatch, AWatcherReadsWhileTheTableLockIsHeldAndWritesNothing) {
    const std::string name = unique_name("watch");
    Table owner = Table::create(name, parse_svar_string(kVars, "w.svar"));
    Table w = Table::watch(name);
    EXPECT_TRUE(w.read_only());
    EXPECT_FALSE(owner.read_only());
    ASSERT_EQ(w.size(), 2u);
    EXPECT_EQ(w.var("POS").units(), "m");

    // This thread holds the table lock (between two transfers, no write
    // open): a locked read would answer `reentered`; the watcher's copies.
    ASSERT_TRUE(ipc::holds(ipc::lock(owner.lock_word())));
    int count = 0;
    EXPECT_EQ(owner.read(owner.index_of("COUNT"), &count), Status::reentered);
    EXPECT_EQ(w.read(w.index_of("COUNT"), &count), Status::ok);
    EXPECT_EQ(count, 5);
    EXPECT_TRUE(ipc::unlock(owner.lock_word()));

    const int six = 6;
    EXPECT_EQ(w.write(w.index_of("COUNT"), &six), Status::read_only);
    EXPECT_EQ(owner.read(owner.index_of("COUNT"), &count), Status::ok);
    EXPECT_EQ(count, 5);
    w.set_illegal_configuration(1);  // ignored: a watcher's mapping is PROT_READ
    EXPECT_EQ(owner.illegal_configuration(), 0u);
    EXPECT_THROW(LocalTable(w, std::vector<std::string>{"POS"}), Error);
    EXPECT_EQ(std::string(to_string(Status::read_only)),
              "permission denied: the table is watched read-only (only its owner writes)");

    EXPECT_TRUE(owner.destroy());  // the watcher is not a user: it keeps nothing alive
    EXPECT_FALSE(ipc::Segment::exists(name));
}

// A write in progress (the write sequence odd, as between undo_mark and
// undo_clear): the watcher gives up after its timeout rather than copy half
// of it, and reads again once the write is done.
TEST(SvarWatch, AWriteInProgressIsNeverCopiedHalfWritten) {
    const std::string name = unique_name("open");
    Table owner = Table::create(name, parse_svar_string(kVars, "w.svar"));
    TableOptions quick;
    quick.lock.timeout_ns = 5'000'000;
    Table w = Table::watch(name, quick);
    ipc::Segment raw = ipc::Segment::attach(name, {ipc::ObjectType::svar_table, kLayoutVersion});
    auto& h = *static_cast<detail::TableHeader*>(raw.base());
    double pos[8];
    detail::undo_mark(h, 0, 1);
    EXPECT_EQ(w.read(w.index_of("POS"), pos), Status::timed_out);
    detail::undo_clear(h);
    EXPECT_EQ(w.read(w.index_of("POS"), pos), Status::ok);
    EXPECT_EQ(pos[7], 1.0);
    raw.detach();
    owner.destroy();
}

// A task writes POS (8 doubles, all equal) as fast as it can through its
// local table; a watcher never sees two different values in one copy.
TEST(SvarWatch, AWatcherNeverSeesATornWrite) {
    const std::string name = unique_name("torn");
    Table owner = Table::create(name, parse_svar_string(kVars, "w.svar"));
    Table w = Table::watch(name);
    std::atomic<bool> stop{false};
    std::thread writer([&] {
        LocalTable lt(owner, std::vector<std::string>{"POS"});
        double* pos = lt.translate<double>("POS");
        for (double k = 2; !stop.load(std::memory_order_relaxed); ++k) {
            for (int i = 0; i < 8; ++i) pos[i] = k;
            if (lt.write(pos) != Status::ok) return;
        }
    });
    const std::size_t ix = w.index_of("POS");
    int torn = 0, read = 0;
    const auto end = std::chrono::steady_clock::now() + std::chrono::milliseconds(300);
    while (std::chrono::steady_clock::now() < end) {
        double v[8];
        if (w.read(ix, v) != Status::ok) continue;
        ++read;
        for (int i = 1; i < 8; ++i)
            if (v[i] != v[0]) ++torn;
    }
    stop = true;
    writer.join();
    EXPECT_GT(read, 0);
    EXPECT_EQ(torn, 0);
    owner.destroy();
}
