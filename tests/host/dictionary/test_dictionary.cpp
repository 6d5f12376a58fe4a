// The PSF dictionary: synthesis, tiered OpenEXR storage, read-back by our
// reader and by OpenEXR's own tools, resumable builds, clear errors, and
// streaming under a memory budget.
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>
#include <thread>

#include "engine/forward.h"
#include "host/dictionary/build.h"
#include "host/dictionary/service.h"
#include "support.h"

namespace fs = std::filesystem;

namespace {

// A 2 x 1 x 2 grid at 16 x 16 binning: 419 x 298 px, 10 levels, built once.
struct SmallDictionary {
  std::string dir;
  prism::Scene scene = prism::builtin_scene("prototype");
  prism::DictionaryBuildOptions options;
  prism::DictionaryBuildReport first;
  SmallDictionary() {
    dir = (fs::temp_directory_path() / ("prism-dict-test-" + std::to_string(::getpid()))).string();
    fs::remove_all(dir);
    options.grid = {{-5.0, 5.0}, {0.0}, {10.0, 30.0}};
    options.base_binning = 16;
    options.rays_per_lenslet = 1024;
    first = prism::build_dictionary(prism::test::gpu(), scene, dir, options);
  }
  ~SmallDictionary() { fs::remove_all(dir); }
};

SmallDictionary& small() {
  static SmallDictionary d;
  return d;
}

double max_abs(const std::vector<float>& v) {
  double m = 0;
  for (float x : v) m = std::max(m, double(std::abs(x)));
  return m;
}

}  // namespace

TEST_CASE("the paper's grid: 11 x 11 x 10 = 1210 positions at 5 mm spacing") {
  auto g = prism::DictionaryGrid::paper();
  CHECK(g.size() == 1210);
  CHECK(g.position(0) == glm::dvec3(-25, -25, 5));
  CHECK(g.position(1209) == glm::dvec3(25, 25, 50));
  CHECK(g.position(11) == glm::dvec3(-25, -20, 5));
}

TEST_CASE("the default grid: the paper's nodes, planes from the face every 1 mm to 12 mm, 5 mm beyond 20") {
  auto g = prism::DictionaryGrid::fine_near_face();
  CHECK(g.x_mm == prism::DictionaryGrid::paper().x_mm);
  CHECK(g.y_mm == g.x_mm);
  REQUIRE(g.depth_mm.size() == 23);
  CHECK(g.size() == 11 * 11 * 23);
  CHECK(g.depth_mm.front() == 0.0);
  CHECK(g.depth_mm.back() == prism::defaults::volume_depth_mm);
  for (size_t i = 1; i < g.depth_mm.size(); ++i) {
    const double step = g.depth_mm[i] - g.depth_mm[i - 1], at = g.depth_mm[i];
    CHECK(step <= (at <= 12 ? 1.0 : at <= 20 ? 2.5 : 5.0));
  }
  CHECK_NOTHROW(g.validate());
  CHECK_NOTHROW(prism::DictionaryGrid::paper().validate());
}

TEST_CASE("a grid whose positions do not increase is refused, naming the axis, before anything is written") {
  auto g = prism::DictionaryGrid::paper();
  g.depth_mm = {5, 10, 10, 15};
  CHECK_THROWS_WITH_AS(g.validate(), doctest::Contains("depth positions must increase, but 10 follows 10"),
                       prism::DictionaryError);
  g.depth_mm = {5};
  g.y_mm.clear();
  CHECK_THROWS_WITH_AS(g.validate(), doctest::Contains("no y positions"), prism::DictionaryError);
  const std::string dir = (fs::temp_directory_path() / ("prism-dict-badgrid-" + std::to_string(::getpid()))).string();
  fs::remove_all(dir);
  prism::DictionaryBuildOptions o;
  o.grid = {{0.0}, {0.0}, {20.0, 10.0}};
  CHECK_THROWS_WITH_AS(prism::build_dictionary(prism::test::gpu(), prism::builtin_scene("prototype"), dir, o),
                       doctest::Contains("grid: depth positions must increase"), prism::DictionaryError);
  CHECK_FALSE(fs::exists(dir));
  // The CLI checks the grid before it sets up a device: a device that does
  // not exist is not what it reports.
  auto r = prism::test::run_prism("dictionary build --out " + dir + " --grid-depth-mm 20,10 --device no-such-device");
  CHECK(r.status != 0);
  CHECK_MESSAGE(r.output.find("grid: depth positions must increase") != std::string::npos, r.output);
  CHECK_FALSE(fs::exists(dir));
}

