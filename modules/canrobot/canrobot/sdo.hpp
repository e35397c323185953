// canrobot/sdo.hpp — the SDO subset of the canrobot protocol (CiA 301 service
// data objects): the expedited download (a write of 1 to 4 bytes into one
// object of a drive's object dictionary) and the abort transfer, both ends.
// canrobot downloads the drives' own speed and torque-slope limits with it
// (CiA 402 objects 0x6080 max motor speed, 0x6087 torque slope) when VLIMIT
// and TRATE are declared; the simulated drives (drive_sim.hpp) answer it.
//
//   frame             COB-ID      dir     bytes
//   download request  0x600+node  master  cmd u8, index u16, subindex u8, data (1..4 bytes, LSB first, rest 0)
//   download response 0x580+node  drive   0x60, index u16, subindex u8, 0 0 0 0
//   abort             0x580+node  drive   0x80, index u16, subindex u8, abort code u32
//                     (or 0x600+node from the master)
//
// The request's command byte: client command specifier 1 (bits 7..5, initiate
// download), n (bits 3..2) the number of the 4 data bytes that are not data,
// e (bit 1) expedited, s (bit 0) size indicated: 0x2F, 0x2B, 0x27, 0x23 for
// 1, 2, 3, 4 bytes. The server answers with server command specifier 3
// (0x60), or aborts (0x80) with a CiA 301 abort code. Every SDO frame is 8
// bytes. Segmented and block transfers and uploads are not in the subset: a
// drive aborts them with 0x05040001 (command specifier not valid).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "canrobot/cia402.hpp"

