// The continuous refinement (host/reconstruct/refine.h) on the thin-lens
// seven-lenslet row (fast on lavapipe): events are rendered apart from the
// model that fits them (footprint at 4x the cells, other stratification), the
// refinement starts off the truth, and the Vulkan model must agree with the
// double CPU reference. Hard cases: a start on the depth bound, a source
// outside the field, a start on a lattice alias, a start at the wrong depth
// near the face, near-face local optima the ladder must leave, two
// vertices (one of them left far off by the search), and the goodness of
// fit on events the model does and does not explain.
#include <cmath>
#include <map>

#include "host/events/simulate.h"
#include "host/reconstruct/click_geometry.h"
#include "host/reconstruct/refine.h"
#include "support.h"

namespace {

constexpr int binning = 16;  // 419 x 298 click grid, 0.11 mm pixels

prism::Scene small_scene() {
  prism::Scene s;
  s.name = "thin row";
  s.optics = prism::test::small_system(prism::LensModel::thin);
  return s;
}

// Truth: footprint at 4x the refinement's cells, stratification 1.
prism::ForwardTruth& truth() {
  static prism::ForwardTruth t = [] {
    prism::TraceSettings s = prism::refine_trace_settings(binning);
    s.rays_per_lenslet *= 4;
    s.stratification = 1;
    return prism::ForwardTruth(prism::test::gpu(), small_scene(), s, 64);
  }();
  return t;
}

using Source = prism::test::EventSource;

prism::Event make_event(const std::vector<Source>& sources, uint64_t id) {
  return prism::test::sample_event(truth(), sources, 77, id);
}

prism::ReconstructedVertex row(glm::dvec3 at, double alpha) {
  prism::ReconstructedVertex v;
  v.x_mm = at.x, v.y_mm = at.y, v.depth_mm = at.z, v.alpha = alpha;
  return v;
}

const prism::AnalysisGrid& grid() {
  static prism::AnalysisGrid g = prism::AnalysisGrid::of(small_scene().optics, binning);
  return g;
}

// The refinement with the Vulkan model or the CPU reference.
prism::Refiner refiner(bool on_device, prism::RefineSettings rs = {}) {
  // One model per backend for the whole file (a device model builds its pipelines once).
  static auto device_model = prism::make_scene_model(small_scene(), prism::refine_trace_settings(binning), &prism::test::gpu());
  static auto cpu_model = prism::make_scene_model(small_scene(), prism::refine_trace_settings(binning), nullptr);
  return prism::Refiner(on_device ? *device_model : *cpu_model, small_scene(), grid(), rs);
}
std::vector<prism::ReconstructedVertex> refine(const prism::Event& e, std::vector<prism::ReconstructedVertex> start,
                                               bool on_device, prism::RefineSettings rs = {}) {
  return refiner(on_device, rs).refine(e, std::move(start));
}

// The source moved by `pitches` lenslet pitches along the row, times (D + L) / L
// (alias_scale): a lattice alias, every image where a neighbour's was.
glm::dvec3 row_alias(glm::dvec3 at, double pitches) {
  return at + glm::dvec3(pitches * prism::defaults::lenslet_pitch_mm * small_scene().optics.alias_scale(at.z), 0, 0);
}

double error_mm(const prism::ReconstructedVertex& v, glm::dvec3 truth) {
  return glm::length(glm::dvec3(v.x_mm, v.y_mm, v.depth_mm) - truth);
}

// Per-axis error in units of the vertex's own CRLB.
glm::dvec3 z_scores(const prism::ReconstructedVertex& v, glm::dvec3 truth) {
  return glm::abs(glm::dvec3(v.x_mm, v.y_mm, v.depth_mm) - truth) / glm::dvec3(v.crlb_x_mm, v.crlb_y_mm, v.crlb_z_mm);
}

}  // namespace

TEST_CASE("refinement: lattice vectors are the lenslets' nearest neighbours") {
  auto hex = prism::lattice_vectors(prism::builtin_scene("prototype").optics);
  CHECK(hex.size() == 6);
  for (auto v : hex) CHECK(glm::length(v) == doctest::Approx(prism::defaults::lenslet_pitch_mm));
  auto wide = prism::lattice_vectors(prism::builtin_scene("prototype").optics, 2.0);
  CHECK(wide.size() == 18);  // 6 of 1 pitch, 6 of sqrt(3), 6 of 2
  std::vector<glm::dvec2> ring2;  // beyond the nearest neighbours
  for (auto v : wide)
    if (glm::length(v) > 1.01 * prism::defaults::lenslet_pitch_mm) ring2.push_back(v);
  CHECK(ring2.size() == 12);
  for (auto v : ring2) CHECK(glm::length(v) > 1.5 * prism::defaults::lenslet_pitch_mm);
  auto row = prism::lattice_vectors(small_scene().optics);  // one row: +-x only
  REQUIRE(row.size() == 2);
  CHECK(std::abs(row[0].y) < 1e-12);
  CHECK(row[0].x == doctest::Approx(-row[1].x));
}