TEST_CASE("a synthesised dictionary reads back: level 0 is the normalised PSF within half precision") {
  auto& d = small();
  CHECK(d.first.rendered == 4);
  prism::DictionaryReader r(d.dir);
  REQUIRE(r.present() == 4);
  CHECK(r.manifest().width == 419);
  CHECK(r.manifest().height == 298);
  prism::TraceSettings t;
  t.rays_per_lenslet = d.options.rays_per_lenslet;
  t.binning = 16;
  prism::ForwardVulkan fw(prism::test::gpu(), d.scene.optics, t);
  for (size_t i = 0; i < 4; ++i) {
    auto l0 = r.read_level(i, 0);
    double sum = 0;
    for (float p : l0.p) sum += p;
    CHECK(sum == doctest::Approx(1.0).epsilon(1e-3));
    auto img = fw.psf(r.manifest().grid.position(i));
    double total = img.photons();
    CHECK(r.photons_on_sensor(i) == doctest::Approx(total).epsilon(1e-5));
    double peak = max_abs(l0.p), worst = 0;
    for (size_t p = 0; p < l0.p.size(); ++p) worst = std::max(worst, std::abs(l0.p[p] - img.data[4 * p] / total));
    CHECK(worst <= peak / 1024);  // half: 10 mantissa bits
  }
  prism::test::check_validation_clean();
}

TEST_CASE("tier consistency: level k equals level 0 binned by 2^k within half precision") {
  prism::DictionaryReader r(small().dir);
  for (size_t i = 0; i < 4; ++i) {
    auto l0 = r.read_level(i, 0);
    for (int k = 1; k < r.manifest().levels; ++k) {
      auto stored = r.read_level(i, k);
      auto binned = prism::bin_level(l0, k);
      REQUIRE(stored.width == binned.width);
      REQUIRE(stored.height == binned.height);
      double worst = 0;
      for (size_t p = 0; p < stored.p.size(); ++p) {
        // Both sides carry half rounding (2^-11 relative) of their own sums.
        double tol = std::ldexp(std::max(std::abs(stored.p[p]), std::abs(binned.p[p])), -9) + 1e-9;
        worst = std::max(worst, std::abs(stored.p[p] - binned.p[p]) / tol);
      }
      CAPTURE(k);
      CHECK(worst <= 1.0);
    }
  }
}

TEST_CASE("OpenEXR's own tools read the dictionary files") {
  prism::DictionaryReader r(small().dir);
  std::string f = r.path_of(0);
  bool tools = std::system("command -v exrheader >/dev/null 2>&1") == 0 &&
               std::system("command -v oiiotool >/dev/null 2>&1") == 0;
  if (!tools) {
    MESSAGE("exrheader/oiiotool not installed (Debian: openexr, openimageio-tools): outside-reader check skipped");
    return;
  }
  CHECK(std::system(("exrheader " + f + " | grep -q 'mip-map'").c_str()) == 0);
  CHECK(std::system(("exrheader " + f + " | grep -q prismScaleLog2").c_str()) == 0);
  CHECK(std::system(("oiiotool --info -v " + f + " | grep -q '419 x  298'").c_str()) == 0);
}

TEST_CASE("an interrupted build resumes, a different dictionary in the same place is refused") {
  auto& d = small();
  prism::DictionaryReader r(d.dir);
  fs::remove(r.path_of(2));
  // A half-written file from a crash has a temporary name and is ignored.
  std::ofstream(r.path_of(3) + ".partial-12345") << "garbage";
  auto again = prism::build_dictionary(prism::test::gpu(), d.scene, d.dir, d.options);
  CHECK(again.rendered == 1);
  CHECK(again.reused == 3);
  CHECK(r.present() == 4);
  auto other = d.options;
  other.rays_per_lenslet = 4096;
  CHECK_THROWS_WITH_AS(prism::build_dictionary(prism::test::gpu(), d.scene, d.dir, other),
                       doctest::Contains("holds a different dictionary"), prism::DictionaryError);
  prism::test::check_validation_clean();
}

TEST_CASE("a PSF file that cannot be written stops the build, naming it: the files before it stay whole") {
  // The build writes a PSF's file on a thread while the device renders the
  // next: the write's error must still stop it, and progress must still
  // count every entry once, in order.
  const std::string dir = (fs::temp_directory_path() / ("prism-dict-badwrite-" + std::to_string(::getpid()))).string();
  fs::remove_all(dir);
  prism::DictionaryBuildOptions o;
  o.grid = {{-5.0, 0.0, 5.0}, {0.0}, {20.0}};
  o.base_binning = 16;
  o.rays_per_lenslet = 256;
  const prism::Scene scene = prism::builtin_scene("prototype");
  prism::prepare_dictionary(scene, dir, o);
  prism::DictionaryReader r(dir);
  // The second PSF's temporary is a folder, which OpenEXR cannot open.
  fs::create_directories(r.path_of(1) + ".partial-" + std::to_string(::getpid()) + "/x");
  std::vector<std::pair<size_t, size_t>> calls;
  auto record = [&](size_t done, size_t total) { calls.emplace_back(done, total); };
  const std::string why = r.path_of(1) + ": cannot write";
  CHECK_THROWS_WITH_AS(prism::build_dictionary(prism::test::gpu(), scene, dir, o, record),
                       doctest::Contains(why.c_str()), prism::DictionaryError);
  CHECK(r.has(0));
  CHECK_FALSE(r.has(1));
  CHECK(calls == std::vector<std::pair<size_t, size_t>>{{1, 3}});
  CHECK(r.read_level(0, 0).p.size() == size_t(r.manifest().width) * r.manifest().height);
  // Mended, the build continues from the file written.
  fs::remove_all(r.path_of(1) + ".partial-" + std::to_string(::getpid()));
  calls.clear();
  auto again = prism::build_dictionary(prism::test::gpu(), scene, dir, o, record);
  CHECK(again.reused == 1);
  CHECK(again.rendered == 2);
  CHECK(again.seconds_per_psf > 0);
  CHECK(calls == std::vector<std::pair<size_t, size_t>>{{1, 3}, {2, 3}, {3, 3}});
  CHECK(r.present() == 3);
  fs::remove_all(dir);
  prism::test::check_validation_clean();
}

