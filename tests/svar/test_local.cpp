// Local tables: translate, single and multi-variable transfers, port sets,
// and the roll-back of a write-set interrupted by a dead lock holder.
#include "sanitizer.hpp"
#include "segment_guard.hpp"
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <unistd.h>

#include <cstring>
#include <thread>

#include "chimera/svar.hpp"
#include "layout.hpp"  // the segment layout, to stage a holder that died mid-write
#include "svar_test_util.hpp"

using namespace chimera;
using namespace chimera::svar;
using namespace svar_test;

namespace {

const char* kTable =
    "NAME NDOF\nTYPE int\nDESC joints\nUNITS none\nNELEM 1\nINIT 6\n"
    "NAME GAIN\nTYPE float\nDESC gain\nUNITS none\nNELEM 1\nINIT 2.5\n"
    "NAME Q_REF\nTYPE float\nDESC reference\nUNITS rad\nNELEM 6\n"
    "NAME Q_MEZ\nTYPE float\nDESC measured\nUNITS rad\nNELEM 6\n"
    "NAME TAU\nTYPE double\nDESC torque\nUNITS Nm\nNELEM 6\n"
    "NAME MODE\nTYPE word\nDESC mode\nUNITS none\nNELEM 1\n"
    "NAME POSE\nTYPE struct[16]\nDESC pose\nUNITS none\nNELEM 1\n"
    "EOF\n";

struct Pose {
    float x, y, z, w;
};

class SvarLocal : public ::testing::Test {
protected:
    void SetUp() override {
        name = unique_name("local");
        table = Table::create(name, parse_svar_string(kTable, "ctl.svar"));
    }
    void TearDown() override {
        // Children that attached and were killed are counted out (issue #15.2):
        // the last live user removes the table.
        EXPECT_TRUE(table.destroy());
        EXPECT_EQ(chimera::test::SegmentGuard(name.substr(1)).remove_all(), 0);
    }
    std::string name;
    Table table;
};

template <typename F>
std::string error_of(F&& body) {
    try {
        body();
    } catch (const Error& e) {
        return e.what();
    }
    return "";
}

}  // namespace

TEST_F(SvarLocal, TranslateGivesTypedPointersAndRefusesMistakes) {
    LocalTable lt(table, {"NDOF"}, {"GAIN"}, {"Q_REF", "Q_MEZ"}, {"TAU", "POSE"});
    EXPECT_EQ(lt.size(), 6u);
    std::int32_t* ndof = lt.translate<std::int32_t>("NDOF");
    EXPECT_EQ(*ndof, 6);  // the local table starts from the global values
    EXPECT_EQ(*lt.translate<float>("GAIN"), 2.5f);
    EXPECT_NE(lt.translate<double>("TAU"), nullptr);
    EXPECT_NE(lt.translate<Pose>("POSE"), nullptr);
    EXPECT_NE(lt.translate<std::byte>("POSE"), nullptr);
    EXPECT_EQ(lt.index_of(lt.translate<float>("Q_MEZ")), 3u);
    EXPECT_EQ(error_of([&] { lt.translate<double>("Q_REF"); }),
              "translate: variable Q_REF is float, not double");
    EXPECT_EQ(error_of([&] { lt.translate<std::int16_t>("NDOF"); }),
              "translate: variable NDOF is int, not short");
    EXPECT_EQ(error_of([&] { lt.translate<double[3]>("POSE"); }),
              "translate: variable POSE is struct[16], not a 24-byte struct");
    EXPECT_EQ(error_of([&] { lt.translate<float>("Q_DES"); }),
              "translate: table " + name + " has no variable Q_DES");
    EXPECT_EQ(error_of([&] { lt.translate<std::uint16_t>("MODE"); }),
              "translate: variable MODE is not one of this task's variables (not in its local "
              "table)");
    EXPECT_TRUE(lt.contains("TAU"));
    EXPECT_FALSE(lt.contains("MODE"));
}

TEST_F(SvarLocal, UnknownPortNameIsRefusedAtConstruction) {
    EXPECT_EQ(error_of([&] { LocalTable(table, {}, {}, {"Q_REF", "Q_DES"}, {}); }),
              "table " + name + " (ctl.svar) has no variable Q_DES (in the in-vars list)");
}

