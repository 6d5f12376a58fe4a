#include "hw/stream.h"

#include <libusb.h>

#include <chrono>
#include <deque>
#include <memory>
#include <optional>

#include "hw/u3v_regs.h"
#include "hw/usb.h"

namespace prism::hw {

namespace {

// Checks what leader and trailer share: size, magic and the size field.
bool check_header(std::span<const uint8_t> b, size_t min_size, uint32_t magic, const char* what, std::string& why) {
  using namespace u3v;
  if (b.size() < min_size) {
    why = std::string(what) + " truncated (" + std::to_string(b.size()) + " of " + std::to_string(min_size) + " bytes)";
    return false;
  }
  if (get32(b, kStreamMagic) != magic) {
    why = std::string(what) + " has wrong magic";
    return false;
  }
  if (get16(b, kStreamHeaderSize) < min_size || get16(b, kStreamHeaderSize) > b.size()) {
    why = std::string(what) + " size field " + std::to_string(get16(b, kStreamHeaderSize)) +
          " disagrees with the transfer";
    return false;
  }
  return true;
}

}  // namespace

std::optional<Leader> parse_leader(std::span<const uint8_t> b, std::string& why) {
  using namespace u3v;
  if (!check_header(b, kImageLeaderSize, kLeaderMagic, "leader", why)) return std::nullopt;
  if (get16(b, kLeaderPayloadType) != kPayloadImage) {
    why = "leader payload type is not an image";
    return std::nullopt;
  }
  return Leader{get64(b, kStreamBlockId), get64(b, kLeaderTimestamp), get32(b, kLeaderPixelFormat),
                get32(b, kLeaderSizeX), get32(b, kLeaderSizeY)};
}

std::optional<Trailer> parse_trailer(std::span<const uint8_t> b, std::string& why) {
  using namespace u3v;
  if (!check_header(b, kImageTrailerSize, kTrailerMagic, "trailer", why)) return std::nullopt;
  return Trailer{get64(b, kStreamBlockId), get64(b, kTrailerValidPayload), get16(b, kTrailerStatus),
                 get32(b, kTrailerSizeY)};
}

StreamLayout plan_layout(uint64_t payload, uint32_t alignment, uint32_t leader, uint32_t trailer,
                         uint32_t max_transfer) {
  if (alignment == 0 || payload == 0) throw std::runtime_error("stream layout needs a payload size and alignment");
  StreamLayout l;
  l.payload_size = payload;
  auto up = [&](uint64_t v) { return uint32_t((v + alignment - 1) / alignment * alignment); };
  l.max_leader = up(std::max<uint32_t>(leader, u3v::kImageLeaderSize));
  l.max_trailer = up(std::max<uint32_t>(trailer, u3v::kImageTrailerSize));
  l.transfer_size = std::max(alignment, max_transfer / alignment * alignment);
  l.transfer_count = uint32_t(payload / l.transfer_size);
  uint64_t rest = payload - uint64_t(l.transfer_count) * l.transfer_size;
  // Final transfer 1 takes the aligned part of the rest, final 2 the last unaligned bytes
  // (rounded up: the device pads it to the alignment).
  l.final1 = uint32_t(rest / alignment * alignment);
  l.final2 = rest % alignment ? alignment : 0;
  return l;
}

namespace {

enum class Role { Leader, Payload, Trailer };

// One frame's worth of transfers; payload transfers point into `data`.
struct Slot {
  Bytes leader, data, trailer;
  std::vector<libusb_transfer*> xfers;  // leader, payloads..., trailer
  std::vector<Role> roles;
  Leader leader_info;
  bool has_leader = false;  // leader_info is this frame's (its leader parsed)
  std::string bad;          // first reason this frame cannot be delivered
  unsigned pending = 0;
};

struct Completion {
  unsigned slot, index;
};

class Streamer {
 public:
  Streamer(UsbDevice& dev, const StreamLayout& l, const StreamOptions& o) : dev_(dev), l_(l), opt_(o) {
    slots_.resize(std::max(1u, o.frames_in_flight));
    for (unsigned s = 0; s < slots_.size(); ++s) build(s);
  }
  ~Streamer() {
    cancel_all();
    if (in_flight_ > 0) return;  // the kernel still owns some: leaking beats a use-after-free
    for (auto& s : slots_)
      for (auto* t : s.xfers) libusb_free_transfer(t);
  }

  StreamResult run(unsigned frames, const std::function<void(Frame&&)>& on_frame) {
    wanted_ = frames;
    for (unsigned s = 0; s < slots_.size() && res_.error.empty(); ++s) submit_slot(s, true);
    auto last = std::chrono::steady_clock::now();
    while (res_.delivered < wanted_ && res_.error.empty()) {
      if (in_flight_ == 0 && done_.empty()) break;  // nothing queued: submission failed
      timeval tv{0, 50000};
      int r = libusb_handle_events_timeout_completed(dev_.context(), &tv, nullptr);
      if (r != 0 && r != LIBUSB_ERROR_INTERRUPTED) res_.error = usb_error_text("waiting for stream data", r);
      if (!done_.empty()) last = std::chrono::steady_clock::now();
      while (!done_.empty() && res_.error.empty()) {
        Completion c = done_.front();
        done_.pop_front();
        handle(c, on_frame);
      }
      if (std::chrono::steady_clock::now() - last > std::chrono::milliseconds(opt_.idle_timeout_ms))
        res_.error = "no stream data for " + std::to_string(opt_.idle_timeout_ms) +
                     " ms; is acquisition started and the camera triggered?";
    }
    if (res_.error.empty() && res_.delivered < wanted_) res_.error = "stream stopped before all frames arrived";
    return res_;
  }

