// Calibration stacks on disk (capture-hdr's format): round trip, errors that
// name the file and field, and `prism dictionary merge-hdr` and `assemble`
// end to end.
#include <cstdlib>
#include <functional>
#include <filesystem>
#include <fstream>
#include <numeric>
#include <sstream>

#include "compare.h"
#include "engine/ref/forward_ref.h"
#include "engine/ref/hdr_merge_ref.h"
#include "host/dictionary/hdr_stack.h"
#include "host/dictionary/store.h"
#include "host/scene/scene.h"
#include "host/util/image_io.h"
#include "host/util/memory.h"
#include "support.h"

namespace fs = std::filesystem;
using namespace prism;

namespace {

fs::path fresh_dir(const std::string& name) {
  fs::path d = prism::test::scratch_dir() / "hdr" / name;
  fs::remove_all(d);
  fs::create_directories(d);
  return d;
}

HdrStack small_stack(int w = 32, int h = 24, uint64_t seed = 1) {
  HdrStack s;
  s.source_mm = {5.0, -10.0, 25.0};
  s.frames = simulate_hdr_frames(synthetic_psf(w, h, 2e6), w, h, log_spaced_times(20e-6, 0.2, 7), {0.2, 0.2, 0.2},
                                 SyntheticSensor{}, seed);
  return s;
}

// What read_hdr_stack says about a stack after `spoil` changed it; "" if it reads.
template <class F> std::string error_after(F&& spoil) {
  fs::path d = fresh_dir("bad");
  write_hdr_stack(d.string(), small_stack());
  spoil(d);
  try {
    read_hdr_stack(d.string());
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}

void edit_json(const fs::path& dir, const std::function<void(nlohmann::json&)>& edit) {
  nlohmann::json j;
  std::ifstream(dir / "stack.json") >> j;
  edit(j);
  std::ofstream(dir / "stack.json") << j.dump();
}

// Runs the prism binary on the tests' device (main.cpp's PRISM_DEVICE,
// inherited); returns its exit status, with stdout+stderr in `output`.
int prism_cli(const std::string& args, std::string& output) {
  auto r = prism::test::run_prism(args);
  output = r.output;
  return r.status;
}

}  // namespace

TEST_CASE("HDR stack: written and read back unchanged") {
  fs::path d = fresh_dir("roundtrip");
  HdrStack s = small_stack();
  write_hdr_stack(d.string(), s);
  HdrStack r = read_hdr_stack(d.string());
  CHECK(r.frames.width == 32);
  CHECK(r.frames.height == 24);
  CHECK(r.frames.bit_depth == 12);
  CHECK(r.pixel_format == "Mono12");
  CHECK(r.source_mm == s.source_mm);
  REQUIRE(r.frames.exposure_s.size() == 7);
  for (size_t i = 0; i < 7; ++i) CHECK(r.frames.exposure_s[i] == doctest::Approx(s.frames.exposure_s[i]).epsilon(1e-12));
  CHECK(r.frames.exposures == s.frames.exposures);
  CHECK(r.frames.darks == s.frames.darks);
  CHECK(r.exposure_files[3] == "exposure_3.raw");
  CHECK(r.dark_files[0] == "dark_0.raw");
}

TEST_CASE("HDR stack: bad stacks give errors naming the file and field") {
  using J = nlohmann::json;
  auto has = [](const std::string& what, std::initializer_list<const char*> parts) {
    INFO(what);
    for (const char* p : parts) CHECK(what.find(p) != std::string::npos);
  };
  has(error_after([](const fs::path& d) { fs::remove(d / "stack.json"); }), {"stack.json: missing"});
  has(error_after([](const fs::path& d) { std::ofstream(d / "stack.json") << "{\"format_version\": 1,"; }),
      {"stack.json: not valid JSON"});
  has(error_after([](const fs::path& d) { edit_json(d, [](J& j) { j["format_version"] = 2; }); }),
      {"stack.json: format_version 2 is not supported"});
  has(error_after([](const fs::path& d) { edit_json(d, [](J& j) { j.erase("width"); }); }),
      {"missing field 'width'"});
  has(error_after([](const fs::path& d) { edit_json(d, [](J& j) { j["exposures"][1].erase("exposure_us"); }); }),
      {"missing field 'exposures[1].exposure_us'"});
  has(error_after([](const fs::path& d) { edit_json(d, [](J& j) { j["source"]["depth_mm"] = "deep"; }); }),
      {"field 'source.depth_mm' must be a number"});
  // Missing exposures: too few listed, or a listed frame absent.
  has(error_after([](const fs::path& d) {
        edit_json(d, [](J& j) { j["exposures"] = J::array({j["exposures"][0], j["exposures"][1]}); });
      }),
      {"lists 2 exposures; the merge needs at least 3"});
  has(error_after([](const fs::path& d) { fs::remove(d / "exposure_4.raw"); }),
      {"exposure_4.raw: missing raw frame"});
  has(error_after([](const fs::path& d) { edit_json(d, [](J& j) { j["darks"] = J::array(); }); }),
      {"'darks' is empty"});
  // Mismatched sizes: a truncated frame, a frame of another size, stack.json's size wrong.
  has(error_after([](const fs::path& d) { fs::resize_file(d / "exposure_2.raw", 1000); }),
      {"exposure_2.raw: truncated: 1000 bytes, expected 1536"});
  has(error_after([](const fs::path& d) { fs::resize_file(d / "dark_1.raw", 2 * 40 * 24); }),
      {"dark_1.raw: 1920 bytes, expected 1536: the frame is not 32 x 24"});
  has(error_after([](const fs::path& d) { edit_json(d, [](J& j) { j["height"] = 25; }); }),
      {"exposure_0.raw: truncated"});
  // A sample beyond the bit depth: wrong bit_depth or packed data.
  has(error_after([](const fs::path& d) { edit_json(d, [](J& j) { j["bit_depth"] = 8; }); }),
      {"exceeds the 8-bit range"});
  // A frame size beyond the memory limit is refused from stack.json alone,
  // before a frame is read: 10 frames of 30000 x 30000 px at 2 bytes are
  // 16.8 GiB, the merge's outputs at 16 bytes per pixel 13.4 GiB.
  prism::set_memory_limit_bytes(1ull << 30);
  has(error_after([](const fs::path& d) { edit_json(d, [](J& j) { j["width"] = j["height"] = 30000; }); }),
      {"needs an estimated 30.2 GiB of memory", "10 frames of 16-bit pixels: 16.8 GiB", "limit of 1.00 GiB",
       "--max-memory"});
  prism::use_default_memory_limit();
  CHECK(error_after([](const fs::path&) {}).empty());
}

TEST_CASE("HDR stack: a parent directory holds one stack per subdirectory") {
  fs::path parent = fresh_dir("parent");
  write_hdr_stack((parent / "pos_b").string(), small_stack());
  write_hdr_stack((parent / "pos_a").string(), small_stack());
  fs::create_directories(parent / "not_a_stack");
  auto found = find_hdr_stacks(parent.string());
  REQUIRE(found.size() == 2);
  CHECK(fs::path(found[0]).filename() == "pos_a");
  CHECK(find_hdr_stacks((parent / "pos_b").string()).size() == 1);
  CHECK_THROWS_WITH(find_hdr_stacks((parent / "not_a_stack").string()), doctest::Contains("no stack.json"));
}

TEST_CASE("prism dictionary merge-hdr writes normalised PSFs with sidecars (CLI)") {
  fs::path root = fresh_dir("cli");
  write_hdr_stack((root / "stacks" / "pos_a").string(), small_stack(64, 48, 1));
  HdrStack b = small_stack(64, 48, 2);
  b.source_mm = {0.0, 5.0, 30.0};
  write_hdr_stack((root / "stacks" / "pos_b").string(), b);
  std::string out;
  for (const char* backend : {"vulkan", "cpu"}) {
    CAPTURE(backend);
    fs::path o = root / backend;
    int rc = prism_cli("dictionary merge-hdr --stacks " + (root / "stacks").string() + " --out " + o.string() +
                           " --backend " + backend,
                       out);
    INFO(out);
    REQUIRE(rc == 0);
    CHECK(out.find("[2/2] pos_b") != std::string::npos);
    for (const char* name : {"pos_a", "pos_b"}) {
      int w = 0, h = 0;
      auto y = read_exr_channel((o / (std::string(name) + ".exr")).string(), "Y", w, h);
      auto valid = read_exr_channel((o / (std::string(name) + ".exr")).string(), "valid", w, h);
      CHECK(w == 64);
      CHECK(h == 48);
      CHECK(std::accumulate(y.begin(), y.end(), 0.0) == doctest::Approx(1.0).epsilon(1e-5));
      double kept = std::accumulate(valid.begin(), valid.end(), 0.0);
      nlohmann::json j;
      std::ifstream(o / (std::string(name) + ".json")) >> j;
      CHECK(j["pixels"]["kept"].get<double>() == kept);
      CHECK(j["pixels"]["kept"].get<double>() > 50);
      CHECK(j["pixels"]["rejected"]["faint"].get<double>() > 0);
      CHECK(j["exposures"].size() == 7);
      CHECK(j["dark_model"] == "constant");
      CHECK(j["normalisation"]["sum_dn_per_s"].get<double>() > 0);
      CHECK(j["limits_dn"]["floor"].get<double>() == doctest::Approx(16.0));
    }
    nlohmann::json jb;
    std::ifstream(o / "pos_b.json") >> jb;
    CHECK(jb["source"]["depth_mm"] == 30.0);
  }
  // The same stack merged by both backends agrees.
  int w, h;
  auto gv = read_exr_channel((root / "vulkan" / "pos_a.exr").string(), "Y", w, h);
  auto gc = read_exr_channel((root / "cpu" / "pos_a.exr").string(), "Y", w, h);
  auto both = prism::test::compare_values(gc, gv, {.abs = 1e-6, .rel = 1e-5});
  CHECK_MESSAGE(both.ok(), both.report("merged PSF, Vulkan vs CPU backend"));

  // A bad stack fails with its file named and a non-zero status, before any
  // stack is merged or the output folder made (pos_a sorts first and is whole).
  fs::resize_file(root / "stacks" / "pos_b" / "exposure_3.raw", 100);
  int rc = prism_cli("dictionary merge-hdr --stacks " + (root / "stacks").string() + " --out " +
                         (root / "bad").string(),
                     out);
  CHECK(rc != 0);
  CHECK(out.find("exposure_3.raw: truncated") != std::string::npos);
  CHECK_FALSE(fs::exists(root / "bad"));
  rc = prism_cli("dictionary merge-hdr --stack " + (root / "none").string() + " --out " + (root / "bad").string(), out);
  CHECK(rc != 0);
  CHECK(out.find("none: no such stack directory") != std::string::npos);
  rc = prism_cli("dictionary merge-hdr --out " + (root / "bad").string(), out);
  CHECK(rc != 0);
  CHECK(out.find("--stack DIR") != std::string::npos);
  fs::remove_all(root);
}

TEST_CASE("prism dictionary assemble: merged PSFs on a grid become a calibrated dictionary (CLI)") {
  fs::path root = fresh_dir("assemble");
  write_hdr_stack((root / "stacks" / "p").string(), small_stack(64, 48, 3));
  std::string out;
  REQUIRE(prism_cli("dictionary merge-hdr --stacks " + (root / "stacks").string() + " --out " +
                        (root / "merged0").string() + " --backend cpu",
                    out) == 0);
  // The camera: one lenslet over a 64 x 48 px sensor of 100 um pixels.
  const std::string scene = (root / "camera.json").string();
  std::ofstream(scene) << R"({"name": "camera", "lenslets": [{"x_mm": 0, "y_mm": 0, "focal_mm": 9}],
                             "sensor": {"width_px": 64, "height_px": 48, "pixel_um": 100}})";
  // That PSF as if measured at the four nodes of x {-2, 2} x y {0} x depth {10, 20}.
  auto place = [&](const std::string& name, double x, double depth) {
    fs::copy_file(root / "merged0" / "p.exr", root / "merged" / (name + ".exr"), fs::copy_options::overwrite_existing);
    nlohmann::json j;
    std::ifstream(root / "merged0" / "p.json") >> j;
    j["source"] = {{"x_mm", x}, {"y_mm", 0.0}, {"depth_mm", depth}};
    std::ofstream(root / "merged" / (name + ".json")) << j.dump();
  };
  fs::create_directories(root / "merged");
  place("a", -2, 10), place("b", 2, 10), place("c", -2, 20), place("d", 2, 20);
  const std::string dict = (root / "dict").string();
  const std::string args = "dictionary assemble --merged " + (root / "merged").string() + " --scene " + scene;
  int rc = prism_cli(args + " --binning 2 --out " + dict, out);
  INFO(out);
  REQUIRE(rc == 0);
  CHECK(out.find("4 merged PSFs, a 2 x 1 x 2 grid") != std::string::npos);
  const DictionaryReader reader(dict);
  const DictionaryManifest& m = reader.manifest();
  CHECK(m.source == "calibrated");
  CHECK(m.grid.x_mm == std::vector<double>{-2, 2});
  CHECK(m.grid.depth_mm == std::vector<double>{10, 20});
  CHECK(m.base_binning == 2);
  REQUIRE(reader.present() == 4);
  REQUIRE(prism_cli("dictionary info " + dict, out) == 0);
  CHECK(out.find("measured    PSFs merged from calibration exposures") != std::string::npos);
  // Level 0: the merged PSF binned 2 x 2, normalised, in half precision.
  int w = 0, h = 0;
  const auto y = read_exr_channel((root / "merged0" / "p.exr").string(), "Y", w, h);
  PsfLevel binned = bin_level(PsfLevel{0, w, h, y}, 1);
  const double sum = std::accumulate(binned.p.begin(), binned.p.end(), 0.0);
  for (float& v : binned.p) v = float(v / sum);
  const PsfLevel stored = reader.read_level(3, 0);
  REQUIRE(stored.width == 32);
  auto cmp = prism::test::compare_values(binned.p, stored.p, {.abs = 1e-7, .rel = 2e-3});
  CHECK_MESSAGE(cmp.ok(), cmp.report("stored level 0 vs the merged PSF binned"));
  CHECK(std::accumulate(stored.p.begin(), stored.p.end(), 0.0) == doctest::Approx(1.0).epsilon(1e-3));

  // Errors, and nothing written.
  rc = prism_cli(args + " --out " + dict, out);
  CHECK(rc != 0);
  CHECK(out.find("exists; give --out a new folder") != std::string::npos);
  const std::string fresh = (root / "dict2").string();
  rc = prism_cli(args + " --binning 3 --out " + fresh, out);
  CHECK(rc != 0);
  CHECK(out.find("--binning 3: give a power of two") != std::string::npos);
  place("e", 2, 20);  // twice at one node
  rc = prism_cli(args + " --out " + fresh, out);
  CHECK(rc != 0);
  CHECK(out.find("were both taken at (2, 0, 20) mm") != std::string::npos);
  fs::remove(root / "merged" / "e.json");
  fs::remove(root / "merged" / "e.exr");
  fs::remove(root / "merged" / "b.json");  // a node without its PSF
  fs::remove(root / "merged" / "b.exr");
  rc = prism_cli(args + " --out " + fresh, out);
  CHECK(rc != 0);
  CHECK(out.find("1 of its nodes have no PSF: (2, 0, 10) mm") != std::string::npos);
  CHECK_FALSE(fs::exists(fresh));
  for (const auto& e : fs::directory_iterator(root)) CHECK(e.path().filename().string().find("assembling") == std::string::npos);
  fs::remove_all(root);
}