TEST_CASE("refinement: from 0.5 mm off to the truth within the CRLB's scale, Vulkan = CPU reference") {
  const glm::dvec3 at(1.3, -0.7, 22.4);  // off every grid a dictionary would have
  auto e = make_event({{at, 2000}}, 1);
  REQUIRE(e.clicks.size() > 500);
  const auto start = std::vector{row(at + glm::dvec3(0.5, -0.4, 0.5), 1500)};
  auto dev = refine(e, start, true);
  auto cpu = refine(e, start, false);
  for (const auto* v : {&dev[0], &cpu[0]}) {
    CAPTURE(v->x_mm);
    CAPTURE(v->y_mm);
    CAPTURE(v->depth_mm);
    CAPTURE(v->crlb_3d_mm);
    REQUIRE(v->refined);
    REQUIRE(std::isfinite(v->crlb_3d_mm));
    CHECK(v->crlb_3d_mm < 0.05);  // 2000 photons
    glm::dvec3 z = z_scores(*v, at);
    CHECK(std::max({z.x, z.y, z.z}) < 4.0);  // one event: within 4 sigma on every axis
    CHECK(v->alpha == doctest::Approx(2000).epsilon(0.1));
    CHECK(v->flags == prism::vertex_ok);
    CHECK(v->fit_pvalue > prism::defaults::fit_pvalue_flag);
  }
  // Device (float) and reference (double) models: the same optimum to a
  // small fraction of the CRLB.
  CHECK(std::abs(dev[0].x_mm - cpu[0].x_mm) < 0.1 * dev[0].crlb_x_mm);
  CHECK(std::abs(dev[0].y_mm - cpu[0].y_mm) < 0.1 * dev[0].crlb_y_mm);
  CHECK(std::abs(dev[0].depth_mm - cpu[0].depth_mm) < 0.1 * dev[0].crlb_z_mm);
  CHECK(dev[0].crlb_3d_mm == doctest::Approx(cpu[0].crlb_3d_mm).epsilon(0.02));
  prism::test::check_validation_clean();
}

TEST_CASE("refinement hazards: a start on the depth bound, a source outside the field, 10 and 10^4 photons") {
  const auto lo = prism::RefineBounds::of(small_scene()).lo, hi = prism::RefineBounds::of(small_scene()).hi;
  SUBCASE("start on the far depth bound, truth inside: the bound lets go") {
    const glm::dvec3 at(0.5, 0.5, 44);
    auto v = refine(make_event({{at, 1000}}, 2), {row({0.5, 0.5, hi.z}, 800)}, true);
    CHECK(std::abs(v[0].depth_mm - at.z) < 4 * v[0].crlb_z_mm);
    CHECK((v[0].flags & prism::edge) == 0);
  }
  SUBCASE("a source beyond x_max: the estimate stops on the bound, flagged edge") {
    const glm::dvec3 at(hi.x + 2, 0, 30);
    auto e = make_event({{at, 1000}}, 3);
    REQUIRE(e.clicks.size() > 100);
    auto v = refine(e, {row({hi.x - 1, 0, 30}, 800)}, true, {.aliases = false});
    CHECK(v[0].x_mm > hi.x - 0.05);
    CHECK((v[0].flags & prism::edge) != 0);
  }
  SUBCASE("10 photons: finite, bounded, a CRLB that says how little is known") {
    const glm::dvec3 at(-2, 1, 30);
    auto v = refine(make_event({{at, 10}}, 4), {row(at + glm::dvec3(0.3), 12)}, true);
    CHECK(std::isfinite(v[0].x_mm));
    CHECK(v[0].depth_mm >= lo.z);
    CHECK(v[0].depth_mm <= hi.z);
    CHECK(v[0].crlb_3d_mm > 0.1);
  }
  SUBCASE("10^4 photons: saturated clicks do not break the steps") {
    const glm::dvec3 at(-2, 1, 30);
    auto v = refine(make_event({{at, 1e4}}, 5), {row(at + glm::dvec3(0.3, -0.3, 0.6), 5e3)}, true);
    CHECK(glm::length(glm::dvec3(v[0].x_mm, v[0].y_mm, v[0].depth_mm) - at) < 0.1);
    CHECK(v[0].alpha == doctest::Approx(1e4).epsilon(0.1));
  }
  prism::test::check_validation_clean();
}

TEST_CASE("refinement: a start on a lattice alias comes back to the truth") {
  // The source moved by one lenslet pitch times (D + L) / L (alias_scale) puts
  // every image where its neighbour's was; only the neighbours' focal lengths
  // differ.
  const glm::dvec3 at(-1.2, 0.4, 12.5);
  const glm::dvec3 alias = row_alias(at, 1);
  auto e = make_event({{at, 300}}, 6);
  auto without = refine(e, {row(alias, 300)}, true, {.aliases = false, .lattice_scan = false});
  auto with = refine(e, {row(alias, 300)}, true);
  CAPTURE(without[0].x_mm);
  CAPTURE(with[0].x_mm);
  CHECK(glm::length(glm::dvec3(with[0].x_mm, with[0].y_mm, with[0].depth_mm) - at) < 0.5);
  CHECK(with[0].nll < without[0].nll);
}

TEST_CASE("refinement: a poor fit two pitches off is rescued by the far aliases") {
  // Near the face a source two pitches away makes a look-alike the nearest
  // aliases cannot reach (from +2 pitches they try +1 and +3).
  const glm::dvec3 at(0.6, 0.3, 4.5);
  const glm::dvec3 alias = row_alias(at, 2);
  auto e = make_event({{at, 300}}, 8);
  auto stuck = refine(e, {row(alias, 300)}, true, {.rescue = false, .lattice_scan = false});
  auto rescued = refine(e, {row(alias, 300)}, true);
  CAPTURE(stuck[0].x_mm);
  CAPTURE(stuck[0].fit_pvalue);
  CAPTURE(rescued[0].x_mm);
  CHECK(glm::length(glm::dvec3(stuck[0].x_mm, stuck[0].y_mm, stuck[0].depth_mm) - at) > 3);
  CHECK((stuck[0].flags & prism::poor_fit) != 0);
  CHECK(glm::length(glm::dvec3(rescued[0].x_mm, rescued[0].y_mm, rescued[0].depth_mm) - at) < 0.5);
  CHECK((rescued[0].flags & prism::poor_fit) == 0);
  CHECK(rescued[0].nll < stuck[0].nll);
  prism::test::check_validation_clean();
}

