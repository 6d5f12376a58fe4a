// The `prism` command as a user runs it: outputs, files that outside tools
// read, and errors that say what to do.
#include <fcntl.h>
#include <spawn.h>
#include <sys/wait.h>

#include <array>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <glm/glm.hpp>

#include "engine/defaults.h"
#include "host/util/image_io.h"
#include "support.h"

namespace {

std::string temp_dir() {
  auto d = prism::test::scratch_dir() / "cli";
  std::filesystem::create_directories(d);
  return d.string();
}

// `prism ARGS` fails, saying `says`, before any tracing.
void refused(const std::string& args, const std::string& says) {
  auto r = prism::test::run_prism(args);
  CAPTURE(args);
  INFO(r.output);
  CHECK(r.status != 0);
  CHECK(r.output.find(says) != std::string::npos);
  CHECK(r.output.find("rays/lenslet ...") == std::string::npos);  // nothing traced
}

}  // namespace

TEST_CASE("prism --help names every subcommand, and a word where one must stand that names none is told the choices") {
  auto r = prism::test::run_prism("--help");
  CHECK(r.status == 0);
  for (const char* sub : {"crlb", "psf", "camera", "devices"}) CHECK(r.output.find(sub) != std::string::npos);
  auto c = prism::test::run_prism("crlb --help");
  for (const char* opt : {"--scene", "--depth-mm", "--x-mm", "--y-mm", "--rays", "--binning", "--lens-model",
                          "--photons", "--backend", "--csv", "--plot", "--device", "--fisher-estimator"})
    CHECK(c.output.find(opt) != std::string::npos);
  // A word where a command must stand names the commands there (CLI11 alone
  // says "A subcommand is required" to a typo).
  refused("dictionry", "'dictionry' is not a command of prism; choose from crlb, psf, dictionary");
  refused("dictionary merge", "'merge' is not a command of prism dictionary; choose from build, info, simulate-hdr, merge-hdr, assemble");
  refused("dictionary", "prism dictionary needs a command: build, info, simulate-hdr, merge-hdr, assemble");
  refused("crlb extra", "not expected: extra");  // a command's own words: CLI11's message
  for (const char* command : {"reconstruct", "evaluate"}) {
    const std::string help = prism::test::run_prism(std::string(command) + " --help").output;
    CHECK(help.find("--dark-rate FLOAT=1e-06") != std::string::npos);
    CHECK(help.find("--search-dark-rate FLOAT=3.90625e-07") != std::string::npos);
  }
  refused("reconstruct --dictionary d --events e --out o.csv --dark-rate 0", "--dark-rate");
  refused("evaluate --dictionary d --search-dark-rate -1", "--search-dark-rate");
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
  // Real lenses at 13.8 um from few cells: the caustics' slivers keep the
  // geometric CRLB moving, and the note names the effect; thin lenses get no
  // note. (At 27.6 um the real lenses' CRLB now settles at 256 cells: what
  // kept it moving there was the rim's large pieces given to their
  // centroids' pixels, which are rasterised since.)
  auto real = prism::test::run_prism("crlb --scene prototype --depth-mm 10 --rays 256 --binning 2");
  INFO(real.output);
  REQUIRE(real.status == 0);
  REQUIRE(real.output.find("  moving") != std::string::npos);
  CHECK(real.output.find("\"effects\": [\"diffraction\"]") != std::string::npos);
  auto thin = prism::test::run_prism("crlb --scene prototype --lens-model thin --depth-mm 10 --rays 256 --binning 2");
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

TEST_CASE("bad numbers, sources behind the lenses and unwritable outputs are refused before any work") {
  std::string dir = temp_dir();
  refused("crlb --x-mm nan --depth-mm 10", "--x-mm: 'nan' is not a finite number");
  // NaN passes CLI11's range checks (every comparison with it is false).
  refused("reconstruct --dictionary " + dir + " --events x --tau-mm nan --out " + dir + "/v.csv",
          "--tau-mm: 'nan' is not a finite number");
  // Signs and infinities said in words, not as a range up to the largest double.
  refused("crlb --depth-mm 10 --photons 0", "--photons: 0 must be > 0");
  refused("reconstruct --dictionary " + dir + " --events x --carry-margin inf --out " + dir + "/v.csv",
          "--carry-margin: 'inf' is not a finite number");
  refused("reconstruct --dictionary " + dir + " --events x --level -1 --out " + dir + "/v.csv", "--level: -1 must be >= 0");
  refused("evaluate --dictionary " + dir + " --level -2 --out " + dir + "/e", "--level: -2 must be >= 0");
  refused("evaluate --dictionary " + dir + " --always-scan-below-mm=-1 --out " + dir + "/e",
          "--always-scan-below-mm: -1 must be >= 0");
  refused("crlb --depth-mm=-10", "--depth-mm: depth -10 mm is not in front of prototype's lenses");
  refused("psf --source-mm 0,0,-5 --out " + dir + "/p.exr", "--source-mm: depth -5 mm is not in front");
  refused("simulate --vertex 0,0,1 --jitter-mm 7 --out " + dir + "/e.events", "--vertex less --jitter-mm");
  refused("crlb --depth-mm 10 --csv " + dir, "cannot write " + dir + ": it is a directory");
  std::ofstream(dir + "/a-file") << "x";
  refused("dictionary build --out " + dir + "/a-file --grid-depth-mm 5 --binning 16",
          dir + "/a-file: is a file, not a folder");
  std::filesystem::remove(dir + "/a-file");
  refused("crlb --depth-mm 10 --plot " + dir + "/none/x.png", "the folder " + dir + "/none does not exist");
  refused("crlb --depth-mm 10 --plot " + dir + "/c.txt", "plot " + dir + "/c.txt: use a .png or .svg file name");
  refused("psf --source-mm 0,0,10 --out " + dir + "/none/p.exr", "the folder " + dir + "/none does not exist");
  refused("psf --source-mm 0,0,10 --out " + dir + "/p.txt", dir + "/p.txt: the PSF is written as OpenEXR");
  CHECK_FALSE(std::filesystem::exists(dir + "/p.txt"));
  // Work and memory bounded before they are used.
  refused("crlb --depth-mm=-1e308:1e308:1e300", "--depth-mm: '-1e308:1e308:1e300' gives too many values; at most");
  refused("dictionary build --out " + dir + "/d --grid-x-mm 0:1000:1 --grid-y-mm 0:1000:1",
          "grid: 2.3046e+07 PSFs (1001 x 1001 x 23), more than 1e+06");
  std::ofstream(dir + "/big.json") << R"({"name": "big", "sensor": {"width_px": 100000, "height_px": 100000},
      "lenslets": [{"x_mm": 0, "y_mm": 0, "focal_mm": 9}]})";
  refused("crlb --scene " + dir + "/big.json --depth-mm 10", "sensor.width_px: must be a whole number of pixels from 1 to 65536");
  std::ofstream(dir + "/s.json") << R"({"name": "s", "sensor": 5, "lenslets": [{"x_mm": 0, "y_mm": 0, "focal_mm": 9}]})";
  refused("crlb --scene " + dir + "/s.json --depth-mm 10", "sensor: must be an object with the fields width_px");
  // Beyond physics: photons past any event (the device's float sums gave
  // inf), a holder bore longer than the way to the sensor.
  refused("crlb --depth-mm 10 --photons 1e300", "--photons: '1e300' is more than 1e+12 photons");
  std::ofstream(dir + "/s.json") << R"({"base": "prototype", "photons_emitted": 1e300})";
  refused("crlb --scene " + dir + "/s.json --depth-mm 10", "photons_emitted: must be in (0, 1e+12]");
  std::ofstream(dir + "/s.json") << R"({"base": "prototype", "effects": [{"name": "holder_vignetting", "bore_mm": 1e9}]})";
  refused("crlb --scene " + dir + "/s.json --depth-mm 10",
          "effects.holder_vignetting.bore_mm: must be in [0, lens_to_sensor_mm = 18.5 mm]");
  for (const auto& f : std::filesystem::directory_iterator(dir))  // the scene files only
    CHECK((f.path().filename() == "s.json" || f.path().filename() == "big.json"));
  std::filesystem::remove_all(dir);
}

