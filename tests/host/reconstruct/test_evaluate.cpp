// prism evaluate (host/reconstruct/evaluate.h): the protocol's trimming, a reduced run of
// every experiment on a small dictionary, and the CLI end to end.
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "host/dictionary/build.h"
#include "host/reconstruct/evaluate.h"
#include "host/scene/crlb_study.h"
#include "support.h"

namespace fs = std::filesystem;

namespace {

// x, y in {-5, 0, 5}, depth 5..35 every 5 mm (7.5 mm, the double experiment's
// fixed vertex, inside): 63 PSFs at 16 x 16 binning. Dictionary, truth and
// CRLB with the point splat, which keeps these end-to-end runs quick on
// lavapipe (the footprint splat's own tests: test_footprint.cpp).
struct EvalDictionary {
  std::string dir = (fs::temp_directory_path() / ("prism-eval-test-" + std::to_string(::getpid()))).string();
  std::unique_ptr<prism::DictionaryReader> reader;
  EvalDictionary() {
    prism::DictionaryBuildOptions o;
    o.grid = {{-5.0, 0.0, 5.0}, {-5.0, 0.0, 5.0}, {5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0}};
    o.base_binning = 16;
    o.rays_per_lenslet = 1024;
    o.splat = prism::Splat::point;
    prism::build_dictionary(prism::test::gpu(), prism::builtin_scene("prototype"), dir + "/dict", o);
    reader = std::make_unique<prism::DictionaryReader>(dir + "/dict");
  }
  ~EvalDictionary() { fs::remove_all(dir); }
};
EvalDictionary& dictionary() {
  static EvalDictionary d;
  return d;
}

std::vector<std::string> lines_of(const std::string& path) {
  std::ifstream in(path);
  std::vector<std::string> v;
  for (std::string l; std::getline(in, l);) v.push_back(l);
  return v;
}

}  // namespace

TEST_CASE("evaluation protocol: best and worst trial by 3D error dropped, mean and sample std of the rest") {
  // Sorted by 3D error: 1 (alpha 10) and 100 (alpha 1000) go; 2, 3, 5 and
  // their alpha errors 20, 30, 0 stay, whatever the alpha errors' own order.
  auto s = prism::trimmed_stats({5, 1, 2, 3, 100}, {0, 10, 20, 30, 1000});
  CHECK(s.trials_used == 3);
  CHECK(s.err3d_mean == doctest::Approx(10.0 / 3));
  CHECK(s.err3d_std == doctest::Approx(std::sqrt((std::pow(2 - 10.0 / 3, 2) + std::pow(3 - 10.0 / 3, 2) +
                                                  std::pow(5 - 10.0 / 3, 2)) / 2)));
  CHECK(s.alpha_err_mean == doctest::Approx(50.0 / 3));
  CHECK(s.alpha_err_std == doctest::Approx(std::sqrt((std::pow(20 - 50.0 / 3, 2) + std::pow(30 - 50.0 / 3, 2) +
                                                      std::pow(0 - 50.0 / 3, 2)) / 2)));
  CHECK_THROWS(prism::trimmed_stats({1, 2}, {1, 2}));
}

