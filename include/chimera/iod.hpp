// chimera/iod.hpp — reconfigurable I/O device drivers (thesis §7.2, §7.2.1).
//
// An IOD object is one open instance of a device that a task uses: a range of
// ports of a device named in the device database, with a direction, a WAIT
// mode and an element size fixed at open. The driver runs in user space, in
// the caller's thread; nothing is started behind the caller's back.
//
//   auto db  = iod::Database::load("lab.iod");
//   auto dio = iod::open(db, "dio0", 0, 7, iod::READ | iod::BYTE);
//   std::uint8_t bits[8];
//   dio->read(bits, 8);            // one element per port
//
// Classes and drivers (DRIVER in the database):
//   PIO  gpio       GPIO lines through libgpiod 1.6; a port is WIDTH adjacent
//                   lines (bit i = line start+i); input lines are requested
//                   with both-edge events so reads can wait for changes.
//   RCB  socketcan  a SocketCAN raw socket; each FRAME line of the database
//                   maps one CAN identifier to N ports of B bits packed
//                   little-endian in the payload (a CiA 301 PDO layout).
//   SIO  termios    a serial line (stream device, one port, bytes).
//   MEM  shm        a shared-memory block (one port, bytes, plus mmap()).
//
// Device database (a configuration file in the project's style, cfg.hpp):
//   DEVICE <name> <class> <driver>
//     PATH <chip | interface | tty | segment name>
//     ...driver keywords (see each driver below)...
//   END
//   ...
//   EOF
// PIO:  LINES <n>  [WIDTH <bits per port, default 1>]  [DIRECTION IN|OUT|INOUT]
// RCB:  FRAME <can-id> IN|OUT <ports> <bits per port>   (one line per frame)
//       [EXTENDED]  (29-bit identifiers)
// SIO:  [BAUD <rate>] [BITS 5-8] [STOP 1|2] [PARITY NONE|ODD|EVEN|MARK|SPACE]
// MEM:  SIZE <bytes>
//
// Ports opened by one instance are refused to every other instance, in this
// process or any other (an OFD byte-range lock per port on a lock file in
// /dev/shm, released by the kernel when the process dies). Direction, size,
// conversion and WAIT flags are checked at open, never in the cycle.
//
// Errors: open() and Database::load() throw iod::Error (what() names the file
// and line, or the device). read/write/status/control are noexcept and return
// a negative errno on failure, as the thesis's time-critical methods do.
#pragma once

#include "chimera/export.hpp"

#include <cstddef>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace chimera::iod {

// --- open flags (thesis §7.2.1) ----------------------------------------------
inline constexpr unsigned NONE = 0x0;       ///< neither read nor write (the default)
inline constexpr unsigned READ = 0x1;
inline constexpr unsigned WRITE = 0x2;
inline constexpr unsigned RW = READ | WRITE;
/// Wait for all requested data; block if necessary.
inline constexpr unsigned WAITALL = 0x10;
/// Wait for at least one piece of data; block if necessary.
inline constexpr unsigned WAITONE = 0x20;
/// Do not wait; return what is available.
inline constexpr unsigned WAITNONE = 0x40;
/// Do not wait; return everything or nothing.
inline constexpr unsigned WAITNOALL = 0x80;
inline constexpr unsigned BYTE = 0x100;  ///< 8-bit buffer elements
inline constexpr unsigned WORD = 0x200;  ///< 16-bit buffer elements
inline constexpr unsigned LONG = 0x400;  ///< 32-bit buffer elements
/// Expanding: pad with the sign bit instead of zeros.
inline constexpr unsigned SIGNED = 0x1000;
/// Reducing: drop least significant bits instead of most significant ones
/// (and, symmetrically, writing a narrow element fills the port's high bits).
inline constexpr unsigned TRUNC_LSB = 0x2000;

inline constexpr unsigned kDirectionMask = RW;
inline constexpr unsigned kWaitMask = WAITALL | WAITONE | WAITNONE | WAITNOALL;
inline constexpr unsigned kSizeMask = BYTE | WORD | LONG;

/// Device classes of §7.2.
enum class DeviceClass { SIO, PIO, ADC, DAC, RCB, SBS, MEM };
CHIMERA_API std::string_view class_name(DeviceClass c) noexcept;

