// teleop/feed.hpp — the operator feed of the teleoperation input module: one
// triple buffer (TBUF, thesis §5.6) per operator, written by the operator's
// process (a joystick reader, `teleop_feed`, a script) and read by the
// `teleop` module each cycle. Both sides include this header, so the segment
// name and the item layout cannot disagree.
//
// Item: NDOF doubles, the operator's joint set-points in rad (absolute, not
// increments: a lost or late item is harmless, the next one carries the whole
// command). The item's time-stamp is the time it was written.
#pragma once

#include <chimera/ipc/segment.hpp>
#include <chimera/tbuf.hpp>

#include <cerrno>
#include <cstddef>
#include <string>
#include <string_view>

namespace chimera::teleop {

/// Segment of the operator feed called `name` (the teleop module's LOCAL TBUF):
/// "/chimera.tbuf.<name>".
inline std::string feed_segment(std::string_view name) { return ipc::segment_name("tbuf", name); }

/// Bytes of one item for a robot of `ndof` joints.
constexpr std::size_t item_size(std::size_t ndof) { return ndof * sizeof(double); }

/// Opens the feed `name` for items of `ndof` joints: attaches when it exists
/// (the other side came first), creates it otherwise, or anew when no live
/// process maps the one that exists. Either side may start first. Throws ipc::SegmentError naming the segment when it exists with
/// another item size (a feed for a robot with a different NDOF).
inline tbuf::Tbuf open_feed(std::string_view name, std::size_t ndof) {
    const std::string seg = feed_segment(name);
    tbuf::Tbuf buf;
    try {
        buf = tbuf::Tbuf::create(seg, item_size(ndof));
    } catch (const ipc::SegmentError& e) {
        if (e.error_number() != EEXIST) throw;
        // A feed no live process maps was left by runs that have ended (maybe
        // of an older library, whose layout this one refuses): made anew, as
        // the module drops what was sent before it is switched on anyway.
        if (ipc::Segment::destroy_if_unused(seg))
            buf = tbuf::Tbuf::create(seg, item_size(ndof));
        else
            buf = tbuf::Tbuf::attach(seg);
    }
    if (buf.item_size() != item_size(ndof)) {
        const std::size_t have = buf.item_size();
        buf.detach();
        throw ipc::SegmentError(seg, "holds items of " + std::to_string(have) + " bytes (" +
                                         std::to_string(have / sizeof(double)) + " joints), expected " +
                                         std::to_string(ndof) + " joints");
    }
    return buf;
}

}  // namespace chimera::teleop