namespace chimera::canrobot::sdo {

using cia402::Frame;

inline constexpr std::uint32_t kResponse = 0x580;  ///< + node: server (drive) -> client (master)
inline constexpr std::uint32_t kRequest = 0x600;   ///< + node: client (master) -> server (drive)

inline constexpr std::uint8_t kCcsInitiateDownload = 1;  ///< bits 7..5 of a request
inline constexpr std::uint8_t kScsInitiateDownload = 3;  ///< bits 7..5 of a response
inline constexpr std::uint8_t kAbort = 0x80;             ///< command byte of an abort, either way
inline constexpr std::uint8_t kDownloadResponse = 0x60;

// --- abort codes (CiA 301) ------------------------------------------------------------------
inline constexpr std::uint32_t kAbortTimeout = 0x05040000;          ///< SDO protocol timed out
inline constexpr std::uint32_t kAbortCommand = 0x05040001;          ///< command specifier not valid or unknown
inline constexpr std::uint32_t kAbortReadOnly = 0x06010002;         ///< attempt to write a read-only object
inline constexpr std::uint32_t kAbortNoObject = 0x06020000;         ///< object does not exist in the dictionary
inline constexpr std::uint32_t kAbortLength = 0x06070010;           ///< data type does not match, length of parameter does not match
inline constexpr std::uint32_t kAbortNoSubindex = 0x06090011;       ///< sub-index does not exist
inline constexpr std::uint32_t kAbortRange = 0x06090030;            ///< value range of parameter exceeded
inline constexpr std::uint32_t kAbortTooHigh = 0x06090031;          ///< value of parameter written too high
inline constexpr std::uint32_t kAbortTooLow = 0x06090032;           ///< value of parameter written too low
inline constexpr std::uint32_t kAbortGeneral = 0x08000000;          ///< general error
inline constexpr std::uint32_t kAbortDeviceState = 0x08000022;      ///< not possible in the present device state
/// "object does not exist in the object dictionary" for the codes above; "" for others.
std::string_view abort_name(std::uint32_t code) noexcept;

// --- CiA 402 objects the drives take by SDO ----------------------------------------------------
inline constexpr std::uint16_t kMaxTorque = 0x6072;      ///< u16, thousandths of the rated torque
inline constexpr std::uint16_t kMaxMotorSpeed = 0x6080;  ///< u32, velocity units (here counts/s, as 0x606C)
inline constexpr std::uint16_t kTorqueSlope = 0x6087;    ///< u32, thousandths of the rated torque per second
/// "max motor speed" for the objects above; "" for others.
std::string_view object_name(std::uint16_t index) noexcept;

// --- encode / decode ---------------------------------------------------------------------------
/// Client: an expedited download of the low `size` (1..4) bytes of `value`
/// into `index`/`subindex` of `node`'s dictionary. `size` outside 1..4 is taken as 4.
Frame download_request(int node, std::uint16_t index, std::uint8_t subindex, std::uint32_t value,
                       std::uint8_t size = 4) noexcept;
/// Server: the confirmation of a download.
Frame download_response(int node, std::uint16_t index, std::uint8_t subindex) noexcept;
/// Either end: abort the transfer of `index`/`subindex` with `code`. `server`
/// true: sent by the drive (0x580+node), false: by the master (0x600+node).
Frame abort_frame(int node, std::uint16_t index, std::uint8_t subindex, std::uint32_t code, bool server) noexcept;

/// What a request frame (0x600+node) asks, as a server reads it.
struct Request {
    enum class Kind : std::uint8_t { download, abort, unsupported } kind = Kind::unsupported;
    std::uint16_t index = 0;
    std::uint8_t subindex = 0;
    std::uint32_t value = 0;  ///< download: the data, zero-extended; abort: the code
    std::uint8_t size = 0;    ///< download: 1..4 when indicated, 0 when not (take it as the object's size)
};
/// Server side: the request in `f`; nullopt when `f` is not an SDO request
/// frame at all (wrong COB-ID range, not 8 bytes).
std::optional<Request> decode_request(const Frame& f) noexcept;

/// What a response frame (0x580+node) says, as a client reads it.
struct Response {
    enum class Kind : std::uint8_t { downloaded, aborted, other } kind = Kind::other;
    std::uint16_t index = 0;
    std::uint8_t subindex = 0;
    std::uint32_t abort_code = 0;  ///< aborted: the code
};
/// Client side: nullopt when `f` is not an SDO response frame (wrong COB-ID
/// range, not 8 bytes).
std::optional<Response> decode_response(const Frame& f) noexcept;

// --- a master's downloads to several drives ----------------------------------------------------

/// One value to download: into `index`/0 of `node`, the drive of `joint` (0-based).
struct Download {
    int node = 0;
    std::size_t joint = 0;
    std::uint16_t index = 0;
    std::uint32_t value = 0;
    std::uint8_t size = 4;
};

/// The client's side of a list of downloads, without I/O or clock: one
/// request outstanding per node (CiA 301: one SDO transfer at a time per
/// server), the next sent when the previous is confirmed. The caller sends
/// what start()/receive() put in `out`, feeds every frame it reads, and
/// gives up after its own timeout (resend() sends the outstanding requests
/// again: a frame can be lost). The first abort fails the whole sequence.
class DownloadSequence {
public:
    DownloadSequence(std::vector<Download> downloads, std::string interface);

    /// The first request of every node.
    void start(std::vector<Frame>& out);
    /// Every node's outstanding request again.
    void resend(std::vector<Frame>& out) const;
    /// A frame from the bus (anything; only the nodes' SDO responses count).
    void receive(const Frame& f, std::vector<Frame>& out);

    bool done() const noexcept;                       ///< every download confirmed
    bool failed() const noexcept { return !failure_.empty(); }
    /// Failed: "node 3 (joint 3) on vcan0 refused 0x6080 max motor speed = 166886:
    /// SDO abort 0x06090030 value range of parameter exceeded".
    const std::string& failure() const noexcept { return failure_; }
    /// Not done: the downloads not yet confirmed, for a timeout's message
    /// ("node 3 (joint 3) on vcan0: 0x6080 max motor speed not confirmed; ...").
    std::string unconfirmed() const;
    std::size_t confirmed() const noexcept { return confirmed_; }

private:
    std::string describe(const Download& d) const;
    std::vector<Download> downloads_;
    std::vector<bool> ok_;
    std::string interface_;
    std::string failure_;
    std::size_t confirmed_ = 0;
};

}  // namespace chimera::canrobot::sdo
