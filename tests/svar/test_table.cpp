// The global table: create from a file, attach, descriptors, destroy.
#include <gtest/gtest.h>

#include <cstring>

#include "chimera/cfg.hpp"
#include "chimera/svar.hpp"
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