TEST_F(SvarLocal, SingleVariableReadWriteAndIndexVariants) {
    LocalTable a(table, {"Q_REF", "MODE"});
    LocalTable b(table, {"Q_REF", "MODE"});
    float* qa = a.translate<float>("Q_REF");
    float* qb = b.translate<float>("Q_REF");
    for (int i = 0; i < 6; ++i) qa[i] = static_cast<float>(i) + 0.5f;
    EXPECT_EQ(qb[3], 0.0f);
    EXPECT_EQ(a.write(qa), Status::ok);
    EXPECT_EQ(qb[3], 0.0f);  // b's local copy changes only when b reads
    EXPECT_EQ(b.read(qb), Status::ok);
    EXPECT_EQ(qb[3], 3.5f);
    EXPECT_EQ(a.read(qa + 1), Status::bad_argument);  // not the start of a variable
    int not_local = 0;
    EXPECT_EQ(a.read(&not_local), Status::bad_argument);
    *a.translate<std::uint16_t>("MODE") = 7;
    const std::size_t mode = table.index_of("MODE");
    EXPECT_EQ(a.write_ix(mode), Status::ok);
    EXPECT_EQ(b.read_ix(mode), Status::ok);
    EXPECT_EQ(*b.translate<std::uint16_t>("MODE"), 7);
    EXPECT_EQ(b.read_ix(table.index_of("TAU")), Status::bad_argument);  // not in b
    EXPECT_EQ(b.read_ix(1000), Status::bad_argument);
}

// read(p)/write(p) take only a translated pointer: the first element of a
// variable of this local table.
TEST_F(SvarLocal, PointersThatAreNotVariablesAreRefused) {
    LocalTable lt(table, {"Q_REF", "TAU", "POSE"});
    const auto* qref = lt.translate<float>("Q_REF");
    const auto* tau = lt.translate<double>("TAU");
    const auto* pose = lt.translate<Pose>("POSE");
    // Inside TAU (48 bytes) at a 16-byte boundary, where no variable starts.
    const void* inside = reinterpret_cast<const std::byte*>(tau) + 16;
    // Just past the last variable, and below the first.
    const void* past = reinterpret_cast<const std::byte*>(pose) + 16;
    const void* below = reinterpret_cast<const std::byte*>(qref) - 16;
    for (const void* p : {inside, past, below}) {
        EXPECT_EQ(lt.read(p), Status::bad_argument);
        EXPECT_EQ(lt.write(p), Status::bad_argument);
        EXPECT_FALSE(lt.index_of(p).has_value());
    }
    EXPECT_EQ(lt.write(nullptr), Status::bad_argument);
    EXPECT_EQ(lt.index_of(tau), table.index_of("TAU"));
    EXPECT_EQ(lt.write(tau), Status::ok);
    EXPECT_EQ(lt.read(pose), Status::ok);
}

// Every size is copied whole and nothing around it is touched: the inline
// copy of 8 to 64 bytes (overlapping 8- and 16-byte moves) and memcpy beyond.
TEST(SvarCopyVar, CopiesEveryLengthExactly) {
    alignas(16) std::byte src[160], dst[160];
    for (std::size_t n = 1; n <= 130; ++n) {
        for (std::size_t i = 0; i < sizeof src; ++i) {
            src[i] = static_cast<std::byte>(i * 7 + n);
            dst[i] = std::byte{0xEE};
        }
        detail::copy_var(dst + 8, src + 8, n);
        for (std::size_t i = 0; i < sizeof dst; ++i) {
            const bool inside = i >= 8 && i < 8 + n;
            ASSERT_EQ(dst[i], inside ? src[i] : std::byte{0xEE}) << "n " << n << " byte " << i;
        }
    }
}