TEST_CASE("corrupt files, wrong versions and another sensor give errors naming the file") {
  auto& d = small();
  std::string copy = d.dir + "-broken";
  fs::remove_all(copy);
  fs::copy(d.dir, copy, fs::copy_options::recursive);
  prism::DictionaryReader r(copy);
  fs::resize_file(r.path_of(1), fs::file_size(r.path_of(1)) / 2);
  CHECK_THROWS_WITH_AS(r.read_level(1, 0), doctest::Contains(r.path_of(1).c_str()), prism::DictionaryError);
  // Tile by tile, as the search reads them (OpenEXR's C core alone): the
  // same error, at the first tile the cut took.
  auto every_tile = [&](size_t i) {
    const auto& m = r.manifest();
    std::vector<uint16_t> bits(size_t(m.tile_px) * m.tile_px);
    prism::PsfFile f(r, i);
    for (int level = 0; level < m.levels; ++level)
      for (int ty = 0; ty * m.tile_px < m.level_height(level); ++ty)
        for (int tx = 0; tx * m.tile_px < m.level_width(level); ++tx) f.read_tile(level, tx, ty, bits);
  };
  CHECK_NOTHROW(every_tile(2));
  CHECK_THROWS_WITH_AS(every_tile(1), doctest::Contains(r.path_of(1).c_str()), prism::DictionaryError);
  {
    std::ofstream(r.path_of(0), std::ios::trunc) << "not an exr";
  }
  CHECK_THROWS_WITH_AS(r.read_level(0, 2), doctest::Contains("corrupt"), prism::DictionaryError);

  auto other = prism::builtin_scene("prototype").optics;
  other.pixel_um = 3.45;
  CHECK_THROWS_WITH_AS(prism::DictionaryReader(copy, &other), doctest::Contains("3.45"), prism::DictionaryError);

  std::string manifest = copy + "/manifest.json";
  std::ifstream in(manifest);
  auto j = nlohmann::json::parse(in);
  in.close();
  j["grid"]["x_mm"] = {0.0, -5.0};
  std::ofstream(manifest) << j.dump();
  CHECK_THROWS_WITH_AS(prism::DictionaryReader{copy},
                       doctest::Contains((manifest + ": grid: x positions must increase, but -5 follows 0").c_str()),
                       prism::DictionaryError);
  // Edited integers are refused by field, before anything divides by them.
  const auto good = nlohmann::json::parse(std::ifstream(d.dir + "/manifest.json"));
  auto edited = [&](const char* field, const nlohmann::json::json_pointer& at, const nlohmann::json& v) {
    auto e = good;
    e[at] = v;
    std::ofstream(manifest) << e.dump();
    CAPTURE(field);
    CAPTURE(v.dump());
    CHECK_THROWS_WITH_AS(prism::DictionaryReader{copy}, doctest::Contains((manifest + ": " + field).c_str()),
                         prism::DictionaryError);
  };
  edited("levels.base_binning: must be an integer", nlohmann::json::json_pointer("/levels/base_binning"), 0);
  edited("levels.base_binning: must be an integer", nlohmann::json::json_pointer("/levels/base_binning"), 1099511627776.0);
  edited("levels.base_binning: must be an integer", nlohmann::json::json_pointer("/levels/base_binning"), 2.5);
  edited("storage.tile_px: must be an integer", nlohmann::json::json_pointer("/storage/tile_px"), 0);
  edited("levels.count", nlohmann::json::json_pointer("/levels/count"), good["levels"]["count"].get<int>() + 1);
  edited("levels.level0_px", nlohmann::json::json_pointer("/levels/level0_px/0"), good["levels"]["level0_px"][0].get<int>() - 1);
  edited("rays_per_lenslet: must be an integer", nlohmann::json::json_pointer("/rays_per_lenslet"), -4);
  // Copies of what the scene or the format fixes must agree with it; fields of
  // the wrong type are named, not reported as a JSON library's message.
  using ptr = nlohmann::json::json_pointer;
  edited("sensor.pixel_um: is 7.0, but the manifest's scene has 6.9", ptr("/sensor/pixel_um"), 7.0);
  edited("sensor.width_px", ptr("/sensor/width_px"), 6000);
  edited("storage.scale_log2: is 14; format version 1 stores 15", ptr("/storage/scale_log2"), 14);
  edited("storage.compression", ptr("/storage/compression"), "piz");
  edited("storage.pixel", ptr("/storage/pixel"), "float");
  edited("source: must be \"synthesised\" or \"calibrated\"", ptr("/source"), "measured");
  edited("source: is \"calibrated\" with rays_per_lenslet 1024", ptr("/source"), "calibrated");
  edited("source: missing or of the wrong type", ptr("/source"), 5);
  edited("grid.x_mm (a list of numbers): missing or of the wrong type", ptr("/grid/x_mm"), "a");
  edited("levels.level0_px[0]: missing or of the wrong type", ptr("/levels/level0_px"), 5);
  edited("storage.tile_px: missing or of the wrong type", ptr("/storage"), 3);
  edited("levels.base_binning: missing or of the wrong type", ptr("/levels"), nullptr);
  j["version"] = 99;
  std::ofstream(manifest) << j.dump();
  CHECK_THROWS_WITH_AS(prism::DictionaryReader{copy}, doctest::Contains("version"), prism::DictionaryError);
  CHECK_THROWS_WITH_AS(prism::DictionaryReader{copy + "/nowhere"}, doctest::Contains("nowhere: no such folder"),
                       prism::DictionaryError);
  fs::create_directories(copy + "/empty");
  CHECK_THROWS_WITH_AS(prism::DictionaryReader{copy + "/empty"}, doctest::Contains("no dictionary manifest here"),
                       prism::DictionaryError);
  fs::remove_all(copy);
}

