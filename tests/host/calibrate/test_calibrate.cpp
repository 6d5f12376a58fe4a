// Calibration (host/calibrate/calibrate.h, issue 18): a synthetic as-built
// array (host/calibrate/synthetic.h), its PSFs rendered apart from the model
// that fits them (more cells, another stratification) and passed through
// the HDR merge from simulated exposure stacks as `capture-hdr` would record
// them; the fit starts from the nominal scene and must find the as-built one
// within 3 of its own uncertainties. The fit's derivatives come from the CPU
// reference, and in the dictionary command's test from the calibrate kernels
// on lavapipe (bench_calibrate: the same parameters and sigmas either way).
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>

#include "host/calibrate/calibrate.h"
#include "host/calibrate/synthetic.h"
#include "host/dictionary/hdr_stack.h"
#include "host/dictionary/store.h"
#include "support.h"

namespace {

using prism::ref::Param;

// The prototype's central row from lenslet `first` on (real lenses; f = 15,
// 3, 4.5, 6, 7.5, 9, 12 mm from 0). By default the five from f = 4.5 mm on,
// for the tests of other things than the f = 3 mm lenslet's large images.
prism::OpticalSystem nominal_row(size_t first = 2) {
  prism::OpticalSystem s = prism::test::small_system(prism::LensModel::real);
  s.lenslets.erase(s.lenslets.begin(), s.lenslets.begin() + std::ptrdiff_t(first));
  return s;
}

// The model: footprint, 1024 cells per lenslet (256 under the sanitizers),
// 110 um pixels.
prism::TraceSettings model_settings() {
  prism::TraceSettings t = prism::TraceSettings::defaults_for(prism::Splat::footprint);
  t.rays_per_lenslet = prism::test::under_sanitizer ? 256 : 1024;
  t.binning = 16;
  return t;
}

// The truth's rendering: footprint at `times` the command's 1024 cells,
// stratification 1, in the sanitizer build too.
prism::TraceSettings truth_settings(unsigned binning, unsigned times = 4) {
  prism::TraceSettings t = model_settings();
  t.rays_per_lenslet = times * prism::defaults::calibration_rays_per_lenslet;
  t.stratification = 1;
  t.binning = binning;
  return t;
}

// PSF theta of `truth` as capture-hdr stacks merged by merge-hdr would give
// it, rendered at `times` the command's cells.
prism::MeasuredPsf measured(const prism::OpticalSystem& truth, const glm::dvec3& theta, uint64_t seed,
                            unsigned times = 4) {
  return prism::synthetic_measured_psf(truth, truth_settings(model_settings().binning, times), theta, seed);
}

// `prism calibrate --csv`'s table: every parameter of the default --fit in
// order, within 3 sigma of the truth, and as the fitted scene has it.
void check_table(const std::string& csv, const prism::OpticalSystem& truth, const prism::OpticalSystem& fitted) {
  std::ifstream table(csv);
  std::string line;
  std::getline(table, line);
  CHECK(line == "parameter,start,fitted,sigma,change_over_sigma,at_bound,sigma_residuals,sigma_cells,sigma_bootstrap");
  for (const auto& p : prism::calibration_parameters(truth, prism::calibration_default_groups())) {
    REQUIRE(std::getline(table, line));
    CAPTURE(line);
    REQUIRE(line.rfind(p.name() + ",", 0) == 0);
    double start, value, sigma;
    int at_bound = -1;
    REQUIRE(std::sscanf(line.c_str() + p.name().size(), ",%lf,%lf,%lf,%*[^,],%d", &start, &value, &sigma, &at_bound) == 4);
    CHECK(at_bound == 0);
    CHECK(std::abs(value - p.get(truth)) <= 3 * sigma);
    CHECK(p.get(fitted) == doctest::Approx(value).epsilon(1e-9));
  }
  CHECK(!std::getline(table, line));
}

// Three lenslets of the row (f = 6, 7.5, 9 mm), for the command's tests.
prism::Scene three_lenses(const std::string& name) {
  prism::Scene s{name, nominal_row(3), {}, prism::defaults::photons_emitted};
  s.optics.lenslets.resize(3);
  return s;
}

// Sources over the field and the depths: near the face, where the images
// are large, and deep, where they are small. Under the sanitizers `few` is
// two, one at each depth: every path of a fit, a third of its work.
std::vector<glm::dvec3> positions(bool few) {
  if (few && prism::test::under_sanitizer) return {{-6, -3, 6}, {8, -2, 30}};
  std::vector<glm::dvec3> out;
  for (double depth : few ? std::vector<double>{6, 30} : std::vector<double>{6, 15, 30, 45})
    for (glm::dvec2 xy : {glm::dvec2(-6, -3), glm::dvec2(2, 3), glm::dvec2(8, -2)}) out.push_back({xy.x, xy.y, depth});
  return out;
}

}  // namespace

