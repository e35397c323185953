// The global table: create from a file, attach, descriptors, destroy.
#include <gtest/gtest.h>

#include <cstring>
#include <functional>
#include <vector>

#include "chimera/cfg.hpp"
#include "chimera/svar.hpp"
#include "layout.hpp"  // the segment layout, to corrupt it
#include "sanitizer.hpp"
#include "svar_test_util.hpp"

using namespace chimera;
using namespace chimera::svar;
using namespace svar_test;

namespace {

const char* kSmall =
    "DEFINE N 3\n"
    "NAME POS\nTYPE double\nDESC position\nUNITS m\nNELEM N\nINIT 1 2\nMIN -5 -5 -5\nMAX 5 5 5\n"
    "NAME COUNT\nTYPE int\nDESC count\nUNITS none\nNELEM 1\nINIT -7\n"
    "NAME FLAGS\nTYPE byte\nDESC flags\nUNITS\nNELEM 4\n"
    "NAME BLOB\nTYPE struct[12]\nDESC opaque\nUNITS none\nNELEM 2\n"
    "EOF\n";

}  // namespace

TEST(SvarTable, CreateFromThesisSampleAndAttachByName) {
    const std::string name = unique_name("thesis");
    Table t = Table::create(name, data_file("thesis_sample_fixed.svar"));
    EXPECT_EQ(t.size(), 4u);
    EXPECT_EQ(t.source_file(), data_file("thesis_sample_fixed.svar"));
    Table a = Table::attach(name);
    ASSERT_EQ(a.size(), 4u);
    const VarInfo q = a.var("Q_REF");
    EXPECT_EQ(q.index(), 0u);
    EXPECT_EQ(q.name(), "Q_REF");
    EXPECT_EQ(q.type(), Type::double_);
    EXPECT_EQ(q.nelem(), 7u);
    EXPECT_EQ(q.bytes(), 56u);
    EXPECT_EQ(q.desc(), "reference joint position");
    EXPECT_EQ(q.units(), "radians");
    EXPECT_TRUE(q.has_range());
    EXPECT_DOUBLE_EQ(q.init(0), -3.141592653589793);
    EXPECT_DOUBLE_EQ(q.min(4), -6.283185307179586);
    EXPECT_DOUBLE_EQ(q.max(6), 6.283185307179586);
    // INIT applied at creation
    double v[7];
    EXPECT_EQ(a.read(0, v), Status::ok);
    EXPECT_DOUBLE_EQ(v[0], -3.141592653589793);
    EXPECT_DOUBLE_EQ(v[2], 6.283185307179586);
    EXPECT_DOUBLE_EQ(v[5], -3.141592653589793);
    const VarInfo sg = a.var("SG_MEZ");
    EXPECT_EQ(sg.index(), 2u);
    EXPECT_EQ(sg.type(), Type::int_);
    EXPECT_DOUBLE_EQ(sg.min(7), -1000);
    EXPECT_DOUBLE_EQ(sg.max(0), 1000);
    const VarInfo traj = a.var("TRAJ_REF");
    EXPECT_EQ(traj.type(), Type::struct_);
    EXPECT_EQ(traj.elem_size(), 32u);
    EXPECT_EQ(traj.bytes(), 128u);
    EXPECT_FALSE(traj.has_range());
    a.detach();
    EXPECT_TRUE(t.destroy());
    EXPECT_FALSE(ipc::Segment::exists(name));
}

TEST(SvarTable, InitZerosAndTypedValues) {
    const std::string name = unique_name("init");
    Table t = Table::create(name, parse_svar_string(kSmall, "small.svar"));
    double pos[3];
    ASSERT_EQ(t.read(t.index_of("POS"), pos), Status::ok);
    EXPECT_EQ(pos[0], 1.0);
    EXPECT_EQ(pos[1], 2.0);
    EXPECT_EQ(pos[2], 0.0);  // fewer INIT values than NELEM: the rest are 0
    std::int32_t count = 0;
    ASSERT_EQ(t.read(t.index_of("COUNT"), &count), Status::ok);
    EXPECT_EQ(count, -7);
    std::uint8_t flags[4] = {9, 9, 9, 9};
    ASSERT_EQ(t.read(t.index_of("FLAGS"), flags), Status::ok);
    EXPECT_EQ(flags[0] | flags[1] | flags[2] | flags[3], 0);  // no INIT: zero
    unsigned char blob[24];
    std::memset(blob, 0xff, sizeof blob);
    ASSERT_EQ(t.read(t.index_of("BLOB"), blob), Status::ok);
    for (unsigned char b : blob) EXPECT_EQ(b, 0);
    EXPECT_FALSE(t.var("COUNT").has_range());
    EXPECT_EQ(t.var("COUNT").min(0), 0.0);
    EXPECT_EQ(t.var("FLAGS").units(), "");
    t.destroy();
}

