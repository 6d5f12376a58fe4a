// A small USB3 Vision camera, written from the device's side: USB descriptors,
// bootstrap registers, a GenICam XML manifest, GenCP responder and a frame
// stream, plus switchable faults. fake_usb.cpp serves it to libusb through
// umockdev's usbdevfs ioctl emulation.
#pragma once
#include <cstdint>
#include <deque>
#include <map>
#include <mutex>
#include <optional>
#include <random>
#include <string>
#include <vector>

namespace prism::hw::test {

using Bytes = std::vector<uint8_t>;

// Endpoints of the model (control OUT/IN, event IN, stream IN).
inline constexpr uint8_t kCtrlOut = 0x01, kCtrlIn = 0x81, kEventIn = 0x82, kStreamIn = 0x83;
inline constexpr uint64_t kSbrmAddr = 0x1000, kSirmAddr = 0x2000, kManifestAddr = 0x3000, kXmlAddr = 0x10000;
inline constexpr uint64_t kRegWidth = 0x8000, kRegHeight = 0x8004, kRegPixelFormat = 0x8008, kRegExposure = 0x800C,
                          kRegAcqStart = 0x8010, kRegAcqStop = 0x8014, kRegBinning = 0x8018;
inline constexpr uint32_t kSensorW = 64, kSensorH = 48, kAlignment = 64, kMaxCmd = 256, kMaxAck = 256;

struct Faults {
  bool pending_ack = false;        // answer the first READMEM with PENDING_ACK first
  bool drop_first_ack = false;     // swallow one acknowledge: the host must retry
  bool zipped_xml = true;          // manifest entry holds a zip (else plain XML)
  std::optional<unsigned> frame;   // frame index (0-based) the stream fault hits
  enum class Stream { None, ShortTransfer, LostTransfer, BadLeaderMagic, TruncatedLeader, BadTrailerMagic,
                      TruncatedTrailer, Oversize, TrailerStatus, Stall, Unplug, Silence } stream = Stream::None;
  size_t usbfs_limit = 0;          // bytes of URB buffers the "kernel" accepts at once (0 = unlimited)
  // Soak: besides `frame`, each frame gets a fault with probability
  // random_rate, of a kind drawn from random_kinds (a kind listed n times is
  // drawn n times as often); seeded, so a failing run repeats exactly.
  double random_rate = 0;
  std::vector<Stream> random_kinds;
  uint64_t random_seed = 1;
};

// Pixel value the model puts at (x, y) of frame `block`, before packing.
uint16_t pattern(uint32_t x, uint32_t y, uint64_t block, unsigned bits);

class DeviceModel {
 public:
  explicit DeviceModel(Faults f = {});
  std::string umockdev_description() const;  // sysfs + descriptors for the testbed
  std::string serial() const { return "PRISM-0001"; }

  // USB side, called by the ioctl handler (thread-safe).
  void out(uint8_t ep, const Bytes& data);          // host wrote a bulk OUT transfer
  struct In { int status; Bytes data; };            // status is 0 or -errno
  std::optional<In> in(uint8_t ep, size_t length);  // nullopt: nothing to send yet
  Bytes control_in(const uint8_t setup[8]);         // standard GET_DESCRIPTOR requests
  void clear_halt(uint8_t ep);
  bool unplugged() const;
  Faults faults;

  // Inspection for tests.
  uint32_t reg32(uint64_t addr) const;
  float exposure_us() const;
  unsigned frames_sent() const;
  std::map<uint64_t, Faults::Stream> faults_injected() const;  // block id -> the fault its frame got
  std::string xml() const { return xml_; }

 private:
  void handle_command(const Bytes& cmd);
  void queue_ack(uint16_t status, uint16_t command, uint16_t id, const Bytes& scd);
  void queue_frame();
  uint32_t r32(uint64_t a) const;
  void w32(uint64_t a, uint32_t v);

  mutable std::mutex mu_;
  std::map<uint64_t, uint8_t> mem_;  // sparse device memory
  std::string xml_;
  std::deque<Bytes> acks_;
  std::deque<Bytes> stream_;         // device transfers waiting for host buffers
  bool acquiring_ = false, halted_ = false, gone_ = false, dropped_ack_ = false, pended_ = false;
  unsigned frames_ = 0;
  std::map<uint64_t, Faults::Stream> injected_;
  std::mt19937_64 random_;
};

}  // namespace prism::hw::test