TEST_F(SvarLocal, PortSetsCopyWholeSets) {
    // A controller: reads Q_REF and Q_MEZ, writes TAU; a sensor writes Q_MEZ.
    LocalTable ctl(table, {"NDOF", "GAIN"}, {}, {"Q_REF", "Q_MEZ"}, {"TAU"});
    LocalTable sensor(table, {}, {"GAIN"}, {}, {"Q_MEZ"});
    EXPECT_EQ(ctl.in_vars().size(), 2u);
    EXPECT_EQ(ctl.out_vars().size(), 1u);
    *sensor.translate<float>("GAIN") = 4.0f;
    EXPECT_EQ(sensor.copy_out_consts(), Status::ok);
    EXPECT_EQ(ctl.copy_in_consts(), Status::ok);
    EXPECT_EQ(*ctl.translate<float>("GAIN"), 4.0f);
    float* mez = sensor.translate<float>("Q_MEZ");
    for (int i = 0; i < 6; ++i) mez[i] = static_cast<float>(10 + i);
    EXPECT_EQ(sensor.copy_out_vars(), Status::ok);
    EXPECT_EQ(ctl.copy_in_vars(), Status::ok);
    EXPECT_EQ(ctl.translate<float>("Q_MEZ")[5], 15.0f);
    double* tau = ctl.translate<double>("TAU");
    tau[0] = -1.25;
    EXPECT_EQ(ctl.copy_out_vars(), Status::ok);
    double g[6];
    ASSERT_EQ(table.read(table.index_of("TAU"), g), Status::ok);
    EXPECT_EQ(g[0], -1.25);
    // copy_on reads the out-vars too: a task switched on starts from the
    // values its outputs hold now.
    tau[0] = 99.0;
    g[0] = 3.0;
    ASSERT_EQ(table.write(table.index_of("TAU"), g), Status::ok);
    EXPECT_EQ(ctl.copy_on(), Status::ok);
    EXPECT_EQ(tau[0], 3.0);
    EXPECT_EQ(ctl.copy_in_vars(), Status::ok);  // in-vars only: TAU untouched
    EXPECT_EQ(tau[0], 3.0);
}

TEST_F(SvarLocal, ExplicitSetsByNameAndIndex) {
    LocalTable lt(table, {"Q_REF", "Q_MEZ", "TAU"});
    const VarSet s = lt.make_set({"Q_REF", "TAU", "Q_REF"});
    EXPECT_EQ(s.size(), 2u);  // listed twice: copied once
    const VarSet si = lt.make_set_ix({table.index_of("Q_MEZ")});
    EXPECT_EQ(si.size(), 1u);
    EXPECT_EQ(error_of([&] { lt.make_set({"MODE"}); }),
              "local table on " + name + ": variable MODE (set) is not in this local table");
    EXPECT_THROW(lt.make_set_ix({77}), Error);
    lt.translate<float>("Q_REF")[0] = 1;
    lt.translate<double>("TAU")[5] = 2;
    EXPECT_EQ(lt.copy_to_global(s), Status::ok);
    LocalTable other(table, {"Q_REF", "TAU"});
    EXPECT_EQ(other.copy_from_global(other.make_set({"Q_REF", "TAU"})), Status::ok);
    EXPECT_EQ(other.translate<float>("Q_REF")[0], 1.0f);
    EXPECT_EQ(other.translate<double>("TAU")[5], 2.0);
}

TEST_F(SvarLocal, TimeoutTransfersNothingAndIsCounted) {
    LocalTable lt(table, {"Q_REF"});
    float* q = lt.translate<float>("Q_REF");
    q[0] = 5;
    table.set_lock_options(ipc::LockOptions{.timeout_ns = 2'000'000});
    std::atomic<int> held{0}, release{0};
    std::thread holder([&] {
        (void)ipc::lock(table.lock_word());
        held = 1;
        while (!release) std::this_thread::sleep_for(std::chrono::milliseconds(1));
        EXPECT_TRUE(ipc::unlock(table.lock_word()));
    });
    while (!held) std::this_thread::yield();
    EXPECT_EQ(lt.write(q), Status::timed_out);
    EXPECT_EQ(lt.copy_in_vars(), Status::ok);  // empty set: no lock needed
    EXPECT_EQ(table.stats().timeouts, 1u);
    release = 1;
    holder.join();
    float g[6];
    ASSERT_EQ(table.read(table.index_of("Q_REF"), g), Status::ok);
    EXPECT_EQ(g[0], 0.0f);
}

TEST_F(SvarLocal, ReentryFromTheLockHolderIsRefused) {
    LocalTable lt(table, {"Q_REF", "TAU"});
    const VarSet set = lt.make_set({"Q_REF", "TAU"});
    float* q = lt.translate<float>("Q_REF");
    ASSERT_EQ(ipc::lock(table.lock_word()), ipc::LockStatus::acquired);
    q[0] = 42.0f;
    EXPECT_EQ(lt.read(q), Status::reentered);
    EXPECT_EQ(lt.write(q), Status::reentered);
    EXPECT_EQ(lt.read_ix(table.index_of("TAU")), Status::reentered);
    EXPECT_EQ(lt.copy_from_global(set), Status::reentered);
    EXPECT_EQ(lt.copy_to_global(set), Status::reentered);
    EXPECT_EQ(q[0], 42.0f);  // nothing read
    EXPECT_TRUE(ipc::unlock(table.lock_word()));
    float g[6];
    ASSERT_EQ(table.read(table.index_of("Q_REF"), g), Status::ok);
    EXPECT_EQ(g[0], 0.0f);  // nothing written
}