// The whole central row, its f = 3 and 4.5 mm lenslets too, from PSFs
// rendered at 16x the model's cells, the check's count (defaults.h), with
// another stratification: the check is not the truth's own rendering.
// Under the sanitizers the command's test below fits every default
// parameter with both backends.
TEST_CASE("calibration recovers an as-built array from HDR-merged PSFs within 3 of its uncertainties" *
          prism::test::skip_under_sanitizer) {
  const prism::OpticalSystem nominal = nominal_row(0);
  const prism::OpticalSystem truth = prism::synthetic_as_built(nominal);
  std::vector<prism::MeasuredPsf> psfs;
  uint64_t seed = 1;
  for (const auto& theta : positions(false)) psfs.push_back(measured(truth, theta, seed++, 16));

  prism::CalibrationOptions o;
  o.settings = model_settings();
  o.threads = 2;  // the CPU reference; the dictionary command's test below fits with the calibrate kernels
  const auto free = prism::calibration_parameters(nominal, prism::calibration_default_groups());
  REQUIRE(free.size() == nominal.lenslets.size() * 5 + 6);
  const auto r = prism::calibrate(nominal, psfs, free, o);
  MESSAGE("chi2 " << r.chi2_start << " -> " << r.chi2 << ", chi2/dof " << r.reduced_chi2() << ", " << r.steps
                  << " steps (" << r.stretched << " stretched, " << r.pattern_moves << " pattern moves), " << r.seconds
                  << " s, of which the check of the model's cells (" << r.check_cells
                  << " cells) " << r.check_seconds << " s");
  CHECK(r.chi2 < 0.05 * r.chi2_start);
  CHECK(r.converged);
  // Gauss-Newton overstates chi2's curvature here (the f = 3 mm lenslet's
  // misfit): steps taken further along their line (calibrate.cpp, stretch)
  // brought the fit from 58 steps to 35, to the same chi2.
  CHECK(r.stretched > 0);
  CHECK(r.steps < 50);

  size_t far_at_start = 0;
  std::string beyond_residuals;  // parameters beyond 3 sigma of the sandwich alone
  for (const auto& e : r.estimates) {
    const double want = e.parameter.get(truth);
    CAPTURE(e.parameter.name());
    CAPTURE(e.start);
    CAPTURE(e.value);
    CAPTURE(want);
    CAPTURE(e.sigma);
    CAPTURE(e.sigma_residuals);
    CAPTURE(e.sigma_cells);
    REQUIRE(std::isfinite(e.sigma));
    CHECK(std::abs(e.value - want) <= 3 * e.sigma);
    if (std::abs(e.value - want) > 3 * e.sigma_residuals) beyond_residuals += e.parameter.name() + " ";
    far_at_start += std::abs(e.start - want) > 3 * e.sigma;
    // Small enough to matter: lens positions to better than 10 um, except
    // the f = 3 mm near hemisphere's, which the model's 1024 cells limit (x
    // off by 15 um, sigma 10.6 um, nearly all of it the cells'; at a 4x
    // check its sigma read 7 um while the error was as large): more cells
    // (--rays) are what would pin it.
    if (e.parameter.param == Param::lens_x || e.parameter.param == Param::lens_y) {
      const bool cells_limit_it =
          nominal.lenslets[size_t(e.parameter.lens)].focal_mm < 4 && e.sigma_cells > 2 * e.sigma_residuals;
      CHECK((e.sigma < 0.010 || cells_limit_it));
    }
  }
  // The nominal scene is not already the answer: most parameters start
  // many sigmas away.
  CHECK(far_at_start >= r.estimates.size() * 3 / 4);
  // What the model's cells add is needed: the sandwich alone leaves the
  // f = 3 mm lenslet's position 6-10 of its sigmas off (its image is the
  // largest and most curved, and the model's error runs alike along its
  // edges). Should this fail, the model has become good enough without it.
  MESSAGE("beyond 3 sigma of the residuals alone: " << beyond_residuals);
  CHECK(beyond_residuals.find("lenslets[1].x_mm") != std::string::npos);
}

// A fit pulled toward shorter focal lengths (the f = 3 mm lenslets, on PSFs
// of another pixel model) met validate's plano-convex wall inside its
// bounds and stopped there as "converged": every trial beyond the wall was
// untraceable. The wall is now the bound: clamped steps, `at_bound`.
TEST_CASE("calibration: a real lens's focal length is bounded at the plano-convex limit that the model can trace") {
  const prism::OpticalSystem nominal = nominal_row(0);
  size_t walled = 0;
  for (const auto& p : prism::calibration_parameters(nominal, {"lens_focal"})) {
    CAPTURE(p.name());
    const auto [lo, hi] = p.bounds(nominal);
    // The wall written out here, not through shortest_focal_mm: R = f (n - 1) = D / 2.
    const double f = p.get(nominal), wall = 0.5 * nominal.lenslets[size_t(p.lens)].diameter_mm / (nominal.glass_index - 1);
    CHECK(lo >= wall);
    CHECK(hi == doctest::Approx(f * (1 + prism::defaults::calibration_max_focal_change)));
    if (lo > f * (1 - prism::defaults::calibration_max_focal_change)) {
      ++walled;
      CHECK(lo == doctest::Approx(wall).epsilon(1e-9));
    }
    prism::OpticalSystem at = nominal;
    p.set(at, lo);
    CHECK_NOTHROW(prism::validate(at));  // the bound itself is a lens the model traces
    p.set(at, wall * (1 - 1e-9));
    CHECK_THROWS_AS(prism::validate(at), std::invalid_argument);  // just beyond the wall, none
  }
  CHECK(walled > 0);  // the row's f = 3 mm lenslet (D = 3 mm: f >= 2.90 mm, within 20% of 3)
  // A thin lens has no such wall: the 20% range alone.
  prism::OpticalSystem thin = nominal;
  thin.lens_model = prism::LensModel::thin;
  for (const auto& p : prism::calibration_parameters(thin, {"lens_focal"}))
    CHECK(p.bounds(thin).first == doctest::Approx(p.get(thin) * (1 - prism::defaults::calibration_max_focal_change)));
}

