// The XM server of an RTPU process (thesis §5.3, §5.4): reads its mailbox,
// acts as the name server for the IPC objects it owns, routes replies to the
// local tasks that asked, and runs mailbox-interrupt and message handlers.
#include <dirent.h>

#include <algorithm>
#include <condition_variable>
#include <cstring>
#include <vector>

#include "chimera/ipc/clock.hpp"
#include "detail.hpp"

namespace chimera::xm {

namespace {

// Name-server messages (kinds below 0x100; the rest are user messages).
enum : std::uint32_t { kNsCreate = 1, kNsAttach = 2, kNsDestroy = 3, kNsReply = 4 };

struct NsRequest {
    std::uint32_t kind;
    std::uint32_t request_id;
    std::uint32_t type;       // ipc::ObjectType
    std::uint32_t reserved;
    char reply_rtpu[32];
    char name[32];            // the object part of "rtpu:name"
    std::uint64_t params[4];
};
static_assert(sizeof(NsRequest) == 112);

struct NsReply {
    std::uint32_t kind;
    std::uint32_t request_id;
    std::uint32_t ok;
    std::uint32_t type;
    char segment[96];
    char message[160];
};
static_assert(sizeof(NsReply) == 272);

template <std::size_t N>
void put(char (&dst)[N], std::string_view src) noexcept {
    std::memset(dst, 0, N);
    std::memcpy(dst, src.data(), std::min(src.size(), N - 1));
}
template <std::size_t N>
std::string get(const char (&src)[N]) {
    return std::string(src, strnlen(src, N));
}

// An RTPU whose mailbox exists, says alive and whose owner process runs.
bool rtpu_alive(const std::string& sys, const std::string& rtpu) noexcept {
    try {
        ipc::AttachOptions opt;
        opt.ready_timeout_ns = 0;
        opt.prefault = false;
        ipc::Segment seg = ipc::Segment::attach(Mailbox::segment_name(sys, rtpu),
                                                {ipc::ObjectType::xmail_mailbox, layout::kMailboxVersion}, opt);
        const auto& h = *static_cast<const layout::MailboxHeader*>(seg.base());
        const auto pid = static_cast<std::uint32_t>(h.owner_pid.load());
        return h.alive.load() != 0 && ipc::owner_alive(std::uint64_t{pid} << 32 | pid);
    } catch (const std::exception&) {
        return false;
    }
}

bool valid_part(std::string_view s) noexcept {
    if (s.empty() || s.size() > layout::kNameMax) return false;
    for (char c : s)
        if (c == '/' || c == ':' || c == '.' || static_cast<unsigned char>(c) <= ' ') return false;
    return true;
}

}  // namespace

std::pair<std::string, std::string> split_name(std::string_view full) {
    const auto colon = full.find(':');
    if (colon == std::string_view::npos)
        throw Error("'" + std::string(full) + "': an object name has the form \"rtpu:name\"");
    const std::string_view rtpu = full.substr(0, colon), name = full.substr(colon + 1);
    if (!valid_part(rtpu) || !valid_part(name))
        throw Error("'" + std::string(full) + "': rtpu and name must each have 1.." +
                    std::to_string(layout::kNameMax) + " characters, none of '/', ':', '.', space");
    return {std::string(rtpu), std::string(name)};
}

struct CHIMERA_LOCAL Rtpu::Pending {
    bool done = false;
    NsReply reply{};
};

struct CHIMERA_LOCAL Rtpu::Owned {
    ipc::ObjectType type;
    std::string segment;
    // Until then a new object may have no user yet (the requester attaches
    // after our answer); after it, no user means its users have all gone.
    std::int64_t grace_until = 0;  // a second after creation
};

Rtpu::Rtpu(std::string sys, std::string name, std::uint32_t bid, MailboxConfig config)
    : mailbox_(std::move(sys), std::move(name), bid, config) {
    sweep_orphans();  // a dead predecessor's objects that nobody uses any more
    server_ = std::thread([this] { serve(); });
}

Rtpu::~Rtpu() {
    stop_.store(true);
    // Our own interrupt wakes the server at once.
    mailbox_.header().pending.fetch_or(1u << kMboxSigBuf);
    mailbox_.header().trigger.fetch_add(1);
    ipc::futex_wake_all(mailbox_.header().trigger);
    if (server_.joinable()) server_.join();
    std::lock_guard lock(mutex_);
    for (auto& [name, owned] : owned_) ipc::Segment::unlink(owned->segment);
    owned_.clear();
}

// Objects whose users have all gone, detached or killed, are freed by their
// owner: the last live user frees an object when it detaches, but when the
// last users were killed nobody is left to (issue #15.2). Lock held.
void Rtpu::reap_objects() noexcept {
    const std::int64_t now = ipc::now_ns();
    for (auto it = owned_.begin(); it != owned_.end();) {
        const Owned& o = *it->second;
        const bool gone = now >= o.grace_until && (!ipc::Segment::exists(o.segment) ||
                                                   ipc::Segment::destroy_if_unused(o.segment));
        it = gone ? owned_.erase(it) : std::next(it);
    }
}

// Segments of this system that nobody can free any more but us, freed when
// no live process maps them: objects whose owner RTPU is gone (or an earlier
// run of this one), and the mailboxes of RTPUs that died.
void Rtpu::sweep_orphans() noexcept {
    const std::string objects = "chimera." + sys() + ".obj.", mailboxes = "chimera." + sys() + ".xm.";
    std::vector<std::string> names;
    if (DIR* d = opendir("/dev/shm")) {
        while (const dirent* e = readdir(d))
            if (std::strncmp(e->d_name, objects.c_str(), objects.size()) == 0 ||
                std::strncmp(e->d_name, mailboxes.c_str(), mailboxes.size()) == 0)
                names.emplace_back(e->d_name);
        closedir(d);
    }
    for (const std::string& n : names) {
        const bool object = n.compare(0, objects.size(), objects) == 0;
        const std::string rest = n.substr(object ? objects.size() : mailboxes.size());
        const std::string owner = rest.substr(0, rest.find('.'));  // "<rtpu>.<object>" or "<rtpu>"
        if (owner == name()) {
            if (!object) continue;  // our own mailbox
            std::lock_guard lock(mutex_);
            if (owned_.count(rest.substr(std::min(rest.size(), owner.size() + 1))) != 0)
                continue;  // ours: reap_objects() looks after it
        } else if (rtpu_alive(sys(), owner)) {
            continue;
        }
        ipc::Segment::destroy_if_unused("/" + n);
    }
}

void Rtpu::install(std::uint32_t mbox, std::function<void(std::uint32_t)> handler) {
    if (mbox < kMboxUser || mbox >= mailbox_.config().nmbox)
        throw Error("RTPU '" + name() + "': mailbox interrupt " + std::to_string(mbox) +
                    " is not user-definable (" + std::to_string(kMboxUser) + ".." +
                    std::to_string(mailbox_.config().nmbox - 1) + ")");
    std::lock_guard lock(mutex_);
    handlers_[mbox] = std::move(handler);
}

void Rtpu::on_message(std::function<void(std::uint32_t, const void*, std::size_t)> handler) {
    std::lock_guard lock(mutex_);
    message_handler_ = std::move(handler);
}

void Rtpu::serve() {
    std::vector<std::byte> buffer(mailbox_.config().bufsize);
    std::int64_t next_check = 0, next_sweep = 0;
    while (!stop_.load()) {
        const std::uint32_t pending = mailbox_.wait_interrupts(100'000'000);
        // Every 100 ms: messages our tasks wrote to an RTPU that died unread
        // are counted, whether or not anyone writes to it again; objects whose
        // users all went are freed. Every 250 ms: orphans of dead owners.
        if (const std::int64_t now = ipc::now_ns(); now >= next_check) {
            mailbox_.check_peers();
            {
                std::lock_guard lock(mutex_);
                reap_objects();
            }
            next_check = now + 100'000'000;
            if (now >= next_sweep) {
                sweep_orphans();
                next_sweep = now + 250'000'000;
            }
        }
        if (pending & (1u << kMboxReset)) mailbox_.reset_buffers();
        // Interrupts are not stacked: always look at every ring.
        ReadInfo info;
        while (mailbox_.read(buffer.data(), buffer.size(), &info) == Status::ok)
            handle_message(info.from_bid, buffer.data(), info.length);
        for (std::uint32_t m = kMboxUser; m < mailbox_.config().nmbox; ++m) {
            if (!(pending & (1u << m))) continue;
            std::function<void(std::uint32_t)> h;
            {
                std::lock_guard lock(mutex_);
                auto it = handlers_.find(m);
                if (it != handlers_.end()) h = it->second;
            }
            if (h) h(mailbox_.mbox_value(m));
        }
    }
}

void Rtpu::handle_message(std::uint32_t from, const std::byte* data, std::size_t length) {
    std::uint32_t kind = 0;
    if (length >= sizeof kind) std::memcpy(&kind, data, sizeof kind);
    if (kind == kNsReply && length == sizeof(NsReply)) {
        NsReply reply;
        std::memcpy(&reply, data, sizeof reply);
        std::lock_guard lock(mutex_);
        auto it = pending_.find(reply.request_id);
        if (it != pending_.end()) {
            it->second->reply = reply;
            it->second->done = true;
        }
        done_.notify_all();
        return;
    }
    if ((kind == kNsCreate || kind == kNsAttach || kind == kNsDestroy) && length == sizeof(NsRequest)) {
        NsRequest req;
        std::memcpy(&req, data, sizeof req);
        handle_request(&req);
        return;
    }
    std::function<void(std::uint32_t, const void*, std::size_t)> h;
    {
        std::lock_guard lock(mutex_);
        h = message_handler_;
    }
    if (h) h(from, data, length);
}

// The name server: this RTPU's database of the objects created on it.
void Rtpu::handle_request(const void* request) {
    const auto& req = *static_cast<const NsRequest*>(request);
    const std::string object = get(req.name);
    const std::string full = name() + ":" + object;
    const auto type = static_cast<ipc::ObjectType>(req.type);
    NsReply reply{};
    reply.kind = kNsReply;
    reply.request_id = req.request_id;
    auto answer = [&](bool ok, const std::string& text) {
        reply.ok = ok ? 1 : 0;
        if (ok)
            put(reply.segment, text);
        else
            put(reply.message, text);
    };
    try {
        std::lock_guard lock(mutex_);
        auto it = owned_.find(object);
        // A name whose segment the last user already freed is gone.
        if (it != owned_.end() && !ipc::Segment::exists(it->second->segment)) {
            owned_.erase(it);
            it = owned_.end();
        }
        if (req.kind == kNsCreate) {
            if (it != owned_.end())
                throw Error("'" + full + "' already exists (a " +
                            ipc::object_type_name(it->second->type) + ")");
            ObjectParams p{req.params[0], req.params[1], req.params[2], req.params[3]};
            const std::string segment = ipc::segment_name(sys(), "obj." + name() + "." + object);
            ipc::Segment::unlink(segment);  // left by an earlier run of this RTPU
            ipc::Segment seg;
            switch (type) {
                case ipc::ObjectType::xmail_shm: seg = detail::create_shm_segment(segment, full, p); break;
                case ipc::ObjectType::xmail_sem: seg = detail::create_sem_segment(segment, full, p); break;
                case ipc::ObjectType::xmail_msg: seg = detail::create_msg_segment(segment, full, p); break;
                default:
                    throw Error("'" + full + "': cannot create objects of type " +
                                ipc::object_type_name(type));
            }
            // The server does not stay a user: the requester attaches next,
            // and the last user to detach frees the segment (or, when the
            // last ones were killed, reap_objects()).
            seg.detach();
            owned_.emplace(object, std::make_unique<Owned>(Owned{
                                       type, segment, ipc::now_ns() + 1'000'000'000}));
            answer(true, segment);
        } else if (it == owned_.end()) {
            throw Error("'" + full + "': no such object on RTPU '" + name() + "'");
        } else if (req.kind == kNsAttach) {
            if (it->second->type != type)
                throw Error("'" + full + "' is a " + ipc::object_type_name(it->second->type) +
                            ", not a " + ipc::object_type_name(type));
            answer(true, it->second->segment);
        } else {
            ipc::Segment::unlink(it->second->segment);
            answer(true, it->second->segment);
            owned_.erase(it);
        }
    } catch (const std::exception& e) {
        answer(false, e.what());
    }
    try {
        Peer& back = mailbox_.peer(get(req.reply_rtpu));
        // Not delivered (the requester died or its ring stayed full): it
        // times out on its own (request_timeout_ns) and says so.
        (void)mailbox_.write(back, &reply, sizeof reply, 100'000'000);
    } catch (const Error&) {
        // The requester is gone: nobody to answer.
    }
}

ObjectRef Rtpu::request(std::string_view full_name, std::uint32_t op, ipc::ObjectType type,
                        const ObjectParams& params) {
    const auto [owner, object] = split_name(full_name);
    Peer& peer = mailbox_.peer(owner);  // throws: no such RTPU / not alive
    auto pending = std::make_shared<Pending>();
    NsRequest req{};
    req.kind = op;
    req.type = static_cast<std::uint32_t>(type);
    put(req.reply_rtpu, name());
    put(req.name, object);
    req.params[0] = params.a;
    req.params[1] = params.b;
    req.params[2] = params.c;
    req.params[3] = params.d;
    {
        std::lock_guard lock(mutex_);
        req.request_id = next_request_++;
        pending_[req.request_id] = pending;
    }
    auto forget = [&] {
        std::lock_guard lock(mutex_);
        pending_.erase(req.request_id);
    };
    const Status s = mailbox_.write(peer, &req, sizeof req, request_timeout_ns_);
    if (s != Status::ok) {
        forget();
        throw Error("'" + std::string(full_name) + "': cannot reach the XM server of RTPU '" + owner +
                    "': " + to_string(s));
    }
    std::unique_lock lock(mutex_);
    const bool answered = done_.wait_for(lock, std::chrono::nanoseconds(request_timeout_ns_),
                                         [&] { return pending->done; });
    pending_.erase(req.request_id);
    if (!answered)
        throw Error("'" + std::string(full_name) + "': no answer from the XM server of RTPU '" +
                    owner + "'" + (mailbox_.alive(peer) ? "" : " (it is not alive)"));
    if (!pending->reply.ok) throw Error(get(pending->reply.message));
    return ObjectRef{get(pending->reply.segment), type};
}

ObjectRef Rtpu::create_object(std::string_view full_name, ipc::ObjectType type,
                              const ObjectParams& params) {
    return request(full_name, kNsCreate, type, params);
}

ObjectRef Rtpu::attach_object(std::string_view full_name, ipc::ObjectType type) {
    return request(full_name, kNsAttach, type, {});
}

void Rtpu::destroy_object(std::string_view full_name) {
    request(full_name, kNsDestroy, ipc::ObjectType{}, {});
}

}  // namespace chimera::xm