TEST_CASE("dictionary info --verify finds a flipped bit and a file that is not where the manifest says") {
  auto& d = small();
  std::string copy = d.dir + "-verify";
  fs::remove_all(copy);
  fs::copy(d.dir, copy, fs::copy_options::recursive);
  auto ok = prism::test::run_prism("dictionary info --verify " + copy);
  INFO(ok.output);
  CHECK(ok.status == 0);
  CHECK(ok.output.find("verified") != std::string::npos);
  CHECK(ok.output.find(" 0 of ") == std::string::npos);
  // Without --verify, info says it did not read the files.
  CHECK(prism::test::run_prism("dictionary info " + copy).output.find("not read") != std::string::npos);

  prism::DictionaryReader r(copy);
  const std::string damaged = r.path_of(2);
  {
    std::fstream f(damaged, std::ios::in | std::ios::out | std::ios::binary);
    f.seekg(0, std::ios::end);
    const auto middle = std::streamoff(f.tellg()) * 3 / 4;  // in the tiles' compressed data
    f.seekg(middle);
    char byte = 0;
    f.read(&byte, 1);
    f.seekp(middle);
    byte = char(byte ^ 0x10);
    f.write(&byte, 1);
  }
  auto bad = prism::test::run_prism("dictionary info --verify " + copy);
  INFO(bad.output);
  CHECK(bad.status == 1);
  CHECK(bad.output.find("1 of ") != std::string::npos);
  CHECK(bad.output.find(damaged) != std::string::npos);
  {  // The search's own tile reads (exr_zip, libdeflate) find it too, naming the file and the tile.
    prism::PsfFile f(r, 2);
    const int t = r.manifest().tile_px;
    std::vector<uint16_t> tile(size_t(t) * size_t(t));
    auto read_every_tile = [&] {
      for (int l = 0; l < r.manifest().levels; ++l)
        for (int ty = 0; ty * t < r.manifest().level_height(l); ++ty)
          for (int tx = 0; tx * t < r.manifest().level_width(l); ++tx) f.read_tile(l, tx, ty, tile);
    };
    CHECK_THROWS_WITH_AS(read_every_tile(), doctest::Contains((damaged + ": cannot read the PSF file (tile (").c_str()),
                         prism::DictionaryError);
  }

  // Two entries swapped on disk: each holds another source's PSF.
  fs::copy_file(d.dir + "/" + r.manifest().file_of(0), damaged, fs::copy_options::overwrite_existing);
  auto moved = prism::test::run_prism("dictionary info --verify " + copy);
  CHECK(moved.status == 1);
  CHECK(moved.output.find(damaged + ": holds entry 0") != std::string::npos);
  // An edited grid: the files' sources are no longer where it says.
  fs::copy_file(d.dir + "/" + r.manifest().file_of(2), damaged, fs::copy_options::overwrite_existing);
  auto j = nlohmann::json::parse(std::ifstream(copy + "/manifest.json"));
  for (auto& x : j["grid"]["x_mm"]) x = x.get<double>() + 1.0;
  std::ofstream(copy + "/manifest.json") << j.dump();
  CHECK_THROWS_WITH_AS(prism::DictionaryReader(copy).read_level(0, 0),
                       doctest::Contains("but the manifest's grid puts entry 0 at"), prism::DictionaryError);
  fs::remove_all(copy);
}