TEST_CASE("calibration: on coarse pixels a partly censored pixel holds at least its measured sub-pixels' light") {
  // A coarse pixel over a faint rim mixes measured sub-pixels with censored
  // ones. Counted as "at most" alone, such pixels pulled no light toward
  // them: on the whole prototype the coarse levels left the faint discs of
  // an f = 3 mm corner lenslet 150 um of position and focal length from the
  // truth (docs/calibration.md). Here every other pixel of the PSF is censored, a
  // checkerboard: each 2 x 2 coarse pixel is partly censored, and only what
  // its measured half holds can pull lenslet 3 (f = 9 mm, its spot bright 30
  // mm deep) back from 40 um off. The fit is stopped at the model's pixels.
  const prism::OpticalSystem truth = nominal_row();
  prism::MeasuredPsf psf = measured(truth, {2, 3, 30}, 7);
  const auto grid = prism::AnalysisGrid::of(truth, model_settings().binning);
  for (size_t i = 0; i < psf.p.size(); ++i)
    if ((i % size_t(grid.width) + i / size_t(grid.width)) % 2) psf.p[i] = 0;  // censored: below any reliable value
  prism::OpticalSystem start = truth;
  start.lenslets[3].x_mm += 0.040;
  prism::CalibrationOptions o;
  o.settings = model_settings();
  o.coarse_levels = 1;
  std::vector<double> x_after;  // lenslet 3's x after each step on the 2x pixels
  struct ModelPixels {};
  o.progress = [&](const prism::CalibrationStep& s) {
    if (s.level == 0) throw ModelPixels{};
    x_after.push_back(s.reached.lenslets[3].x_mm);
  };
  const auto free = prism::calibration_parameters(start, {"lens_xy"});
  REQUIRE(free[6].name() == "lenslets[3].x_mm");
  CHECK_THROWS_AS(prism::calibrate(start, {psf}, {free.begin() + 6, free.begin() + 8}, o), ModelPixels);
  REQUIRE_MESSAGE(!x_after.empty(), "no step on the coarse pixels: nothing there pulled the lenslet");
  const double error_um = 1e3 * (x_after.back() - truth.lenslets[3].x_mm);
  MESSAGE(x_after.size() << " steps on the coarse pixels: x error 40 um -> " << error_um << " um");
  CHECK(std::abs(error_um) < 10);
}

TEST_CASE("calibration: the blur term (an extended source's sigma) is found and frees the rest of its bias") {
  // Three lenslets as built, imaging a Gaussian source of 0.25 mm per axis.
  // The truth is the engine's source_extent (a random source offset per
  // footprint cell) at 256x the model's cells, so that its speckle lies near
  // the HDR noise; the model blurs each lenslet's point image smoothly
  // (source_blur.h). Both fits start from the nominal scene of a point
  // source; one frees sigma too (from its default, 0.3 mm).
  const prism::OpticalSystem nominal = three_lenses("nominal").optics;
  prism::OpticalSystem truth = prism::synthetic_as_built(nominal);
  truth.effects.source_extent = true;
  truth.effects.source_sigma_mm = 0.25;
  prism::TraceSettings fine = truth_settings(model_settings().binning);
  fine.rays_per_lenslet = (prism::test::under_sanitizer ? 4 : 256) * prism::defaults::calibration_rays_per_lenslet;
  std::vector<prism::MeasuredPsf> psfs;
  uint64_t seed = 70;
  for (const auto& theta : positions(true)) psfs.push_back(prism::synthetic_measured_psf(truth, fine, theta, seed++));
  prism::CalibrationOptions o;
  o.settings = model_settings();
  o.threads = 2;
  if (prism::test::under_sanitizer) o.max_steps = 2, o.coarse_levels = 1;  // the paths, for memory errors
  // At the truth, the blur on 2x finer pixels (calibrate --blur-supersample)
  // explains the PSFs as well as on the model's (0.07% better): the finer
  // pixels bin back onto the model's (a grid off by a fine pixel, or light
  // lost at the edges, would not).
  prism::CalibrationOptions at_truth = o;
  at_truth.max_steps = 0, at_truth.coarse_levels = 0;
  const auto only_sigma = prism::calibration_parameters(truth, {"source_extent"});
  const double chi2_1 = prism::calibrate(truth, psfs, only_sigma, at_truth).chi2;
  at_truth.blur_supersample = 2;
  const double chi2_2 = prism::calibrate(truth, psfs, only_sigma, at_truth).chi2;
  MESSAGE("chi2 at the truth: " << chi2_1 << " blurred on the model's pixels, " << chi2_2 << " on 2x finer");
  CHECK(chi2_2 == doctest::Approx(chi2_1).epsilon(0.02));

  std::vector<std::string> groups = prism::calibration_default_groups();
  const prism::CalibrationResult point = prism::calibrate(nominal, psfs, prism::calibration_parameters(nominal, groups), o);
  groups.push_back("source_extent");
  const auto free = prism::calibration_parameters(nominal, groups);
  REQUIRE(free.back().param == Param::source_sigma);
  const prism::CalibrationResult blurred = prism::calibrate(nominal, psfs, free, o);
  CHECK(blurred.fitted.effects.source_extent);
  CHECK_FALSE(point.fitted.effects.source_extent);
  // The largest error of the lens positions, and how many parameters lie
  // within 3 sigma of the truth.
  auto summary = [&](const prism::CalibrationResult& r, double& worst_xy_mm) {
    size_t within = 0;
    worst_xy_mm = 0;
    for (const auto& e : r.estimates) {
      const double error = std::abs(e.value - e.parameter.get(truth));
      within += error <= 3 * e.sigma;
      if (e.parameter.param == Param::lens_x || e.parameter.param == Param::lens_y)
        worst_xy_mm = std::max(worst_xy_mm, error);
    }
    return within;
  };
  double worst_point = 0, worst_blurred = 0;
  const size_t within_point = summary(point, worst_point), within_blurred = summary(blurred, worst_blurred);
  const auto& sigma = blurred.estimates.back();
  MESSAGE("point source: chi2 " << point.chi2 << ", " << within_point << " of " << point.estimates.size()
                                << " within 3 sigma, lens positions up to " << 1e3 * worst_point << " um off");
  MESSAGE("blur term: chi2 " << blurred.chi2 << ", " << within_blurred << " of " << blurred.estimates.size()
                             << " within 3 sigma, lens positions up to " << 1e3 * worst_blurred << " um off; sigma "
                             << sigma.value << " +- " << sigma.sigma << " mm (truth 0.25), " << blurred.steps
                             << " steps, " << blurred.seconds << " s");
  if (prism::test::under_sanitizer) return;
  CHECK(blurred.converged);
  CHECK(blurred.chi2 < 0.25 * point.chi2);
  CHECK(worst_blurred < 0.5 * worst_point);
  CHECK(std::isfinite(sigma.sigma));
  // Found to a few per cent: the first-order blur puts it 2% high (docs/calibration.md, the blur term).
  CHECK(std::abs(sigma.value - 0.25) < 0.05 * 0.25);
}