TEST_CASE("click geometry: the clicks vote for the source's depth and its lattice of aliases") {
  // Near the face only the three central lenslets image the source on the
  // sensor; each click, paired with each lenslet, votes for a position.
  const glm::dvec3 at(0.6, 0.3, 2.5);
  const auto& o = small_scene().optics;
  auto e = make_event({{at, 300}}, 9);
  const prism::RefineBounds field = prism::RefineBounds::of(small_scene());
  auto peaks = prism::vote_source_positions(o, grid(), e.clicks, field.lo, field.hi, 3);
  REQUIRE(peaks.size() == 3);
  CAPTURE(peaks[0].position_mm.z);
  CAPTURE(peaks[0].votes);
  CHECK(std::abs(peaks[0].position_mm.z - at.z) < 0.15);
  CHECK(peaks[0].votes > 0.5);  // most clicks in one peak (a third of the clicks per lenslet image)
  for (size_t i = 1; i < peaks.size(); ++i) {
    CHECK(peaks[i].votes <= peaks[0].votes);
    CHECK(std::abs(peaks[i].position_mm.z - peaks[0].position_mm.z) >= 0.5);
  }
  // The peak is the source or one of its aliases along the row.
  const double scale = o.alias_scale(at.z);
  const double pitches = (peaks[0].position_mm.x - at.x) / (prism::defaults::lenslet_pitch_mm * scale);
  CAPTURE(pitches);
  CHECK(std::abs(pitches - std::round(pitches)) * prism::defaults::lenslet_pitch_mm * scale < 0.3);
  CHECK(std::abs(peaks[0].position_mm.y - at.y) < 0.3);
  // No clicks, no peaks.
  CHECK(prism::vote_source_positions(o, grid(), {}, field.lo, field.hi, 3).empty());
}

TEST_CASE("refinement: a poor fit at another depth is rescued by the lattice its clicks vote for") {
  // The search's answer at the wrong depth, far from the source near the
  // face: no alias or ladder of it reaches the truth; the clicks' votes do.
  const glm::dvec3 at(0.6, 0.3, 2.5);
  auto e = make_event({{at, 300}}, 10);
  const prism::RefineSettings alone{.aliases = false, .rescue = false, .lattice_scan = false, .ladder_starts = 0};
  prism::RefineSettings scan = alone;
  scan.lattice_scan = true;
  auto stuck = refine(e, {row({7.0, -2.0, 14.0}, 300)}, true, alone);
  auto found = refine(e, {row({7.0, -2.0, 14.0}, 300)}, true, scan);
  CAPTURE(stuck[0].x_mm);
  CAPTURE(stuck[0].depth_mm);
  CAPTURE(stuck[0].fit_pvalue);
  CAPTURE(found[0].x_mm);
  CAPTURE(found[0].depth_mm);
  CHECK(glm::length(glm::dvec3(stuck[0].x_mm, stuck[0].y_mm, stuck[0].depth_mm) - at) > 3);
  CHECK(stuck[0].fit_pvalue < prism::defaults::refine_lattice_scan_pvalue);
  CHECK(glm::length(glm::dvec3(found[0].x_mm, found[0].y_mm, found[0].depth_mm) - at) < 0.3);
  CHECK(found[0].fit_pvalue >= prism::defaults::fit_pvalue_flag);
  CHECK(found[0].nll < stuck[0].nll);
  prism::test::check_validation_clean();
}

TEST_CASE("refinement: two vertices jointly, and the goodness of fit") {
  const glm::dvec3 a(-4, 0.5, 20), b(5, -0.5, 36);
  auto e = make_event({{a, 400}, {b, 400}}, 7);
  auto two = refine(e, {row(a + glm::dvec3(0.4), 300), row(b - glm::dvec3(0.4), 300)}, true);
  CHECK(glm::length(glm::dvec3(two[0].x_mm, two[0].y_mm, two[0].depth_mm) - a) < 5 * two[0].crlb_3d_mm);
  CHECK(glm::length(glm::dvec3(two[1].x_mm, two[1].y_mm, two[1].depth_mm) - b) < 5 * two[1].crlb_3d_mm);
  CHECK(two[0].fit_pvalue > prism::defaults::fit_pvalue_flag);
  // One vertex for two sources: the second source's clicks are not explained.
  auto one = refine(e, {row(a, 400)}, true, {.aliases = false});
  CHECK(one[0].fit_pvalue < prism::defaults::fit_pvalue_flag);
  CHECK((one[0].flags & prism::poor_fit) != 0);
  // Ordinary events: p-values spread over (0, 1]; at most one of 20 below
  // 0.01 (3 under the sanitizers: the same code, for memory errors).
  int flagged = 0;
  for (uint64_t id = 100; id < (prism::test::under_sanitizer ? 103 : 120); ++id) {
    const glm::dvec3 at(0.3 * double(id - 110), 0.2, 15 + double(id - 100));
    auto v = refine(make_event({{at, 200}}, id), {row(at + glm::dvec3(0.2), 200)}, true, {.aliases = false});
    flagged += v[0].fit_pvalue < prism::defaults::fit_pvalue_flag;
  }
  CHECK(flagged <= 1);
  prism::test::check_validation_clean();
}