TEST_CASE("summed-area tables give the on-sensor mass of a shifted PSF in four look-ups") {
  prism::DictionaryReader r(small().dir);
  auto l = r.read_level(1, 2);
  prism::SummedArea sat(l);
  CHECK(sat.mass_shifted(0, 0) == doctest::Approx(1.0).epsilon(1e-3));
  for (auto [dx, dy] : {std::pair{7, -3}, std::pair{-40, 11}, std::pair{500, 0}}) {
    double brute = 0;
    for (int y = 0; y < l.height; ++y)
      for (int x = 0; x < l.width; ++x)
        if (x + dx >= 0 && x + dx < l.width && y + dy >= 0 && y + dy < l.height) brute += l.p[size_t(y) * l.width + x];
    CHECK(sat.mass_shifted(dx, dy) == doctest::Approx(brute).epsilon(1e-9));
  }
}

TEST_CASE("streaming serves a dictionary several times larger than its budget") {
  auto& d = small();
  prism::DictionaryReader r(d.dir);
  const auto& m = r.manifest();
  uint64_t level0_bytes = uint64_t(m.width) * m.height * sizeof(float) * m.grid.size();
  prism::ServiceBudget budget{320u << 10, 1u << 20};  // 320 KiB host, 1 MiB device
  REQUIRE(level0_bytes >= 5 * budget.host_bytes);
  prism::DictionaryService svc(r, &prism::test::gpu(), 3, budget);
  // The coarse level on the device equals what the file holds.
  for (size_t i = 0; i < m.grid.size(); ++i) {
    auto slot = svc.coarse_slot(i);
    auto want = r.read_level(i, 3);
    std::vector<float> got(want.p.size());
    svc.coarse_chunk(slot.chunk).download(got.data(), got.size() * sizeof(float), slot.offset * sizeof(float));
    CHECK(got == want.p);
  }
  {
    // On a CPU device, each PSF's row table for the serial scan after its
    // float summed-area table (ScanLevel::rows): texel (x, y) holds P(x - k,
    // y), k = 0..3, zero off the sensor; none where it would pass the budget.
    const int w = m.level_width(3), h = m.level_height(3);
    const bool rows = prism::test::gpu().is_cpu();
    CHECK(prism::DictionaryService::device_rows(m, 3, &prism::test::gpu(), false, budget.device_bytes) == rows);
    CHECK(svc.scan_level().rows == rows);
    for (size_t i = 0; rows && i < m.grid.size(); ++i) {
      CAPTURE(i);
      auto slot = svc.coarse_slot(i);
      auto want = r.read_level(i, 3);
      const uint64_t row_word = (slot.sat_offset + uint64_t(w + 1) * uint64_t(h + 1) + 3) / 4 * 4;
      std::vector<float> got(size_t(w + 3) * size_t(h) * 4);
      svc.coarse_chunk(slot.chunk).download(got.data(), got.size() * sizeof(float), row_word * sizeof(float));
      size_t wrong = 0;
      for (int y = 0; y < h; ++y)
        for (int x = 0; x < w + 3; ++x)
          for (int k = 0; k < 4; ++k) {
            const float p = x - k >= 0 && x - k < w ? want.p[size_t(y) * size_t(w) + size_t(x - k)] : 0.0f;
            wrong += got[(size_t(y) * size_t(w + 3) + size_t(x)) * 4 + size_t(k)] != p;
          }
      CHECK(wrong == 0);
    }
    const uint64_t without = prism::DictionaryService::device_bytes(m, 3, false, false);
    CHECK(prism::DictionaryService::device_bytes(m, 3, false, true) > without);
    CHECK_FALSE(prism::DictionaryService::device_rows(m, 3, &prism::test::gpu(), false, without));
    prism::DictionaryService tight(r, &prism::test::gpu(), 3, {budget.host_bytes, without});
    CHECK_FALSE(tight.scan_level().rows);
    CHECK_FALSE(prism::DictionaryService::device_rows(m, 3, &prism::test::gpu(), true, budget.device_bytes));
  }
  // Random pixel requests all over every PSF's level 0.
  std::mt19937 rng(7);
  std::vector<prism::PsfLevel> truth;
  for (size_t i = 0; i < m.grid.size(); ++i) truth.push_back(r.read_level(i, 0));
  for (int round = 0; round < 200; ++round) {
    size_t i = rng() % m.grid.size();
    std::vector<glm::ivec2> px;
    for (int k = 0; k < 20; ++k) px.push_back({int(rng() % (m.width + 10)) - 5, int(rng() % m.height)});
    auto v = svc.values(i, 0, px);
    for (size_t k = 0; k < px.size(); ++k) {
      bool on = px[k].x >= 0 && px[k].x < m.width;
      CHECK(v[k] == (on ? truth[i].p[size_t(px[k].y) * m.width + px[k].x] : 0.0f));
    }
    CHECK(svc.stats().host_bytes <= budget.host_bytes);
  }
  // One call over every tile of a PSF's level 0, twice over and interleaved:
  // more tiles than the budget holds, so fetches within the call evict tiles
  // the call has already used (values() must not read them after).
  {
    const int t = m.tile_px;
    std::vector<glm::ivec2> px;
    for (int pass = 0; pass < 2; ++pass)
      for (int ty = 0; ty * t < m.height; ++ty)
        for (int tx = 0; tx * t < m.width; ++tx) {
          px.push_back({tx * t + (pass * 7) % t, ty * t + (pass * 5) % t});
          px.push_back({std::min(m.width - 1, (tx / 2) * t + 3), std::min(m.height - 1, ty * t + 1)});
        }
    REQUIRE(uint64_t(px.size() / 2) * uint64_t(t) * uint64_t(t) * sizeof(uint16_t) > budget.host_bytes / 4);
    const uint64_t before = svc.stats().evictions;
    const size_t i = m.grid.size() / 2;
    auto v = svc.values(i, 0, px);
    for (size_t k = 0; k < px.size(); ++k) {
      CAPTURE(k);
      CHECK(v[k] == truth[i].p[size_t(px[k].y) * m.width + px[k].x]);
    }
    CHECK(svc.stats().evictions > before);
  }
  CHECK(svc.stats().host_peak_bytes <= budget.host_bytes);
  CHECK(svc.stats().evictions > 0);
  CHECK(svc.stats().device_bytes <= budget.device_bytes);
  prism::DictionaryReader r2(d.dir);
  CHECK_THROWS_WITH_AS(prism::DictionaryService(r2, &prism::test::gpu(), 0, budget), doctest::Contains("budget"),
                       prism::DictionaryError);
  prism::test::check_validation_clean();
}

