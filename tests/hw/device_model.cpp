#include "device_model.h"

#include <zip.h>

#include <cerrno>
#include <cstring>
#include <stdexcept>

#include "hw/bytes.h"
#include "hw/pixels.h"
#include "hw/u3v_regs.h"

namespace prism::hw::test {
namespace {

const char* kXml = R"(<?xml version="1.0" encoding="utf-8"?>
<RegisterDescription ModelName="PrismSim" VendorName="PRISM">
  <Category Name="Root"><pFeature>Width</pFeature></Category>
  <Integer Name="Width"><pValue>WidthReg</pValue><Min>8</Min><Max>64</Max><Inc>2</Inc></Integer>
  <IntReg Name="WidthReg"><Address>0x8000</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Sign>Unsigned</Sign><Endianess>LittleEndian</Endianess></IntReg>
  <Integer Name="Height"><pValue>HeightReg</pValue><Min>8</Min><Max>48</Max></Integer>
  <IntReg Name="HeightReg"><Address>0x8004</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Endianess>LittleEndian</Endianess></IntReg>
  <Enumeration Name="PixelFormat">
    <EnumEntry Name="Mono8"><Value>0x01080001</Value></EnumEntry>
    <EnumEntry Name="Mono12"><Value>0x01100005</Value></EnumEntry>
    <EnumEntry Name="Mono12p"><Value>0x010C0047</Value></EnumEntry>
    <EnumEntry Name="Mono16"><Value>0x01100007</Value></EnumEntry>
    <pValue>PixelFormatReg</pValue>
  </Enumeration>
  <IntReg Name="PixelFormatReg"><Address>0x8008</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Endianess>LittleEndian</Endianess></IntReg>
  <Float Name="ExposureTime"><pValue>ExposureTimeReg</pValue><Min>10</Min><Max>1000000</Max><Unit>us</Unit></Float>
  <FloatReg Name="ExposureTimeReg"><Address>0x800C</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><Endianess>LittleEndian</Endianess></FloatReg>
  <Command Name="AcquisitionStart"><pValue>AcquisitionStartReg</pValue><CommandValue>1</CommandValue></Command>
  <IntReg Name="AcquisitionStartReg"><Address>0x8010</Address><Length>4</Length><AccessMode>WO</AccessMode><pPort>Device</pPort><Endianess>LittleEndian</Endianess></IntReg>
  <Command Name="AcquisitionStop"><pValue>AcquisitionStopReg</pValue><CommandValue>1</CommandValue></Command>
  <IntReg Name="AcquisitionStopReg"><Address>0x8014</Address><Length>4</Length><AccessMode>WO</AccessMode><pPort>Device</pPort><Endianess>LittleEndian</Endianess></IntReg>
  <Integer Name="BinningHorizontal"><pValue>BinningHorizontalReg</pValue><Min>1</Min><Max>4</Max></Integer>
  <MaskedIntReg Name="BinningHorizontalReg"><Address>0x8018</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><LSB>0</LSB><MSB>3</MSB><Endianess>LittleEndian</Endianess></MaskedIntReg>
  <Integer Name="BinningVertical"><pValue>BinningVerticalReg</pValue><Min>1</Min><Max>4</Max></Integer>
  <MaskedIntReg Name="BinningVerticalReg"><Address>0x8018</Address><Length>4</Length><AccessMode>RW</AccessMode><pPort>Device</pPort><LSB>8</LSB><MSB>11</MSB><Endianess>LittleEndian</Endianess></MaskedIntReg>
  <Integer Name="SensorWidth"><Value>64</Value></Integer>
  <Port Name="Device"/>
</RegisterDescription>
)";

Bytes zip_xml(const std::string& xml) {
  zip_error_t err;
  zip_error_init(&err);
  zip_source_t* src = zip_source_buffer_create(nullptr, 0, 0, &err);
  zip_source_keep(src);
  zip_t* za = zip_open_from_source(src, ZIP_TRUNCATE, &err);
  zip_source_t* member = zip_source_buffer(za, xml.data(), xml.size(), 0);
  zip_file_add(za, "PrismSim.xml", member, 0);
  if (zip_close(za) != 0) throw std::runtime_error("model: cannot build zip");
  zip_source_open(src);
  zip_source_seek(src, 0, SEEK_END);
  Bytes out(size_t(zip_source_tell(src)));
  zip_source_seek(src, 0, SEEK_SET);
  zip_source_read(src, out.data(), out.size());
  zip_source_close(src);
  zip_source_free(src);
  return out;
}

std::string hex(const Bytes& b) {
  std::string s;
  char t[3];
  for (uint8_t v : b) snprintf(t, sizeof t, "%02X", v), s += t;
  return s;
}

}  // namespace