// --- status and control commands -----------------------------------------------
enum class Status : int {
    PORTSIZE = 1,   ///< arg: port number; returns its size in bits
    PORTNUM = 2,    ///< returns the number of logical ports of the device
    FLAGS = 3,      ///< returns the instance's current flags
    SIO_GET = 100,  ///< arg: SioParam*; current line settings
    SIO_SET = 101,  ///< arg: const SioParam*; applies them
    SIO_NREAD = 102,///< returns bytes waiting to be read
    CAN_RX_FRAMES = 200,   ///< frames received for this instance
    CAN_ERRORS = 201,      ///< error frames received
    CAN_LAST_ERROR = 202,  ///< can_id of the last error frame (CAN_ERR_* class bits)
    CAN_TIMESTAMP = 203,   ///< arg: port; kernel receive time (ns, CLOCK_REALTIME) of its frame
    PIO_EVENTS = 300,      ///< edge events seen since open
    /// arg: a port of this instance (device numbering, start..end); edge
    /// events seen on that port's lines since open (-EINVAL for another port).
    /// Like PIO_EVENTS, a lower bound when the kernel's event buffer of a line
    /// overflowed between two reads.
    PIO_PORT_EVENTS = 301,
    MEM_SIZE = 400,        ///< bytes in the block
};

enum class Control : int {
    /// arg: new flags. WAIT, size and conversion flags may change at run time;
    /// the direction may not (-EINVAL), and unsupported combinations are
    /// refused exactly as at open.
    SET_FLAGS = 1,
    /// MEM: arg is the byte offset that read/write use (-EINVAL past the end).
    MEM_SEEK = 400,
    /// SIO: discard unread input and unsent output.
    SIO_FLUSH = 101,
    /// arg: microseconds, or -1 to wait without bound (the default). Bounds
    /// how long one read with WAITONE or WAITALL blocks: when the time runs
    /// out first, read() returns 0 with the buffer untouched, and what had
    /// arrived stays pending for the next read. For a task that blocks on its
    /// input (a synchronous task's sync()) and must still answer commands.
    /// PIO, RCB and SIO reads (-ENOTSUP for MEM, which never blocks).
    WAIT_TIMEOUT = 2,
};

/// Serial parameters (the thesis's iodSioParam_t).
struct SioParam {
    int baud_rx = 9600;
    int baud_tx = 9600;
    std::uint8_t bits = 8;
    std::uint8_t stop = 1;
    std::uint8_t parity = 0;  ///< one of the SIO_* parity values below
};
inline constexpr std::uint8_t SIO_NONE = 0;
inline constexpr std::uint8_t SIO_ODD = 1;
inline constexpr std::uint8_t SIO_EVEN = 2;
inline constexpr std::uint8_t SIO_MARK = 3;
inline constexpr std::uint8_t SIO_SPACE = 4;

/// Set-up error (open, database); what() names the device or FILE:LINE.
class CHIMERA_API Error : public std::runtime_error {
public:
    explicit Error(const std::string& message) : std::runtime_error(message) {}
};

// --- the device database ----------------------------------------------------------
struct FrameSpec {
    std::uint32_t can_id = 0;
    bool input = true;
    int ports = 0;        ///< ports carried by this frame
    int port_bits = 0;    ///< bits per port, ports * port_bits <= 64
    int first_port = 0;   ///< logical number of its first port
};

struct CHIMERA_API DeviceSpec {
    std::string name;
    DeviceClass device_class = DeviceClass::PIO;
    std::string driver;   ///< gpio, socketcan, termios, shm
    std::string path;
    std::string file;     ///< database file and line, for messages
    int line = 0;
    // PIO
    int lines = 0;
    int width = 1;
    unsigned directions = RW;   ///< what the hardware allows (IN = READ, OUT = WRITE)
    // RCB
    std::vector<FrameSpec> frames;
    bool extended = false;
    // SIO
    SioParam sio;
    // MEM
    std::size_t size = 0;

    int port_count() const noexcept;
    int port_bits(int port) const noexcept;
};

class CHIMERA_API Database {
public:
    /// Parses a database file; throws iod::Error "FILE:LINE: message".
    static Database load(const std::string& path);
    static Database from_string(std::string_view text, std::string name);
    /// The device of that logical name, or nullptr.
    const DeviceSpec* find(std::string_view name) const noexcept;
    const std::vector<DeviceSpec>& devices() const noexcept { return devices_; }

private:
    std::vector<DeviceSpec> devices_;
};

