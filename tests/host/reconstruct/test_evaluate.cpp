// prism evaluate (host/reconstruct/evaluate.h): the protocol's trimming and
// per-axis statistics, a reduced run of every experiment on a small
// dictionary, the volume experiment with the refinement, and the CLI end to
// end.
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "host/dictionary/build.h"
#include "host/reconstruct/evaluate.h"
#include "host/scene/crlb_study.h"
#include "host/util/journal.h"
#include "support.h"

namespace fs = std::filesystem;

namespace {

// Relative allowance for a CRLB computed twice from the same inputs: its
// Fisher sums add in the order the device's invocations reach them
// (support.h, same_render_tolerance).
constexpr double crlb_twice_allowance = prism::test::same_render_tolerance;

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

// The volume experiment on the small dictionary, the search alone (quick).
prism::EvaluationOptions search_volume(int events) {
  prism::EvaluationOptions o;
  o.experiments = {"volume"};
  o.model = prism::RefineModel::none;
  o.volume_events = events;
  o.volume_x_mm = {-4, 4};
  o.volume_y_mm = {-3, 3};  // depth: the grid's 5..35 mm
  o.rays = 1024;
  o.splat = prism::Splat::point;
  o.seed = 11;
  return o;
}

// A 7-lenslet thin-lens row (test_refine.cpp's scene) and a 15-PSF
// dictionary of it, in the test process's scratch folder.
struct ThinRow {
  prism::Scene scene;
  std::string dir;
  std::unique_ptr<prism::DictionaryReader> reader;
  explicit ThinRow(const std::string& name) : dir((prism::test::scratch_dir() / name).string()) {
    scene.name = "thin row";
    scene.optics = prism::test::small_system(prism::LensModel::thin);
    prism::DictionaryBuildOptions b;
    b.grid = {{-2.0, 0.0, 2.0}, {0.0}, {10.0, 15.0, 20.0, 25.0, 30.0}};
    b.base_binning = 16;
    b.rays_per_lenslet = 1024;
    b.splat = prism::Splat::point;
    prism::build_dictionary(prism::test::gpu(), scene, dir + "/dict", b);
    reader = std::make_unique<prism::DictionaryReader>(dir + "/dict");
  }
};

// The thin row's volume experiment: 4 events over its middle, with the
// ambiguity, which with a refinement also fits the truth on each event's
// clicks (VolumeEvent::truth_fit_*).
prism::EvaluationOptions thin_row_volume() {
  prism::EvaluationOptions o;
  o.experiments = {"volume"};
  o.volume_events = 4;
  o.volume_x_mm = {-1.5, 1.5};
  o.volume_y_mm = {-0.5, 0.5};
  o.volume_depth_mm = {12, 28};
  o.seed = 2;
  o.volume_ambiguity = true;
  return o;
}

// The depth CRLB at 100 detected photons that search_volume()'s events get
// at `at_mm`: crlb_study with the truth's settings.
double volume_depth_bound(const prism::Scene& scene, const prism::EvaluationOptions& o, const glm::dvec3& at_mm) {
  prism::TraceSettings t;
  t.binning = 16;
  t.rays_per_lenslet = o.rays;
  t.splat = o.splat;
  t.estimator = prism::TraceSettings::default_estimator(t.splat);
  t.stratification = o.stratification;
  t.photons_emitted = scene.photons_emitted;
  const auto b = prism::crlb_study(scene, {at_mm}, t, prism::Backend::vulkan, prism::SensorModel::poisson,
                                   &prism::test::gpu());
  return b[0].crlb.depth_mm * std::sqrt(b[0].photons / 100);
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

TEST_CASE("evaluation statistics per axis: catastrophic events counted and left out, efficiency against each CRLB") {
  // Errors (mm) with their CRLBs: the third is 4 mm off in 3D, catastrophic.
  std::vector<glm::dvec3> err{{0.1, -0.2, 0.3}, {-0.3, 0.2, -0.1}, {0, 0, 4}, {0.2, 0, 0.6}};
  std::vector<glm::dvec3> crlb{{0.1, 0.1, 0.3}, {0.1, 0.2, 0.1}, {1, 1, 1}, {0.2, 0.1, 0.3}};
  auto a = prism::axis_stats(err, crlb);
  CHECK(a.events == 4);
  CHECK(a.catastrophic_rate == doctest::Approx(0.25));
  CHECK(a.rmse_mm.x == doctest::Approx(std::sqrt((0.01 + 0.09 + 0.04) / 3)));
  CHECK(a.rmse_mm.z == doctest::Approx(std::sqrt((0.09 + 0.01 + 0.36) / 3)));
  CHECK(a.crlb_mm.y == doctest::Approx(std::sqrt((0.01 + 0.04 + 0.01) / 3)));
  // err / crlb on depth: 1, -1, 2 -> RMS sqrt(2), median 1.
  CHECK(a.efficiency.z == doctest::Approx(std::sqrt(2.0)));
  CHECK(a.median_ratio.z == doctest::Approx(1.0));
  // x: 1, -3, 1 -> median 1; y: -2, 1, 0 -> median 1.
  CHECK(a.median_ratio.x == doctest::Approx(1.0));
  CHECK(a.efficiency.y == doctest::Approx(std::sqrt(5.0 / 3)));
  // Nothing but catastrophes: a rate and no per-axis figures.
  auto bad = prism::axis_stats({{5, 0, 0}}, {{1, 1, 1}});
  CHECK(bad.catastrophic_rate == 1.0);
  CHECK(std::isnan(bad.rmse_mm.x));
  CHECK_THROWS(prism::axis_stats(err, {{1, 1, 1}}));
}

TEST_CASE("evaluation: every experiment on a reduced grid, CSV and PNG per experiment") {
  auto& d = dictionary();
  prism::EvaluationOptions o;
  o.model = prism::RefineModel::none;  // the search alone (refinement: the thin-lens case below)
  o.quick = true;
  o.trials = 4;
  o.rays = 1024;
  o.splat = prism::Splat::point;
  o.seed = 3;
  auto result = prism::evaluate(prism::test::gpu(), d.reader->manifest().scene, *d.reader, o);
  const auto& rows = result.rows;
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
    CHECK(r.axes.events == o.trials);
    if (r.axes.catastrophic_rate < 1) CHECK(r.axes.efficiency.x == doctest::Approx(r.axes.rmse_mm.x / r.axes.crlb_mm.x));
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
    CHECK(rows[i].axes.crlb_mm.z == doctest::Approx(scaled[0].crlb.depth_mm).epsilon(1e-4));
  }
  CHECK(rows[8].series == "moving");
  CHECK(rows[9].position_mm.z == 7.5);

  const std::string out = d.dir + "/eval";
  auto written = prism::write_evaluation(out, result);
  CHECK(written.size() == 6);
  for (const auto& name : {"single-lines", "photons", "double"}) {
    CAPTURE(name);
    CHECK(fs::file_size(out + "/" + name + ".png") > 1000);
    auto csv = lines_of(out + "/" + name + ".csv");
    REQUIRE(!csv.empty());
    CHECK(csv[0] ==
          "experiment,series,varied,x_mm,y_mm,depth_mm,photons,trials_used,err3d_mean_mm,err3d_std_mm,"
          "alpha_err_mean,alpha_err_std,flagged,catastrophic_rate,rmse_x_mm,rmse_y_mm,rmse_z_mm,crlb_x_mm,crlb_y_mm,"
          "crlb_z_mm,crlb_3d_mm,efficiency_x,efficiency_y,efficiency_z,median_ratio_x,median_ratio_y,"
          "median_ratio_z");
    CHECK(csv.size() == (std::string(name) == "single-lines" ? 7u : 3u));
  }
  // The fixed vertex's rows name the moving vertex's depth they belong to.
  CHECK(lines_of(out + "/double.csv")[2].rfind("double,fixed,31,1,1,7.5,125,2,", 0) == 0);
  prism::test::check_validation_clean();
}

TEST_CASE("prism evaluate: --quick from the CLI, and errors that say what to do") {
  auto& d = dictionary();
  const std::string out = d.dir + "/cli";
  auto r = prism::test::run_prism("evaluate --dictionary " + d.dir + "/dict --experiments photons --quick --trials 3 "
                                  "--rays 1024 --splat point --seed 5 --model none --out " + out);
  INFO(r.output);
  REQUIRE(r.status == 0);
  CHECK(r.output.find("vulkan scan") != std::string::npos);  // the default backend
  CHECK(r.output.find("events/s") != std::string::npos);
  CHECK(r.output.find("photons.csv") != std::string::npos);
  auto csv = lines_of(out + "/photons.csv");
  REQUIRE(csv.size() == 3);
  CHECK(csv[1].rfind("photons,,50,1,1,31,50,1,", 0) == 0);
  CHECK(fs::exists(out + "/photons.png"));
  CHECK(!fs::exists(out + "/double.csv"));

  auto help = prism::test::run_prism("evaluate --help");
  CHECK(help.output.find("dense") != std::string::npos);
  auto bad = prism::test::run_prism("evaluate --dictionary " + d.dir + "/dict --experiments lines --out " + out);
  CHECK(bad.status != 0);
  CHECK(bad.output.find("single-lines, photons, double, volume") != std::string::npos);
  auto empty = prism::test::run_prism("evaluate --dictionary " + d.dir + "/dict --experiments volume "
                                      "--volume-depth-mm 20,10 --out " + out);
  CHECK(empty.status != 0);
  CHECK(empty.output.find("--volume-depth-mm: give lo,hi") != std::string::npos);
  // A box beyond the scene's volume (here behind the lenses) is refused, as --vertex is.
  auto behind = prism::test::run_prism("evaluate --dictionary " + d.dir + "/dict --experiments volume "
                                       "--volume-depth-mm=-50,5 --out " + out);
  CHECK(behind.status != 0);
  CHECK_MESSAGE(behind.output.find("--volume-depth-mm: depth -50 mm lies outside") != std::string::npos, behind.output);
  auto binning = prism::test::run_prism("evaluate --dictionary " + d.dir + "/dict --binning 24 --out " + out);
  CHECK(binning.status != 0);
  CHECK(binning.output.find("--binning 24") != std::string::npos);
  auto refine_level = prism::test::run_prism("evaluate --dictionary " + d.dir + "/dict --refine-level 99 --out " + out);
  CHECK(refine_level.status != 0);
  CHECK_MESSAGE(refine_level.output.find("--refine-level 99: choose 0 (the clicks' own) to") != std::string::npos,
                refine_level.output);
  auto truth = prism::test::run_prism("evaluate --dictionary " + d.dir + "/dict --truth-scene no-such-scene.json --out " + out);
  CHECK(truth.status != 0);
  CHECK_MESSAGE(truth.output.find("unknown scene 'no-such-scene.json'") != std::string::npos, truth.output);
}

TEST_CASE("evaluation volume: events uniform over the field, by depth band, every event's own CRLB") {
  auto& d = dictionary();
  const prism::EvaluationOptions o = search_volume(8);
  const auto& scene = d.reader->manifest().scene;
  auto result = prism::evaluate(prism::test::gpu(), scene, *d.reader, o);
  REQUIRE(result.volume.size() == 8);
  for (const auto& v : result.volume) {
    CAPTURE(v.index);
    CHECK(std::abs(v.truth_mm.x) <= 4);
    CHECK(std::abs(v.truth_mm.y) <= 3);
    CHECK(v.truth_mm.z >= 5);
    CHECK(v.truth_mm.z <= 35);
    CHECK(v.estimate.clicks > 0);
  }
  CHECK(result.volume[0].truth_mm != result.volume[1].truth_mm);
  // Bands 5-10 .. 30-35 and the whole field; every event in exactly one band.
  REQUIRE(result.rows.size() == 7);
  int in_bands = 0;
  for (size_t b = 0; b < 6; ++b) {
    CHECK(result.rows[b].depth_lo_mm == 5.0 + 5.0 * double(b));
    in_bands += result.rows[b].axes.events;
  }
  CHECK(in_bands == 8);
  const auto& all = result.rows.back();
  CHECK(all.series == "all");
  // The whole field's figures are axis_stats over the events' own errors and bounds.
  std::vector<glm::dvec3> err, crlb;
  for (const auto& v : result.volume) {
    err.push_back(glm::dvec3(v.estimate.x_mm, v.estimate.y_mm, v.estimate.depth_mm) - v.truth_mm);
    crlb.push_back(v.crlb_mm);
  }
  auto expect = prism::axis_stats(err, crlb);
  CHECK(all.axes.catastrophic_rate == expect.catastrophic_rate);
  if (expect.catastrophic_rate < 1) CHECK(all.axes.efficiency.z == doctest::Approx(expect.efficiency.z));
  // An event's CRLB is the study's at its truth, at 100 detected photons.
  const auto& v = result.volume[3];
  CHECK(v.crlb_mm.z == doctest::Approx(volume_depth_bound(scene, o, v.truth_mm)).epsilon(1e-6));

  const std::string out = d.dir + "/volume";
  prism::write_evaluation(out, result);
  CHECK(lines_of(out + "/volume.csv").size() == 8);
  CHECK(lines_of(out + "/volume.csv")[7].rfind("volume,all,5,35,100,8,", 0) == 0);
  auto events = lines_of(out + "/volume-events.csv");
  REQUIRE(events.size() == 9);
  CHECK(events[1].rfind("0,", 0) == 0);
  CHECK(fs::file_size(out + "/volume.png") > 1000);
  CHECK(fs::file_size(out + "/volume-catastrophic.png") > 1000);
  prism::test::check_validation_clean();
}

TEST_CASE("evaluation volume with --truth-scene: events, CRLB and journal from the truth, the scene only the model") {
  auto& d = dictionary();
  prism::EvaluationOptions o = search_volume(4);
  const auto& scene = d.reader->manifest().scene;
  const auto nominal = prism::evaluate(prism::test::gpu(), scene, *d.reader, o);

  // The same system named as the truth: the same events and estimates, to
  // the order of the device's float sums (support.h, same_render_tolerance),
  // which moved one estimate by 2.4 um on an H200.
  o.truth_scene = scene;
  const auto same = prism::evaluate(prism::test::gpu(), scene, *d.reader, o);
  REQUIRE(same.volume.size() == 4);
  const double same_mm = 0.01;
  for (size_t i = 0; i < 4; ++i)
    CHECK(std::abs(same.volume[i].estimate.x_mm - nominal.volume[i].estimate.x_mm) <= same_mm);

  // A sensor 0.3 mm farther from the lenses than the dictionary's: other
  // clicks, hence other estimates, and the bounds of that system.
  prism::Scene far = scene;
  far.name = "prototype, sensor 0.3 mm farther";
  far.optics.lens_to_sensor_mm += 0.3;
  o.truth_scene = far;
  o.journal_dir = d.dir + "/truth-scene";
  const auto moved = prism::evaluate(prism::test::gpu(), scene, *d.reader, o);
  REQUIRE(moved.volume.size() == 4);
  int differ = 0;
  for (size_t i = 0; i < 4; ++i) {
    CAPTURE(i);
    const auto &a = nominal.volume[i], &b = moved.volume[i];
    CHECK(b.truth_mm == a.truth_mm);  // the positions are the seed's
    differ += b.estimate.x_mm != a.estimate.x_mm || b.estimate.depth_mm != a.estimate.depth_mm;
  }
  CHECK(differ >= 3);
  // Each event's bound is that system's (crlb_study at its truth). With these
  // few point rays the split Fisher estimate of a defocused image can come out
  // singular (an infinite bound, on one backend and not the other): compared
  // where both are finite.
  int compared = 0;
  for (const auto& v : moved.volume) {
    const double far_bound = volume_depth_bound(far, o, v.truth_mm), nominal_bound = volume_depth_bound(scene, o, v.truth_mm);
    if (!std::isfinite(far_bound) || !std::isfinite(v.crlb_mm.z)) continue;
    CAPTURE(v.index);
    CHECK(v.crlb_mm.z == doctest::Approx(far_bound).epsilon(1e-4));
    CHECK(std::abs(far_bound / nominal_bound - 1) > 1e-3);  // the check above can tell the two apart
    ++compared;
  }
  CHECK(compared >= 2);
  // The journal names the truth: a run with another truth does not resume it.
  const auto header = nlohmann::json::parse(lines_of(o.journal_dir + "/volume-journal.jsonl").at(0));
  CHECK(header.dump().find("sensor 0.3 mm farther") != std::string::npos);
  o.truth_scene = scene;
  o.resume = true;
  CHECK_THROWS_AS(prism::evaluate(prism::test::gpu(), scene, *d.reader, o), prism::JournalError);

  // Events must be clicks on the dictionary's pixels.
  prism::Scene other_sensor = scene;
  other_sensor.optics.pixel_um *= 2;
  o.truth_scene = other_sensor;
  o.resume = false;
  CHECK_THROWS_WITH_AS(prism::evaluate(prism::test::gpu(), scene, *d.reader, o), doctest::Contains("another sensor"),
                       std::invalid_argument);
  prism::test::check_validation_clean();
}

TEST_CASE("evaluation volume: a stopped run resumes from its journal, which must match the run") {
  auto& d = dictionary();
  prism::EvaluationOptions o = search_volume(5);
  const std::string dir = d.dir + "/journal";
  o.journal_dir = dir;  // made by evaluate()
  const std::string journal = dir + "/volume-journal.jsonl";
  const auto& scene = d.reader->manifest().scene;
  const auto whole = prism::evaluate(prism::test::gpu(), scene, *d.reader, o);
  CHECK(whole.resumed == 0);
  auto lines = lines_of(journal);
  REQUIRE(lines.size() == 6);  // the header and one line per event

  // A run killed while writing its fourth event: three events and a torn line.
  {
    std::ofstream cut(journal, std::ios::trunc);
    for (size_t i = 0; i < 4; ++i) cut << lines[i] << '\n';
    cut.write(lines[4].data(), std::streamsize(lines[4].size() / 2));
  }
  o.volume_events = 6;  // and asked for one more event
  {  // The journal alone: its three events, nothing reconstructed or written.
    prism::EvaluationOptions only = o;
    only.journal_only = true;
    const auto bytes = std::filesystem::file_size(journal);
    const auto so_far = prism::evaluate(prism::test::gpu(), scene, *d.reader, only);
    CHECK(so_far.cost.events == 0);
    REQUIRE(so_far.volume.size() == 3);
    for (size_t i = 0; i < 3; ++i) CHECK(so_far.volume[i].estimate.x_mm == whole.volume[i].estimate.x_mm);
    CHECK(std::filesystem::file_size(journal) == bytes);  // the torn line left for the run to mend
    const prism::Journal reader(journal, nlohmann::json::object(), "", /*read_only=*/true);
    CHECK(reader.records().size() == 3);
    CHECK_THROWS_AS(reader.append({{"index", 9}}), prism::JournalError);
  }
  o.resume = true;
  const auto resumed = prism::evaluate(prism::test::gpu(), scene, *d.reader, o);
  CHECK(resumed.resumed == 3);
  CHECK(resumed.cost.events == 3);  // only the events not in the journal were reconstructed
  REQUIRE(resumed.volume.size() == 6);
  for (size_t i = 0; i < 5; ++i) {
    CAPTURE(i);
    const auto &a = whole.volume[i], &b = resumed.volume[i];
    CHECK(b.index == i);
    CHECK(b.truth_mm == a.truth_mm);
    // The CRLB is computed again, to the float sums' order on a GPU (support.h).
    CHECK(b.crlb_mm.z == doctest::Approx(a.crlb_mm.z).epsilon(crlb_twice_allowance));
    CHECK(b.estimate.x_mm == doctest::Approx(a.estimate.x_mm).epsilon(1e-12));
    CHECK(b.estimate.depth_mm == doctest::Approx(a.estimate.depth_mm).epsilon(1e-12));
    CHECK(b.estimate.alpha == doctest::Approx(a.estimate.alpha).epsilon(1e-12));
    CHECK(b.estimate.flags == a.estimate.flags);
    CHECK(std::isnan(b.estimate.fit_pvalue));  // not refined: NaN survives the journal (as null)
    CHECK(b.seconds > 0);                      // its cost travels with it
    CHECK(b.renders == 0);                     // the search alone renders nothing
  }
  CHECK(lines_of(journal).size() == 7);

  // Another seed draws other events: the journal is refused, not mixed in.
  o.seed = 12;
  CHECK_THROWS_WITH_AS(prism::evaluate(prism::test::gpu(), scene, *d.reader, o), doctest::Contains("different seed"),
                       prism::JournalError);
  prism::test::check_validation_clean();
}

TEST_CASE("evaluation protocol: a stopped run resumes from its journal with the same trials") {
  auto& d = dictionary();
  prism::EvaluationOptions o;
  o.experiments = {"photons"};
  o.model = prism::RefineModel::none;
  o.quick = true;  // 50 and 400 photons
  o.trials = 4;
  o.rays = 1024;
  o.splat = prism::Splat::point;
  o.seed = 5;
  const std::string dir = d.dir + "/protocol-journal";
  o.journal_dir = dir;  // made by evaluate()
  const std::string journal = dir + "/protocol-journal.jsonl";
  const auto& scene = d.reader->manifest().scene;
  const auto whole = prism::evaluate(prism::test::gpu(), scene, *d.reader, o);
  auto lines = lines_of(journal);
  REQUIRE(lines.size() == 1 + 8);
  {  // stopped after five of the eight events
    std::ofstream cut(journal, std::ios::trunc);
    for (size_t i = 0; i < 6; ++i) cut << lines[i] << '\n';
  }
  {  // The journal alone: the 50-photon point (trials 0..3), not the 400 (1 trial); nothing reconstructed.
    prism::EvaluationOptions only = o;
    only.journal_only = true;
    const auto so_far = prism::evaluate(prism::test::gpu(), scene, *d.reader, only);
    CHECK(so_far.resumed == 5);
    CHECK(so_far.cost.events == 0);
    REQUIRE(so_far.rows.size() == 1);
    CHECK(so_far.rows[0].photons == whole.rows[0].photons);
    CHECK(so_far.rows[0].stats.err3d_mean == doctest::Approx(whole.rows[0].stats.err3d_mean).epsilon(1e-12));
    CHECK(so_far.rows[0].crlb_3d_mm == doctest::Approx(whole.rows[0].crlb_3d_mm).epsilon(crlb_twice_allowance));
    CHECK(lines_of(journal).size() == 6);  // read, not written
    // Another estimator reads the same events and says what made them.
    only.settings.newton_iterations += 1;
    const auto again = prism::evaluate(prism::test::gpu(), scene, *d.reader, only);
    CHECK(again.rows.size() == 1);
    REQUIRE(again.journal_estimators.size() == 1);
    CHECK(again.journal_estimators[0].find("\"newton_iterations\":" +
                                           std::to_string(o.settings.newton_iterations)) != std::string::npos);
    only.seed = 99;  // other events: refused
    CHECK_THROWS_WITH_AS(prism::evaluate(prism::test::gpu(), scene, *d.reader, only), doctest::Contains("different seed"),
                         prism::JournalError);
    only.seed = o.seed;
    only.journal_dir = d.dir + "/no-journal-here";
    CHECK_THROWS_WITH_AS(prism::evaluate(prism::test::gpu(), scene, *d.reader, only),
                         doctest::Contains("no journal to report from"), std::runtime_error);
    CHECK_FALSE(std::filesystem::exists(only.journal_dir));
  }
  o.resume = true;
  const auto resumed = prism::evaluate(prism::test::gpu(), scene, *d.reader, o);
  CHECK(resumed.resumed == 5);
  CHECK(resumed.cost.events == 3);
  REQUIRE(resumed.rows.size() == whole.rows.size());
  for (size_t i = 0; i < whole.rows.size(); ++i) {
    CAPTURE(i);
    CHECK(resumed.rows[i].stats.err3d_mean == doctest::Approx(whole.rows[i].stats.err3d_mean).epsilon(1e-12));
    CHECK(resumed.rows[i].axes.rmse_mm.z == doctest::Approx(whole.rows[i].axes.rmse_mm.z).epsilon(1e-12));
  }
  o.trials = 5;  // another protocol: refused
  CHECK_THROWS_WITH_AS(prism::evaluate(prism::test::gpu(), scene, *d.reader, o), doctest::Contains("different trials"),
                       prism::JournalError);
  o.resume = false;  // without --resume: started over
  const auto fresh = prism::evaluate(prism::test::gpu(), scene, *d.reader, o);
  CHECK(fresh.resumed == 0);
  CHECK(fresh.cost.events == 10);
  CHECK(lines_of(journal).size() == 1 + 10);
  prism::test::check_validation_clean();
}

TEST_CASE("evaluation volume with the refinement: thin-lens row, truth at 4x the model's cells and other strata") {
  // The refinement's model: the row's forward model.
  ThinRow row("eval-thin");
  const auto& scene = row.scene;
  auto& reader = *row.reader;

  prism::EvaluationOptions o = thin_row_volume();
  auto result = prism::evaluate(prism::test::gpu(), scene, reader, o);
  REQUIRE(result.volume.size() == 4);
  CHECK(result.cost.refine_s > 0);
  for (const auto& v : result.volume) {
    auto text = [](glm::dvec3 p) {
      std::ostringstream s;
      s << '(' << p.x << ", " << p.y << ", " << p.z << ')';
      return s.str();
    };
    const glm::dvec3 estimate(v.estimate.x_mm, v.estimate.y_mm, v.estimate.depth_mm);
    INFO("event ", v.index, ": truth ", text(v.truth_mm), " estimate ", text(estimate), " CRLB ", text(v.crlb_mm),
         " p-value ", v.estimate.fit_pvalue);
    CHECK(v.estimate.refined);
    CHECK(v.renders > 0);
    CHECK(v.seconds > 0);
    CHECK(std::isfinite(v.estimate.fit_pvalue));
    CHECK(std::isfinite(v.estimate.crlb_3d_mm));
    const glm::dvec3 z = (estimate - v.truth_mm) / v.crlb_mm;
    CHECK(std::max({std::abs(z.x), std::abs(z.y), std::abs(z.z)}) < 4.0);  // within 4 sigma on every axis
    // The truth's own fit lands in the estimate's basin: the estimator,
    // which tried more starts, did at least as well.
    CAPTURE(v.truth_fit_nll);
    CAPTURE(v.estimate.nll);
    CHECK(glm::length(v.truth_fit_mm - v.truth_mm) < 6 * v.estimate.crlb_3d_mm);
    CHECK(v.estimate.nll <= v.truth_fit_nll + 1e-3);
    CHECK_FALSE(v.search_failure());
  }
  CHECK(result.rows.back().axes.catastrophic_rate == 0);
  CHECK(result.rows.back().catastrophic_classified == 0);
  // The classification itself: catastrophic and the truth's fit better and
  // by the truth is the search's; the same fit 3 mm off, the likelihood's.
  prism::VolumeEvent wrong = result.volume[0];
  wrong.estimate.x_mm = wrong.truth_mm.x + 5;
  wrong.estimate.nll = wrong.truth_fit_nll + 10;
  CHECK(wrong.search_failure());
  wrong.truth_fit_mm = wrong.truth_mm + glm::dvec3(3.5, 0, 0);
  CHECK_FALSE(wrong.search_failure());
  wrong.truth_fit_mm = wrong.truth_mm;
  wrong.estimate.nll = wrong.truth_fit_nll - 1;
  CHECK_FALSE(wrong.search_failure());
  prism::test::check_validation_clean();
}

TEST_CASE("evaluation volume with the refinement staged: rendered on 4 x 4 blocks of the clicks, then on the clicks") {
  // Refinement with refine_level 2 (441.6 um blocks) above 110 um clicks: the
  // starts, aliases and scans on the clicks binned, then the answer fitted
  // again on the clicks themselves. The polish must land at the clicks' own
  // optimum: near the local fit from the truth (on the clicks,
  // Refinement::local_fit), with its NLL on the clicks (not the blocks').
  ThinRow row("eval-thin-staged");
  prism::EvaluationOptions o = thin_row_volume();
  o.refine_level = 2;
  o.journal_dir = (prism::test::scratch_dir() / "eval-thin-staged" / "run").string();
  auto result = prism::evaluate(prism::test::gpu(), row.scene, *row.reader, o);
  REQUIRE(result.volume.size() == 4);
  for (const auto& v : result.volume) {
    const glm::dvec3 estimate(v.estimate.x_mm, v.estimate.y_mm, v.estimate.depth_mm);
    INFO("event ", v.index, ": truth depth ", v.truth_mm.z, ", estimate depth ", estimate.z, ", CRLB ",
         v.estimate.crlb_3d_mm, ", NLL ", v.estimate.nll, " against the truth's fit ", v.truth_fit_nll);
    CHECK(v.estimate.refined);
    CHECK(std::isfinite(v.estimate.crlb_3d_mm));
    const glm::dvec3 z = (estimate - v.truth_mm) / v.crlb_mm;
    CHECK(std::max({std::abs(z.x), std::abs(z.y), std::abs(z.z)}) < 4.0);
    // The thin lenses' sharp images make the clicks' likelihood a staircase
    // whose local fits lie on steps a fraction of a CRLB apart: with the
    // device's float sums varying from run to run, one event in about ten
    // stopped 0.09 mm (0.7 CRLB) and 13 NLL from the truth's own fit. The
    // coarse answer unpolished lay 2 CRLB off, its NLL hundreds lower (on
    // the blocks' clicks).
    CHECK(glm::length(estimate - v.truth_fit_mm) < v.estimate.crlb_3d_mm);
    CHECK(std::abs(v.estimate.nll - v.truth_fit_nll) < 15);
  }
  // The journal records the staging (a run resumed without it is refused).
  const auto header = nlohmann::json::parse(lines_of(o.journal_dir + "/volume-journal.jsonl").at(0));
  CHECK(header.at("refine").at("level") == 2);
  // A level finer than the clicks' is refused, naming the option.
  o.refine_level = 0;
  o.level = 1;
  o.journal_dir.clear();
  CHECK_THROWS_WITH_AS(prism::evaluate(prism::test::gpu(), row.scene, *row.reader, o),
                       doctest::Contains("--refine-level 0"), std::invalid_argument);
  prism::test::check_validation_clean();
}

TEST_CASE("evaluation volume with --ambiguity: each event's predicted confusion at its truth, band means, journal") {
  // The thin-lens row again (quick renders), the search alone: the ambiguity
  // does not depend on the estimate.
  ThinRow row("eval-ambiguity");
  const auto& scene = row.scene;
  auto& reader = *row.reader;
  const std::string& dir = row.dir;

  prism::EvaluationOptions o;
  o.experiments = {"volume"};
  o.model = prism::RefineModel::none;
  o.volume_events = 3;
  o.volume_photons = 60;
  o.volume_ambiguity = true;
  o.volume_x_mm = {-1.5, 1.5};
  o.volume_y_mm = {-0.5, 0.5};
  o.volume_depth_mm = {12, 28};
  o.band_mm = 8;  // two bands
  o.seed = 4;
  o.journal_dir = dir + "/out";
  const auto result = prism::evaluate(prism::test::gpu(), scene, reader, o);
  REQUIRE(result.volume.size() == 3);
  CHECK(result.cost.ambiguity_s > 0);
  CHECK(result.cost.ambiguity_renders > 0);
  CHECK(result.cost.renders == 0);  // the search alone: the ambiguity's renders are its own

  // The same figure as `prism crlb --ambiguity` at the event's truth and photons.
  auto model = prism::make_scene_model(scene, prism::refine_trace_settings(16), &prism::test::gpu());
  for (const auto& v : result.volume) {
    CAPTURE(v.index);
    const prism::Ambiguity a = prism::ambiguity(*model, scene, v.truth_mm, 60.0);
    // (lavapipe's float sums may come out in another order: 1e-4)
    CHECK(v.p_confusion == doctest::Approx(a.p_confusion).epsilon(1e-4));
    CHECK(v.alias_kl == doctest::Approx(a.kl).epsilon(1e-4));
    CHECK(v.p_confusion >= 0);
    CHECK(v.p_confusion <= 1);
    CHECK(glm::length(v.alias_mm - v.truth_mm) >= prism::defaults::catastrophic_error_mm - 1e-9);
  }
  // Each band's predicted rate is the mean over its events.
  double all = 0;
  for (const auto& v : result.volume) all += v.p_confusion;
  REQUIRE(result.rows.back().series == "all");
  CHECK(result.rows.back().p_confusion_mean == doctest::Approx(all / 3));
  CHECK(result.rows.back().photons == 60);
  for (const auto& r : result.rows) {
    if (r.series == "all") continue;
    double sum = 0;
    int n = 0;
    for (const auto& v : result.volume)
      if (v.truth_mm.z >= r.depth_lo_mm && v.truth_mm.z <= r.depth_hi_mm) sum += v.p_confusion, ++n;
    if (n) CHECK(r.p_confusion_mean == doctest::Approx(sum / n));
  }
  // The files: the events' columns and the bands' predicted rate.
  const std::string out = dir + "/files";
  prism::write_evaluation(out, result);
  auto events = lines_of(out + "/volume-events.csv");
  REQUIRE(events.size() == 4);
  CHECK(events[0].find(",alias_kl,alias_x_mm,alias_y_mm,alias_depth_mm,p_confusion") != std::string::npos);
  {  // p_confusion written; the truth's fit not (the search alone has no refinement to fit it)
    auto fields = [](const std::string& line) {
      std::vector<std::string> out(1);
      for (char c : line)
        if (c == ',') out.emplace_back();
        else out.back().push_back(c);
      return out;
    };
    const auto names = fields(events[0]), values = fields(events[1]);
    REQUIRE(names.size() == values.size());
    auto value = [&](const std::string& name) {
      const auto at = std::find(names.begin(), names.end(), name);
      REQUIRE(at != names.end());
      return values[size_t(at - names.begin())];
    };
    CHECK(value("p_confusion") != "");
    CHECK(value("truth_fit_nll") == "");
    CHECK(value("search_failure") == "");
  }
  auto bands = lines_of(out + "/volume.csv");
  CHECK(bands[0].find(",p_confusion_mean") != std::string::npos);
  CHECK(bands.back().back() != ',');

  // The journal keeps the figure; another photon count is refused rather
  // than mixed in, and a run without --ambiguity reports none.
  o.resume = true;
  const auto resumed = prism::evaluate(prism::test::gpu(), scene, reader, o);
  CHECK(resumed.resumed == 3);
  CHECK(resumed.cost.ambiguity_s == 0);
  for (size_t i = 0; i < 3; ++i) CHECK(resumed.volume[i].p_confusion == doctest::Approx(result.volume[i].p_confusion));
  auto other = o;
  other.volume_photons = 100;
  CHECK_THROWS_AS(prism::evaluate(prism::test::gpu(), scene, reader, other), prism::JournalError);
  other = o;
  other.volume_ambiguity = false;
  const auto without = prism::evaluate(prism::test::gpu(), scene, reader, other);
  CHECK(without.resumed == 3);
  CHECK(std::isnan(without.volume[0].p_confusion));
  CHECK(std::isnan(without.rows.back().p_confusion_mean));
  // Asked for without the volume experiment: refused before any work.
  other = o;
  other.experiments = {"photons"};
  CHECK_THROWS_WITH(prism::evaluate(prism::test::gpu(), scene, reader, other), doctest::Contains("--ambiguity"));
  prism::test::check_validation_clean();
}