TEST(SvarTable, UnknownNameIsASetUpError) {
    const std::string name = unique_name("unknown");
    Table t = Table::create(name, parse_svar_string(kSmall, "small.svar"));
    try {
        t.index_of("VEL");
        FAIL() << "no error";
    } catch (const Error& e) {
        EXPECT_EQ(std::string(e.what()), "table " + name + " (small.svar) has no variable VEL");
    }
    EXPECT_EQ(t.read(99, nullptr), Status::bad_argument);
    t.destroy();
}

TEST(SvarTable, BadFileLeavesNoSegmentBehind) {
    const std::string name = unique_name("bad");
    EXPECT_THROW(Table::create(name, data_file("thesis_sample.svar")), cfg::ParseError);
    EXPECT_FALSE(ipc::Segment::exists(name));
    EXPECT_THROW(Table::create(name, "/nonexistent.svar"), cfg::ParseError);
    EXPECT_FALSE(ipc::Segment::exists(name));
}

TEST(SvarTable, CreateTwiceFailsAndKeepsTheFirst) {
    const std::string name = unique_name("twice");
    Table t = Table::create(name, parse_svar_string(kSmall, "small.svar"));
    EXPECT_THROW(Table::create(name, parse_svar_string(kSmall, "small.svar")), ipc::SegmentError);
    EXPECT_TRUE(ipc::Segment::exists(name));
    EXPECT_EQ(Table::attach(name).size(), 4u);
    t.destroy();
}

TEST(SvarTable, AttachFromAnotherProcessAndDestroyByTheLastUser) {
    CHIMERA_NOT_UNDER_TSAN("a forked user");
    const std::string name = unique_name("procs");
    Table t = Table::create(name, parse_svar_string(kSmall, "small.svar"));
    const pid_t child = fork_child([&] {
        Table a = Table::attach(name);
        double pos[3] = {7, 8, 9};
        if (a.write(a.index_of("POS"), pos) != Status::ok) return 2;
        a.set_illegal_configuration(1);
        return a.destroy() ? 3 : 0;  // the parent still uses it
    });
    ASSERT_EQ(wait_child(child), 0);
    double pos[3];
    ASSERT_EQ(t.read(0, pos), Status::ok);
    EXPECT_EQ(pos[2], 9.0);
    EXPECT_EQ(t.illegal_configuration(), 1u);
    t.set_illegal_configuration(0);
    EXPECT_EQ(t.illegal_configuration(), 0u);
    EXPECT_TRUE(t.destroy());
    EXPECT_FALSE(ipc::Segment::exists(name));
    try {
        Table::attach(name);
        FAIL() << "attached to a destroyed table";
    } catch (const ipc::SegmentError& e) {
        EXPECT_EQ(std::string(e.what()), "segment " + name + ": does not exist");
    }
}

TEST(SvarTable, AttachRefusesAnotherObjectType) {
    const std::string name = unique_name("other");
    ipc::Segment s = ipc::Segment::create(name, 4096, {ipc::ObjectType::tbuf, 1});
    s.publish();
    try {
        Table::attach(name);
        FAIL() << "attached to a tbuf";
    } catch (const ipc::SegmentError& e) {
        EXPECT_EQ(std::string(e.what()), "segment " + name + ": holds a tbuf, expected a svar_table");
    }
    s.detach_destroy_if_last();
}

// --- memory another process writes is bounded before use (issue #15.3) ------------

