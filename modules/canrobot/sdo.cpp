#include "canrobot/sdo.hpp"

#include <cstdio>

namespace chimera::canrobot::sdo {

using cia402::get_u16;
using cia402::get_u32;
using cia402::put_u16;
using cia402::put_u32;

std::string_view abort_name(std::uint32_t code) noexcept {
    switch (code) {
    case kAbortTimeout: return "SDO protocol timed out";
    case kAbortCommand: return "client/server command specifier not valid or unknown";
    case kAbortReadOnly: return "attempt to write a read only object";
    case kAbortNoObject: return "object does not exist in the object dictionary";
    case kAbortLength: return "data type does not match, length of service parameter does not match";
    case kAbortNoSubindex: return "sub-index does not exist";
    case kAbortRange: return "value range of parameter exceeded";
    case kAbortTooHigh: return "value of parameter written too high";
    case kAbortTooLow: return "value of parameter written too low";
    case kAbortGeneral: return "general error";
    case kAbortDeviceState: return "data cannot be transferred because of the present device state";
    default: return "";
    }
}

std::string_view object_name(std::uint16_t index) noexcept {
    switch (index) {
    case kMaxTorque: return "max torque";
    case kMaxMotorSpeed: return "max motor speed";
    case kTorqueSlope: return "torque slope";
    default: return "";
    }
}

namespace {
Frame sdo_frame(std::uint32_t function, int node, std::uint8_t cmd, std::uint16_t index, std::uint8_t subindex) noexcept {
    Frame f{.id = cia402::cob_id(function, node), .len = 8, .data = {}};
    f.data[0] = cmd;
    put_u16(f, 1, index);
    f.data[3] = subindex;
    return f;
}
}  // namespace

Frame download_request(int node, std::uint16_t index, std::uint8_t subindex, std::uint32_t value,
                       std::uint8_t size) noexcept {
    if (size < 1 || size > 4) size = 4;
    const auto n = static_cast<std::uint8_t>(4 - size);
    Frame f = sdo_frame(kRequest, node, static_cast<std::uint8_t>(kCcsInitiateDownload << 5 | n << 2 | 0x3), index,
                        subindex);
    for (int b = 0; b < size; ++b) f.data[4 + b] = static_cast<std::uint8_t>(value >> (8 * b));
    return f;
}

Frame download_response(int node, std::uint16_t index, std::uint8_t subindex) noexcept {
    return sdo_frame(kResponse, node, kDownloadResponse, index, subindex);
}

Frame abort_frame(int node, std::uint16_t index, std::uint8_t subindex, std::uint32_t code, bool server) noexcept {
    Frame f = sdo_frame(server ? kResponse : kRequest, node, kAbort, index, subindex);
    put_u32(f, 4, code);
    return f;
}

std::optional<Request> decode_request(const Frame& f) noexcept {
    if (f.id <= kRequest || f.id > kRequest + 127 || f.len != 8) return std::nullopt;
    Request r;
    r.index = get_u16(f, 1);
    r.subindex = f.data[3];
    const std::uint8_t cmd = f.data[0];
    if (cmd == kAbort) {
        r.kind = Request::Kind::abort;
        r.value = get_u32(f, 4);
        return r;
    }
    // Initiate download, expedited (e = 1); bit 4 is reserved (0).
    if ((cmd >> 5) != kCcsInitiateDownload || (cmd & 0x10) || !(cmd & 0x02)) return r;  // unsupported
    r.kind = Request::Kind::download;
    r.size = (cmd & 0x01) ? static_cast<std::uint8_t>(4 - ((cmd >> 2) & 0x3)) : 0;
    const int bytes = r.size ? r.size : 4;
    for (int b = 0; b < bytes; ++b) r.value |= static_cast<std::uint32_t>(f.data[4 + b]) << (8 * b);
    return r;
}

std::optional<Response> decode_response(const Frame& f) noexcept {
    if (f.id <= kResponse || f.id > kResponse + 127 || f.len != 8) return std::nullopt;
    Response r;
    r.index = get_u16(f, 1);
    r.subindex = f.data[3];
    if (f.data[0] == kAbort) {
        r.kind = Response::Kind::aborted;
        r.abort_code = get_u32(f, 4);
    } else if ((f.data[0] >> 5) == kScsInitiateDownload) {
        r.kind = Response::Kind::downloaded;
    }
    return r;
}

// --- DownloadSequence ------------------------------------------------------------------------

DownloadSequence::DownloadSequence(std::vector<Download> downloads, std::string interface)
    : downloads_(std::move(downloads)), ok_(downloads_.size(), false), interface_(std::move(interface)) {}

namespace {
// The outstanding download of `node`: its first not yet confirmed, or -1.
int outstanding(const std::vector<Download>& d, const std::vector<bool>& ok, int node) {
    for (std::size_t i = 0; i < d.size(); ++i)
        if (d[i].node == node && !ok[i]) return static_cast<int>(i);
    return -1;
}
}  // namespace

void DownloadSequence::start(std::vector<Frame>& out) { resend(out); }

void DownloadSequence::resend(std::vector<Frame>& out) const {
    if (failed()) return;
    for (std::size_t i = 0; i < downloads_.size(); ++i) {
        const Download& d = downloads_[i];
        if (outstanding(downloads_, ok_, d.node) == static_cast<int>(i))
            out.push_back(download_request(d.node, d.index, 0, d.value, d.size));
    }
}

void DownloadSequence::receive(const Frame& f, std::vector<Frame>& out) {
    if (failed()) return;
    const auto r = decode_response(f);
    if (!r) return;
    const int node = static_cast<int>(f.id - kResponse);
    const int i = outstanding(downloads_, ok_, node);
    if (i < 0) return;
    const Download& d = downloads_[static_cast<std::size_t>(i)];
    if (r->index != d.index || r->subindex != 0) return;  // not the answer to this request (a stale one)
    if (r->kind == Response::Kind::aborted) {
        char code[64];
        std::snprintf(code, sizeof code, ": SDO abort 0x%08X", r->abort_code);
        const std::string_view name = abort_name(r->abort_code);
        failure_ = describe(d) + code + (name.empty() ? "" : " " + std::string(name));
        return;
    }
    if (r->kind != Response::Kind::downloaded) return;
    ok_[static_cast<std::size_t>(i)] = true;
    ++confirmed_;
    const int next = outstanding(downloads_, ok_, node);
    if (next >= 0) {
        const Download& n = downloads_[static_cast<std::size_t>(next)];
        out.push_back(download_request(n.node, n.index, 0, n.value, n.size));
    }
}

bool DownloadSequence::done() const noexcept { return !failed() && confirmed_ == downloads_.size(); }

std::string DownloadSequence::describe(const Download& d) const {
    char obj[48];
    std::snprintf(obj, sizeof obj, "0x%04X", d.index);
    const std::string_view name = object_name(d.index);
    return "node " + std::to_string(d.node) + " (joint " + std::to_string(d.joint + 1) + ") on " + interface_ +
           " refused " + obj + (name.empty() ? "" : " " + std::string(name)) + " = " + std::to_string(d.value);
}

std::string DownloadSequence::unconfirmed() const {
    std::string s;
    for (std::size_t i = 0; i < downloads_.size(); ++i) {
        if (ok_[i]) continue;
        const Download& d = downloads_[i];
        char obj[48];
        std::snprintf(obj, sizeof obj, "0x%04X", d.index);
        const std::string_view name = object_name(d.index);
        s += (s.empty() ? "" : "; ") + std::string("node ") + std::to_string(d.node) + " (joint " +
             std::to_string(d.joint + 1) + ") on " + interface_ + ": " + obj +
             (name.empty() ? "" : " " + std::string(name)) + " not confirmed";
    }
    return s;
}

}  // namespace chimera::canrobot::sdo