// A writer that died between saving its undo record and finishing its
// write-set: the next user recovers the lock and rolls the set back.
TEST_F(SvarLocal, DeadWriterMidSetIsRolledBack) {
    CHIMERA_NOT_UNDER_TSAN("a forked writer killed");
    LocalTable lt(table, {"Q_REF", "TAU"});
    float* q = lt.translate<float>("Q_REF");
    double* tau = lt.translate<double>("TAU");
    for (int i = 0; i < 6; ++i) {
        q[i] = 1.0f;
        tau[i] = 1.0;
    }
    const VarSet set = lt.make_set({"Q_REF", "TAU"});
    ASSERT_EQ(lt.copy_to_global(set), Status::ok);  // the consistent set: all 1

    // Stage the death in a child: lock, save the undo record exactly as a
    // write does, overwrite Q_REF and half of TAU with 2, then die.
    const pid_t child = fork_child([&] {
        auto* base = static_cast<std::byte*>(static_cast<void*>(&table.lock_word())) - 64;
        auto& hdr = *reinterpret_cast<detail::TableHeader*>(base);
        auto* desc = reinterpret_cast<detail::Descriptor*>(base + hdr.desc_offset);
        if (ipc::lock(hdr.lock) != ipc::LockStatus::acquired) return 2;
        std::byte* data = base + hdr.data_offset;
        std::byte* undo = base + hdr.undo_offset;
        auto* list = reinterpret_cast<std::uint32_t*>(base + hdr.undo_index_offset);
        const std::uint32_t ix[2] = {2, 4};  // Q_REF, TAU
        for (int i = 0; i < 2; ++i) {
            std::memcpy(undo + desc[ix[i]].data_offset, data + desc[ix[i]].data_offset,
                        desc[ix[i]].bytes);
            list[i] = ix[i];
        }
        hdr.undo_count = 2;
        hdr.undo_active.store(1);
        auto* gq = reinterpret_cast<float*>(data + desc[2].data_offset);
        auto* gt = reinterpret_cast<double*>(data + desc[4].data_offset);
        for (int i = 0; i < 6; ++i) gq[i] = 2.0f;
        for (int i = 0; i < 3; ++i) gt[i] = 2.0;
        raise(SIGKILL);
        return 0;
    });
    EXPECT_EQ(wait_child(child), 128 + SIGKILL);
    for (int i = 0; i < 6; ++i) {
        q[i] = 0;
        tau[i] = 0;
    }
    EXPECT_EQ(lt.copy_from_global(set), Status::recovered);
    for (int i = 0; i < 6; ++i) {
        EXPECT_EQ(q[i], 1.0f) << i;
        EXPECT_EQ(tau[i], 1.0) << i;
    }
    EXPECT_EQ(table.stats().recoveries, 1u);
    EXPECT_EQ(table.stats().rollbacks, 1u);
    EXPECT_EQ(lt.copy_from_global(set), Status::ok);  // back to normal
}

