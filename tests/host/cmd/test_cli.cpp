// The `prism` command as a user runs it: outputs, files that outside tools
// read, and errors that say what to do.
#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <sstream>

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