TEST_CASE("evaluation: every experiment on a reduced grid, CSV and PNG per experiment") {
  auto& d = dictionary();
  prism::EvaluationOptions o;
  o.quick = true;
  o.trials = 4;
  o.rays = 1024;
  o.splat = prism::Splat::point;
  o.seed = 3;
  auto rows = prism::evaluate(prism::test::gpu(), d.reader->manifest().scene, *d.reader, o);
  // Lines: 2 points each (centre +- 2 mm); photons: 50 and 400; double: one
  // depth, two vertices.
  REQUIRE(rows.size() == 6 + 2 + 2);
  for (const auto& r : rows) {
    CAPTURE(r.experiment);
    CAPTURE(r.series);
    CAPTURE(r.varied);
    CHECK(r.stats.trials_used == o.trials - 2);
    CHECK(std::isfinite(r.crlb_3d_mm));
    CHECK(r.crlb_3d_mm > 0);
    CHECK(r.crlb_3d_mm < 5);
    CHECK(std::isfinite(r.stats.err3d_mean));
    CHECK(r.stats.err3d_std > 0);  // two different events never give the very same error
    if (r.experiment != "double") CHECK(r.stats.err3d_mean < 2.5);  // half the plane spacing
  }
  // The CRLB beside each error is the bound at that row's detected photons:
  // an independent study with the emitted photons scaled so that the point
  // detects 50 (or 400) on average must give the same number.
  CHECK(rows[6].photons == 50);
  CHECK(rows[7].photons == 400);
  const auto& scene = d.reader->manifest().scene;
  prism::TraceSettings t;
  t.binning = 16;
  t.rays_per_lenslet = 1024;
  t.splat = prism::Splat::point;
  t.estimator = prism::TraceSettings::default_estimator(t.splat);  // as prism evaluate,
  t.stratification = o.stratification;                             // with the truth's strata
  t.photons_emitted = scene.photons_emitted;
  const glm::dvec3 centre = rows[6].position_mm;
  auto at_default = prism::crlb_study(scene, {centre}, t, prism::Backend::vulkan, prism::SensorModel::poisson,
                                      &prism::test::gpu());
  for (int i : {6, 7}) {
    CAPTURE(rows[i].photons);
    t.photons_emitted = scene.photons_emitted * rows[i].photons / at_default[0].photons;
    auto scaled = prism::crlb_study(scene, {centre}, t, prism::Backend::vulkan, prism::SensorModel::poisson,
                                    &prism::test::gpu());
    CHECK(scaled[0].photons == doctest::Approx(rows[i].photons).epsilon(1e-5));
    CHECK(rows[i].crlb_3d_mm == doctest::Approx(scaled[0].crlb.r3_mm).epsilon(1e-4));
  }
  CHECK(rows[8].series == "moving");
  CHECK(rows[9].position_mm.z == 7.5);

  const std::string out = d.dir + "/eval";
  auto written = prism::write_evaluation(out, rows);
  CHECK(written.size() == 6);
  for (const auto& name : {"single-lines", "photons", "double"}) {
    CAPTURE(name);
    CHECK(fs::file_size(out + "/" + name + ".png") > 1000);
    auto csv = lines_of(out + "/" + name + ".csv");
    REQUIRE(!csv.empty());
    CHECK(csv[0] ==
          "experiment,x_mm,y_mm,depth_mm,photons,trials_used,err3d_mean_mm,err3d_std_mm,alpha_err_mean,"
          "alpha_err_std,crlb_3d_mm");
    CHECK(csv.size() == (std::string(name) == "single-lines" ? 7u : 3u));
  }
  CHECK(lines_of(out + "/double.csv")[2].rfind("double:fixed,1,1,7.5,125,2,", 0) == 0);
  prism::test::check_validation_clean();
}

TEST_CASE("prism evaluate: --quick from the CLI, and errors that say what to do") {
  auto& d = dictionary();
  const std::string out = d.dir + "/cli";
  auto r = prism::test::run_prism("evaluate --dictionary " + d.dir + "/dict --experiments photons --quick --trials 3 "
                                  "--rays 1024 --splat point --seed 5 --out " + out);
  INFO(r.output);
  REQUIRE(r.status == 0);
  CHECK(r.output.find("vulkan scan") != std::string::npos);  // the default backend
  CHECK(r.output.find("events/s") != std::string::npos);
  CHECK(r.output.find("photons.csv") != std::string::npos);
  auto csv = lines_of(out + "/photons.csv");
  REQUIRE(csv.size() == 3);
  CHECK(csv[1].rfind("photons,1,1,31,50,1,", 0) == 0);
  CHECK(fs::exists(out + "/photons.png"));
  CHECK(!fs::exists(out + "/double.csv"));

  auto help = prism::test::run_prism("evaluate --help");
  CHECK(help.output.find("dense") != std::string::npos);
  auto bad = prism::test::run_prism("evaluate --dictionary " + d.dir + "/dict --experiments lines --out " + out);
  CHECK(bad.status != 0);
  CHECK(bad.output.find("single-lines, photons, double") != std::string::npos);
  auto binning = prism::test::run_prism("evaluate --dictionary " + d.dir + "/dict --binning 24 --out " + out);
  CHECK(binning.status != 0);
  CHECK(binning.output.find("--binning 24") != std::string::npos);
}