uint16_t pattern(uint32_t x, uint32_t y, uint64_t block, unsigned bits) {
  return uint16_t((x * 37 + y * 101 + block * 7) % (1u << bits));
}

DeviceModel::DeviceModel(Faults f) : faults(f), xml_(kXml), random_(f.random_seed) {
  auto put = [&](uint64_t a, uint64_t v, size_t n) {
    for (size_t i = 0; i < n; ++i) mem_[a + i] = uint8_t(v >> (8 * i));
  };
  auto str = [&](uint64_t a, const std::string& s) {
    for (size_t i = 0; i < u3v::kStringSize; ++i) mem_[a + i] = i < s.size() ? uint8_t(s[i]) : 0;
  };
  for (uint64_t a = 0; a < u3v::kAbrmSize; ++a) mem_[a] = 0;
  put(u3v::kAbrmGenCpVersion, 0x00010000, 4);
  str(u3v::kAbrmManufacturerName, "PRISM");
  str(u3v::kAbrmModelName, "PrismSim U3V");
  str(u3v::kAbrmSerialNumber, serial());
  put(u3v::kAbrmMaxDeviceResponseTime, 150, 4);
  put(u3v::kAbrmManifestTableAddress, kManifestAddr, 8);
  put(u3v::kAbrmSbrmAddress, kSbrmAddr, 8);
  for (uint64_t a = 0; a < u3v::kSbrmSize; ++a) mem_[kSbrmAddr + a] = 0;
  put(kSbrmAddr + u3v::kSbrmU3vVersion, 0x00010000, 4);
  put(kSbrmAddr + u3v::kSbrmMaxCmdTransfer, kMaxCmd, 4);
  put(kSbrmAddr + u3v::kSbrmMaxAckTransfer, kMaxAck, 4);
  put(kSbrmAddr + u3v::kSbrmNumStreamChannels, 1, 4);
  put(kSbrmAddr + u3v::kSbrmSirmAddress, kSirmAddr, 8);
  put(kSbrmAddr + u3v::kSbrmSirmLength, u3v::kSirmSize, 4);
  for (uint64_t a = 0; a < u3v::kSirmSize; ++a) mem_[kSirmAddr + a] = 0;
  put(kSirmAddr + u3v::kSirmInfo, 6u << 24, 4);  // 2^6 = 64-byte alignment
  put(kSirmAddr + u3v::kSirmRequiredLeader, u3v::kImageLeaderSize, 4);
  put(kSirmAddr + u3v::kSirmRequiredTrailer, u3v::kImageTrailerSize, 4);
  put(kRegWidth, kSensorW, 4);
  put(kRegHeight, kSensorH, 4);
  put(kRegPixelFormat, kMono16, 4);
  float e = 1000.f;
  uint32_t eb;
  std::memcpy(&eb, &e, 4);
  put(kRegExposure, eb, 4);
  put(kRegAcqStart, 0, 4);
  put(kRegAcqStop, 0, 4);
  put(kRegBinning, 0x0101, 4);
  Bytes file = faults.zipped_xml ? zip_xml(xml_) : Bytes(xml_.begin(), xml_.end());
  put(kManifestAddr, 1, 8);
  for (uint64_t a = 0; a < u3v::kManifestEntrySize; ++a) mem_[kManifestAddr + 8 + a] = 0;
  put(kManifestAddr + 8 + u3v::kManifestSchemaOffset, (faults.zipped_xml ? 1u : 0u) << 10, 4);
  put(kManifestAddr + 8 + u3v::kManifestAddressOffset, kXmlAddr, 8);
  put(kManifestAddr + 8 + u3v::kManifestSizeOffset, file.size(), 8);
  for (size_t i = 0; i < file.size(); ++i) mem_[kXmlAddr + i] = file[i];
}

