#include "hw/gencp.h"

#include <algorithm>

#include "hw/usb.h"

namespace prism::hw {
namespace {

Bytes header(uint16_t command, uint16_t scd_size, uint16_t request_id) {
  Bytes b;
  put_le(b, u3v::kCommandPrefix, 4);
  put_le(b, u3v::kFlagRequestAck, 2);
  put_le(b, command, 2);
  put_le(b, scd_size, 2);
  put_le(b, request_id, 2);
  return b;
}

std::string hex(uint64_t v) {
  char s[32];
  snprintf(s, sizeof s, "0x%llx", static_cast<unsigned long long>(v));
  return s;
}

}  // namespace

std::string status_text(uint16_t s) {
  using u3v::Status;
  switch (Status(s)) {
    case Status::Success: return "success";
    case Status::NotImplemented: return "command not implemented by the camera";
    case Status::InvalidParameter: return "invalid parameter";
    case Status::InvalidAddress: return "address not mapped on the camera (check the GenICam XML)";
    case Status::WriteProtect: return "register is read-only";
    case Status::BadAlignment: return "address or length misaligned";
    case Status::AccessDenied: return "access denied (register locked, e.g. while streaming: stop acquisition first)";
    case Status::Busy: return "camera busy; retry later";
    case Status::MsgTimeout: return "camera timed out internally";
    case Status::InvalidHeader: return "camera rejected the command header";
    case Status::WrongConfig: return "not allowed in the current configuration";
    case Status::GenericError: return "unspecified camera error";
    case Status::ResendNotSupported: return "resend not supported";
    case Status::StreamEndpointHalted: return "stream endpoint halted";
    case Status::PayloadNotAligned: return "payload size not aligned to the stream alignment";
    case Status::InvalidSiState: return "stream interface registers written while streaming";
    case Status::EventEndpointHalted: return "event endpoint halted";
  }
  return "unknown status " + hex(s);
}

GenCpError::GenCpError(const std::string& what, uint16_t s)
    : std::runtime_error(what + ": " + status_text(s) + " (GenCP status " + hex(s) + ")"), status(s) {}

Bytes encode_readmem(uint16_t id, uint64_t address, uint16_t count) {
  Bytes b = header(u3v::kReadMemCmd, u3v::kReadMemScdSize, id);
  put_le(b, address, 8);
  put_le(b, 0, 2);
  put_le(b, count, 2);
  return b;
}

Bytes encode_writemem(uint16_t id, uint64_t address, std::span<const uint8_t> data) {
  Bytes b = header(u3v::kWriteMemCmd, uint16_t(u3v::kWriteMemAddrSize + data.size()), id);
  put_le(b, address, 8);
  b.insert(b.end(), data.begin(), data.end());
  return b;
}

std::optional<Ack> parse_ack(std::span<const uint8_t> p, std::string& why) {
  if (p.size() < u3v::kHeaderSize) {
    why = "acknowledge shorter than its 12-byte header (" + std::to_string(p.size()) + " bytes)";
    return std::nullopt;
  }
  if (get32(p, 0) != u3v::kCommandPrefix) {
    why = "acknowledge has wrong prefix " + hex(get32(p, 0)) + " (expected U3VC)";
    return std::nullopt;
  }
  Ack a{get16(p, 4), get16(p, 6), get16(p, 10), {}};
  size_t scd = get16(p, 8);
  if (u3v::kHeaderSize + scd > p.size()) {
    why = "acknowledge announces " + std::to_string(scd) + " data bytes but carries " +
          std::to_string(p.size() - u3v::kHeaderSize);
    return std::nullopt;
  }
  a.scd.assign(p.begin() + u3v::kHeaderSize, p.begin() + long(u3v::kHeaderSize + scd));
  if (a.command == u3v::kPendingAck && a.scd.size() < 4) {
    why = "pending acknowledge without its timeout field";
    return std::nullopt;
  }
  return a;
}

GenCp::GenCp(UsbDevice& dev) : dev_(dev) {}

void GenCp::set_transfer_limits(uint32_t max_cmd, uint32_t max_ack) {
  // Below header + address + 4 data bytes no register could ever be accessed.
  constexpr uint32_t kMin = u3v::kHeaderSize + u3v::kWriteMemAddrSize + 4;
  if (max_cmd < kMin || max_ack < kMin)
    throw std::runtime_error("camera announces unusable GenCP transfer limits (command " + std::to_string(max_cmd) +
                             ", ack " + std::to_string(max_ack) + " bytes); its SBRM is broken");
  max_cmd_ = std::min<uint32_t>(max_cmd, 65536);
  max_ack_ = std::min<uint32_t>(max_ack, 65536);
}

bool GenCp::send(const Bytes& command) {
  int done = 0;
  int r = dev_.bulk_out(dev_.control_out, command, done, timeout_ms_);
  if (r == LIBUSB_ERROR_PIPE) {
    dev_.clear_halt(dev_.control_out);
    return false;
  }
  if (r == LIBUSB_ERROR_TIMEOUT) return false;
  if (r != 0) throw UsbError("sending a GenCP command", r);
  if (size_t(done) != command.size())
    throw std::runtime_error("camera accepted only " + std::to_string(done) + " of " +
                             std::to_string(command.size()) + " command bytes");
  return true;
}

std::optional<Ack> GenCp::receive(unsigned timeout_ms) {
  Bytes buf(max_ack_);
  int done = 0;
  int r = dev_.bulk_in(dev_.control_in, buf, done, timeout_ms);
  if (r == LIBUSB_ERROR_PIPE) {
    dev_.clear_halt(dev_.control_in);
    return std::nullopt;
  }
  if (r == LIBUSB_ERROR_TIMEOUT) return std::nullopt;
  if (r != 0) throw UsbError("reading a GenCP acknowledge", r);
  std::string why;
  auto ack = parse_ack(std::span(buf).first(size_t(done)), why);
  if (!ack) throw std::runtime_error("malformed GenCP acknowledge: " + why);
  return ack;
}

// The one place that sends a command and waits for its acknowledge.
Bytes GenCp::transact(const Bytes& command, uint16_t id, uint16_t expected_ack) {
  for (int attempt = 0; attempt < kAttempts; ++attempt) {
    if (attempt > 0) ++retries;
    if (!send(command)) continue;
    unsigned timeout = timeout_ms_;
    while (auto ack = receive(timeout)) {
      if (ack->request_id != id) {  // answer to a request we already gave up on
        ++stale_acks;
        continue;
      }
      if (ack->command == u3v::kPendingAck) {  // device asks for more time
        ++pending_acks;
        timeout = get16(ack->scd, 2);
        continue;
      }
      if (ack->status != uint16_t(u3v::Status::Success))
        throw GenCpError("camera refused GenCP command " + hex(get16(command, 6)), ack->status);
      if (ack->command != expected_ack)
        throw std::runtime_error("camera answered command " + hex(get16(command, 6)) + " with " + hex(ack->command));
      return ack->scd;
    }
  }
  throw UsbError("no GenCP acknowledge after " + std::to_string(kAttempts) + " attempts of " +
                     std::to_string(timeout_ms_) + " ms",
                 LIBUSB_ERROR_TIMEOUT);
}

Bytes GenCp::read(uint64_t address, size_t count) {
  Bytes out;
  const size_t chunk = max_ack_ - u3v::kHeaderSize;
  while (out.size() < count) {
    size_t n = std::min(chunk, count - out.size());
    uint16_t id = next_id_++;
    Bytes scd = transact(encode_readmem(id, address + out.size(), uint16_t(n)), id, u3v::kReadMemAck);
    if (scd.size() != n)
      throw std::runtime_error("camera returned " + std::to_string(scd.size()) + " bytes for a " +
                               std::to_string(n) + "-byte read at " + hex(address + out.size()));
    out.insert(out.end(), scd.begin(), scd.end());
  }
  return out;
}

void GenCp::write(uint64_t address, std::span<const uint8_t> data) {
  const size_t chunk = max_cmd_ - u3v::kHeaderSize - u3v::kWriteMemAddrSize;
  for (size_t off = 0; off < data.size(); off += chunk) {
    auto part = data.subspan(off, std::min(chunk, data.size() - off));
    uint16_t id = next_id_++;
    Bytes scd = transact(encode_writemem(id, address + off, part), id, u3v::kWriteMemAck);
    if (scd.size() >= 4 && get16(scd, 2) != part.size())
      throw std::runtime_error("camera wrote " + std::to_string(get16(scd, 2)) + " of " +
                               std::to_string(part.size()) + " bytes at " + hex(address + off));
  }
}

void GenCp::write32(uint64_t address, uint32_t v) {
  Bytes b;
  put_le(b, v, 4);
  write(address, b);
}
void GenCp::write64(uint64_t address, uint64_t v) {
  Bytes b;
  put_le(b, v, 8);
  write(address, b);
}

}  // namespace prism::hw