// A writer that dies inside the uncontended inline write path, after its undo
// record is marked active and part of its set is written: the child's mapping
// of the page holding V2 is made read-only, so its store into V2 faults. The
// next user recovers the lock and rolls the set back to the last complete one.
// The padding keeps V1, V2, the header and the undo area on different pages.
TEST(SvarLocalDeath, WriterDyingInsideTheInlinePathIsRolledBack) {
    CHIMERA_NOT_UNDER_TSAN("forked writers killed");
    const std::string name = unique_name("inline");
    const char* text =
        "NAME V1\nTYPE float\nDESC v1\nUNITS none\nNELEM 6\n"
        "NAME PAD1\nTYPE struct[8192]\nDESC pad\nUNITS none\nNELEM 1\n"
        "NAME V2\nTYPE double\nDESC v2\nUNITS none\nNELEM 6\n"
        "NAME PAD2\nTYPE struct[8192]\nDESC pad\nUNITS none\nNELEM 1\n"
        "EOF\n";
    Table table = Table::create(name, parse_svar_string(text, "inline.svar"));
    auto* base = reinterpret_cast<std::byte*>(&table.lock_word()) - 64;
    const auto& hdr = *reinterpret_cast<const detail::TableHeader*>(base);
    const auto* desc = reinterpret_cast<const detail::Descriptor*>(base + hdr.desc_offset);
    const auto page = static_cast<std::uintptr_t>(sysconf(_SC_PAGESIZE));
    const auto page_of = [&](std::uint64_t off) {
        return (reinterpret_cast<std::uintptr_t>(base) + off) / page;
    };
    const std::uint64_t v1 = hdr.data_offset + desc[0].data_offset;
    const std::uint64_t v2 = hdr.data_offset + desc[2].data_offset;
    const std::uint64_t v2_end = v2 + desc[2].bytes - 1;
    for (std::uint64_t other : {std::uint64_t{0}, std::uint64_t{64}, hdr.undo_index_offset,
                                v1, hdr.undo_offset + desc[0].data_offset,
                                hdr.undo_offset + desc[2].data_offset + desc[2].bytes - 1}) {
        ASSERT_NE(page_of(other), page_of(v2));
        ASSERT_NE(page_of(other), page_of(v2_end));
    }
    LocalTable reader(table, {"V1", "V2"});
    const VarSet rset = reader.make_set({"V1", "V2"});
    auto write_all = [&](float value) {  // a complete set, left in the table
        LocalTable lt(table, {"V1", "V2"});
        for (int i = 0; i < 6; ++i) {
            lt.translate<float>("V1")[i] = value;
            lt.translate<double>("V2")[i] = value;
        }
        return lt.copy_to_global(lt.make_set({"V1", "V2"}));
    };
    auto die_writing = [&](bool whole_set) {
        return fork_child([&] {
            prctl(PR_SET_DUMPABLE, 0);  // no core file for the fault below
            signal(SIGSEGV, SIG_DFL);   // the fault kills (a sanitizer's handler would exit instead)
            LocalTable w(table, {"V1", "V2"});
            const VarSet set = w.make_set({"V1", "V2"});
            for (int i = 0; i < 6; ++i) {
                w.translate<float>("V1")[i] = 2.0f;
                w.translate<double>("V2")[i] = 2.0;
            }
            const std::uintptr_t first = page_of(v2) * page;
            const std::uintptr_t len = (page_of(v2_end) + 1) * page - first;
            if (mprotect(reinterpret_cast<void*>(first), len, PROT_READ) != 0) return 2;
            if (whole_set)
                (void)w.copy_to_global(set);  // V1 written, then the store into V2 faults
            else
                (void)w.write(w.translate<double>("V2"));
            return 3;
        });
    };
    // Each round starts from a new complete set, so an undo area left over
    // from an earlier write would restore the wrong values.
    for (const bool whole_set : {true, false}) {
        SCOPED_TRACE(whole_set ? "copy_to_global" : "write");
        const float complete = whole_set ? 1.0f : 3.0f;
        ASSERT_EQ(write_all(complete), Status::ok);
        const std::uint32_t rollbacks = table.stats().rollbacks;
        ASSERT_EQ(wait_child(die_writing(whole_set)), 128 + SIGSEGV);
        EXPECT_EQ(reader.copy_from_global(rset), Status::recovered);
        EXPECT_EQ(table.stats().rollbacks, rollbacks + 1);
        for (int i = 0; i < 6; ++i) {
            EXPECT_EQ(reader.translate<float>("V1")[i], complete) << i;
            EXPECT_EQ(reader.translate<double>("V2")[i], complete) << i;
        }
        EXPECT_EQ(reader.copy_from_global(rset), Status::ok);  // back to normal
    }
    table.destroy();
}

// A reader that died holding the lock: recovered, nothing to roll back.
TEST_F(SvarLocal, DeadReaderIsRecoveredWithoutRollback) {
    CHIMERA_NOT_UNDER_TSAN("a forked reader killed");
    const pid_t child = fork_child([&] {
        Table t = Table::attach(name);
        if (ipc::lock(t.lock_word()) != ipc::LockStatus::acquired) return 2;
        raise(SIGKILL);
        return 0;
    });
    EXPECT_EQ(wait_child(child), 128 + SIGKILL);
    LocalTable lt(table, {"GAIN"});  // construction copies under the lock: recovers it
    EXPECT_EQ(*lt.translate<float>("GAIN"), 2.5f);
    EXPECT_EQ(table.stats().recoveries, 1u);
    EXPECT_EQ(table.stats().rollbacks, 0u);
    EXPECT_EQ(lt.read(lt.translate<float>("GAIN")), Status::ok);
}
