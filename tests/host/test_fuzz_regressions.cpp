// Inputs the fuzz harnesses found (fuzz/README.md), kept as regression
// tests: each harness must handle its parser's input with the parser's own
// errors. tests/data/fuzz/<harness>/<kind>-<hash> is the input as libFuzzer
// wrote it (binary ones as `xxd -p` text, <kind>-<hash>.hex); the fix is
// named in the commit that added it.
#include <sys/resource.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <vector>

#include "fuzz/fuzz.h"
#include "fuzz/tiny_dictionary.h"
#include "support.h"

namespace fs = std::filesystem;

namespace {

// `xxd -p` text back to its bytes (whitespace ignored).
std::vector<uint8_t> from_hex(const std::vector<uint8_t>& text) {
  std::vector<uint8_t> out;
  int high = -1;
  for (uint8_t c : text) {
    const int v = c >= '0' && c <= '9' ? c - '0' : c >= 'a' && c <= 'f' ? c - 'a' + 10 : -1;
    if (v < 0) continue;
    if (high < 0) high = v;
    else out.push_back(uint8_t(high * 16 + v)), high = -1;
  }
  return out;
}

}  // namespace

TEST_CASE("fuzz regressions: every input that once crashed a parser gets the parser's own error") {
  std::map<std::string, std::function<void(const uint8_t*, size_t)>> harnesses{
      {"scene", prism::fuzz::scene},         {"space", prism::fuzz::space},
      {"manifest", prism::fuzz::manifest},   {"events", prism::fuzz::events},
      {"psf_exr", prism::fuzz::psf_exr},     {"hdr_stack", prism::fuzz::hdr_stack},
#ifdef PRISM_FUZZ_CAMERA
      {"genicam", prism::fuzz::genicam},     {"gencp_ack", prism::fuzz::gencp_ack},
      {"stream_leader_trailer", prism::fuzz::stream_leader_trailer},
#endif
  };
  const fs::path root = fs::path(PRISM_SOURCE_DIR) / "tests" / "data" / "fuzz";
  size_t inputs = 0;
  for (const auto& dir : fs::directory_iterator(root)) {
    const std::string name = dir.path().filename().string();
    auto h = harnesses.find(name);
    if (h == harnesses.end()) {
#ifdef PRISM_FUZZ_CAMERA
      FAIL("tests/data/fuzz/" << name << ": no harness of that name (fuzz/fuzz.h)");
#endif
      continue;
    }
    for (const auto& f : fs::directory_iterator(dir.path())) {
      std::ifstream in(f.path(), std::ios::binary);
      std::vector<uint8_t> bytes((std::istreambuf_iterator<char>(in)), {});
      if (f.path().extension() == ".hex") bytes = from_hex(bytes);  // binary inputs are kept as `xxd -p` text
      CAPTURE(f.path().string());
      CHECK_NOTHROW(h->second(bytes.data(), bytes.size()));
      ++inputs;
    }
  }
  CHECK(inputs >= 4);  // the first long run's findings at least
}

TEST_CASE("fuzz regressions: a PSF header OpenEXR would allocate gigabytes for, or the walk misread, is refused before OpenEXR reads it") {
  // Without the sanitizer's allocation limit these inputs only cost time and
  // memory, so the check is the store's own refusal: the header walk finds
  // the declared size the file cannot hold (or a fixed-size value whose size
  // field differs, which puts OpenEXR's reading out of step with the file).
  const prism::DictionaryManifest m = prism::fuzz::tiny_manifest();
  const fs::path dir = prism::test::scratch_dir() / "psf-oom";
  fs::create_directories(dir / "psf");
  std::ofstream(dir / "manifest.json") << m.to_json().dump();
  size_t inputs = 0;
  for (const auto& f : fs::directory_iterator(fs::path(PRISM_SOURCE_DIR) / "tests/data/fuzz/psf_exr")) {
    const std::string name = f.path().filename().string();
    if (name.rfind("oom-", 0) != 0 && name.rfind("ub-", 0) != 0) continue;
    std::ifstream in(f.path(), std::ios::binary);
    const std::vector<uint8_t> bytes = from_hex(std::vector<uint8_t>((std::istreambuf_iterator<char>(in)), {}));
    std::ofstream(dir / m.file_of(0), std::ios::binary).write(reinterpret_cast<const char*>(bytes.data()),
                                                              std::streamsize(bytes.size()));
    CAPTURE(f.path().string());
    prism::DictionaryReader r(dir.string());
    CHECK_THROWS_AS(r.read_level(0, 0), prism::DictionaryError);
    // 862f3e55: a 'v3or' attribute whose size field reads 1.6e9 once OpenEXR
    // had read an earlier fixed-size value by its type, not by its size;
    // 74896006: tiles of 16 x 2.8e8 px (OpenEXR sized its buffers by them);
    // ub-04ed12f3: a preview of two damaged sizes whose product overflowed
    // the walk's own size check (undefined; the sanitizer suite reports it).
    if (name.find("862f3e55") != std::string::npos || name.find("74896006") != std::string::npos ||
        name.find("04ed12f3") != std::string::npos)
      CHECK_THROWS_WITH_AS(r.read_level(0, 0), doctest::Contains("corrupt OpenEXR header"), prism::DictionaryError);
    ++inputs;
  }
  CHECK(inputs >= 4);
}

TEST_CASE("fuzz regressions: an event file refused in its header leaves no file open") {
  // The events harness ran out of file descriptors: a reader whose
  // constructor threw never closed its file.
  const std::vector<uint8_t> bad{'P', 'R', 'I', 'S', 'M', 'E', 'V', 'T', 1, 0, 0, 0, 0, 0, 0, 0};  // sensor width 0
  // A few hundred descriptors at most for this check, whatever the machine allows.
  rlimit was{};
  REQUIRE(::getrlimit(RLIMIT_NOFILE, &was) == 0);
  rlimit low = was;
  low.rlim_cur = std::min<rlim_t>(was.rlim_cur, 512);
  REQUIRE(::setrlimit(RLIMIT_NOFILE, &low) == 0);
  for (int i = 0; i < 600; ++i) prism::fuzz::events(bad.data(), bad.size());
  std::FILE* f = std::fopen(PRISM_SOURCE_DIR "/README.md", "rb");
  ::setrlimit(RLIMIT_NOFILE, &was);
  CHECK(f != nullptr);
  if (f) std::fclose(f);
}
