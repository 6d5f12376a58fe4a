// The `prism` command as a user runs it: outputs, files that outside tools
// read, and errors that say what to do.
#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "engine/defaults.h"
#include "host/util/image_io.h"
#include "support.h"

namespace {

std::string temp_dir() {
  auto d = std::filesystem::temp_directory_path() / ("prism-cli-test-" + std::to_string(::getpid()));
  std::filesystem::create_directories(d);
  return d.string();
}

}  // namespace

TEST_CASE("prism --help names every subcommand") {
  auto r = prism::test::run_prism("--help");
  CHECK(r.status == 0);
  for (const char* sub : {"crlb", "psf", "camera", "devices"}) CHECK(r.output.find(sub) != std::string::npos);
  auto c = prism::test::run_prism("crlb --help");
  for (const char* opt : {"--scene", "--depth-mm", "--x-mm", "--y-mm", "--rays", "--binning", "--lens-model",
                          "--photons", "--backend", "--csv", "--plot", "--device", "--fisher-estimator"})
    CHECK(c.output.find(opt) != std::string::npos);
}

TEST_CASE("prism crlb writes the documented CSV columns and a plot") {
  std::string dir = temp_dir();
  auto r = prism::test::run_prism("crlb --scene prototype --scene single-f9 --depth-mm 5,30 --rays 1024 --binning 32 --csv " + dir +
               "/c.csv --plot " + dir + "/c.png");
  INFO(r.output);
  REQUIRE(r.status == 0);
  CHECK(r.output.find("# device:") != std::string::npos);
  CHECK(r.output.find("# convergence:") != std::string::npos);
  std::ifstream in(dir + "/c.csv");
  std::string header;
  std::getline(in, header);
  CHECK(header.rfind("scene,x_mm,y_mm,depth_mm,photons,crlb_x_mm,crlb_y_mm,crlb_z_mm,crlb_3d_mm", 0) == 0);
  int rows = 0;
  for (std::string line; std::getline(in, line);) ++rows;
  CHECK(rows == 4);
  CHECK(std::filesystem::file_size(dir + "/c.png") > 1000);
  std::filesystem::remove_all(dir);
}

TEST_CASE("prism crlb --ambiguity adds the closest impostor and the predicted confusion, and their plot") {
  std::string dir = temp_dir();
  auto r = prism::test::run_prism("crlb --scene unifocal-f15 --scene prototype --lens-model thin --depth-mm 25 --x-mm 1 "
                                  "--y-mm 1 --rays 1024 --binning 32 --ambiguity --csv " + dir + "/c.csv --plot " + dir +
                                  "/c.png");
  INFO(r.output);
  REQUIRE(r.status == 0);
  CHECK(r.output.find("# ambiguity: binary sensor") != std::string::npos);
  std::ifstream in(dir + "/c.csv");
  std::string line;
  std::getline(in, line);
  CHECK(line.find(",flag,alias_kl,alias_x_mm,alias_y_mm,alias_depth_mm,p_confusion") != std::string::npos);
  int rows = 0;
  while (std::getline(in, line)) {
    std::vector<std::string> f = prism::test::csv_fields(line);
    REQUIRE(f.size() == 21);
    ++rows;
    const glm::dvec3 impostor(std::stod(f[17]), std::stod(f[18]), std::stod(f[19]));
    CHECK(glm::length(impostor - glm::dvec3(1, 1, 25)) >= prism::defaults::catastrophic_error_mm - 1e-3);  // CSV digits
    CHECK(std::stod(f[16]) > 0);
    CHECK(std::stod(f[20]) >= 0);
    CHECK(std::stod(f[20]) <= 1);
  }
  CHECK(rows == 2);
  CHECK(std::filesystem::file_size(dir + "/c-ambiguity.png") > 1000);
  std::filesystem::remove_all(dir);
}

TEST_CASE("prism crlb checks every row against a quarter of the cells and flags rows still moving") {
  // single-f15 at depth 0: its blur disc (radius ~34 mm) overfills the sensor,
  // so almost no information is on it (the thin-lens oracle: 3.9 mm) and the
  // footprint's discretisation dominates at few cells: far from converged.
  // The thin-lens prototype at depth 25 is dominated by sharp disc edges and
  // converged at 4096 cells.
  std::string dir = temp_dir();
  auto r = prism::test::run_prism("crlb --scene single-f15 --scene prototype --lens-model thin --depth-mm 0,25 --rays 4096 "
                                  "--binning 32 --csv " + dir + "/c.csv");
  INFO(r.output);
  REQUIRE(r.status == 0);
  CHECK(r.output.find("flag 'moving'") != std::string::npos);
  std::ifstream in(dir + "/c.csv");
  std::string line;
  std::getline(in, line);
  std::map<std::string, std::pair<double, std::string>> change_and_flag;  // "scene@depth"
  while (std::getline(in, line)) {
    std::vector<std::string> f = prism::test::csv_fields(line);
    REQUIRE(f.size() == 16);
    REQUIRE(!f[14].empty());  // change_vs_quarter_rays is always measured
    change_and_flag[f[0] + "@" + f[3]] = {std::stod(f[14]), f[15]};
  }
  REQUIRE(change_and_flag.size() == 4);
  CHECK(change_and_flag["single-f15@0"].first > 0.1);
  CHECK(change_and_flag["single-f15@0"].second == "moving");
  CHECK(change_and_flag["prototype@25"].first <= 0.01);
  CHECK(change_and_flag["prototype@25"].second == "ok");
  for (const auto& [key, cf] : change_and_flag) CHECK_MESSAGE((cf.second == "moving") == (cf.first > 0.01), key);
  std::filesystem::remove_all(dir);
}