TEST_CASE("refinement: K = 2, a vertex the search left on stray clicks is sent to the source nobody claims") {
  // The paper's double-vertex failure: one vertex on a source, the other
  // far off on stray light, the second source unclaimed. Aliases, ladder
  // and rescue move the stray vertex only near where it is.
  auto pos = [](const prism::ReconstructedVertex& v) { return glm::dvec3(v.x_mm, v.y_mm, v.depth_mm); };
  const glm::dvec3 a(-2, 0.3, 16), b(1.5, -0.2, 7.5);
  // Events 29 and 40: a re-seed fitted sharp from the runner-up (0.6 mm
  // off, near the face) stopped a few tenths of a mm short, and the rescue
  // then preferred a lattice alias 13 mm away (a failure rate of 4 in 30
  // event ids before the re-seed's near-face starts were blurred first).
  // Under the sanitizers the first alone (the same code; 190 s there for all three).
  const std::vector<uint64_t> ids = prism::test::under_sanitizer ? std::vector<uint64_t>{11} : std::vector<uint64_t>{11, 29, 40};
  for (uint64_t id : ids) {
    CAPTURE(id);
    auto e = make_event({{a, 400}, {b, 150}}, id);
    std::vector<prism::ReconstructedVertex> start{row(a + glm::dvec3(0.3, -0.2, 0.4), 300), row({9, 0.5, 40}, 100)};
    prism::RefineSettings neither;
    neither.reseed = false;
    neither.lattice_scan = false;
    auto stuck = refine(e, start, true, neither);
    CAPTURE(stuck[1].x_mm);
    CAPTURE(stuck[1].y_mm);
    CAPTURE(stuck[1].depth_mm);
    CHECK(glm::length(pos(stuck[1]) - b) > 3);
    // The re-seed: the source is a runner-up of the other vertex's scan.
    start[0].runners_up = {glm::dvec4(a + glm::dvec3(1.0, 0, 1.5), 300), glm::dvec4(b + glm::dvec3(0.3, -0.2, 0.5), 150)};
    prism::RefineSettings reseed = neither;
    reseed.reseed = true;
    auto v = refine(e, start, true, reseed);
    CAPTURE(v[1].x_mm);
    CAPTURE(v[1].y_mm);
    CAPTURE(v[1].depth_mm);
    CAPTURE(v[1].fit_pvalue);
    CHECK(glm::length(pos(v[0]) - a) < 5 * v[0].crlb_3d_mm);
    CHECK(glm::length(pos(v[1]) - b) < 5 * v[1].crlb_3d_mm);
    CHECK(v[1].nll < stuck[1].nll);
    CHECK(v[1].fit_pvalue > prism::defaults::fit_pvalue_flag);
    // Without the runner-up: stuck again (the re-seed has nothing to try);
    // once is enough.
    if (id != ids.front()) continue;
    start[0].runners_up.clear();
    CHECK(glm::length(pos(refine(e, start, true, reseed)[1]) - b) > 3);
  }
  prism::test::check_validation_clean();
}

TEST_CASE("refinement hazards with several vertices: 0.5 mm apart, a lattice alias apart, K = 4") {
  auto pos = [](const prism::ReconstructedVertex& v) { return glm::dvec3(v.x_mm, v.y_mm, v.depth_mm); };
  SUBCASE("0.5 mm apart: finite, the light shared, both near the pair") {
    const glm::dvec3 a(0.5, 0.2, 25), b(1.0, 0.2, 25);
    auto e = make_event({{a, 300}, {b, 300}}, 8);
    auto v = refine(e, {row(a + glm::dvec3(-0.3, 0, 0.4), 300), row(b + glm::dvec3(0.3, 0, -0.4), 300)}, true);
    for (const auto& x : v) {
      CHECK(std::isfinite(x.crlb_3d_mm));
      CHECK(glm::length(pos(x) - 0.5 * (a + b)) < 1.5);
    }
    CHECK(v[0].alpha + v[1].alpha == doctest::Approx(600).epsilon(0.15));
  }
  SUBCASE("a lattice alias apart: both found, each where it is") {
    const glm::dvec3 a(-3, 0.3, 15);
    const glm::dvec3 b = row_alias(a, 1);
    auto e = make_event({{a, 400}, {b, 400}}, 9);
    auto v = refine(e, {row(a + glm::dvec3(0.3, -0.2, 0.5), 300), row(b + glm::dvec3(-0.3, 0.2, -0.5), 300)}, true);
    CHECK(glm::length(pos(v[0]) - a) < 5 * v[0].crlb_3d_mm);
    CHECK(glm::length(pos(v[1]) - b) < 5 * v[1].crlb_3d_mm);
    CHECK((v[0].flags & prism::merged) == 0);
  }
  // Under the sanitizers K = 2 (above, and the joint case before) runs the same code.
  if (!prism::test::under_sanitizer) SUBCASE("K = 4 jointly") {
    const std::vector<glm::dvec3> at{{-8, 0.5, 12}, {-2, -0.5, 22}, {3, 0.4, 32}, {8, -0.2, 42}};
    std::vector<Source> src;
    std::vector<prism::ReconstructedVertex> start;
    for (size_t k = 0; k < at.size(); ++k) {
      src.push_back({at[k], 300});
      start.push_back(row(at[k] + glm::dvec3(0.3, -0.3, k % 2 ? 0.6 : -0.6), 250));
    }
    auto v = refine(make_event(src, 10), start, true);
    REQUIRE(v.size() == 4);
    for (size_t k = 0; k < at.size(); ++k) {
      CAPTURE(k);
      CHECK(glm::length(pos(v[k]) - at[k]) < 5 * v[k].crlb_3d_mm);
      CHECK(v[k].fit_pvalue > prism::defaults::fit_pvalue_flag);
    }
  }
  prism::test::check_validation_clean();
}