// Every offset and length of the header and of a descriptor, corrupted in a
// live table by "another process": attach refuses it, naming the segment and
// the field; a handle attached before keeps what it checked and reads on.
TEST(SvarTable, CorruptOffsetsAndLengthsAreRefusedNamingTheSegment) {
    const std::string name = unique_name("bad");
    Table t = Table::create(name, parse_svar_string(kSmall, "small.svar"));
    Table before = Table::attach(name);
    ipc::Segment raw = ipc::Segment::attach(name, {ipc::ObjectType::svar_table, kLayoutVersion});
    auto& h = *static_cast<detail::TableHeader*>(raw.base());
    auto* d = reinterpret_cast<detail::Descriptor*>(static_cast<std::byte*>(raw.base()) + h.desc_offset);
    const std::uint64_t huge = std::uint64_t{1} << 40;
    struct Case {
        const char* field;
        std::function<void(bool)> corrupt;  // true: corrupt, false: restore
    };
    auto u64 = [](std::uint64_t& f, std::uint64_t bad) {
        return [&f, bad, good = f](bool on) mutable { f = on ? bad : good; };
    };
    auto u32 = [](std::uint32_t& f, std::uint32_t bad) {
        return [&f, bad, good = f](bool on) mutable { f = on ? bad : good; };
    };
    const Case cases[] = {
        {"nvars", u32(h.nvars, 0)},
        {"descriptors end", u32(h.nvars, 1u << 30)},
        {"descriptors end", u64(h.desc_offset, huge)},
        {"undo list offset", u64(h.undo_index_offset, huge)},
        {"data end", u64(h.data_bytes, huge)},
        {"undo data end", u64(h.undo_offset, h.undo_offset + 64 * 1024)},
        {"source name end", u32(h.source_len, 1u << 31)},
        {"variable name length", [&, saved = std::string(d[1].name)](bool on) {
             std::memset(d[1].name, on ? 'X' : 0, sizeof d[1].name);  // no NUL in the field
             if (!on) std::memcpy(d[1].name, saved.data(), saved.size());
         }},
        {"variable type", u32(d[0].type, 99)},
        {"variable element size", u32(d[0].elem_size, 3)},
        {"variable bytes", u64(d[0].bytes, 1u << 20)},
        {"variable bytes", u32(d[2].nelem, 1u << 31)},
        {"variable data offset", u64(d[1].data_offset, 8)},
        {"variable data end", u64(d[1].data_offset, huge)},
        {"variable INIT/MIN/MAX offset", u64(d[0].init_offset, huge)},
        {"variable INIT/MIN/MAX offset", u64(d[0].max_offset, raw.size() - 8)},
        {"variable DESC end", u64(d[3].desc_offset, huge)},
        {"variable UNITS end", u32(d[3].units_len, 1u << 31)},
    };
    std::vector<double> pos(3);
    for (const Case& c : cases) {
        c.corrupt(true);
        try {
            Table::attach(name);
            ADD_FAILURE() << c.field << ": attached";
        } catch (const Error& e) {
            const std::string what = e.what();
            EXPECT_NE(what.find("segment " + name + ": " + c.field), std::string::npos) << what;
        }
        EXPECT_TRUE(validate_table(raw.base(), raw.size())) << c.field;
        // The handle attached before uses the descriptors it copied.
        EXPECT_EQ(before.read(before.index_of("POS"), pos.data()), Status::ok) << c.field;
        EXPECT_EQ(pos[1], 2.0);
        EXPECT_EQ(before.var("BLOB").bytes(), 24u);
        c.corrupt(false);
        ASSERT_FALSE(validate_table(raw.base(), raw.size())) << "not restored: " << c.field;
    }
    // An undo record a dead writer left with indices past the table: refused on
    // attach, and a recovery that rolls it back skips them.
    h.undo_count = 2;
    auto* list = reinterpret_cast<std::uint32_t*>(static_cast<std::byte*>(raw.base()) + h.undo_index_offset);
    list[0] = 1000;
    list[1] = 0;
    h.undo_active.store(1);
    EXPECT_NE(std::string(validate_table(raw.base(), raw.size()).field), "");
    h.undo_active.store(0);
    raw.detach();
    before.detach();
    EXPECT_TRUE(t.destroy());
}