TEST_CASE("calibration: light the model puts where the merged PSF is dark counts against it") {
  // The merge rejects pixels too faint to measure; the fit censors them (at
  // most the reliable value). A lenslet moved 1.5 mm off the row sends its
  // image where the measurement is dark: left out, those pixels would cost
  // nothing, and a fit could park a lenslet's light there. Counted, they
  // are that lenslet's residual, and the PSF's photon scale, fitted to every
  // pixel that counts, falls. Lenslet 3 (f = 9 mm) focuses a source 30 mm
  // deep to a spot bright enough to count.
  const prism::OpticalSystem truth = nominal_row();
  const std::vector<prism::MeasuredPsf> psfs{measured(truth, {2, 3, 30}, 7)};
  prism::CalibrationOptions o;
  o.settings = model_settings();
  o.max_steps = 0, o.coarse_levels = 0;
  auto at = [&](const prism::OpticalSystem& start) {
    const auto free = prism::calibration_parameters(start, {"lens_xy"});
    return prism::calibrate(start, psfs, {free.begin(), free.begin() + 2}, o);
  };
  prism::OpticalSystem moved = truth;
  moved.lenslets[3].y_mm += 1.5;
  const prism::CalibrationResult r = at(moved), r0 = at(truth);
  REQUIRE(r.lenses.size() == truth.lenslets.size());
  std::string per_lens;
  for (size_t l = 0; l < r.lenses.size(); ++l)
    per_lens += "\nlenslet " + std::to_string(l) + ": chi2 " + std::to_string(r.lenses[l].chi2) + " over " +
                std::to_string(r.lenses[l].pixels) + " px";
  INFO(per_lens);
  CHECK(r.lenses[3].pixels > r0.lenses[3].pixels / 2);
  CHECK(r.lenses[3].chi2 > 100 * r0.lenses[3].chi2);
  CHECK(r.psfs[0].scale < 0.9 * r0.psfs[0].scale);
}

TEST_CASE("calibration: a parameter the data push past its range ends on its bound, without a sigma") {
  // The sensor lies 2.3 mm farther than nominal in truth; the fit may move it
  // by 2 mm (defaults::calibration_max_distance_mm), so it ends there, flagged.
  prism::OpticalSystem truth = nominal_row();
  truth.lens_to_sensor_mm += 2.3;
  std::vector<prism::MeasuredPsf> psfs;
  uint64_t seed = 40;
  // Under the sanitizers the truth at the command's cells (its rendering was
  // most of this case's time there); the bound is reached all the same.
  for (const glm::dvec3& theta : positions(true))
    psfs.push_back(measured(truth, theta, seed++, prism::test::under_sanitizer ? 1 : 4));
  const prism::OpticalSystem start = nominal_row();
  prism::CalibrationOptions o;
  o.settings = model_settings();
  o.max_steps = 10;
  std::vector<prism::CalibrationParameter> free = prism::calibration_parameters(start, {"lens_to_sensor"});
  free.push_back(prism::calibration_parameters(start, {"lens_xy"}).at(4));  // lenslet 2's x
  const prism::CalibrationResult r = prism::calibrate(start, psfs, free, o);
  REQUIRE(r.estimates.size() == 2);
  const auto& distance = r.estimates[0];
  CAPTURE(distance.value);
  CAPTURE(distance.sigma);
  CHECK(distance.at_bound);
  CHECK(distance.value == doctest::Approx(start.lens_to_sensor_mm + prism::defaults::calibration_max_distance_mm));
  CHECK(std::isinf(distance.sigma));
  CHECK_FALSE(r.estimates[1].at_bound);
  CHECK(std::isfinite(r.estimates[1].sigma));

  // sigma is the residuals' and the model's cells' in quadrature; the check
  // rendered the default factor's cells; the parameter on its bound has no
  // cells' part.
  const auto& x = r.estimates[1];
  CHECK(r.check_cells == prism::defaults::calibration_cells_check_factor * o.settings.rays());
  CHECK(x.sigma_cells > 0);
  CHECK(x.sigma == doctest::Approx(std::hypot(x.sigma_residuals, x.sigma_cells)));
  CHECK(distance.sigma_cells == 0);
  // Without the check, and on one thread: the same fit, sigma the
  // residuals' alone. The PSFs' sums add in PSF order whichever thread
  // rendered them, so the fit repeats to the bit.
  o.cells_check = 1;
  o.threads = 1;
  const prism::CalibrationResult unchecked = prism::calibrate(start, psfs, free, o);
  CHECK(unchecked.check_cells == 0);
  CHECK(unchecked.estimates[1].value == x.value);
  CHECK(unchecked.estimates[1].sigma_cells == 0);
  CHECK(unchecked.estimates[1].sigma == x.sigma_residuals);
}