TEST_CASE("refinement: the ladder's rungs, moved by whole pixels, take near-face local optima to better ones") {
  // Ten starts 0.76-1.0 mm off a source at depth 4: without the ladder, some
  // converge in local optima worse than the truth's by more than 10 in NLL
  // (0.05-1.6 mm off), the rest in the truth's basin. The ladder, its rungs
  // scored with their images moved by up to 2 pixels, must take at least one
  // of those to a better optimum (10 or more lower, nearer the source) and
  // never leave a fit worse. Which starts get stuck, and which the ladder
  // frees, is not fixed: the event's clicks and the renders' float sums
  // differ between machines and compilers, and the path forks at the
  // likelihood's cliffs. Over eight events here, 1-5 of the ten were stuck
  // and the ladder freed 20 of 27; one start alone, as this test once had,
  // failed on CI when its start reached a shallower optimum. On the real
  // lenses the moved rungs reached the truth for three events of the
  // acceptance run where the unmoved ones did not (docs/reconstruction.md,
  // defaults::refine_ladder_reach_px).
  constexpr double worse_nll = 10;  // a likelihood ratio of e^10: another optimum, not the truth's
  const glm::dvec3 at(0.6, 0.3, 4.0);
  const auto e = make_event({{at, 100}}, 102);
  const prism::RefineSettings none{.aliases = false, .rescue = false, .lattice_scan = false, .ladder_starts = 0,
                                   .continuation = false};
  prism::RefineSettings ladder = none;
  ladder.ladder_starts = prism::defaults::refine_ladder_starts;
  ladder.ladder_reach_px = prism::defaults::refine_ladder_reach_px;
  const double truth_nll = refine(e, {row(at, 100)}, true, none)[0].nll;
  int stuck = 0, freed = 0;
  for (glm::dvec3 off : {glm::dvec3(0.3, 0, -0.7), glm::dvec3(-0.3, 0, -0.7), glm::dvec3(0, 0.3, -0.7),
                         glm::dvec3(0, -0.3, -0.7), glm::dvec3(0.3, 0, 0.7), glm::dvec3(-0.3, 0, 0.7),
                         glm::dvec3(0, 0.3, 0.7), glm::dvec3(0, -0.3, 0.7), glm::dvec3(0.2, 0.2, -1.0),
                         glm::dvec3(-0.2, -0.2, 1.0)}) {
    const auto v = refine(e, {row(at + off, 100)}, true, none)[0];
    if (v.nll < truth_nll + worse_nll) continue;  // in the truth's basin: nothing for the ladder to do
    ++stuck;
    const auto moved = refine(e, {row({v.x_mm, v.y_mm, v.depth_mm}, v.alpha)}, true, ladder)[0];
    CAPTURE(off);
    CAPTURE(truth_nll);
    CAPTURE(v.nll);
    CAPTURE(moved.nll);
    CAPTURE(error_mm(v, at));
    CAPTURE(error_mm(moved, at));
    CHECK(moved.nll < v.nll + 0.1);  // the ladder keeps the best it has seen
    if (moved.nll < v.nll - worse_nll && error_mm(moved, at) < error_mm(v, at)) ++freed;
  }
  CAPTURE(stuck);
  REQUIRE(stuck >= 1);  // the premise: near the face, starts this far off do get stuck
  CHECK(freed >= 1);
  prism::test::check_validation_clean();
}

TEST_CASE("refinement: a shallow estimate on a wrong site that fits as well as expected still gets the lattice scan") {
  // 40 photons at depth 2.5 started two pitches off: without the rescue the
  // fit settles on that site and the model finds nothing wrong with it (p
  // well above the lattice scan's trigger); its depth alone sends it to the
  // scan, which finds the source (RefineSettings::always_scan_below_mm).
  const glm::dvec3 at(0.6, 0.3, 2.5);
  const glm::dvec3 alias = row_alias(at, 2);
  auto e = make_event({{at, 40}}, 101);
  prism::RefineSettings by_pvalue{.rescue = false};
  by_pvalue.always_scan_below_mm = 0;
  by_pvalue.always_scan_below_clicks = 0;
  const auto stuck = refine(e, {row(alias, 40)}, true, by_pvalue)[0];
  const auto found = refine(e, {row(alias, 40)}, true, {.rescue = false})[0];
  CAPTURE(error_mm(stuck, at));
  CAPTURE(stuck.fit_pvalue);
  CAPTURE(error_mm(found, at));
  CHECK(error_mm(stuck, at) > 3);
  CHECK(stuck.fit_pvalue > prism::defaults::refine_lattice_scan_pvalue);
  CHECK(error_mm(found, at) < 5 * found.crlb_3d_mm);
  CHECK(found.nll < stuck.nll - 20);
  // What evaluate calls the search's failure: fitted from the truth alone,
  // the likelihood stays by the truth and scores better than the stuck
  // estimate (VolumeEvent::search_failure).
  const auto from_truth = refiner(true).local_fit(e, at, 40);
  CAPTURE(from_truth.nll);
  CHECK(glm::length(from_truth.position_mm - at) < 5 * found.crlb_3d_mm);
  CHECK(from_truth.nll < stuck.nll - 20);
  CHECK(from_truth.nll == doctest::Approx(found.nll).epsilon(1e-3));
  prism::test::check_validation_clean();
}