TEST_CASE("a pixel dark on the coarse level is served as zero without its tile") {
  auto& d = small();
  prism::DictionaryReader r(d.dir);
  const auto& m = r.manifest();
  const int coarse = 2;  // 105 x 75 px of 441 um: the lenslets' images leave some dark
  prism::DictionaryService svc(r, nullptr, coarse, prism::ServiceBudget{});
  // Every pixel of every finer level, against the file.
  uint64_t pixels = 0;
  for (size_t i = 0; i < m.grid.size(); ++i)
    for (int level = 0; level < coarse; ++level) {
      CAPTURE(i);
      CAPTURE(level);
      const auto want = r.read_level(i, level);
      std::vector<glm::ivec2> px;
      for (int y = 0; y < want.height; ++y)
        for (int x = 0; x < want.width; ++x) px.push_back({x, y});
      pixels += px.size();
      CHECK(svc.values(i, level, px) == want.p);
    }
  CHECK(svc.stats().dark_pixels < pixels);
  // The level-0 pixels under a pixel dark on the coarse level (entry 0, 10
  // mm deep: the light of its lenslets' images leaves a few dark there),
  // asked for on their own: zeros, no tile read.
  const auto level = r.read_level(0, coarse);
  const auto dark = std::find(level.p.begin(), level.p.end(), 0.0f);
  REQUIRE(dark != level.p.end());
  const int dx = int(dark - level.p.begin()) % level.width, dy = int(dark - level.p.begin()) / level.width;
  std::vector<glm::ivec2> under;
  for (int y = 0; y < 1 << coarse; ++y)
    for (int x = 0; x < 1 << coarse; ++x) under.push_back({(dx << coarse) + x, (dy << coarse) + y});
  const prism::ServiceStats before = svc.stats();
  for (const glm::ivec2& px : under) CHECK(svc.values(0, 0, std::span(&px, 1)).front() == 0.0f);
  CHECK(svc.stats().dark_pixels == before.dark_pixels + under.size());
  CHECK(svc.stats().tile_misses == before.tile_misses);
  CHECK(svc.stats().tile_hits == before.tile_hits);
  // The count over rectangles, clipped to the level.
  prism::LitPixels lit(level);
  uint32_t brute = 0;
  for (float p : level.p) brute += p > 0.0f ? 1u : 0u;
  CHECK(lit.count(-3, -3, level.width + 9, level.height + 1) == brute);
  CHECK(lit.count(-3, -3, 0, 5) == 0);
}