TEST_CASE("a second set of bad inputs: outputs over inputs, sources outside the volume, repeated keys") {
  std::string dir = temp_dir();
  const std::string d = dir + "/d", events = dir + "/e.events";
  REQUIRE(prism::test::run_prism("dictionary build --out " + d + " --grid-x-mm 0 --grid-y-mm 0 --grid-depth-mm 10,20 "
                                 "--binning 16 --splat point --rays 64").status == 0);
  REQUIRE(prism::test::run_prism("simulate --vertex 0,0,15 --events 3 --binning 16 --splat point --rays 64 --out " +
                                 events).status == 0);
  const auto events_size = std::filesystem::file_size(events);
  std::string manifest;
  {
    std::ifstream in(d + "/manifest.json");
    manifest.assign(std::istreambuf_iterator<char>(in), {});
  }
  // An output that would replace an input: refused, the input untouched.
  refused("reconstruct --dictionary " + d + " --events " + events + " --model none --out " + events,
          "--out " + events + " is the input given by --events");
  CHECK(std::filesystem::file_size(events) == events_size);
  refused("reconstruct --dictionary " + d + " --events " + events + " --model none --out " + d + "/manifest.json",
          "lies inside " + d + ", the folder given by --dictionary");
  refused("evaluate --dictionary " + d + " --experiments volume --out " + d, "is the input given by --dictionary");
  {
    // A misspelt experiment: refused as the arguments are read, before the run's header lines.
    auto r = prism::test::run_prism("evaluate --dictionary " + d + " --experiments volume,dubble --out " + dir + "/ev");
    INFO(r.output);
    CHECK(r.status != 0);
    CHECK(r.output.find("unknown experiment 'dubble': choose from single-lines, photons, double, volume") !=
          std::string::npos);
    CHECK(r.output.find(d) == std::string::npos);  // the header names the dictionary
    CHECK_FALSE(std::filesystem::exists(dir + "/ev"));
  }
  std::ofstream(dir + "/s.json") << R"({"base": "prototype"})";
  refused("crlb --scene " + dir + "/s.json --depth-mm 10 --csv " + dir + "/s.json", "is the input given by --scene");
  // Geometry: a vertex outside the scintillator, a grid or a volume behind the lenses.
  refused("simulate --vertex 1e300,0,20 --out " + dir + "/x.events",
          "--vertex: x 1e+300 mm lies outside prototype's volume (x -25..25 mm)");
  // A point is its numbers, no ranges or empty items; a dictionary the truth would not read.
  refused("simulate --vertex 0,0,15, --out " + dir + "/x.events",
          "--vertex: '' is not a number (expected X,Y,DEPTH[,ALPHA] (mm, mm, mm, photons), got '0,0,15,')");
  refused("simulate --vertex 0,0,15,,1 --out " + dir + "/x.events",
          "--vertex: expected X,Y,DEPTH[,ALPHA] (mm, mm, mm, photons), got '0,0,15,,1'");
  refused("simulate --vertex 0:1:1,0,15 --out " + dir + "/x.events", "--vertex: '0:1:1' is not a number");
  refused("psf --source-mm 0,0 --out " + dir + "/p.exr", "--source-mm: expected X,Y,DEPTH in mm, got '0,0'");
  refused("simulate --vertex 0,0,15 --dictionary " + d + " --out " + dir + "/x.events",
          "--dictionary is read only with --truth dictionary");
  refused("crlb --depth-mm 10,20, --csv " + dir + "/c.csv", "--depth-mm: '' is not a number");
  refused("dictionary info " + events, events + ": a file, not a dictionary; a dictionary is the folder that");
  // A refinement scene with another sensor than the dictionary's (it ran, fitting clicks to the wrong pixels).
  std::ofstream(dir + "/px.json") << R"({"base": "prototype", "sensor": {"width_px": 3348, "height_px": 2382, "pixel_um": 13.8}})";
  refused("reconstruct --dictionary " + d + " --events " + events + " --scene " + dir + "/px.json --out " + dir + "/r.csv",
          "the dictionary is for a 6696 x 4764 px sensor of 6.9 um pixels, not the 3348 x 2382 px sensor of 13.8 um "
          "pixels of the scene given");
  CHECK_FALSE(std::filesystem::exists(dir + "/r.csv"));
  refused("dictionary info " + dir + "/none", dir + "/none: no such folder");
  CHECK_FALSE(std::filesystem::exists(dir + "/x.events"));
  refused("dictionary build --out " + dir + "/d2 --grid-x-mm 0 --grid-y-mm 0 --grid-depth-mm=-30,10",
          "depth -30 mm is not in front of the lenses, which lie 5 mm before the scintillator face");
  CHECK_FALSE(std::filesystem::exists(dir + "/d2"));
  std::ofstream(dir + "/v.json") << R"({"base": "prototype", "volume": {"depth_mm": [-100, 10]}})";
  refused("crlb --scene " + dir + "/v.json --depth-mm 10", "volume.depth_mm: starts at -100 mm, not in front");
  // A key or an effect given twice: which one was meant is unknown.
  std::ofstream(dir + "/k.json") << R"({"base": "prototype", "volume": {"x_mm": [-5, 5], "x_mm": [-6, 6]}})";
  refused("crlb --scene " + dir + "/k.json --depth-mm 10", "key \"volume.x_mm\" is given twice");
  std::ofstream(dir + "/fx.json") << R"({"base": "prototype", "effects": ["diffraction", {"name": "diffraction"}]})";
  refused("crlb --scene " + dir + "/fx.json --depth-mm 10", "effects[1].name: 'diffraction' is given twice");
  // A manifest edited: its count against its grid, a grid behind the lenses, a repeated key.
  auto edited = [&](const std::string& from, const std::string& to) {
    std::string text = manifest;
    const auto at = text.find(from);
    REQUIRE(at != std::string::npos);
    text.replace(at, from.size(), to);
    std::ofstream(d + "/manifest.json") << text;
  };
  edited("\"entries\": 2", "\"entries\": 3");
  refused("dictionary info " + d, "entries: is 3, but the grid has 1 x 1 x 2 = 2 positions");
  edited("10.0,", "-30.0,");
  refused("dictionary info " + d, "grid: depth -30 mm is not in front of the lenses");
  edited("\"entries\": 2", "\"entries\": 2, \"entries\": 2");
  refused("dictionary info " + d, "key \"entries\" is given twice");
  std::filesystem::remove_all(dir);
}