TEST_CASE("refinement: an event of few clicks gets the lattice scan and the continuation at any depth, one of many not") {
  // Depth 20, past always_scan_below_mm: what decides is the clicks.
  const glm::dvec3 at(0.4, -0.2, 20.0);
  // Under the sanitizers the event of few clicks alone (the paths, for memory errors).
  const std::vector<double> counts = prism::test::under_sanitizer ? std::vector<double>{15} : std::vector<double>{15, 300};
  for (double photons : counts) {
    CAPTURE(photons);
    auto e = make_event({{at, photons}}, 7);
    const bool few = e.clicks.size() < size_t(prism::defaults::refine_always_scan_below_clicks);
    CAPTURE(e.clicks.size());
    CHECK(few == (photons < 100));  // the premise
    prism::Refiner by_default = refiner(true);
    const auto v = by_default.refine(e, {row(at + glm::dvec3(0.2, 0.1, 0.5), photons)})[0];
    CHECK(by_default.stats().continuations == (few ? 1u : 0u));
    if (few) CHECK(by_default.stats().lattice_scans == 1);
    prism::Refiner never = refiner(true, {.always_scan_below_clicks = 0});
    never.refine(e, {row(at + glm::dvec3(0.2, 0.1, 0.5), photons)});
    CHECK(never.stats().continuations == 0);
    CHECK(glm::length(glm::dvec3(v.x_mm, v.y_mm, v.depth_mm) - at) < 3);
  }
  prism::test::check_validation_clean();
}

TEST_CASE("refinement: the continuation crosses the cliffs that hard-edged images make in the likelihood") {
  // 100 photons at depth 4.5: the NLL has two optima 0.05 mm apart (4 depth
  // CRLBs), 9.7 apart, with a cliff between them where an image edge passes
  // a click. Started on the worse one, the local fit stays; refitted through
  // blurred images it crosses to the better.
  const glm::dvec3 at(0.6, 0.3, 4.5);
  auto e = make_event({{at, 100}}, 111);
  prism::RefineSettings none{.aliases = false, .search_starts = 0, .rescue = false, .lattice_scan = false, .ladder_starts = 0};
  none.continuation = false;
  prism::RefineSettings continued = none;
  continued.continuation = true;
  const glm::dvec3 worse(0.6075, 0.3099, 4.5511);
  for (bool on_device : {true, false}) {
    CAPTURE(on_device);
    const auto stays = refine(e, {row(worse, 71.5)}, on_device, none)[0];
    const auto crossed = refine(e, {row(worse, 71.5)}, on_device, continued)[0];
    CAPTURE(error_mm(stays, at));
    CAPTURE(stays.nll);
    CAPTURE(error_mm(crossed, at));
    CAPTURE(crossed.nll);
    CHECK(error_mm(stays, at) > 0.03);
    CHECK(crossed.nll < stays.nll - 5);
    CHECK(error_mm(crossed, at) < 0.5 * error_mm(stays, at));
  }
  prism::test::check_validation_clean();
}

TEST_CASE("refinement near the face is reproducible: runs and backends reach the same optimum") {
  // The device's float sums come in another order each run (differences of
  // 1e-9 in the model), and near the face a local fit forks at the cliffs of
  // hard-edged images; started two pitches off, one run in three ended 0.05
  // mm from the best optimum, 9.7 worse in NLL, before the continuation.
  // Every run and the double reference must now agree.
  const glm::dvec3 at(0.6, 0.3, 4.5);
  const glm::dvec3 alias = row_alias(at, 2);
  auto e = make_event({{at, 100}}, 111);
  const prism::RefineSettings rs{.rescue = false};
  const auto reference = refine(e, {row(alias, 100)}, false, rs)[0];
  CAPTURE(reference.nll);
  for (int run = 0; run < (prism::test::under_sanitizer ? 1 : 3); ++run) {  // once for memory errors
    const auto v = refine(e, {row(alias, 100)}, true, rs)[0];
    CAPTURE(run);
    CAPTURE(v.nll);
    CHECK(std::abs(v.nll - reference.nll) < 0.05);
    CHECK(glm::length(glm::dvec3(v.x_mm - reference.x_mm, v.y_mm - reference.y_mm, v.depth_mm - reference.depth_mm)) <
          0.2 * v.crlb_3d_mm);
  }
  prism::test::check_validation_clean();
}