// The bootstrap over the PSFs (calibrate.h): a replicate counts a PSF drawn
// twice twice, which must be the fit of that PSF given twice; the spread is
// the replicates', repeats with the seed, and takes sigma's residual part
// where it is larger than the sandwich's.
TEST_CASE("calibration's bootstrap: a PSF drawn twice counts as the PSF given twice; the spread repeats by seed") {
  // Only what the fit frees differs from the nominal row: the model is right
  // but for its cells and the noise.
  const prism::OpticalSystem nominal = nominal_row();
  prism::OpticalSystem truth = nominal;
  for (size_t l = 0; l < truth.lenslets.size(); ++l)
    truth.lenslets[l].x_mm += 0.01 * double(l) - 0.02, truth.lenslets[l].y_mm += 0.015 - 0.01 * double(l % 3);
  truth.lens_to_sensor_mm += 0.1;
  std::vector<prism::MeasuredPsf> psfs;
  uint64_t seed = 60;
  for (const glm::dvec3& theta : positions(true)) psfs.push_back(measured(truth, theta, seed++, 1));
  prism::CalibrationOptions o;
  o.settings = model_settings();
  o.threads = 1;  // sums in PSF order: fits repeat to the bit
  o.cells_check = 1;
  o.max_steps = 4;
  const auto free = prism::calibration_parameters(nominal, {"lens_xy", "lens_to_sensor"});

  std::vector<prism::MeasuredPsf> twice = psfs, counted = psfs;
  twice.push_back(psfs[1]);
  counted[1].count = 2;
  // Each accepted step's progress: chi2's fall and what Gauss-Newton's model
  // predicted for it. The model is right here but for its cells and the
  // noise, so the first step (the largest) gains about what was predicted.
  std::vector<prism::CalibrationStep> steps;
  o.progress = [&](const prism::CalibrationStep& s) { steps.push_back(s); };
  const prism::CalibrationResult a = prism::calibrate(nominal, twice, free, o);
  o.progress = nullptr;
  REQUIRE(steps.size() == size_t(a.steps));
  REQUIRE(!steps.empty());
  for (const auto& s : steps) {
    CAPTURE(s.step);
    CHECK(s.gain > 0);
    CHECK(s.predicted > 0);
  }
  MESSAGE("first step: gain " << steps[0].gain << ", predicted " << steps[0].predicted);
  CHECK(steps[0].gain / steps[0].predicted > 0.5);
  CHECK(steps[0].gain / steps[0].predicted < 2);
  // Pattern moves take a point only where chi2 is lower than the step's
  // own: every step still gains, and where both fits converge, they reach
  // the same optimum. At a step limit neither end is bound to be the lower:
  // the paths part at the first move (under the sanitizers, 256 cells and
  // two PSFs, 4 steps a level stop both fits, and with 2 moves taken the
  // patterned one ended 24% higher). At 1024 cells none is taken here and
  // the two fits are one.
  o.pattern_moves = true;
  std::vector<prism::CalibrationStep> patterned_steps;
  o.progress = [&](const prism::CalibrationStep& s) { patterned_steps.push_back(s); };
  const prism::CalibrationResult patterned = prism::calibrate(nominal, twice, free, o);
  o.pattern_moves = false;
  o.progress = nullptr;
  MESSAGE("pattern moves: " << patterned.pattern_moves << " taken, " << patterned.steps << " steps, chi2 "
                            << patterned.chi2 << std::string(patterned.converged ? " converged" : " at the step limit")
                            << " (without: " << a.steps << " steps, " << a.chi2
                            << std::string(a.converged ? ", converged)" : ", at the step limit)"));
  for (const auto& s : patterned_steps) {
    CAPTURE(s.step);
    CHECK(s.gain > 0);
  }
  CHECK(patterned.chi2 < patterned.chi2_start);
  if (!prism::test::under_sanitizer) REQUIRE(a.converged);
  if (a.converged && patterned.converged) CHECK(patterned.chi2 == doctest::Approx(a.chi2).epsilon(1e-5));
  for (size_t j = 0; j < free.size() && a.converged && patterned.converged; ++j) {
    CAPTURE(free[j].name());
    CHECK(std::abs(patterned.estimates[j].value - a.estimates[j].value) < 0.2 * a.estimates[j].sigma_residuals);
  }
  const prism::CalibrationResult b = prism::calibrate(nominal, counted, free, o);
  CHECK(b.chi2_start == doctest::Approx(a.chi2_start).epsilon(1e-12));
  CHECK(b.chi2 == doctest::Approx(a.chi2).epsilon(1e-9));
  CHECK(b.pixels == a.pixels);
  CHECK(b.psfs[1].chi2 == doctest::Approx(a.psfs[1].chi2 + a.psfs.back().chi2).epsilon(1e-9));
  for (size_t j = 0; j < free.size(); ++j) {
    CAPTURE(free[j].name());
    CHECK(b.estimates[j].value == doctest::Approx(a.estimates[j].value).epsilon(1e-9));
    CHECK(b.estimates[j].sigma_residuals == doctest::Approx(a.estimates[j].sigma_residuals).epsilon(1e-6));
  }

  o.bootstrap = 4;
  o.bootstrap_steps = 3;
  unsigned reported = 0;
  std::vector<std::vector<double>> values(free.size());  // each parameter's value per replicate
  o.bootstrap_progress = [&](unsigned rep, const prism::CalibrationResult& f) {
    CHECK(rep == ++reported);
    CHECK(f.steps <= 3);
    for (size_t j = 0; j < free.size(); ++j) values[j].push_back(f.estimates[j].value);
  };
  const prism::CalibrationResult r = prism::calibrate(nominal, psfs, free, o);
  CHECK(reported == 4);
  CHECK(r.bootstrap_replicates == 4);
  o.bootstrap_progress = nullptr;
  const prism::CalibrationResult again = prism::calibrate(nominal, psfs, free, o);
  o.bootstrap_seed = 2;
  const prism::CalibrationResult other = prism::calibrate(nominal, psfs, free, o);
  size_t differ = 0;
  std::vector<double> ratio;
  for (size_t j = 0; j < free.size(); ++j) {
    const auto& e = r.estimates[j];
    CAPTURE(e.parameter.name());
    CAPTURE(e.sigma_residuals);
    CAPTURE(e.sigma_bootstrap);
    REQUIRE(std::isfinite(e.sigma_residuals));
    CHECK(e.sigma_bootstrap > 0);
    CHECK(e.sigma == doctest::Approx(std::max(e.sigma_residuals, e.sigma_bootstrap)));
    CHECK(again.estimates[j].sigma_bootstrap == e.sigma_bootstrap);
    differ += other.estimates[j].sigma_bootstrap != e.sigma_bootstrap;
    ratio.push_back(e.sigma_bootstrap / e.sigma_residuals);
    // The replicates' sample standard deviation.
    double mean = 0, var = 0;
    for (double v : values[j]) mean += v / 4;
    for (double v : values[j]) var += (v - mean) * (v - mean) / 3;
    CHECK(e.sigma_bootstrap == doctest::Approx(std::sqrt(var)).epsilon(1e-6));
  }
  CHECK(differ == free.size());
  // The model is right but for its cells and the noise, and the two estimate
  // one spread. Four replicates of six PSFs scatter by a factor of a few
  // (median 0.33 here, seeds 1 and 2 differing up to 30x on one parameter):
  // this catches a spread in the wrong units, not a subtle bias (the whole
  // prototype's measurement in docs/calibration.md is the check of that).
  std::sort(ratio.begin(), ratio.end());
  const double median = ratio[ratio.size() / 2];
  MESSAGE("bootstrap / sandwich over " << ratio.size() << " parameters: median " << median << ", range " << ratio.front()
                                       << " .. " << ratio.back());
  CHECK(median > 0.05);
  CHECK(median < 20);
}

