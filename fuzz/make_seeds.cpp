// fuzz/make_seeds.cpp — the seed images of the shared-memory validator
// harnesses, made by the services themselves, and the check that the
// committed ones are still images the validators accept.
//
//   make_seeds OUTDIR           writes OUTDIR/<harness>/valid-*.img
//   make_seeds --check CORPUS   every CORPUS/<harness>/valid-* is accepted by
//                               its validator (fails naming the file: after a
//                               layout change, run make_seeds fuzz/corpus)
//
// Each image is a live object's bytes: a table laid out from a .svar, a
// triple buffer after writes and a read, semaphores with units taken, queues
// holding messages (FIFO and HPF), a shared segment, a mailbox whose ring
// holds records from a sender.
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "chimera/ipc/fault.hpp"
#include "chimera/msg.hpp"
#include "chimera/sem.hpp"
#include "chimera/shm.hpp"
#include "chimera/svar.hpp"
#include "chimera/tbuf.hpp"
#include "chimera/xmail.hpp"

using namespace chimera;
namespace fs = std::filesystem;

namespace {

using Validator = ipc::Fault (*)(const void*, std::size_t) noexcept;

struct Harness {
    const char* folder;
    Validator validate;
};

const Harness kHarnesses[] = {
    {"svar_table", svar::validate_table}, {"tbuf", tbuf::validate}, {"shm", shm::validate},
    {"sem", sem::validate},               {"msg", msg::validate},   {"mailbox", xm::validate_mailbox},
};

struct FreeAligned {
    void operator()(void* p) const noexcept { std::free(p); }
};
using Memory = std::unique_ptr<void, FreeAligned>;

Memory aligned(std::size_t size) {
    const std::size_t rounded = (size + 64) / 64 * 64;
    void* p = std::aligned_alloc(64, rounded);
    std::memset(p, 0, rounded);
    return Memory(p);
}

class Writer {
public:
    explicit Writer(fs::path root) : root_(std::move(root)) {}
    void save(const char* folder, const std::string& name, const void* bytes, std::size_t size) {
        fs::create_directories(root_ / folder);
        const fs::path path = root_ / folder / ("valid-" + name + ".img");
        std::ofstream(path, std::ios::binary)
            .write(static_cast<const char*>(bytes), static_cast<std::streamsize>(size));
        std::printf("%s (%zu bytes)\n", path.c_str(), size);
    }
    void save_segment(const char* folder, const std::string& name, const std::string& segment) {
        std::ifstream in("/dev/shm" + segment, std::ios::binary);
        if (!in) throw std::runtime_error("cannot read /dev/shm" + segment);
        const std::vector<char> bytes{std::istreambuf_iterator<char>(in), {}};
        save(folder, name, bytes.data(), bytes.size());
    }

private:
    fs::path root_;
};

constexpr const char* kSvar = R"(# every kind of variable: typed with INIT, MIN/MAX, a struct
NAME Q_REF
TYPE double
DESC joint reference
UNITS rad
NELEM 3
INIT 0.5 -1 2
MIN -3.1 -3.1 -3.1
MAX 3.1 3.1 3.1
NAME MODE
TYPE int
DESC mode word
UNITS
NELEM 1
INIT 2
NAME RAW
TYPE struct[12]
DESC raw frame
UNITS bytes
NELEM 2
NAME GAIN
TYPE float
DESC gain
UNITS 1
NELEM 2
EOF
)";

void table(Writer& out, const std::string& sys) {
    const std::string name = "/chimera." + sys + ".svar";
    svar::Table t = svar::Table::create(name, svar::parse_svar_string(kSvar, "seeds.svar"));
    const double q[3] = {1, 2, 3};
    if (t.write(t.index_of("Q_REF"), q) != svar::Status::ok) throw std::runtime_error("table write failed");
    out.save_segment("svar_table", "four-kinds", name);
    t.destroy();
}

void triple_buffer(Writer& out) {
    const std::size_t size = tbuf::required_size(24);
    Memory m = aligned(size);
    tbuf::Tbuf writer = tbuf::Tbuf::create_in(m.get(), size, 24);
    tbuf::Tbuf reader = tbuf::Tbuf::attach_in(m.get(), size);
    char item[24] = "item";
    out.save("tbuf", "empty", m.get(), size);
    bool ok = true;
    for (int i = 0; i < 3; ++i) ok = ok && writer.write(item, 100 + i) != tbuf::kCorrupt;
    ok = ok && reader.read(item).status == tbuf::ReadStatus::fresh;
    ok = ok && writer.write(item, 200) != tbuf::kCorrupt;
    if (!ok) throw std::runtime_error("make_seeds: the TBUF seed was not written and read as intended");
    out.save("tbuf", "written-read-written", m.get(), size);
}