TEST_CASE("refinement: blurred images keep their light and their gradients' sums, and lose what falls off the grid") {
  const auto& g = grid();
  auto image_at = [&](int col, int row) {
    prism::SourceImage s;
    s.photons = 50;
    s.pixels.push_back({uint32_t(row * g.width + col), 0.25, glm::dvec3(1, -2, 3)});
    s.pixels.push_back({uint32_t(row * g.width + col + 1), 0.75, glm::dvec3(-1, 0, 0.5)});
    return s;
  };
  auto sums = [](const prism::SourceImage& s) {
    double p = 0;
    glm::dvec3 grad(0);
    for (const auto& m : s.pixels) p += m.p, grad += m.g;
    return std::pair{p, grad};
  };
  const auto middle = image_at(g.width / 2, g.height / 2);
  const auto same = prism::blurred(middle, 0, g);
  REQUIRE(same.pixels.size() == 2);
  CHECK(same.pixels[1].p == 0.75);
  const auto b = prism::blurred(middle, 1.0, g);
  CHECK(b.pixels.size() > 20);
  CHECK(b.photons == 50);
  for (size_t i = 1; i < b.pixels.size(); ++i) CHECK(b.pixels[i - 1].index < b.pixels[i].index);  // sorted for find()
  auto [p, grad] = sums(b);
  CHECK(p == doctest::Approx(1.0).epsilon(1e-12));
  CHECK(glm::length(grad - glm::dvec3(0, -2, 3.5)) < 1e-12);
  // Symmetric about the pair's centre: the brightest pixel stays the 0.75 one.
  const auto* top = b.find(uint32_t(g.height / 2 * g.width + g.width / 2 + 1));
  REQUIRE(top != nullptr);
  for (const auto& m : b.pixels) CHECK(m.p <= top->p);
  // In the corner what lands at negative columns or rows is lost: per axis
  // the share of the 1-D taps (sigma 1, radius 3) at offsets >= -col.
  double taps[7], total = 0;
  for (int d = -3; d <= 3; ++d) total += taps[d + 3] = std::exp(-0.5 * d * d);
  auto kept = [&](int col) {
    double k = 0;
    for (int d = -col; d <= 3; ++d) k += taps[d + 3];
    return k / total;
  };
  const auto corner = prism::blurred(image_at(0, 0), 1.0, g);
  CHECK(sums(corner).first == doctest::Approx(0.25 * kept(0) * kept(0) + 0.75 * kept(1) * kept(0)).epsilon(1e-12));
}

TEST_CASE("refinement: blurred images equal the naive 2-D convolution, for light far apart and at the grid's edges") {
  // Pixels in rows further apart than the kernel (the sparse passes skip the
  // rows between), two in one row, and at the last column and row; the naive
  // double loop over each pixel's square of taps is the reference.
  const auto& g = grid();
  const double sigma = 1.7;
  const int radius = int(std::ceil(prism::defaults::refine_blur_radius_sigmas * sigma));
  prism::SourceImage s;
  s.photons = 10;
  auto put = [&](int row, int col, double p, glm::dvec3 grad) {
    s.pixels.push_back({uint32_t(row * g.width + col), p, grad});
  };
  put(2, 5, 0.1, {1, 0, 0});
  put(2, 9, 0.2, {0, 1, 0});
  put(40, 100, 0.3, {0, 0, 1});
  put(40 + radius + 1, 102, 0.15, {-1, 2, 0.5});
  put(g.height - 1, g.width - 1, 0.25, {0.5, 0.5, -2});
  std::vector<double> taps;
  double total = 0;
  for (int d = -radius; d <= radius; ++d) total += taps.emplace_back(std::exp(-0.5 * d * d / (sigma * sigma)));
  std::map<uint32_t, glm::dvec4> naive;
  for (const auto& m : s.pixels) {
    const int row = int(m.index) / g.width, col = int(m.index) % g.width;
    for (int dy = -radius; dy <= radius; ++dy)
      for (int dx = -radius; dx <= radius; ++dx)
        if (row + dy >= 0 && row + dy < g.height && col + dx >= 0 && col + dx < g.width)
          naive[uint32_t((row + dy) * g.width + col + dx)] +=
              taps[size_t(dy + radius)] * taps[size_t(dx + radius)] / (total * total) * glm::dvec4(m.p, m.g);
  }
  const auto b = prism::blurred(s, sigma, g);
  REQUIRE(b.pixels.size() == naive.size());
  size_t i = 0;
  for (const auto& [index, v] : naive) {
    const auto& m = b.pixels[i++];
    REQUIRE(m.index == index);
    CHECK(glm::length(glm::dvec4(m.p, m.g) - v) < 1e-14);
  }
}