TEST_CASE("the service keeps a few PSF files open: tiles read through them are the reader's, and the budget counts them") {
  auto& d = small();
  prism::DictionaryReader r(d.dir);
  const auto& m = r.manifest();
  // One open file read many times equals the reader, which opens it per read.
  prism::PsfFile f(r, 1);
  for (int level : {0, 1, 4})
    for (glm::ivec4 w : {glm::ivec4(0, 0, 64, 64), glm::ivec4(70, 130, 90, 40), glm::ivec4(-5, -5, 1000, 1000)}) {
      CAPTURE(level);
      CAPTURE(w.x);
      CHECK(f.read_window(level, w.x, w.y, w.z, w.w).p == r.read_window(1, level, w.x, w.y, w.z, w.w).p);
    }
  CHECK_THROWS_WITH_AS(f.read_window(m.levels, 0, 0, 1, 1), doctest::Contains(r.path_of(1).c_str()), prism::DictionaryError);

  // Two files kept open, four PSFs read in turn: a file still open is not
  // reopened, one closed to make room is.
  prism::ServiceBudget budget;
  budget.open_files = 2;
  prism::DictionaryService svc(r, nullptr, 3, budget);
  // (PSF, level) read in turn and the files opened so far; each read touches
  // tiles not read before, and a PSF that is still open is read in between.
  const std::vector<glm::ivec2> px = {{10, 10}, {100, 20}, {m.width - 1, m.height - 1}};
  struct Read {
    size_t psf;
    int level;
    uint64_t opens;
  };
  for (Read read : {Read{0, 0, 1}, Read{0, 1, 1}, Read{1, 0, 2}, Read{0, 2, 2}, Read{2, 0, 3}, Read{1, 1, 4},
                    Read{2, 1, 4}, Read{0, 3, 5}}) {
    CAPTURE(read.psf);
    CAPTURE(read.level);
    auto v = svc.values(read.psf, read.level, px);
    auto want = r.read_level(read.psf, read.level);
    for (size_t k = 0; k < px.size(); ++k) {
      const bool on = px[k].x < want.width && px[k].y < want.height;
      CHECK(v[k] == (on ? want.p[size_t(px[k].y) * want.width + px[k].x] : 0.0f));
    }
    CHECK(svc.stats().file_opens == read.opens);
  }
  // The host budget counts the tables, the tiles and the open files.
  uint64_t tables = 0;
  for (size_t i = 0; i < m.grid.size(); ++i)
    tables += svc.coarse_mass(i).bytes() + prism::LitPixels(r.read_level(i, 3)).bytes();
  const uint64_t tile_bytes = uint64_t(m.tile_px) * m.tile_px * sizeof(uint16_t);  // tiles are cached as stored, in half floats
  CHECK(svc.stats().evictions == 0);
  CHECK(svc.stats().host_bytes == tables + svc.stats().tile_misses * tile_bytes + 2 * prism::PsfFile::bytes(m));
  // Room for the tables and one tile but not its file: refused, not exceeded.
  prism::ServiceBudget tight;
  tight.host_bytes = tables + tile_bytes;
  prism::DictionaryService small_svc(r, nullptr, 3, tight);
  CHECK_THROWS_WITH_AS(small_svc.values(0, 0, px), doctest::Contains("leaves no room for one tile and its open file"),
                       prism::DictionaryError);
  CHECK(small_svc.stats().host_peak_bytes <= tight.host_bytes);
}

TEST_CASE("services beside one another share one tile cache: a tile read once serves every thread, and evictions while other threads read leave every value the file's") {
  auto& d = small();
  prism::DictionaryReader r(d.dir);
  const auto& m = r.manifest();
  const int coarse = 3;
  std::vector<std::vector<prism::PsfLevel>> truth(m.grid.size());
  for (size_t i = 0; i < m.grid.size(); ++i)
    for (int level : {0, 1}) truth[i].push_back(r.read_level(i, level));
  const std::vector<glm::ivec2> px = {{10, 10}, {100, 20}, {m.width - 1, m.height - 1}};
  {
    // Room for all: what the first read, the second finds.
    prism::DictionaryService first(r, nullptr, coarse, {});
    prism::DictionaryService second(first, {});
    const auto a = first.values(0, 0, px);
    REQUIRE(first.stats().tile_misses == px.size());
    CHECK(second.values(0, 0, px) == a);
    CHECK(second.stats().tile_misses == 0);
    CHECK(second.stats().tile_hits == px.size());
    // The first service counts the cache's bytes, once.
    CHECK(second.stats().host_bytes == 0);
  }
  // Three threads, room for 8 tiles each (a call over level 0 touches up to
  // 35): calls fall back to one tile at a time, and tiles are evicted while
  // the other threads read theirs.
  const uint64_t tile_bytes = uint64_t(m.tile_px) * m.tile_px * sizeof(uint16_t);
  const uint64_t files = uint64_t(prism::ServiceBudget{}.open_files) * prism::PsfFile::bytes(m);
  const uint64_t tables = prism::DictionaryService(r, nullptr, coarse, {}).stats().host_bytes;
  prism::ServiceBudget budget;
  budget.host_bytes = tables + files + 8 * tile_bytes;
  prism::DictionaryService first(r, nullptr, coarse, budget);
  budget.host_bytes = files + 8 * tile_bytes;
  std::vector<std::unique_ptr<prism::DictionaryService>> services;
  for (int t = 0; t < 2; ++t) services.push_back(std::make_unique<prism::DictionaryService>(first, budget));
  std::vector<prism::DictionaryService*> all = {&first, services[0].get(), services[1].get()};
  std::vector<size_t> wrong(all.size(), 0), asked(all.size(), 0);
  std::vector<std::thread> threads;
  for (size_t t = 0; t < all.size(); ++t)
    threads.emplace_back([&, t] {
      std::mt19937 rng(uint32_t(11 + t));
      for (int round = 0; round < 150; ++round) {
        const size_t i = rng() % m.grid.size();
        const int level = int(rng() % 2);
        const prism::PsfLevel& want = truth[i][size_t(level)];
        std::vector<glm::ivec2> q;
        for (int k = 0; k < 40; ++k) q.push_back({int(rng() % uint32_t(want.width)), int(rng() % uint32_t(want.height))});
        const auto v = all[t]->values(i, level, q);
        for (size_t k = 0; k < q.size(); ++k)
          wrong[t] += v[k] != want.p[size_t(q[k].y) * size_t(want.width) + size_t(q[k].x)];
        asked[t] += q.size();
      }
    });
  for (auto& th : threads) th.join();
  uint64_t evictions = 0, misses = 0;
  for (size_t t = 0; t < all.size(); ++t) {
    CAPTURE(t);
    CHECK(wrong[t] == 0);
    CHECK(asked[t] == 150 * 40);
    evictions += all[t]->stats().evictions;
    misses += all[t]->stats().tile_misses;
  }
  CHECK(evictions > 0);
  CHECK(misses > 0);
  // Tables, tiles and open files within the three budgets throughout.
  CHECK(first.stats().host_peak_bytes <= tables + 3 * (files + 8 * tile_bytes));
}

