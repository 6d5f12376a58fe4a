#include "hw/bootstrap.h"

#include <zip.h>

#include <memory>

namespace prism::hw {

Bootstrap read_bootstrap(GenCp& g) {
  Bootstrap b;
  Bytes abrm = g.read(0, u3v::kAbrmSize);
  auto str = [&](uint64_t off) { return get_string(abrm, off, u3v::kStringSize); };
  b.manufacturer = str(u3v::kAbrmManufacturerName);
  b.model = str(u3v::kAbrmModelName);
  b.family = str(u3v::kAbrmFamilyName);
  b.version = str(u3v::kAbrmDeviceVersion);
  b.serial = str(u3v::kAbrmSerialNumber);
  b.user_name = str(u3v::kAbrmUserDefinedName);
  b.response_time_ms = get32(abrm, u3v::kAbrmMaxDeviceResponseTime);
  b.manifest_address = get64(abrm, u3v::kAbrmManifestTableAddress);
  b.sbrm_address = get64(abrm, u3v::kAbrmSbrmAddress);
  // Aravis users hit too-short timeouts: never wait less than the camera asks, nor under 100 ms.
  g.set_response_timeout(std::max<unsigned>(b.response_time_ms, 100));

  Bytes sbrm = g.read(b.sbrm_address, u3v::kSbrmSize);
  b.u3v_version = get32(sbrm, u3v::kSbrmU3vVersion);
  b.max_cmd = get32(sbrm, u3v::kSbrmMaxCmdTransfer);
  b.max_ack = get32(sbrm, u3v::kSbrmMaxAckTransfer);
  b.stream_channels = get32(sbrm, u3v::kSbrmNumStreamChannels);
  b.sirm_address = get64(sbrm, u3v::kSbrmSirmAddress);
  b.sirm_length = get32(sbrm, u3v::kSbrmSirmLength);
  g.set_transfer_limits(b.max_cmd, b.max_ack);

  if (b.stream_channels > 0 && b.sirm_address != 0) {
    uint32_t info = g.read32(b.sirm_address + u3v::kSirmInfo);
    uint32_t shift = info >> 24;
    if (shift > 20) throw std::runtime_error("camera's SIRM announces a 2^" + std::to_string(shift) +
                                             "-byte payload alignment; its SIRM is broken");
    b.payload_alignment = 1u << shift;
  }
  return b;
}

std::string unzip_xml(std::span<const uint8_t> data) {
  zip_error_t err;
  zip_error_init(&err);
  zip_source_t* src = zip_source_buffer_create(data.data(), data.size(), 0, &err);
  zip_t* za = src ? zip_open_from_source(src, ZIP_RDONLY, &err) : nullptr;
  if (!za) {
    std::string msg = zip_error_strerror(&err);
    if (src) zip_source_free(src);
    zip_error_fini(&err);
    throw std::runtime_error("camera's zipped GenICam XML cannot be opened: " + msg);
  }
  std::unique_ptr<zip_t, decltype(&zip_discard)> archive(za, zip_discard);
  for (zip_int64_t i = 0; i < zip_get_num_entries(za, 0); ++i) {
    std::string name = zip_get_name(za, zip_uint64_t(i), 0);
    if (name.size() < 4 || name.substr(name.size() - 4) != ".xml") continue;
    zip_stat_t st;
    zip_stat_index(za, zip_uint64_t(i), 0, &st);
    std::unique_ptr<zip_file_t, decltype(&zip_fclose)> f(zip_fopen_index(za, zip_uint64_t(i), 0), zip_fclose);
    std::string xml(st.size, '\0');
    if (!f || zip_fread(f.get(), xml.data(), st.size) != zip_int64_t(st.size))
      throw std::runtime_error("camera's zipped GenICam XML member '" + name + "' is unreadable");
    return xml;
  }
  throw std::runtime_error("camera's GenICam zip archive holds no .xml file");
}

std::string fetch_genicam_xml(GenCp& g, uint64_t manifest_address) {
  if (g.read64(manifest_address) == 0) throw std::runtime_error("camera's manifest table is empty: no GenICam XML");
  Bytes entry = g.read(manifest_address + 8, u3v::kManifestEntrySize);
  uint64_t address = get64(entry, u3v::kManifestAddressOffset);
  uint64_t size = get64(entry, u3v::kManifestSizeOffset);
  uint32_t type = (get32(entry, u3v::kManifestSchemaOffset) >> 10) & 0x3f;
  if (size == 0 || size > (64u << 20))
    throw std::runtime_error("camera's manifest announces a " + std::to_string(size) + "-byte GenICam file");
  Bytes file = g.read(address, size_t(size));
  if (type == u3v::kManifestTypeZip) return unzip_xml(file);
  if (type != u3v::kManifestTypeXml)
    throw std::runtime_error("camera's GenICam file has unknown type " + std::to_string(type));
  return std::string(file.begin(), file.end());
}

}  // namespace prism::hw