std::string DeviceModel::umockdev_description() const {
  // Device descriptor (USB 3.0, IAD class), then a configuration with the
  // three U3V interfaces; bulk endpoints of 1024 bytes with SS companions.
  Bytes d = {0x12, 0x01, 0x00, 0x03, 0xEF, 0x02, 0x01, 0x09, 0x09, 0x12, 0x33, 0x75, 0x00, 0x01, 1, 2, 3, 1};
  Bytes cfg = {0x09, 0x02, 0, 0, 3, 1, 0, 0xC0, 50, 0x08, 0x0B, 0, 3, 0xEF, 0x05, 0, 0};
  auto itf = [&](uint8_t n, uint8_t proto, std::initializer_list<uint8_t> eps) {
    Bytes i = {0x09, 0x04, n, 0, uint8_t(eps.size()), 0xEF, 0x05, proto, 0};
    cfg.insert(cfg.end(), i.begin(), i.end());
    for (uint8_t ep : eps) {
      Bytes e = {0x07, 0x05, ep, 0x02, 0x00, 0x04, 0, 0x06, 0x30, 0, 0, 0, 0};
      cfg.insert(cfg.end(), e.begin(), e.end());
    }
  };
  itf(0, u3v::kProtocolControl, {kCtrlOut, kCtrlIn});
  itf(1, u3v::kProtocolEvent, {kEventIn});
  itf(2, u3v::kProtocolStream, {kStreamIn});
  cfg[2] = uint8_t(cfg.size()), cfg[3] = uint8_t(cfg.size() >> 8);
  d.insert(d.end(), cfg.begin(), cfg.end());
  return "P: /devices/pci0000:00/0000:00:14.0/usb2/2-1\nN: bus/usb/002/003=" + hex(d) +
         "\nE: SUBSYSTEM=usb\nE: DEVTYPE=usb_device\nE: DRIVER=usb\nE: BUSNUM=002\nE: DEVNUM=003\n"
         "E: DEVNAME=/dev/bus/usb/002/003\nA: busnum=2\nA: devnum=3\nA: speed=5000\nA: bConfigurationValue=1\n"
         "A: bNumConfigurations=1\nH: descriptors=" + hex(d) + "\n";
}

uint32_t DeviceModel::r32(uint64_t a) const {
  uint32_t v = 0;
  for (int i = 0; i < 4; ++i) v |= uint32_t(mem_.at(a + i)) << (8 * i);
  return v;
}
void DeviceModel::w32(uint64_t a, uint32_t v) {
  for (int i = 0; i < 4; ++i) mem_[a + i] = uint8_t(v >> (8 * i));
}
uint32_t DeviceModel::reg32(uint64_t a) const {
  std::lock_guard lock(mu_);
  return r32(a);
}
float DeviceModel::exposure_us() const {
  uint32_t b = reg32(kRegExposure);
  float f;
  std::memcpy(&f, &b, 4);
  return f;
}
unsigned DeviceModel::frames_sent() const {
  std::lock_guard lock(mu_);
  return frames_;
}
std::map<uint64_t, Faults::Stream> DeviceModel::faults_injected() const {
  std::lock_guard lock(mu_);
  return injected_;
}
bool DeviceModel::unplugged() const {
  std::lock_guard lock(mu_);
  return gone_;
}

void DeviceModel::queue_ack(uint16_t status, uint16_t command, uint16_t id, const Bytes& scd) {
  Bytes a;
  put_le(a, u3v::kCommandPrefix, 4);
  put_le(a, status, 2);
  put_le(a, command, 2);
  put_le(a, scd.size(), 2);
  put_le(a, id, 2);
  a.insert(a.end(), scd.begin(), scd.end());
  if (faults.drop_first_ack && !dropped_ack_ && command != u3v::kPendingAck) {
    dropped_ack_ = true;  // lost on the wire: the host's retry gets the next one
    return;
  }
  acks_.push_back(a);
}

void DeviceModel::out(uint8_t ep, const Bytes& data) {
  std::lock_guard lock(mu_);
  if (ep == kCtrlOut) handle_command(data);
}