TEST_CASE("calibration: parameter groups, names and errors") {
  const prism::OpticalSystem s = prism::test::small_system(prism::LensModel::real);
  const auto p = prism::calibration_parameters(s, {"lens_focal", "sensor_tilt", "lens_focal"});
  REQUIRE(p.size() == 7 + 2);
  CHECK(p[0].name() == "lenslets[0].focal_mm");
  CHECK(p[7].name() == "sensor.tilt_x_deg");
  CHECK_THROWS_WITH_AS(prism::calibration_parameters(s, {"lens_zoom"}),
                       doctest::Contains("no parameter group 'lens_zoom'; the groups are lens_xy"),
                       std::invalid_argument);
  prism::CalibrationOptions o;
  o.settings = model_settings();
  prism::MeasuredPsf wrong{{0, 0, 20}, std::vector<float>(10, 1.0f), "wrong.exr", {}};
  CHECK_THROWS_WITH_AS(prism::calibrate(s, {wrong}, p, o), doctest::Contains("PSF wrong.exr has 10 pixels"),
                       std::invalid_argument);
  CHECK_THROWS_WITH_AS(prism::calibrate(s, {wrong}, {}, o), doctest::Contains("no parameter to fit"),
                       std::invalid_argument);
  o.reliable_over_faintest = 0.5;  // below the faintest value kept: nothing would be censored that should be
  CHECK_THROWS_WITH_AS(prism::calibrate(s, {wrong}, p, o), doctest::Contains("--reliable >= 1"), std::invalid_argument);
}

