// Helper process for the multi-process xmail tests (started with fork+exec).
// Usage: xm_helper COMMAND SYS RTPU BID ARGS...   Prints results on stdout.
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "chimera/ipc/segment.hpp"
#include "chimera/msg.hpp"
#include "chimera/sem.hpp"
#include "chimera/shm.hpp"
#include "chimera/xmail.hpp"
#include "kill_log.hpp"

using namespace chimera;
using xm::Status;

namespace {

void say(const std::string& s) {
    std::printf("%s\n", s.c_str());
    std::fflush(stdout);
}

std::int64_t ms(const char* s) {
    const long v = std::atol(s);
    return v < 0 ? -1 : static_cast<std::int64_t>(v) * 1'000'000;
}

// Raw express mail: echo every message back to the RTPU named in it
// ("name|payload"), until "quit".
int xm_echo(const std::string& sys, const std::string& rtpu, std::uint32_t bid) {
    xm::Mailbox mb(sys, rtpu, bid);
    say("ready");
    std::vector<char> buf(mb.config().bufsize);
    for (;;) {
        mb.wait_interrupts(1'000'000'000);
        xm::ReadInfo info;
        while (mb.read(buf.data(), buf.size(), &info) == Status::ok) {
            const std::string m(buf.data(), info.length);
            if (m == "quit") return 0;
            const auto bar = m.find('|');
            if (bar == std::string::npos) continue;
            auto& back = mb.peer(m.substr(0, bar));
            const Status st = mb.write(back, buf.data() + bar + 1, info.length - bar - 1, 1'000'000'000);
            if (st != Status::ok) std::fprintf(stderr, "xm_helper: echo not sent: %s\n", xm::to_string(st));
        }
    }
}

// The mailbox kill test's log, by its plain segment name.
ipc::Segment mail_log(const char* name) {
    return ipc::Segment::attach(name, {ipc::ObjectType::test, 1});
}

// Writes numbered messages to RTPU "r" until told to stop (or, with `limit`,
// until `limit` were written ok, then waits for the stop).
int mb_send(const std::string& sys, const std::string& rtpu, std::uint32_t bid, int slot, const char* log_name,
            std::uint64_t limit) {
    ipc::Segment seg = mail_log(log_name);
    auto* log = reinterpret_cast<kill_test::MailLog*>(static_cast<std::byte*>(seg.base()) + kill_test::kMailLogOffset);
    xm::Mailbox mb(sys, rtpu, bid);
    mb.set_probe_period(0);
    std::uint64_t seq = log->sent[slot].load(), payload[kill_test::kMaxWords];
    xm::Peer* to = nullptr;
    // The receiver died: the last undelivered() we wrote to it are lost, and said so.
    auto record_loss = [&] {
        if (const std::uint64_t lost = to->undelivered()) {
            const std::uint32_t k = log->ranges[slot].load();
            if (k < kill_test::kRangeCap) {
                log->undelivered[slot][k][0] = seq - lost;
                log->undelivered[slot][k][1] = seq;
                log->ranges[slot].store(k + 1);
            }
        }
        to = nullptr;
    };
    while (!log->stop.load()) {
        if (seq >= limit) {
            std::this_thread::sleep_for(std::chrono::microseconds(200));
            continue;
        }
        if (!to) {
            try {
                to = &mb.peer("r");
            } catch (const xm::Error&) {
                std::this_thread::sleep_for(std::chrono::microseconds(200));  // being restarted
                continue;
            }
        }
        const std::uint64_t id = kill_test::make_id(slot, seq);
        const std::size_t n = kill_test::payload_words(id);
        for (std::size_t i = 0; i < n; ++i) payload[i] = kill_test::word(id, i);
        const Status s = mb.write(*to, payload, n * 8, 20'000'000);
        if (s == Status::ok) {
            log->sent[slot].store(++seq);
        } else if (s == Status::not_alive) {
            record_loss();
        } else if (s != Status::full) {
            log->corrupt.fetch_add(1);
            say(std::string("write failed: ") + xm::to_string(s));
            return 3;
        }
    }
    // Told to stop: the receiver we last wrote to may have died since our
    // last write, which would have said so; ask, as an RTPU that stops
    // sending must, or its last messages would go unaccounted.
    mb.check_peers();
    if (to && to->undelivered() != 0) record_loss();
    // What we recorded is what the library counted, no more, no less.
    std::uint64_t recorded = 0;
    for (std::uint32_t k = 0; k < log->ranges[slot].load(); ++k)
        recorded += log->undelivered[slot][k][1] - log->undelivered[slot][k][0];
    if (recorded != mb.undelivered() && log->ranges[slot].load() < kill_test::kRangeCap) {
        log->corrupt.fetch_add(1);
        say("recorded " + std::to_string(recorded) + " lost, the mailbox counted " +
            std::to_string(mb.undelivered()));
        return 3;
    }
    return 0;
}

int mb_recv(const std::string& sys, const std::string& rtpu, std::uint32_t bid, const char* log_name) {
    ipc::Segment seg = mail_log(log_name);
    auto* log = reinterpret_cast<kill_test::MailLog*>(static_cast<std::byte*>(seg.base()) + kill_test::kMailLogOffset);
    xm::Mailbox mb(sys, rtpu, bid);
    say("ready");
    for (;;) {
        log->landing[0] = 0;
        xm::ReadInfo info;
        const Status s = mb.read(log->landing, sizeof log->landing, &info);
        if (s == Status::would_block) {
            if (log->stop.load() == 2) return 0;  // the senders are done and we are empty
            mb.wait_interrupts(5'000'000);
            continue;
        }
        const std::uint64_t id = log->landing[0];
        bool ok = s == Status::ok && info.length == kill_test::payload_words(id) * 8;
        for (std::size_t i = 0; ok && i < info.length / 8; ++i) ok = log->landing[i] == kill_test::word(id, i);
        if (!ok) log->corrupt.fetch_add(1);
        const std::uint64_t n = log->count.load();
        if (n < kill_test::kMailCap) log->ids[n] = id;
        log->count.store(n + 1);  // the receipt is committed
    }
}

int kq_send(xm::Rtpu& self, int slot) {
    shm::Segment log_seg = shm::Segment::attach(self, "host:klog");
    auto* log = static_cast<kill_test::Log*>(log_seg.data());
    msg::Queue q = msg::Queue::attach(self, "host:kq");
    std::uint64_t seq = kill_test::resume_sequence(*log, slot);
    std::uint64_t payload[kill_test::kMaxWords];
    while (!log->stop.load()) {
        const std::uint64_t id = kill_test::make_id(slot, seq);
        const std::size_t n = kill_test::payload_words(id);
        for (std::size_t i = 0; i < n; ++i) payload[i] = kill_test::word(id, i);
        log->attempt[slot].store(seq);
        log->started[slot].store(1);  // only now does attempt name a sequence that may be sent
        const Status s = q.send(payload, n * 8, 0, static_cast<std::int32_t>(id % 7), 100'000'000);
        if (s == Status::ok) {
            log->sent[slot].store(seq + 1);
            ++seq;
        } else if (s != Status::timed_out) {
            say(std::string("send failed: ") + xm::to_string(s));
            return 3;
        }
    }
    return 0;
}

int kq_recv(xm::Rtpu& self, int slot) {
    shm::Segment log_seg = shm::Segment::attach(self, "host:klog");
    auto* log = static_cast<kill_test::Log*>(log_seg.data());
    msg::Queue q = msg::Queue::attach(self, "host:kq");
    // The queue copies straight into the shared landing buffer, so the id is
    // visible to the checker from before the receive commits until it is logged.
    std::uint64_t* landing = log->landing[slot];
    while (!log->stop.load()) {
        const std::uint64_t n = log->count[slot].load();
        if (n >= kill_test::kCap) {
            // Log full: stop taking messages but stay alive until told to
            // stop, as the checker expects of every worker it did not kill.
            std::this_thread::sleep_for(std::chrono::milliseconds(1));
            continue;
        }
        landing[0] = 0;
        msg::Info info;
        const Status s = q.receive(landing, sizeof log->landing[slot], &info, 100'000'000, slot);
        if (s == Status::timed_out) continue;
        if (s != Status::ok) {
            say(std::string("receive failed: ") + xm::to_string(s));
            return 3;
        }
        const std::uint64_t cand = landing[0];  // word 0 is the id itself
        bool ok = info.size == kill_test::payload_words(cand) * 8;
        for (std::size_t i = 0; ok && i < info.size / 8; ++i) ok = landing[i] == kill_test::word(cand, i);
        if (!ok) log->corrupt.fetch_add(1);
        log->ids[slot][n] = cand;
        log->count[slot].store(n + 1);  // the receipt is committed
    }
    return 0;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc < 5) {
        std::fprintf(stderr, "usage: xm_helper COMMAND SYS RTPU BID ARGS...\n");
        return 2;
    }
    const std::string cmd = argv[1], sys = argv[2], rtpu = argv[3];
    const auto bid = static_cast<std::uint32_t>(std::atoi(argv[4]));
    try {
        if (cmd == "xm-echo") return xm_echo(sys, rtpu, bid);
        if (cmd == "mb-send" && argc >= 7)  // SLOT LOG [LIMIT]
            return mb_send(sys, rtpu, bid, std::atoi(argv[5]), argv[6],
                           argc >= 8 ? std::strtoull(argv[7], nullptr, 10) : UINT64_MAX);
        if (cmd == "mb-recv" && argc >= 6) return mb_recv(sys, rtpu, bid, argv[5]);
        xm::Rtpu self(sys, rtpu, bid);
        if (cmd == "serve") {  // an RTPU whose XM server owns objects: runs until killed
            say("ready");
            for (;;) pause();
        }
        if (cmd == "shm-rw" && argc >= 8) {  // OBJ EXPECT WRITE
            shm::Segment s = shm::Segment::attach(self, argv[5]);
            const std::string seen(static_cast<const char*>(s.data()), std::strlen(argv[6]));
            std::strcpy(static_cast<char*>(s.data()), argv[7]);
            say(seen == argv[6] ? "ok " + std::to_string(s.size()) : "saw " + seen);
            return 0;
        }
        if (cmd == "shm-hold" && argc >= 6) {  // OBJ: attach, hold until stdin closes, detach
            shm::Segment s = shm::Segment::attach(self, argv[5]);
            std::memcpy(s.data(), "held", 4);
            say("ready");
            char c;
            while (read(0, &c, 1) > 0) {
            }
            say(s.detach() ? "freed" : "kept");
            return 0;
        }
        if (cmd == "shm-create" && argc >= 7) {  // OBJ SIZE: create on another RTPU
            shm::Segment s = shm::Segment::create(self, argv[5], std::strtoul(argv[6], nullptr, 10));
            std::strcpy(static_cast<char*>(s.data()), "made remotely");
            say("ok");
            s.detach();
            return 0;
        }
        if (cmd == "sem-p" && argc >= 8) {  // OBJ PRIO TIMEOUT_MS
            sem::Semaphore s = sem::Semaphore::attach(self, argv[5]);
            const Status st = s.p(ms(argv[7]), std::atoi(argv[6]));
            say(st == Status::ok ? std::string("got ") + argv[6] : xm::to_string(st));
            return 0;
        }
        if (cmd == "sem-v" && argc >= 7) {  // OBJ COUNT
            sem::Semaphore s = sem::Semaphore::attach(self, argv[5]);
            Status st = Status::ok;
            for (int i = 0; i < std::atoi(argv[6]) && st == Status::ok; ++i) st = s.v();
            say(st == Status::ok ? "ok" : xm::to_string(st));
            return 0;
        }
        if (cmd == "msg-recv" && argc >= 9) {  // OBJ PRIO COUNT TIMEOUT_MS
            msg::Queue q = msg::Queue::attach(self, argv[5]);
            std::vector<char> buf(1 << 16);
            for (int i = 0; i < std::atoi(argv[7]); ++i) {
                msg::Info info;
                const Status st = q.receive(buf.data(), buf.size(), &info, ms(argv[8]), std::atoi(argv[6]));
                if (st != Status::ok) {
                    say(xm::to_string(st));
                    return 0;
                }
                say(std::to_string(info.priority) + " " + std::to_string(info.type) + " " +
                    std::string(buf.data(), info.size));
            }
            return 0;
        }
        if (cmd == "msg-send" && argc >= 8) {  // OBJ PRIO TEXT...
            msg::Queue q = msg::Queue::attach(self, argv[5]);
            for (int i = 7; i < argc; ++i) {
                const Status st = q.send(argv[i], std::strlen(argv[i]), static_cast<std::uint32_t>(i - 7),
                                         std::atoi(argv[6]) + (i - 7), 1'000'000'000);
                if (st != Status::ok) {
                    say(xm::to_string(st));
                    return 1;
                }
            }
            say("ok");
            return 0;
        }
        if (cmd == "kq-send" && argc >= 6) return kq_send(self, std::atoi(argv[5]));
        if (cmd == "kq-recv" && argc >= 6) return kq_recv(self, std::atoi(argv[5]));
        std::fprintf(stderr, "xm_helper: unknown command or arguments: %s\n", cmd.c_str());
        return 2;
    } catch (const std::exception& e) {
        say(std::string("error: ") + e.what());
        return 1;
    }
}