TEST_CASE("outputs are whole: a temporary left by a killed run is removed, Ctrl-C on a sweep exits 130") {
  std::string dir = temp_dir();
  // A temporary of a process that no longer runs (pid beyond any pid_max).
  std::ofstream(dir + "/c.csv.partial-999999999") << "half a row";
  auto r = prism::test::run_prism("crlb --depth-mm 10 --rays 256 --binning 64 --csv " + dir + "/c.csv");
  REQUIRE_MESSAGE(r.status == 0, r.output);
  CHECK(std::filesystem::exists(dir + "/c.csv"));
  CHECK_FALSE(std::filesystem::exists(dir + "/c.csv.partial-999999999"));

  // Ctrl-C: the design in flight is finished and kept, the outputs written,
  // the exit status 130.
  std::ofstream(dir + "/space.json") << R"({"base": "prototype", "focal_mm": [9, 15], "assignment": "free",
      "samples": {"x_mm": [0], "y_mm": [0], "depth_mm": [20]}})";
  // Sent once a design is in the state file: the process spawned directly,
  // with SIGINT at its default (a shell would start a background job with it
  // ignored, and prism keeps a signal ignored that it was started ignoring).
  const std::string state_file = dir + "/sw/evaluated.jsonl", log = dir + "/sweep.log";
  std::vector<std::string> args{PRISM_BINARY, "sweep", "--space", dir + "/space.json", "--budget", "100000",
                                "--batch", "1", "--rays", "256", "--binning", "64", "--out", dir + "/sw"};
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t io;
  posix_spawn_file_actions_init(&io);
  posix_spawn_file_actions_addopen(&io, 1, log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_adddup2(&io, 1, 2);
  posix_spawnattr_t attr;
  posix_spawnattr_init(&attr);
  sigset_t defaults;
  sigemptyset(&defaults);
  sigaddset(&defaults, SIGINT);
  posix_spawnattr_setsigdefault(&attr, &defaults);
  posix_spawnattr_setflags(&attr, POSIX_SPAWN_SETSIGDEF);
  pid_t pid = 0;
  const int spawned = posix_spawn(&pid, PRISM_BINARY, &io, &attr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&io);
  posix_spawnattr_destroy(&attr);
  REQUIRE(spawned == 0);
  auto lines_in = [](const std::string& path) {
    std::ifstream f(path);
    int n = 0;
    for (std::string line; std::getline(f, line);) ++n;
    return n;
  };
  for (int i = 0; i < 1200 && lines_in(state_file) < 2; ++i) std::this_thread::sleep_for(std::chrono::milliseconds(100));
  ::kill(pid, SIGINT);
  int status = 0;
  for (int i = 0; i < 1200 && ::waitpid(pid, &status, WNOHANG) == 0; ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  if (::waitpid(pid, &status, WNOHANG) == 0) {  // still running after 2 minutes: fail, but do not hang
    ::kill(pid, SIGKILL);
    ::waitpid(pid, &status, 0);
  }
  std::ifstream log_in(log);
  prism::test::CommandResult s{0, std::string(std::istreambuf_iterator<char>(log_in), {})};
  INFO(s.output);
  CHECK(WIFEXITED(status));
  CHECK(WEXITSTATUS(status) == 130);
  CHECK(s.output.find("sweep interrupted") != std::string::npos);
  CHECK(std::filesystem::exists(dir + "/sw/ranked.csv"));
  std::ifstream state(dir + "/sw/evaluated.jsonl");
  int lines = 0;
  for (std::string line; std::getline(state, line);) ++lines;
  CHECK(lines >= 2);  // the header and at least the base design
  for (const auto& f : std::filesystem::recursive_directory_iterator(dir))
    CHECK_MESSAGE(f.path().filename().string().find(".partial-") == std::string::npos, f.path().string());
  std::filesystem::remove_all(dir);
}

TEST_CASE("no Vulkan driver: one sentence naming the package, not a crash") {
  auto r = prism::test::run_prism("devices", "VK_ICD_FILENAMES=/nonexistent/icd.json VK_DRIVER_FILES=/nonexistent/icd.json");
  CHECK(r.status == 1);
  CHECK(r.output.find("mesa-vulkan-drivers") != std::string::npos);
}