// The device side of GenCP: decode independently of hw/gencp.cpp and answer.
void DeviceModel::handle_command(const Bytes& c) {
  using u3v::Status;
  if (c.size() < 12 || get32(c, 0) != u3v::kCommandPrefix || c.size() > kMaxCmd || get16(c, 8) != c.size() - 12)
    return queue_ack(uint16_t(Status::InvalidHeader), 0, c.size() >= 12 ? get16(c, 10) : 0, {});
  uint16_t cmd = get16(c, 6), id = get16(c, 10);
  uint64_t addr = get64(c, 12);
  if (cmd == u3v::kReadMemCmd) {
    uint16_t n = get16(c, 22);
    if (faults.pending_ack && !pended_) {
      pended_ = true;
      queue_ack(0, u3v::kPendingAck, id, {0, 0, 200, 0});  // 200 ms more
    }
    if (size_t(n) + 12 > kMaxAck) return queue_ack(uint16_t(Status::InvalidParameter), u3v::kReadMemAck, id, {});
    Bytes scd;
    for (uint64_t a = addr; a < addr + n; ++a) {
      auto it = mem_.find(a);
      if (it == mem_.end()) return queue_ack(uint16_t(Status::InvalidAddress), u3v::kReadMemAck, id, {});
      scd.push_back(it->second);
    }
    return queue_ack(0, u3v::kReadMemAck, id, scd);
  }
  if (cmd == u3v::kWriteMemCmd) {
    size_t n = c.size() - 20;
    for (size_t i = 0; i < n; ++i)
      if (!mem_.count(addr + i)) return queue_ack(uint16_t(Status::InvalidAddress), u3v::kWriteMemAck, id, {});
    if (addr >= kSirmAddr + u3v::kSirmRequiredPayload && addr < kSirmAddr + u3v::kSirmSize && (r32(kSirmAddr + 4) & 1))
      return queue_ack(uint16_t(Status::InvalidSiState), u3v::kWriteMemAck, id, {});
    for (size_t i = 0; i < n; ++i) mem_[addr + i] = c[20 + i];
    if (addr == kRegAcqStart && r32(kRegAcqStart)) acquiring_ = true;
    if (addr == kRegAcqStop && r32(kRegAcqStop)) acquiring_ = false, stream_.clear();
    // Payload size follows the image settings, as on a real camera.
    uint32_t w = r32(kRegWidth), h = r32(kRegHeight);
    uint64_t payload = image_bytes(r32(kRegPixelFormat), w, h);
    for (int i = 0; i < 8; ++i) mem_[kSirmAddr + u3v::kSirmRequiredPayload + i] = uint8_t(payload >> (8 * i));
    return queue_ack(0, u3v::kWriteMemAck, id, {0, 0, uint8_t(n), uint8_t(n >> 8)});
  }
  queue_ack(uint16_t(Status::NotImplemented), uint16_t(cmd + 1), id, {});
}