TEST_CASE("prism crlb says when real lenses at fine pixels need the diffraction effect to settle") {
  // Real lenses at 27.6 um from few cells: the caustics' slivers keep the
  // geometric CRLB moving, and the note names the effect; thin lenses there
  // settle and get no note.
  auto real = prism::test::run_prism("crlb --scene prototype --depth-mm 10 --rays 256 --binning 4");
  INFO(real.output);
  REQUIRE(real.status == 0);
  REQUIRE(real.output.find("  moving") != std::string::npos);
  CHECK(real.output.find("\"effects\": [\"diffraction\"]") != std::string::npos);
  auto thin = prism::test::run_prism("crlb --scene prototype --lens-model thin --depth-mm 10 --rays 256 --binning 4");
  INFO(thin.output);
  REQUIRE(thin.status == 0);
  CHECK(thin.output.find("diffraction") == std::string::npos);
}

TEST_CASE("prism psf writes an OpenEXR that OpenEXR's own tools read, and a PNG preview") {
  std::string dir = temp_dir();
  auto r = prism::test::run_prism("psf --scene prototype --source-mm 1,2,20 --rays 1024 --binning 16 --out " + dir + "/p.exr");
  INFO(r.output);
  REQUIRE(r.status == 0);
  int w = 0, h = 0;
  auto y = prism::read_exr_channel(dir + "/p.exr", "Y", w, h);
  CHECK(w == 419);  // ceil(6696 / 16)
  CHECK(h == 298);  // ceil(4764 / 16)
  double sum = 0;
  for (float v : y) sum += v;
  std::ostringstream printed;
  printed.precision(3);
  printed << std::fixed << sum;
  CHECK(r.output.find(printed.str() + " expected photons") != std::string::npos);
  CHECK(std::filesystem::exists(dir + "/p.png"));
  if (std::system("command -v exrheader >/dev/null 2>&1") == 0) {
    CHECK(std::system(("exrheader " + dir + "/p.exr >/dev/null 2>&1").c_str()) == 0);
  } else {
    MESSAGE("exrheader (Debian: openexr) not installed: outside-reader check skipped");
  }
  std::filesystem::remove_all(dir);
}

TEST_CASE("bad input: the error names the problem and nothing is written") {
  std::string dir = temp_dir();
  auto r = prism::test::run_prism("crlb --scene nonesuch --csv " + dir + "/x.csv");
  CHECK(r.status == 1);
  CHECK(r.output.find("unknown scene 'nonesuch'") != std::string::npos);
  CHECK_FALSE(std::filesystem::exists(dir + "/x.csv"));
  auto d = prism::test::run_prism("crlb --depth-mm 5:1:1");
  CHECK(d.status == 1);
  CHECK(d.output.find("--depth-mm") != std::string::npos);
  // Lists mix numbers and ranges; a grid that does not increase is refused
  // before the directory is made.
  auto g = prism::test::run_prism("dictionary build --out " + dir + "/dict --grid-x-mm 0 --grid-y-mm 0 --grid-depth-mm 1:3:1,2.5");
  CHECK(g.status == 1);
  CHECK(g.output.find("depth positions must increase, but 2.5 follows 3") != std::string::npos);
  CHECK_FALSE(std::filesystem::exists(dir + "/dict"));
  auto x = prism::test::run_prism("dictionary build --out " + dir + "/dict --grid-depth-mm 1:3:1,x");
  CHECK(x.status == 1);
  CHECK(x.output.find("--grid-depth-mm: 'x' is not a number") != std::string::npos);
  auto m = prism::test::run_prism("crlb --scene single-f3 --lens-model real --depth-mm 5");
  CHECK(m.status == 1);
  CHECK(m.output.find("use lens_model thin") != std::string::npos);
  std::filesystem::remove_all(dir);
}

TEST_CASE("no Vulkan driver: one sentence naming the package, not a crash") {
  auto r = prism::test::run_prism("devices", "VK_ICD_FILENAMES=/nonexistent/icd.json VK_DRIVER_FILES=/nonexistent/icd.json");
  CHECK(r.status == 1);
  CHECK(r.output.find("mesa-vulkan-drivers") != std::string::npos);
}