// --- the IOD object ------------------------------------------------------------------
class CHIMERA_API Device {
public:
    virtual ~Device();
    Device(const Device&) = delete;
    Device& operator=(const Device&) = delete;

    /// Port devices: fills `count` >= nports() elements (one per opened port,
    /// element size from the flags) and returns how many ports had new data
    /// (what "data" means per WAIT flag: see docs/iod.md). Stream and memory
    /// devices: reads up to `count` bytes, returns the number read.
    /// Negative errno on failure; 0 when nothing new is available and the
    /// WAIT flag says not to block.
    [[nodiscard]] virtual long read(void* buf, std::size_t count) noexcept = 0;
    /// Port devices: writes one element per opened port from `buf`
    /// (`count` >= nports()). Streams and memory: `count` bytes.
    [[nodiscard]] virtual long write(const void* buf, std::size_t count) noexcept = 0;
    /// Status command (PORTSIZE, PORTNUM, FLAGS are common to all classes).
    [[nodiscard]] long status(Status cmd, long arg = 0) noexcept;
    [[nodiscard]] long status(Status cmd, void* arg) noexcept;
    [[nodiscard]] long control(Control cmd, long arg) noexcept;
    /// MEM only: the mapped block (nullptr for other classes).
    virtual void* mmap() noexcept { return nullptr; }

    const DeviceSpec& spec() const noexcept { return spec_; }
    int start_port() const noexcept { return start_; }
    int end_port() const noexcept { return end_; }
    int nports() const noexcept { return end_ - start_ + 1; }
    unsigned flags() const noexcept { return flags_; }
    /// Bytes per buffer element (1, 2 or 4).
    int element_bytes() const noexcept;

protected:
    Device(const DeviceSpec& spec, int start, int end, unsigned flags);
    virtual long class_status(Status cmd, long arg, void* parg) noexcept;
    virtual long class_control(Control cmd, long arg) noexcept;
    /// Checks a flag set for this device (shared by open and SET_FLAGS);
    /// returns an empty string or the reason it is refused.
    virtual std::string check_flags(unsigned flags) const;
    void set_flags(unsigned flags) noexcept { flags_ = flags; }

    // Element conversion between a port value of `port_bits` and the buffer.
    std::uint32_t element_to_port(const void* buf, int index, int port_bits) const noexcept;
    void port_to_element(std::uint32_t raw, void* buf, int index, int port_bits) const noexcept;

private:
    friend std::unique_ptr<Device> open(const Database&, std::string_view, int, int, unsigned,
                                        const void*);
    DeviceSpec spec_;
    int start_;
    int end_;
    unsigned flags_;
    int lock_fd_ = -1;
};

/// Opens ports start..end of the device `name` (thesis iodOpen). Throws
/// iod::Error: unknown device, bad range, ports already open, direction the
/// hardware does not have, unsupported size/conversion/WAIT flag, or the
/// kernel interface missing ("no AF_CAN support in this kernel", "no gpiochip
/// named ...").
///
/// `initial`, for a PIO device opened WRITE only: one element per port, laid
/// out and converted as for write(), that the lines take as they are
/// requested, so an output never shows any other value first (without it they
/// come up at 0, which is not the safe state of an active-low output). An
/// initial buffer for any other device or direction is refused.
CHIMERA_API std::unique_ptr<Device> open(const Database& db, std::string_view name, int start, int end,
                                         unsigned flags, const void* initial = nullptr);

/// Value conversions of §7.2.1, exposed for tests and SAI modules.
/// Port value (port_bits wide) → element (elem_bits wide).
CHIMERA_API std::uint32_t convert_in(std::uint32_t raw, int port_bits, int elem_bits, unsigned flags) noexcept;
/// Element value (elem_bits wide) → port value (port_bits wide).
CHIMERA_API std::uint32_t convert_out(std::uint32_t value, int elem_bits, int port_bits, unsigned flags) noexcept;

/// Directory of the per-device lock files (default /dev/shm; CHIMERA_IOD_LOCKDIR).
CHIMERA_API std::string lock_directory();

}  // namespace chimera::iod