// Under the sanitizers the other cases' small dictionaries run the same code.
TEST_CASE("the full 1210-PSF prototype dictionary builds, reads back and is tier-consistent" *
          prism::test::skip_under_sanitizer) {
  std::string dir = (fs::temp_directory_path() / ("prism-dict-1210-" + std::to_string(::getpid()))).string();
  fs::remove_all(dir);
  prism::DictionaryBuildOptions o;
  o.grid = prism::DictionaryGrid::paper();
  o.base_binning = 32;              // 210 x 149 px level 0 keeps the suite quick,
  o.rays_per_lenslet = 256;         // as the point splat does (its storage is tested here)
  o.splat = prism::Splat::point;
  auto report = prism::build_dictionary(prism::test::gpu(), prism::builtin_scene("prototype"), dir, o);
  CHECK(report.rendered == 1210);
  prism::DictionaryReader r(dir);
  REQUIRE(r.present() == 1210);
  size_t lit = 0;
  for (size_t i = 0; i < 1210; ++i) {
    auto l0 = r.read_level(i, 0);
    double sum = 0;
    for (float p : l0.p) sum += p;
    if (r.photons_on_sensor(i) == 0) {
      CHECK(sum == 0.0);  // a position that lights nothing is stored as zeros
      continue;
    }
    ++lit;
    CHECK(sum == doctest::Approx(1.0).epsilon(1e-3));
    auto l3 = r.read_level(i, 3);
    auto binned = prism::bin_level(l0, 3);
    for (size_t p = 0; p < l3.p.size(); ++p)
      CHECK(std::abs(l3.p[p] - binned.p[p]) <= std::ldexp(std::max(std::abs(l3.p[p]), std::abs(binned.p[p])), -9) + 1e-9);
  }
  CHECK(lit > 1000);
  fs::remove_all(dir);
  prism::test::check_validation_clean();
}

TEST_CASE("full resolution end to end: a 6696 x 4764 px PSF stored, read by window and by level") {
  std::string dir = (fs::temp_directory_path() / ("prism-dict-full-" + std::to_string(::getpid()))).string();
  fs::remove_all(dir);
  // Under the sanitizers 27.6 um pixels, two levels fewer: the same code
  // (its 32 Mpx took half a minute there).
  const int skipped_levels = prism::test::under_sanitizer ? 2 : 0;
  prism::DictionaryBuildOptions o;
  o.grid = {{2.5}, {-2.5}, {30.0}};
  o.base_binning = 1u << skipped_levels;
  o.rays_per_lenslet = 1024;
  prism::build_dictionary(prism::test::gpu(), prism::builtin_scene("prototype"), dir, o);
  prism::DictionaryReader r(dir);
  CHECK(r.manifest().width == 6696 >> skipped_levels);
  CHECK(r.manifest().height == 4764 >> skipped_levels);
  CHECK(r.manifest().levels == 14 - skipped_levels);
  // The 110 um level against level 0 binned, and a level-0 window where the light is.
  const int level = 4 - skipped_levels, side = 1 << level;
  auto l4 = r.read_level(0, level);
  double sum = 0;
  size_t peak = 0;
  for (size_t p = 0; p < l4.p.size(); ++p) {
    sum += l4.p[p];
    if (l4.p[p] > l4.p[peak]) peak = p;
  }
  CHECK(sum == doctest::Approx(1.0).epsilon(1e-3));
  int px = int(peak % l4.width) * side, py = int(peak / l4.width) * side;
  auto w = r.read_window(0, 0, px, py, side, side);
  double window = 0;
  for (float p : w.p) window += p;
  CHECK(window == doctest::Approx(l4.p[peak]).epsilon(1e-2));
  fs::remove_all(dir);
  prism::test::check_validation_clean();
}
