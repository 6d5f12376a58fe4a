// Shared by the libFuzzer harnesses (fuzz/README.md). Each harness feeds
// outside data to one parser and lets only the parser's documented errors
// (std::runtime_error and its subclasses, which name the file and field)
// pass: anything else that escapes (a raw library exception, bad_alloc, a
// crash, a sanitizer report) is a finding.
#pragma once
// libFuzzer's entry point, left out where the harnesses are linked into the
// regression tests (PRISM_FUZZ_NO_MAIN).
#ifdef PRISM_FUZZ_NO_MAIN
#define PRISM_FUZZ_MAIN(harness)
#else
#define PRISM_FUZZ_MAIN(harness)                                                  \
  extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {       \
    prism::fuzz::harness(data, size);                                             \
    return 0;                                                                     \
  }
#endif
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <optional>
#include <sstream>
#include <string>

#include <nlohmann/json.hpp>

#include "host/util/json_file.h"

namespace prism::fuzz {

// The harnesses, one per parser (fuzz/<name>.cpp). Each returns normally for
// any input the parser handles, errors included; tests/host/test_fuzz_
// regressions.cpp runs them on the inputs that once crashed.
void scene(const uint8_t* data, size_t size);
void space(const uint8_t* data, size_t size);
void manifest(const uint8_t* data, size_t size);
void events(const uint8_t* data, size_t size);
void psf_exr(const uint8_t* data, size_t size);
void hdr_stack(const uint8_t* data, size_t size);
void genicam(const uint8_t* data, size_t size);
void gencp_ack(const uint8_t* data, size_t size);
void stream_leader_trailer(const uint8_t* data, size_t size);

// The input as JSON, or nothing when it is not JSON (the parsers' callers
// report that themselves, naming the file).
inline std::optional<nlohmann::json> json_of(const uint8_t* data, size_t size) {
  // As the commands read their files (host/util/json_file.h).
  std::istringstream in(std::string(reinterpret_cast<const char*>(data), size));
  try {
    return prism::parse_json_file(in);
  } catch (const prism::JsonSyntaxError&) {
  } catch (const prism::JsonDuplicateKey&) {
  }
  return std::nullopt;
}

// A folder of this process's own, made once, for parsers that read files;
// removed when the fuzzer exits normally (a crash leaves it beside its input).
inline const std::filesystem::path& scratch() {
  struct Scratch {
    std::filesystem::path path = std::filesystem::temp_directory_path() / ("prism-fuzz-" + std::to_string(::getpid()));
    Scratch() { std::filesystem::create_directories(path); }
    ~Scratch() {
      std::error_code ignored;
      std::filesystem::remove_all(path, ignored);
    }
  };
  static const Scratch dir;
  return dir.path;
}

inline std::string write_file(const std::filesystem::path& path, const uint8_t* data, size_t size) {
  std::ofstream(path, std::ios::binary | std::ios::trunc).write(reinterpret_cast<const char*>(data), std::streamsize(size));
  return path.string();
}

}  // namespace prism::fuzz
