// teleop/trackball.hpp — the serial protocol of the six-axis trackball that
// jtball reads (thesis Figure 6.10; the device end is examples/fig6_10_teleop's
// trackball_sim). Both ends include this header: one definition of the bytes.
//
// The trackball sends a packet of 16 bytes at its own rate (50 Hz by default;
// 800 bytes/s fits a 9600 baud, 8N1 line), whether or not anyone listens:
//
//   byte  0      0xA5, the sync byte
//   byte  1      buttons: bit 0 = ENABLE (the operator's deadman: the arm moves
//                only while it is held); bits 1-7 reserved, sent as 0
//   bytes 2-13   six axes, int16 little-endian, deflection in counts:
//                -1000..1000 is full scale; beyond it is taken as full scale.
//                Axes 0-2 are the ball's push along x, y, z; 3-5 its twist
//                about x, y, z; jtball maps axis j to joint j.
//   byte 14      sequence number, +1 per packet (mod 256): gaps count lost packets
//   byte 15      checksum: the 16 bytes sum to 0 (mod 256)
//
// A reader that starts mid-packet, or sees a corrupted one, finds the next
// sync byte whose 16 bytes have a good checksum (TrackballParser).
#pragma once

#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>

namespace chimera::teleop {

inline constexpr std::size_t kTrackballPacketBytes = 16;
inline constexpr std::size_t kTrackballAxes = 6;
inline constexpr std::uint8_t kTrackballSync = 0xA5;
inline constexpr std::uint8_t kTrackballEnable = 0x01;
inline constexpr int kTrackballFullScale = 1000;

struct TrackballPacket {
    std::uint8_t buttons = 0;
    std::array<std::int16_t, kTrackballAxes> axes{};
    std::uint8_t sequence = 0;

    bool enabled() const noexcept { return (buttons & kTrackballEnable) != 0; }
    /// Axis j as a fraction of full scale, clamped to [-1, 1].
    double deflection(std::size_t j) const noexcept {
        return std::clamp(static_cast<double>(axes[j]) / kTrackballFullScale, -1.0, 1.0);
    }
};

inline std::array<std::uint8_t, kTrackballPacketBytes> encode(const TrackballPacket& p) noexcept {
    std::array<std::uint8_t, kTrackballPacketBytes> b{};
    b[0] = kTrackballSync;
    b[1] = p.buttons;
    for (std::size_t j = 0; j < kTrackballAxes; ++j) {
        const auto v = static_cast<std::uint16_t>(p.axes[j]);
        b[2 + 2 * j] = static_cast<std::uint8_t>(v & 0xFF);
        b[3 + 2 * j] = static_cast<std::uint8_t>(v >> 8);
    }
    b[14] = p.sequence;
    unsigned sum = 0;
    for (std::size_t i = 0; i + 1 < kTrackballPacketBytes; ++i) sum += b[i];
    b[15] = static_cast<std::uint8_t>(0x100 - (sum & 0xFF));
    return b;
}

/// Turns the byte stream into packets, resynchronising on the sync byte. Fixed
/// size, no allocation: usable in a task's cycle.
class TrackballParser {
public:
    /// Feeds `n` received bytes; returns how many good packets they completed.
    /// The newest is latest().
    std::size_t feed(const std::uint8_t* data, std::size_t n) noexcept {
        std::size_t packets = 0;
        for (std::size_t i = 0; i < n; ++i) {
            buf_[len_++] = data[i];
            while (len_ > 0 && buf_[0] != kTrackballSync) drop(1);  // hunt for sync
            if (len_ < kTrackballPacketBytes) continue;
            if (checksum_ok()) {
                decode();
                ++packets;
                len_ = 0;
            } else {
                ++bad_;
                drop(1);  // not a packet start after all: look for the next sync
                while (len_ > 0 && buf_[0] != kTrackballSync) drop(1);
            }
        }
        return packets;
    }
    const TrackballPacket& latest() const noexcept { return latest_; }
    /// Packets received with a good checksum, and 16-byte candidates refused.
    std::uint64_t good() const noexcept { return good_; }
    std::uint64_t bad() const noexcept { return bad_; }
    /// Packets missing according to the sequence numbers of the good ones.
    std::uint64_t lost() const noexcept { return lost_; }
    /// Forget a partial packet and the last sequence number (after a flush of
    /// the line, whose discarded packets are not lost ones).
    void reset() noexcept {
        len_ = 0;
        have_last_ = false;
    }

private:
    bool checksum_ok() const noexcept {
        unsigned sum = 0;
        for (std::size_t i = 0; i < kTrackballPacketBytes; ++i) sum += buf_[i];
        return (sum & 0xFF) == 0;
    }
    void decode() noexcept {
        TrackballPacket p;
        p.buttons = buf_[1];
        for (std::size_t j = 0; j < kTrackballAxes; ++j)
            p.axes[j] = static_cast<std::int16_t>(static_cast<std::uint16_t>(buf_[2 + 2 * j] | (buf_[3 + 2 * j] << 8)));
        p.sequence = buf_[14];
        if (have_last_) lost_ += static_cast<std::uint8_t>(p.sequence - latest_.sequence - 1);
        latest_ = p;
        have_last_ = true;
        ++good_;
    }
    void drop(std::size_t k) noexcept {
        std::copy(buf_.begin() + static_cast<std::ptrdiff_t>(k), buf_.begin() + static_cast<std::ptrdiff_t>(len_),
                  buf_.begin());
        len_ -= k;
    }

    std::array<std::uint8_t, kTrackballPacketBytes> buf_{};
    std::size_t len_ = 0;
    TrackballPacket latest_;
    std::uint64_t good_ = 0, bad_ = 0, lost_ = 0;
    bool have_last_ = false;
};

}  // namespace chimera::teleop