TEST_CASE("prism calibrate: a dictionary of HDR-merged PSFs in, a scene every command accepts out") {
  namespace fs = std::filesystem;
  const fs::path dir = prism::test::scratch_dir() / "calibrate";
  // The dictionary's scene is the nominal one.
  const prism::Scene nominal = three_lenses("row");
  const prism::OpticalSystem truth = prism::synthetic_as_built(nominal.optics);
  prism::DictionaryManifest m;
  m.scene = nominal;
  m.grid = {{-6, 6}, {0}, {8, 20, 35}};
  m.base_binning = 16;
  const auto grid = prism::AnalysisGrid::of(nominal.optics, 16);
  m.width = grid.width, m.height = grid.height;
  m.levels = prism::DictionaryManifest::mip_levels(m.width, m.height);
  m.source = "calibrated";
  fs::create_directories(dir / "dict");
  {
    std::ofstream out(dir / "dict" / "manifest.json");
    out << m.to_json().dump(2) << '\n';
  }
  for (size_t i = 0; i < m.grid.size(); ++i) {
    const auto psf = measured(truth, m.grid.position(i), 10 + i);
    prism::write_psf_file((dir / "dict" / m.file_of(i)).string(), m, i, {0, m.width, m.height, psf.p}, 0.0);
  }
  const std::string out = (dir / "fitted.json").string(), csv = (dir / "params.csv").string();
  const std::string checkpoint = (dir / "reached.json").string();
  auto run = prism::test::run_prism("calibrate --dictionary " + (dir / "dict").string() + " --out " + out + " --csv " +
                                    csv + " --residuals " + (dir / "residuals").string() + " --checkpoint " +
                                    checkpoint + " --backend vulkan");
  INFO(run.output);
  REQUIRE(run.status == 0);
  CHECK(run.output.find("6 of 6 PSFs") != std::string::npos);
  // The checkpoint holds the scene after the last accepted step: the scene
  // written, to the byte; the progress said how to resume from it, level by level.
  auto text_of = [](const std::string& path) {
    std::ifstream in(path);
    return std::string(std::istreambuf_iterator<char>(in), {});
  };
  CHECK(text_of(checkpoint) == text_of(out));
  CHECK(run.output.find("reached.json holds the scene reached after each step (stopped, the fit resumes with "
                        "--scene " + checkpoint + " --coarse-levels 2)") != std::string::npos);
  CHECK(run.output.find("--coarse-levels 0)") != std::string::npos);
  CHECK(run.output.find("on llvmpipe") != std::string::npos);  // the calibrate kernels, on lavapipe here
  const prism::Scene fitted = prism::load_scene(out);
  CHECK(fitted.name == "row-calibrated");
  // Every parameter (the default --fit frees them all) within 3 sigma of the
  // truth, in the table and in the scene written.
  check_table(csv, truth, fitted.optics);
  for (const char* file : {"residual-0000.png", "residual-0005.png", "psfs.csv", "lenslets.csv", "lenslets.png"})
    CHECK_MESSAGE(fs::exists(dir / "residuals" / file), file);

  // A fitted scene refined on the model's pixels alone (--coarse-levels 0,
  // docs/calibration.md): it starts at the optimum and stays there. With
  // two bootstrap replicates, whose spread may only widen sigma.
  const std::string refined = (dir / "refined.json").string(), csv_refined = (dir / "params-refined.csv").string();
  run = prism::test::run_prism("calibrate --dictionary " + (dir / "dict").string() + " --scene " + out +
                               " --coarse-levels 0 --out " + refined + " --csv " + csv_refined +
                               " --backend cpu --bootstrap 2 --bootstrap-steps 2");
  INFO(run.output);
  REQUIRE(run.status == 0);
  // From the optimum either a step still gains a little or none does; then
  // the smallest step tried must have raised chi2 by well under chi2 / dof
  // (a smooth optimum, not a jump in the model).
  const size_t stopped = run.output.find("(stopped: no step of any damping lowered chi2; the smallest one tried raised it by ");
  if (stopped == std::string::npos) {
    CHECK(run.output.find("(converged)") != std::string::npos);
  } else {
    const double rise = std::stod(run.output.substr(run.output.find(" by ", stopped) + 4));
    MESSAGE("the refit took no step; the smallest one tried raised chi2 by " << rise << " x chi2 / dof");
    CHECK(rise < 1);
  }
  CHECK(run.output.find("bootstrap replicate 2 of 2: chi2 ") != std::string::npos);
  // One line says what sigma holds.
  CHECK(run.output.find("sigma = the larger of the residuals' (sandwich) and the bootstrap's (2 replicates") !=
        std::string::npos);
  check_table(csv_refined, truth, prism::load_scene(refined).optics);
  CHECK(prism::load_scene(refined).name == "row-calibrated");  // not "-calibrated" twice

  // A fitted source extent is the calibration source's: in the table, not
  // in the scene written (events are point sources).
  const std::string out2 = (dir / "fitted-extent.json").string(), csv2 = (dir / "params-extent.csv").string();
  run = prism::test::run_prism("calibrate --dictionary " + (dir / "dict").string() + " --out " + out2 + " --csv " +
                               csv2 + " --fit lens_xy,source_extent --max-steps 2 --backend cpu");
  INFO(run.output);
  REQUIRE(run.status == 0);
  CHECK(run.output.find("The calibration source's extent (sigma ") != std::string::npos);
  CHECK_FALSE(prism::load_scene(out2).optics.effects.source_extent);
  std::ifstream table(csv2);
  std::string line, last;
  while (std::getline(table, line)) last = line;
  CHECK(last.rfind("effects.source_extent.sigma_mm,0.3,", 0) == 0);

  // Errors name what is wrong.
  auto bad = prism::test::run_prism("calibrate --dictionary " + (dir / "dict").string() + " --out " + out +
                                    " --fit lens_zoom");
  CHECK(bad.status != 0);
  CHECK(bad.output.find("no parameter group 'lens_zoom'") != std::string::npos);
  bad = prism::test::run_prism("calibrate --dictionary " + (dir / "dict").string() + " --out " + out +
                               " --coarse-levels 5");
  CHECK(bad.status != 0);
  CHECK(bad.output.find("--coarse-levels") != std::string::npos);
  bad = prism::test::run_prism("calibrate --dictionary " + (dir / "dict").string() + " --out " + out +
                               " --bootstrap 1");
  CHECK(bad.status != 0);
  CHECK(bad.output.find("--bootstrap: one replicate has no spread") != std::string::npos);
  bad = prism::test::run_prism("calibrate --dictionary " + (dir / "dict").string() + " --out " + out + " --level 20");
  CHECK(bad.status != 0);
  CHECK(bad.output.find("--level: 20 is beyond the dictionary's levels 0..") != std::string::npos);
  bad = prism::test::run_prism("calibrate --dictionary " + (dir / "dict").string() + " --out " + out +
                               " --checkpoint " + out);
  CHECK(bad.status != 0);
  CHECK(bad.output.find("--checkpoint: " + out + " is also --out") != std::string::npos);
  bad = prism::test::run_prism("calibrate --dictionary " + (dir / "dict").string() + " --out " +
                               (dir / "dict" / "x.json").string());
  CHECK(bad.status != 0);
  CHECK(bad.output.find("--out") != std::string::npos);
}