 private:
  static void LIBUSB_CALL on_transfer(libusb_transfer* t) {
    auto* self = static_cast<Streamer*>(t->user_data);
    for (unsigned s = 0; s < self->slots_.size(); ++s)
      for (unsigned i = 0; i < self->slots_[s].xfers.size(); ++i)
        if (self->slots_[s].xfers[i] == t) {
          --self->in_flight_;
          --self->slots_[s].pending;
          self->done_.push_back({s, i});
          return;
        }
  }

  void build(unsigned s) {
    Slot& slot = slots_[s];
    auto add = [&](Role r) {
      slot.xfers.push_back(libusb_alloc_transfer(0));
      slot.roles.push_back(r);
    };
    add(Role::Leader);
    unsigned payloads = l_.transfer_count + (l_.final1 > 0) + (l_.final2 > 0);
    for (unsigned i = 0; i < payloads; ++i) add(Role::Payload);
    add(Role::Trailer);
  }

  // Points the slot's transfers at fresh buffers; in hunt mode only the leader goes out.
  void submit_slot(unsigned s, bool with_body) {
    Slot& slot = slots_[s];
    slot.leader.assign(l_.max_leader, 0);
    slot.trailer.assign(l_.max_trailer, 0);
    slot.data.assign(uint64_t(l_.transfer_count) * l_.transfer_size + l_.final1 + l_.final2, 0);
    slot.bad.clear();
    slot.has_leader = false;
    size_t off = 0;
    for (unsigned i = 0; i < slot.xfers.size(); ++i) {
      uint8_t* buf;
      uint32_t len;
      if (slot.roles[i] == Role::Leader) {
        buf = slot.leader.data(), len = l_.max_leader;
      } else if (slot.roles[i] == Role::Trailer) {
        buf = slot.trailer.data(), len = l_.max_trailer;
      } else {
        len = slot_length(i);
        buf = slot.data.data() + off;
        off += len;
      }
      libusb_fill_bulk_transfer(slot.xfers[i], dev_.handle(), dev_.stream_in, buf, int(len), on_transfer, this, 0);
    }
    unsigned first = 0, last = with_body ? unsigned(slot.xfers.size()) : 1;
    submit_range(s, first, last);
  }

  void submit_range(unsigned s, unsigned first, unsigned last) {
    Slot& slot = slots_[s];
    for (unsigned i = first; i < last; ++i) {
      int r = libusb_submit_transfer(slot.xfers[i]);
      if (r != 0) {
        res_.error = usb_error_text("queueing a stream transfer", r);
        return;
      }
      ++in_flight_;
      ++slot.pending;
    }
  }

  void drop(const std::string& why) { ++res_.drops[why]; }

  void handle(Completion c, const std::function<void(Frame&&)>& on_frame) {
    Slot& slot = slots_[c.slot];
    libusb_transfer* t = slot.xfers[c.index];
    Role role = slot.roles[c.index];
    switch (t->status) {
      case LIBUSB_TRANSFER_COMPLETED:
        halt_cleared_ = false;
        break;
      case LIBUSB_TRANSFER_NO_DEVICE:
        res_.error = usb_error_text("streaming", LIBUSB_ERROR_NO_DEVICE);
        return;
      case LIBUSB_TRANSFER_STALL:
        if (slot.bad.empty()) slot.bad = "stream endpoint stalled";
        if (!halt_cleared_) {  // once per stall: every queued transfer reports it
          if (int r = libusb_clear_halt(dev_.handle(), dev_.stream_in); r != 0) {
            res_.error = usb_error_text("clearing the stalled stream endpoint", r);
            return;
          }
          halt_cleared_ = true;
          ++res_.stalls_cleared;
        }
        break;
      case LIBUSB_TRANSFER_OVERFLOW:
        if (slot.bad.empty()) slot.bad = "device sent more than a transfer holds";
        break;
      case LIBUSB_TRANSFER_CANCELLED: return;
      default:
        if (slot.bad.empty()) slot.bad = "transfer failed";
    }
    std::string why;
    if (t->status == LIBUSB_TRANSFER_COMPLETED && slot.bad.empty()) {
      if (role == Role::Leader) {
        auto ld = parse_leader(std::span(slot.leader).first(size_t(t->actual_length)), why);
        if (!ld) slot.bad = why;
        else slot.leader_info = *ld, slot.has_leader = true;
      } else if (role == Role::Payload && uint64_t(t->actual_length) != expected_length(c.index)) {
        slot.bad = "short payload transfer";
      }
    }
    if (hunting_ && role == Role::Leader) {  // resynchronising: only a good leader ends the hunt
      if (!slot.bad.empty()) {
        drop("resync: discarded " + slot.bad);
        return clear_and_resubmit(c.slot, false);
      }
      hunting_ = false;
      submit_range(c.slot, 1, unsigned(slot.xfers.size()));
      for (unsigned s = 0; s < slots_.size(); ++s)
        if (s != c.slot) submit_slot(s, true);
      return;
    }
    if (role != Role::Trailer) return;
    finish(c.slot, t, on_frame);
  }