// Cuts one frame into the transfers SIRM asks for, applying a stream fault if due.
void DeviceModel::queue_frame() {
  using F = Faults::Stream;
  const uint64_t block = frames_++;
  const bool hit = faults.frame && *faults.frame == block;
  F fault = hit ? faults.stream : F::None;
  if (fault == F::None && faults.random_rate > 0 && !faults.random_kinds.empty() &&
      std::uniform_real_distribution<double>(0, 1)(random_) < faults.random_rate)
    fault = faults.random_kinds[random_() % faults.random_kinds.size()];
  if (fault != F::None) injected_[block] = fault;
  uint32_t w = r32(kRegWidth), h = r32(kRegHeight), fmt = r32(kRegPixelFormat);
  unsigned bits = bit_depth(fmt);
  Bytes px;  // pack the pattern in the wire format
  for (uint32_t y = 0; y < h; ++y)
    for (uint32_t x = 0; x < w; ++x) {
      uint16_t v = pattern(x, y, block, bits);
      if (fmt == kMono8) px.push_back(uint8_t(v));
      else if (fmt == kMono12p) {
        uint64_t i = uint64_t(y) * w + x;
        if (i % 2 == 0) px.push_back(uint8_t(v)), px.push_back(uint8_t(v >> 8));
        else px.back() |= uint8_t(v << 4), px.push_back(uint8_t(v >> 4));
      } else put_le(px, v, 2);
    }
  Bytes leader(u3v::kImageLeaderSize, 0);
  set_le(leader, 0, fault == F::BadLeaderMagic ? 0x12345678 : u3v::kLeaderMagic, 4);
  set_le(leader, 6, leader.size(), 2);
  set_le(leader, 8, block, 8);
  set_le(leader, 18, u3v::kPayloadImage, 2);
  set_le(leader, 20, block * 1000, 8);
  set_le(leader, 28, fmt, 4);
  set_le(leader, 32, w, 4);
  set_le(leader, 36, h, 4);
  if (fault == F::TruncatedLeader) leader.resize(20);
  stream_.push_back(leader);
  if (fault == F::Unplug) {
    gone_ = true;
    return;
  }
  const uint32_t ts = r32(kSirmAddr + u3v::kSirmPayloadTransferSize), n = r32(kSirmAddr + u3v::kSirmPayloadTransferCount);
  const uint32_t f1 = r32(kSirmAddr + u3v::kSirmFinalTransfer1), f2 = r32(kSirmAddr + u3v::kSirmFinalTransfer2);
  size_t off = 0;
  std::vector<size_t> sizes(n, ts);
  if (f1) sizes.push_back(f1);
  if (f2) sizes.push_back(f2);
  for (size_t i = 0; i < sizes.size() && off < px.size(); ++i) {
    Bytes t(px.begin() + long(off), px.begin() + long(std::min(px.size(), off + sizes[i])));
    off += t.size();
    if (i == 1 && fault == F::ShortTransfer) t.resize(t.size() / 2);
    if (i == 1 && fault == F::LostTransfer) continue;
    if (i == 1 && fault == F::Stall) {
      stream_.push_back({});  // marker: the endpoint halts here, rest of the frame is lost
      return;
    }
    if (i + 1 == sizes.size() && fault == F::Oversize) t.resize(t.size() + 4096, 0xAB);
    stream_.push_back(t);
  }
  Bytes trailer(u3v::kImageTrailerSize, 0);
  set_le(trailer, 0, fault == F::BadTrailerMagic ? 0x87654321 : u3v::kTrailerMagic, 4);
  set_le(trailer, 6, trailer.size(), 2);
  set_le(trailer, 8, block, 8);
  set_le(trailer, 16, fault == F::TrailerStatus ? 0x8FFF : 0, 2);
  set_le(trailer, 20, px.size(), 8);
  set_le(trailer, 28, h, 4);
  if (fault == F::TruncatedTrailer) trailer.resize(16);
  stream_.push_back(trailer);
  if (fault == F::Silence) acquiring_ = false;  // camera stops sending, nothing tells the host
}

std::optional<DeviceModel::In> DeviceModel::in(uint8_t ep, size_t length) {
  std::lock_guard lock(mu_);
  if (gone_ && (ep != kStreamIn || stream_.empty())) return In{-ENODEV, {}};
  if (ep == kCtrlIn) {
    if (acks_.empty()) return std::nullopt;
    Bytes a = std::move(acks_.front());
    acks_.pop_front();
    if (a.size() > length) return In{-EOVERFLOW, Bytes(a.begin(), a.begin() + long(length))};
    return In{0, a};
  }
  if (ep != kStreamIn) return std::nullopt;
  if (halted_) return In{-EPIPE, {}};
  if (stream_.empty() && acquiring_ && (r32(kSirmAddr + u3v::kSirmControl) & 1) && !gone_) queue_frame();
  if (stream_.empty()) return std::nullopt;
  Bytes t = std::move(stream_.front());
  stream_.pop_front();
  if (t.empty()) {  // stall marker
    halted_ = true;
    return In{-EPIPE, {}};
  }
  if (t.size() > length) return In{-EOVERFLOW, Bytes(t.begin(), t.begin() + long(length))};
  return In{0, t};
}

void DeviceModel::clear_halt(uint8_t ep) {
  std::lock_guard lock(mu_);
  if (ep == kStreamIn) halted_ = false;
}

Bytes DeviceModel::control_in(const uint8_t s[8]) {
  // GET_DESCRIPTOR (0x06) of type string (0x03): index 0 = language list.
  if (s[0] != 0x80 || s[1] != 0x06 || s[3] != 0x03) return {};
  const char* strings[] = {"", "PRISM", "PrismSim U3V", "PRISM-0001"};
  if (s[2] == 0) return {4, 0x03, 0x09, 0x04};
  if (s[2] > 3) return {};
  std::string str = strings[s[2]];
  Bytes d = {uint8_t(2 + 2 * str.size()), 0x03};
  for (char ch : str) d.push_back(uint8_t(ch)), d.push_back(0);
  return d;
}

}  // namespace prism::hw::test