void semaphores(Writer& out) {
    const std::size_t size = sem::Semaphore::memory_size();
    Memory binary = aligned(size), counting = aligned(size);
    sem::Semaphore b = sem::Semaphore::over(binary.get(), sem::Kind::binary, 1, "seed:bin");
    sem::Semaphore c = sem::Semaphore::over(counting.get(), sem::Kind::counting, 5, "seed:count");
    if (c.try_p() != xm::Status::ok || c.try_p() != xm::Status::ok) throw std::runtime_error("sem P failed");
    out.save("sem", "binary", binary.get(), size);
    out.save("sem", "counting-taken", counting.get(), size);
}

void queue(Writer& out, msg::Policy policy, const char* name) {
    const msg::Params params{8, 16, policy};
    const std::size_t size = msg::Queue::memory_size(params);
    Memory m = aligned(size);
    msg::Queue q = msg::Queue::over(m.get(), size, params, std::string("seed:") + name);
    const char text[40] = "a message longer than one block of 16";
    for (int i = 0; i < 4; ++i)
        if (q.send(text, static_cast<std::size_t>(5 + 10 * i), static_cast<std::uint32_t>(i), i % 3, 0) !=
            xm::Status::ok)
            throw std::runtime_error("msg send failed");
    char buf[128];
    if (q.receive(buf, sizeof buf, nullptr, 0) != xm::Status::ok) throw std::runtime_error("msg receive failed");
    out.save("msg", name, m.get(), size);
    q.detach();
}

void shared_memory_and_mailbox(Writer& out, const std::string& sys) {
    const xm::MailboxConfig small{2, 2, 256, 3};
    {
        xm::Rtpu host(sys, "host", 0);
        shm::Segment s = shm::Segment::create(host, "host:area", 100);
        std::memset(s.data(), 0x42, 100);
        out.save_segment("shm", "area-100", host.attach_object("host:area", ipc::ObjectType::xmail_shm).segment);
        s.detach();
    }
    xm::Mailbox a(sys, "a", 0, small), b(sys, "b", 1, small);
    xm::Peer& to_b = a.peer("b");
    for (const char* m : {"hello", "a second, longer record", "3"})
        if (a.write(to_b, m, std::strlen(m)) != xm::Status::ok) throw std::runtime_error("mailbox write failed");
    char buf[64];
    if (b.read(buf, sizeof buf) != xm::Status::ok) throw std::runtime_error("mailbox read failed");
    out.save("mailbox", "two-records-queued", &b.header(), xm::layout::mailbox_size(small));
}

int check(const fs::path& corpus) {
    int bad = 0, checked = 0;
    for (const Harness& h : kHarnesses) {
        if (!fs::is_directory(corpus / h.folder)) continue;
        for (const auto& e : fs::directory_iterator(corpus / h.folder)) {
            if (e.path().filename().string().rfind("valid-", 0) != 0) continue;
            std::ifstream in(e.path(), std::ios::binary);
            const std::vector<char> bytes{std::istreambuf_iterator<char>(in), {}};
            Memory m = aligned(bytes.size());
            std::memcpy(m.get(), bytes.data(), bytes.size());
            ++checked;
            if (const ipc::Fault f = h.validate(m.get(), bytes.size())) {
                std::fprintf(stderr,
                             "%s: not valid any more: %s (after a layout change, regenerate: make_seeds fuzz/corpus)\n",
                             e.path().c_str(), ipc::describe(e.path().filename().string(), f).c_str());
                ++bad;
            }
        }
    }
    std::printf("%d valid seed images checked, %d refused\n", checked, bad);
    return bad || checked == 0 ? 1 : 0;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc == 3 && std::string(argv[1]) == "--check") return check(argv[2]);
    if (argc != 2) {
        std::fprintf(stderr, "usage: %s OUTDIR | --check CORPUS\n", argv[0]);
        return 2;
    }
    try {
        Writer out(argv[1]);
        const std::string sys = "fzseed" + std::to_string(getpid());
        table(out, sys);
        triple_buffer(out);
        semaphores(out);
        queue(out, msg::Policy::fifo, "fifo-three-queued");
        queue(out, msg::Policy::hpf, "hpf-three-queued");
        shared_memory_and_mailbox(out, sys);
    } catch (const std::exception& e) {
        std::fprintf(stderr, "make_seeds: %s\n", e.what());
        return 1;
    }
    return check(argv[1]);
}
