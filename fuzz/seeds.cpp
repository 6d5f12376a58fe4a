// Writes the seed corpus of every harness (fuzz/corpus/<harness>/): valid
// inputs of each format, from the same code that writes them for real.
// Run from fuzz/run.sh when fuzz/corpus is missing, or by hand after a format
// changes: fuzz_seeds DIR.
#include <filesystem>
#include <fstream>
#include <iostream>

#include "fuzz/tiny_dictionary.h"
#include "host/dictionary/hdr_stack.h"
#include "host/events/event_file.h"
#include "host/scene/scene.h"
#ifdef PRISM_FUZZ_CAMERA
#include "hw/u3v_regs.h"
#endif

namespace fs = std::filesystem;

namespace {

void text(const fs::path& path, const std::string& s) {
  fs::create_directories(path.parent_path());
  std::ofstream(path) << s;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::cerr << "usage: fuzz_seeds DIR (writes DIR/<harness>/...)\n";
    return 2;
  }
  const fs::path out = argv[1];
  // Scenes: the built-in ones as scene files.
  for (const char* name : {"prototype", "unifocal-f15", "single-f3"})
    text(out / "scene" / (std::string(name) + ".json"), prism::to_json(prism::builtin_scene(name)).dump(1));
  // Sweep spaces: the examples (host/sweep/spaces), copied by fuzz/run.sh.
  // Manifests and a PSF: the psf_exr harness's one-entry dictionary.
  const prism::DictionaryManifest m = prism::fuzz::tiny_manifest();
  text(out / "manifest" / "tiny.json", m.to_json().dump(1));
  prism::PsfLevel l0{0, m.width, m.height, std::vector<float>(size_t(m.width) * m.height, 0.0f)};
  for (int y = 20; y < 28; ++y)
    for (int x = 28; x < 36; ++x) l0.p[size_t(y) * m.width + x] = 1.0f / 64;
  fs::create_directories(out / "psf_exr");
  prism::write_psf_file((out / "psf_exr" / "blob.exr").string(), m, 0, l0, 50.0);
  // Events: two events, one with two vertices.
  {
    prism::EventFileHeader h;
    h.sensor_width_px = 64;
    h.sensor_height_px = 48;
    h.pixel_um = 110.4;
    h.binning = 1;
    h.seed = 1;
    h.scene = "fuzz";
    h.provenance = "fuzz seed";
    fs::create_directories(out / "events");
    prism::EventWriter w((out / "events" / "two.events").string(), h);
    prism::Event a;
    a.id = 0;
    a.vertices = {{1, 2, 10, 100, 0.9}};
    a.clicks = {5, 70, 71, 300};
    w.write(a);
    prism::Event b;
    b.id = 1;
    b.vertices = {{1, 2, 10, 100, 0.9}, {-3, 0, 20, 50, 0.8}};
    b.clicks = {0, 1000, 3071};
    w.write(b);
    w.close();
  }
  // An HDR stack naming the harness's frames (exposure_0.raw, dark_0.raw).
  {
    prism::HdrStack s;
    s.frames.width = 8;
    s.frames.height = 8;
    s.frames.bit_depth = 12;
    s.frames.exposures = {std::vector<uint16_t>(64, 256)};
    s.frames.exposure_s = {1e-3};
    s.frames.darks = {std::vector<uint16_t>(64, 256)};
    s.frames.dark_s = {1e-3};
    s.source_mm = {1, 1, 31};
    const fs::path dir = out / ".stack";
    prism::write_hdr_stack(dir.string(), s);
    fs::create_directories(out / "hdr_stack");
    fs::copy_file(dir / "stack.json", out / "hdr_stack" / "stack.json", fs::copy_options::overwrite_existing);
    fs::remove_all(dir);
  }
#ifdef PRISM_FUZZ_CAMERA
  // USB3 Vision: a read-memory acknowledge with 4 data bytes, an image leader
  // and trailer (first byte 0: leader, 1: trailer; stream_leader_trailer.cpp).
  {
    using namespace prism::hw::u3v;
    auto put = [](std::vector<uint8_t>& b, size_t at, uint64_t v, int bytes) {
      for (int i = 0; i < bytes; ++i) b[at + size_t(i)] = uint8_t(v >> (8 * i));
    };
    auto binary = [&](const fs::path& path, const std::vector<uint8_t>& b) {
      fs::create_directories(path.parent_path());
      std::ofstream(path, std::ios::binary).write(reinterpret_cast<const char*>(b.data()), std::streamsize(b.size()));
    };
    std::vector<uint8_t> ack(kHeaderSize + 4, 0);
    put(ack, 0, kCommandPrefix, 4);
    put(ack, 6, kReadMemAck, 2);
    put(ack, 8, 4, 2);
    put(ack, 10, 7, 2);
    put(ack, kHeaderSize, 0x12345678, 4);
    binary(out / "gencp_ack" / "readmem.bin", ack);
    std::vector<uint8_t> leader(1 + kImageLeaderSize, 0), trailer(1 + kImageTrailerSize, 0);
    trailer[0] = 1;
    put(leader, 1 + kStreamMagic, kLeaderMagic, 4);
    put(leader, 1 + kStreamHeaderSize, kImageLeaderSize, 2);
    put(leader, 1 + kStreamBlockId, 3, 8);
    put(leader, 1 + kLeaderPayloadType, kPayloadImage, 2);
    put(leader, 1 + kLeaderPixelFormat, 0x01100005, 4);  // Mono12
    put(leader, 1 + kLeaderSizeX, 64, 4);
    put(leader, 1 + kLeaderSizeY, 48, 4);
    binary(out / "stream_leader_trailer" / "leader.bin", leader);
    put(trailer, 1 + kStreamMagic, kTrailerMagic, 4);
    put(trailer, 1 + kStreamHeaderSize, kImageTrailerSize, 2);
    put(trailer, 1 + kStreamBlockId, 3, 8);
    put(trailer, 1 + kTrailerValidPayload, 64 * 48 * 2, 8);
    put(trailer, 1 + kTrailerSizeY, 48, 4);
    binary(out / "stream_leader_trailer" / "trailer.bin", trailer);
  }
#endif
  std::cout << "fuzz_seeds: wrote " << out.string() << "\n";
  return 0;
}