  void finish(unsigned s, libusb_transfer* t, const std::function<void(Frame&&)>& on_frame) {
    Slot& slot = slots_[s];
    std::string why;
    std::optional<Trailer> tr;
    if (t->status == LIBUSB_TRANSFER_COMPLETED) tr = parse_trailer(std::span(slot.trailer).first(size_t(t->actual_length)), why);
    bool aligned = tr.has_value();  // a good trailer means the next frame starts cleanly
    if (slot.bad.empty() && !tr) slot.bad = why;
    if (slot.bad.empty()) {
      const Leader& ld = slot.leader_info;
      if (tr->block_id != ld.block_id) slot.bad = "trailer block id differs from the leader's";
      else if (tr->status != 0) slot.bad = "camera flagged the frame (trailer status)";
      else if (tr->valid_payload_size != l_.payload_size) slot.bad = "payload size differs from SIRM's";
      else if (tr->height != ld.height) slot.bad = "trailer line count differs from the leader's";
    }
    if (res_.delivered >= wanted_) {
      // queued beyond the request: not a drop, just not wanted
      return;
    }
    // The frame's block id, from its leader or else its trailer; with neither,
    // the gap before the next frame with an id counts it.
    const std::optional<uint64_t> id =
        slot.has_leader ? std::optional(slot.leader_info.block_id) : tr ? std::optional(tr->block_id) : std::nullopt;
    if (id) count_missing_before(*id);
    if (slot.bad.empty()) {
      const Leader& ld = slot.leader_info;
      Frame f{ld.block_id, ld.timestamp, ld.pixel_format, ld.width, ld.height, std::move(slot.data)};
      f.data.resize(l_.payload_size);
      ++res_.delivered;
      on_frame(std::move(f));
    } else {
      drop(slot.bad);
      if (id) ++res_.frames_dropped;
    }
    if (!aligned) return start_hunt(s);
    if (res_.delivered + in_flight_frames() < wanted_) submit_slot(s, true);
  }

  // Frames between the last one accounted for and block `id` never arrived
  // whole (their leaders were lost); a camera that restarts its numbering
  // starts the count again.
  void count_missing_before(uint64_t id) {
    if (next_block_ && id > *next_block_) res_.frames_dropped += unsigned(std::min<uint64_t>(id - *next_block_, 1u << 30));
    next_block_ = id + 1;
  }

  // Payload transfer i (1-based) must be full, except the last, which holds what remains.
  uint64_t expected_length(unsigned i) const {
    uint64_t before = 0;
    for (unsigned p = 1; p < i; ++p) before += slot_length(p);
    return std::min<uint64_t>(slot_length(i), l_.payload_size - std::min(before, l_.payload_size));
  }
  uint32_t slot_length(unsigned i) const {
    unsigned p = i - 1;
    return p < l_.transfer_count ? l_.transfer_size : (p == l_.transfer_count && l_.final1 ? l_.final1 : l_.final2);
  }

  unsigned in_flight_frames() const {
    unsigned n = 0;
    for (auto& s : slots_) n += s.pending > 0;
    return n;
  }

  // Transfers after a lost trailer are misaligned: cancel them, then submit
  // single leader buffers until one holds a leader (bulk IN is flow-controlled,
  // so the camera waits for us and nothing after that leader is lost).
  void start_hunt(unsigned s) {
    cancel_all();
    hunting_ = true;
    clear_and_resubmit(s, false);
  }
  void clear_and_resubmit(unsigned s, bool body) {
    if (res_.delivered < wanted_) submit_slot(s, body);
  }

  void cancel_all() {
    for (auto& s : slots_)
      for (auto* t : s.xfers) libusb_cancel_transfer(t);
    for (int spins = 0; in_flight_ > 0 && spins < 100; ++spins) {
      timeval tv{0, 20000};
      libusb_handle_events_timeout_completed(dev_.context(), &tv, nullptr);
    }
    done_.clear();
  }

  UsbDevice& dev_;
  StreamLayout l_;
  StreamOptions opt_;
  std::vector<Slot> slots_;
  std::deque<Completion> done_;
  StreamResult res_;
  unsigned wanted_ = 0, in_flight_ = 0;
  bool hunting_ = false, halt_cleared_ = false;
  std::optional<uint64_t> next_block_;  // block id the next frame should carry
};

}  // namespace

StreamResult run_stream(UsbDevice& dev, const StreamLayout& layout, unsigned frames,
                        const std::function<void(Frame&&)>& on_frame, const StreamOptions& opt) {
  auto s = std::make_unique<Streamer>(dev, layout, opt);
  return s->run(frames, on_frame);
}

}  // namespace prism::hw