TEST_CASE("prism calibrate --merged: capture-hdr stacks through merge-hdr to the fitted scene") {
  namespace fs = std::filesystem;
  const fs::path dir = prism::test::scratch_dir() / "calibrate-merged";
  // A camera whose pixels are 110.4 um (the prototype's sensor binned 16 x
  // 16 in the camera), so that its stacks stay small.
  prism::Scene nominal = three_lenses("camera");
  nominal.optics.sensor_width_px = 419, nominal.optics.sensor_height_px = 298;
  nominal.optics.pixel_um = 6.9 * 16;
  const std::string scene = (dir / "camera.json").string();
  fs::create_directories(dir);
  {
    std::ofstream out(scene);
    out << prism::to_json(nominal).dump(2) << '\n';
  }
  const prism::OpticalSystem truth = prism::synthetic_as_built(nominal.optics);
  uint64_t seed = 30;
  for (const glm::dvec3 theta : {glm::dvec3(-6, 0, 8), glm::dvec3(6, 0, 8), glm::dvec3(-6, 0, 20), glm::dvec3(6, 0, 20),
                                 glm::dvec3(-6, 0, 35), glm::dvec3(6, 0, 35)}) {
    prism::HdrStack stack;
    stack.source_mm = theta;
    stack.frames = prism::synthetic_exposures(truth, truth_settings(1), theta, seed);
    prism::write_hdr_stack((dir / "stacks" / ("p" + std::to_string(seed++))).string(), stack);
  }
  auto merge = prism::test::run_prism("dictionary merge-hdr --stacks " + (dir / "stacks").string() + " --out " +
                                      (dir / "merged").string() + " --backend cpu");
  INFO(merge.output);
  REQUIRE(merge.status == 0);
  const std::string out = (dir / "fitted.json").string(), csv = (dir / "params.csv").string();
  auto run = prism::test::run_prism("calibrate --merged " + (dir / "merged").string() + " --scene " + scene + " --out " +
                                    out + " --csv " + csv + " --threads 2");
  INFO(run.output);
  REQUIRE(run.status == 0);
  CHECK(run.output.find("6 of 6 merged PSFs (every 1) binned 1 x 1") != std::string::npos);
  // --backend auto: the CPU reference, the Vulkan device being lavapipe.
  CHECK(run.output.find("on the CPU reference with 2 threads (auto: the Vulkan device llvmpipe") != std::string::npos);
  check_table(csv, truth, prism::load_scene(out).optics);
  // Merged PSFs name no scene, and have one level.
  auto bad = prism::test::run_prism("calibrate --merged " + (dir / "merged").string() + " --out " + out);
  CHECK(bad.status != 0);
  CHECK(bad.output.find("--merged: give --scene") != std::string::npos);
  bad = prism::test::run_prism("calibrate --merged " + (dir / "merged").string() + " --scene prototype --out " + out);
  CHECK(bad.status != 0);
  CHECK(bad.output.find("px; the scene's sensor is 6696 x 4764: give the scene of this camera") != std::string::npos);
  {  // a source behind the lenses
    const fs::path sidecar = dir / "merged" / "p30.json";
    std::ifstream in(sidecar);
    nlohmann::json j = nlohmann::json::parse(in);
    in.close();
    j["source"]["depth_mm"] = -7.0;
    std::ofstream(sidecar) << j.dump(2);
  }
  bad = prism::test::run_prism("calibrate --merged " + (dir / "merged").string() + " --scene " + scene + " --out " + out);
  CHECK(bad.status != 0);
  CHECK(bad.output.find("p30.exr's source: depth -7 mm is not in front of") != std::string::npos);
  bad = prism::test::run_prism("calibrate --out " + out);
  CHECK(bad.status != 0);
  CHECK(bad.output.find("--dictionary DIR or as --merged DIR") != std::string::npos);
}
