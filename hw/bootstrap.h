// Bootstrap: read ABRM, then SBRM, then SIRM, and fetch the GenICam XML
// through the manifest table (plain or zipped).
#pragma once
#include <string>

#include "hw/gencp.h"

namespace prism::hw {

struct Bootstrap {
  // ABRM
  std::string manufacturer, model, family, version, serial, user_name;
  uint32_t response_time_ms = 0;
  uint64_t manifest_address = 0, sbrm_address = 0;
  // SBRM
  uint32_t u3v_version = 0, max_cmd = 0, max_ack = 0, stream_channels = 0;
  uint64_t sirm_address = 0;
  uint32_t sirm_length = 0;
  // SIRM
  uint32_t payload_alignment = 1;  // bytes; payload transfers must be multiples of it
};

// Reads the three register maps and applies the limits to `gencp`.
Bootstrap read_bootstrap(GenCp& gencp);

// Reads the first manifest entry's file; unzips it when the entry says so.
std::string fetch_genicam_xml(GenCp& gencp, uint64_t manifest_address);

// Extracts the first .xml member of a zip archive held in memory.
std::string unzip_xml(std::span<const uint8_t> zip);

}  // namespace prism::hw