TEST_CASE("goodness of fit: the Monte Carlo p-value equals the exact one of a small sensor, dark pixels included") {
  // Eight lit pixels (lambda from 0.01 to 4) and four dark ones: every one
  // of the 2^12 click patterns enumerated gives the exact P(T >= T_obs) of
  // T = sum over pixels of the binary NLL. The Monte Carlo draws the dark
  // pixels' clicks as one Poisson count and places each lit pixel's clicks
  // by geometric gaps; with 2e5 draws it must agree within 4 standard errors.
  const std::vector<double> lit{0.05, 0.3, 1.2, 2.5, 0.01, 0.7, 4.0, 0.2};
  const int dark_pixels = 4;
  const double dark = 1e-3;
  std::unordered_map<uint32_t, double> rates;
  for (size_t i = 0; i < lit.size(); ++i) rates[uint32_t(10 + 3 * i)] = lit[i];  // scattered indices
  std::vector<double> lambda = lit;
  std::vector<uint32_t> index;
  for (size_t i = 0; i < lit.size(); ++i) index.push_back(uint32_t(10 + 3 * i));
  for (int d = 0; d < dark_pixels; ++d) lambda.push_back(dark), index.push_back(uint32_t(100 + d));
  const size_t n = lambda.size();
  // T of a pattern up to a constant: sum over its clicks of -log(1 - exp(-l)) - l.
  auto term = [](double l) { return -std::log(-std::expm1(-l)) - l; };
  auto exact = [&](uint32_t observed) {
    double t_obs = 0;
    for (size_t i = 0; i < n; ++i)
      if (observed >> i & 1u) t_obs += term(lambda[i]);
    double p = 0;
    for (uint32_t pattern = 0; pattern < (1u << n); ++pattern) {
      double prob = 1, t = 0;
      for (size_t i = 0; i < n; ++i) {
        const double click = -std::expm1(-lambda[i]);
        if (pattern >> i & 1u) prob *= click, t += term(lambda[i]);
        else prob *= 1 - click;
      }
      if (t >= t_obs - 1e-12) p += prob;
    }
    return p;
  };
  const int draws = 200000;
  // Patterns from typical to unlikely: the bright pixels alone, a faint one
  // clicked, a dark pixel clicked, the bright ones dark.
  for (uint32_t observed : {0b01001100u, 0b01011100u, 0b000101001100u, 0b00000011u, 0b11110001u}) {
    std::vector<uint32_t> clicks;
    for (size_t i = 0; i < n; ++i)
      if (observed >> i & 1u) clicks.push_back(index[i]);
    const double want = exact(observed);
    const double got = prism::binary_fit_pvalue(rates, clicks, dark, double(n), draws, 7 + observed);
    const double se = std::sqrt(want * (1 - want) / draws) + 1.0 / draws;
    CAPTURE(observed);
    CAPTURE(want);
    CAPTURE(got);
    CHECK(std::abs(got - want) < 4 * se);
  }
  // A seed gives one answer.
  const std::vector<uint32_t> some{10, 16, 19};
  CHECK(prism::binary_fit_pvalue(rates, some, dark, double(n), 1000, 3) ==
        prism::binary_fit_pvalue(rates, some, dark, double(n), 1000, 3));
}

TEST_CASE("refinement: a focused model renders the clicks' tiles as the whole render does, its P over the sensor's light") {
  // The polish's model at fine pixels (27.6 um here) renders only the tiles
  // around the clicks and takes the sensor's light from a render of every
  // pixel at 110 um with the same cells: P and its gradient at and near the
  // clicks are the whole render's (normalised by its own sum), to float
  // sums. A few clicks at the brightest pixels and a few in faint light.
  const auto fine = prism::refine_trace_settings(4);
  auto whole_model = prism::make_scene_model(small_scene(), fine, &prism::test::gpu());
  auto masked = prism::make_masked_scene_model(small_scene(), fine, prism::refine_trace_settings(binning), prism::test::gpu());
  const std::vector<glm::dvec3> theta{{0.7, -0.4, 12.0}};
  CHECK_THROWS_WITH_AS(masked->render(theta), doctest::Contains("focus"), std::logic_error);
  const auto whole = whole_model->render(theta).front();
  REQUIRE(whole.pixels.size() > 1000);
  std::vector<prism::ModelPixel> by_p = whole.pixels;
  std::sort(by_p.begin(), by_p.end(), [](const auto& a, const auto& b) { return a.p > b.p; });
  std::vector<uint32_t> clicks{by_p[0].index, by_p[1].index, by_p[by_p.size() / 2].index, by_p[by_p.size() - 10].index};
  const int reach = 9;
  masked->focus(clicks, reach);
  const auto part = masked->render(theta).front();
  CHECK(part.photons == doctest::Approx(whole.photons).epsilon(1e-4));
  CHECK(part.pixels.size() < whole.pixels.size() / 4);
  const int W = prism::AnalysisGrid::of(small_scene().optics, 4).width;
  size_t compared = 0;
  double peak = by_p[0].p, peak_g = 0;
  for (const auto& m : whole.pixels) peak_g = std::max(peak_g, glm::length(m.g));
  for (uint32_t c : clicks)
    for (int dy = -reach; dy <= reach; ++dy)
      for (int dx = -reach; dx <= reach; ++dx) {
        const uint32_t i = uint32_t(int(c) + dy * W + dx);
        const prism::ModelPixel* w = whole.find(i);
        const prism::ModelPixel* q = part.find(i);
        CAPTURE(i);
        REQUIRE(bool(w) == bool(q));
        if (!w) continue;
        ++compared;
        CHECK(std::abs(q->p - w->p) <= 1e-4 * peak);
        CHECK(glm::length(q->g - w->g) <= 1e-4 * peak_g);
      }
  CHECK(compared > 100);
  // Clicks whose tiles outgrow the image buffer (1 MiB: 8 tiles): every
  // pixel rendered, the whole model's image.
  auto small = prism::make_masked_scene_model(small_scene(), fine, prism::refine_trace_settings(binning),
                                              prism::test::gpu(), 1u << 20);
  small->focus(clicks, 100);
  const auto all = small->render(theta).front();
  REQUIRE(all.pixels.size() == whole.pixels.size());
  CHECK(all.photons == doctest::Approx(whole.photons).epsilon(1e-5));
  for (size_t i = 0; i < all.pixels.size(); i += 97) {
    CHECK(all.pixels[i].index == whole.pixels[i].index);
    CHECK(std::abs(all.pixels[i].p - whole.pixels[i].p) <= 1e-5 * peak);
  }
  prism::test::check_validation_clean();
}