TEST_CASE("prism dictionary simulate-hdr: a scene's PSFs as capture-hdr stacks that merge back to them (CLI)") {
  fs::path root = fresh_dir("simulate");
  // The camera: one lenslet over a 64 x 48 px sensor of 100 um pixels.
  const std::string scene = (root / "camera.json").string();
  std::ofstream(scene) << R"({"name": "camera", "lenslets": [{"x_mm": 0, "y_mm": 0, "focal_mm": 9}],
                             "sensor": {"width_px": 64, "height_px": 48, "pixel_um": 100}})";
  const std::string stacks = (root / "stacks").string();
  const std::string cmd = "dictionary simulate-hdr --scene " + scene + " --grid-x-mm=-1,1 --rays 1024";
  const std::string args = cmd + " --grid-depth-mm 20";
  std::string out;
  int rc = prism_cli(args + " --seed 5 --out " + stacks, out);
  INFO(out);
  REQUIRE(rc == 0);
  CHECK(out.find("2 stacks written, 0 already present") != std::string::npos);

  // Each stack as capture-hdr writes it: its source, 7 exposures, 3 darks, its seed.
  const OpticalSystem optics = load_scene(scene).optics;
  TraceSettings camera = TraceSettings::defaults_for(Splat::footprint);
  camera.rays_per_lenslet = 1024, camera.binning = 1, camera.stratification = 1;
  for (int i = 0; i < 2; ++i) {
    const fs::path dir = root / "stacks" / ("p000" + std::to_string(i));
    const HdrStack s = read_hdr_stack(dir.string());
    CHECK(s.source_mm == glm::dvec3(i == 0 ? -1 : 1, 0, 20));
    CHECK(s.frames.exposures.size() == 7);
    CHECK(s.frames.darks.size() == 3);
    CHECK(s.camera["seed"] == 5 + i);
    // Merged as on the bench, the stack gives back the PSF it was drawn
    // from, to its noise (the merge's own test: L1 0.026 to the truth).
    const HdrResult merged = ref::hdr_merge(s.frames, {});
    std::vector<double> truth(merged.psf.size(), 0.0);
    double total = 0;
    for (const auto& [key, px] : ref::psf(optics, camera, s.source_mm).pixels) truth[size_t(key)] = px[0], total += px[0];
    double l1 = 0;
    for (size_t k = 0; k < truth.size(); ++k) l1 += std::abs(merged.psf[k] - truth[k] / total);
    CHECK_MESSAGE(l1 < 0.05, "stack " << i << ": the merged PSF is " << l1 << " (L1) from the model's");
  }
  // A rerun writes only what is missing; the same seed draws the same frames.
  const auto written = fs::last_write_time(root / "stacks" / "p0001" / "stack.json");
  REQUIRE(prism_cli(args + " --seed 5 --out " + stacks, out) == 0);
  CHECK(out.find("0 stacks written, 2 already present") != std::string::npos);
  CHECK(fs::last_write_time(root / "stacks" / "p0001" / "stack.json") == written);
  REQUIRE(prism_cli(args + " --seed 5 --out " + (root / "again").string(), out) == 0);
  auto bytes = [](const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(in), {});
  };
  CHECK(bytes(root / "again" / "p0001" / "exposure_3.raw") == bytes(root / "stacks" / "p0001" / "exposure_3.raw"));
  // The capture's exposures as capture-hdr's options name them.
  REQUIRE(prism_cli(args + " --exposures 5 --darks 2 --min-us 50 --max-us 1e6 --out " + (root / "long").string(), out) == 0);
  const HdrStack longer = read_hdr_stack((root / "long" / "p0000").string());
  REQUIRE(longer.frames.exposure_s.size() == 5);
  CHECK(longer.frames.exposure_s.front() == doctest::Approx(50e-6));
  CHECK(longer.frames.exposure_s.back() == doctest::Approx(1.0));
  // Two darks: at the longest and the shortest exposure (the merge fits the dark current).
  REQUIRE(longer.frames.dark_s.size() == 2);
  CHECK(longer.frames.dark_s[0] == doctest::Approx(1.0));
  CHECK(longer.frames.dark_s[1] == doctest::Approx(50e-6));
  // A source behind the lenses, or exposures the wrong way round, are refused, nothing written.
  rc = prism_cli(cmd + " --grid-depth-mm=-20 --out " + (root / "bad").string(), out);
  CHECK(rc != 0);
  CHECK(out.find("--grid-*-mm:") != std::string::npos);
  rc = prism_cli(args + " --min-us 300 --max-us 200 --out " + (root / "bad").string(), out);
  CHECK(rc != 0);
  CHECK(out.find("--max-us must exceed --min-us (300)") != std::string::npos);
  CHECK_FALSE(fs::exists(root / "bad"));
  fs::remove_all(root);
}
