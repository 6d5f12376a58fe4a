// The footprint splat (shaders/common/footprint.glsl) against the exact
// box-pixel oracle for thin lenses (engine/ref/thin_lens_oracle.h) and against
// its own double-precision CPU reference on hard inputs; the oracle against a
// closed form and against its own finite differences.
//
// Tolerances. The footprint's error against the oracle is second order in the
// cell size (uniform light over each cell's image triangle): its CRLB is
// within 0.1% of the oracle's at the cell counts used here (bench_forward
// measures the convergence). Vulkan against the reference: float landing
// points (about 2e-4 of a 6.9 um pixel at the sensor's edge), so pixel values
// agree to 1e-3 of the peak and derivatives to 2e-3; decisions on a
// triangle's shape (thin, large) can flip between float and double for a few
// cells near a caustic, so those cases compare totals and the CRLB.
#include <algorithm>
#include <cmath>
#include <numeric>
#include <string>

#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "engine/ref/thin_lens_oracle.h"
#include "compare.h"
#include "support.h"

namespace {

using prism::test::channel;
using prism::test::gpu;

prism::TraceSettings footprint(unsigned rays, unsigned binning) {
  prism::TraceSettings t;
  t.rays_per_lenslet = rays;
  t.binning = binning;
  t.splat = prism::Splat::footprint;
  t.estimator = prism::FisherEstimator::naive;
  return t;
}

double crlb_3d(const prism::FisherResult& f) { return prism::crlb_from_fisher(f.poisson, f.photons).r3_mm; }

}  // namespace

TEST_CASE("thin-lens oracle: a lenslet's whole light equals the solid angle of its disc") {
  // One lenslet on the axis, a source on the axis: Phi / 2 (1 - h / sqrt(h^2 + R^2)).
  prism::OpticalSystem sys;
  sys.lens_model = prism::LensModel::thin;
  sys.lenslets = {{0.0, 0.0, 3.0, 9.0}};
  prism::TraceSettings t;
  t.binning = 16;
  for (double depth : {2.0, 13.5, 40.0}) {
    CAPTURE(depth);
    auto img = prism::ref::thin_lens_image(sys, t, {0.0, 0.0, depth});
    const double h = depth + sys.working_distance_mm, R = 1.5;
    CHECK(img.photons() == doctest::Approx(0.5 * t.photons_emitted * (1 - h / std::sqrt(h * h + R * R))).epsilon(1e-10));
  }
}

TEST_CASE("thin-lens oracle: its derivatives are those of its values (central differences)") {
  auto sys = prism::test::small_system(prism::LensModel::thin);
  prism::TraceSettings t;
  t.binning = 16;
  const glm::dvec3 theta{1.3, -0.7, 25.0};
  auto img = prism::ref::thin_lens_image(sys, t, theta);
  const double h = 1e-5;
  for (int axis = 0; axis < 3; ++axis) {
    CAPTURE(axis);
    glm::dvec3 d(0.0);
    d[axis] = h;
    auto plus = channel(prism::ref::thin_lens_image(sys, t, theta + d), 0);
    auto minus = channel(prism::ref::thin_lens_image(sys, t, theta - d), 0);
    std::vector<double> fd(plus.size());
    for (size_t i = 0; i < fd.size(); ++i) fd[i] = (plus[i] - minus[i]) / (2 * h);
    auto derivative = channel(img, 1 + axis);
    auto c = prism::test::compare(fd, derivative, {.abs = 1e-6 * prism::test::peak_abs(fd)});
    CHECK_MESSAGE(c.ok(), c.report("d b / d theta vs central differences"));
  }
}

TEST_CASE("footprint splat equals the box-pixel oracle for thin lenses at 6.9, 27.6 and 110 um") {
  auto sys = prism::test::small_system(prism::LensModel::thin);
  const glm::dvec3 theta{1.3, -0.7, 25.0};
  struct Case {
    unsigned binning, rays;
  } cases[] = {{16, 4096}, {4, 16384}, {1, 16384}};
  for (const auto& k : cases) {
    CAPTURE(k.binning);
    if (prism::test::under_sanitizer && k.binning == 1) continue;  // 27.6 um runs the same code
    auto t = footprint(k.rays, k.binning);
    auto oracle = prism::ref::thin_lens_image(sys, t, theta);
    prism::ForwardVulkan fw(gpu(), sys, t);
    auto image = fw.psf(theta);
    CHECK(image.photons() == doctest::Approx(oracle.photons()).epsilon(1e-5));
    // Pixel by pixel: L1 distance under 0.1% of the light.
    auto want = channel(oracle, 0), got = channel(image, 0);
    double l1 = 0;
    for (size_t i = 0; i < want.size(); ++i) l1 += std::abs(got[i] - want[i]);
    CHECK(l1 < 1e-3 * oracle.photons());
    // The CRLB within 1%.
    const double exact = crlb_3d(prism::ref::fisher_of(oracle, 0.0, prism::FisherEstimator::naive));
    const double traced = crlb_3d(fw.fisher(std::vector<glm::dvec3>{theta}).front());
    MESSAGE("binning " << k.binning << ", " << k.rays << " cells per lenslet: CRLB " << traced << " mm, oracle " << exact
                       << " mm");
    CHECK(traced == doctest::Approx(exact).epsilon(0.01));
  }
  prism::test::check_validation_clean();
}

TEST_CASE("footprint splat: Vulkan equals the CPU reference on real lenses, cut cells and every effect") {
  auto plain = prism::test::small_system(prism::LensModel::real);
  auto holder = plain;
  holder.effects.holder_vignetting = true;
  holder.effects.holder_bore_mm = 3.0;
  auto face = plain;
  face.effects.scintillator_refraction = true;
  auto extent = plain;
  extent.effects.source_extent = true;
  extent.effects.source_sigma_mm = 0.3;
  auto efficiency = plain;
  efficiency.effects.detection_efficiency = 0.4;
  auto airy = plain;
  airy.effects.diffraction = true;
  airy.effects.wavelength_nm = 5000.0;  // a core of ~0.4 px at 55 um
  // Pixel by pixel where no triangle sits on a float/double decision; at the
  // sensor's edge, 25 mm off axis, split pieces given to their centroid can
  // land in neighbouring pixels: there the totals and the CRLB.
  struct Case {
    std::string name;
    prism::OpticalSystem sys;
    glm::dvec3 theta;
    unsigned binning, stratification;
    bool pixels;
  } cases[] = {{"real, depth 25", plain, {1.3, -0.7, 25.0}, 8, 0, true},
               {"real, near and off axis (large cells split)", plain, {8.0, 3.0, 2.0}, 8, 0, true},
               {"holder 3 mm (cells cut by bisection)", holder, {8.0, 3.0, 2.0}, 8, 0, true},
               {"scintillator refraction", face, {1.3, -0.7, 25.0}, 8, 0, true},
               {"extended source", extent, {1.3, -0.7, 25.0}, 8, 0, true},
               {"detection efficiency", efficiency, {1.3, -0.7, 25.0}, 8, 0, true},
               {"diffraction (the Airy square)", airy, {1.3, -0.7, 25.0}, 8, 0, true},
               {"another stratification", plain, {1.3, -0.7, 25.0}, 8, 3, true},
               {"at the sensor's edge (partial last pixels)", plain, {-25.0, 0.0, 5.0}, 16, 0, false}};
  for (const auto& k : cases) {
    CAPTURE(k.name);
    // Under the sanitizers 256 cells: the same paths, a quarter of the reference's work.
    auto t = footprint(prism::test::under_sanitizer ? 256 : 1024, k.binning);
    t.stratification = k.stratification;
    auto ref = prism::ref::psf(k.sys, t, k.theta);
    prism::ForwardVulkan fw(gpu(), k.sys, t);
    auto image = fw.psf(k.theta);
    REQUIRE(ref.photons() > 0);
    CHECK(image.photons() == doctest::Approx(ref.photons()).epsilon(1e-5));
    for (int c = 0; c < 4 && k.pixels; ++c) {
      auto want = channel(ref, c);
      auto got = channel(image, c);
      auto cmp = prism::test::compare(want, got, {.abs = (c == 0 ? 1e-3 : 2e-3) * prism::test::peak_abs(want)});
      CHECK_MESSAGE(cmp.ok(), cmp.report("channel " + std::to_string(c) + " (Vulkan vs reference)"));
    }
    const double ref_crlb = crlb_3d(prism::ref::fisher_of(ref, 0.0, prism::FisherEstimator::naive));
    CHECK(crlb_3d(fw.fisher(std::vector<glm::dvec3>{k.theta}).front()) == doctest::Approx(ref_crlb).epsilon(1e-3));
  }
  prism::test::check_validation_clean();
}

TEST_CASE("footprint splat: lists larger than a buffer are taken in chunks of cells, with the same image") {
  // The real prototype at 256 cells and 220 um pixels lists thousands of
  // split entries per source (its rim cells and their large pieces); a 64 KiB
  // budget holds 4095 (and cuts the image into bands of 9 rows).
  auto sys = prism::builtin_scene("prototype").optics;
  auto t = footprint(256, 32);
  const glm::dvec3 theta{2.0, -1.0, 15.0};
  prism::ForwardVulkan whole(gpu(), sys, t);
  prism::ForwardVulkan small(gpu(), sys, t, 64ull << 10);
  auto a = whole.psf_values(theta), b = small.psf_values(theta);
  CHECK(whole.footprint_cell_chunks() == 1);
  CHECK(small.footprint_cell_chunks() > 1);
  std::vector<double> da(a.begin(), a.end()), db(b.begin(), b.end());
  CHECK(std::accumulate(db.begin(), db.end(), 0.0) == doctest::Approx(std::accumulate(da.begin(), da.end(), 0.0)).epsilon(1e-6));
  auto c = prism::test::compare(da, db, {.abs = 1e-5 * prism::test::peak_abs(da)});
  CHECK_MESSAGE(c.ok(), c.report("values, chunked vs whole"));
  // The derivative channels too, through the banded full kernel.
  auto fa = whole.fisher(std::vector<glm::dvec3>{theta}).front(), fb = small.fisher(std::vector<glm::dvec3>{theta}).front();
  CHECK(crlb_3d(fb) == doctest::Approx(crlb_3d(fa)).epsilon(1e-5));
  prism::test::check_validation_clean();
}

TEST_CASE("footprint splat: cells folded by an f/1 lens's caustic converge to where the rays put the light") {
  // The f = 3 mm lenslet alone: spherical aberration folds cells into slivers
  // (spread along their longest edge) and stretches others (split). Its light
  // on the sensor must be the rays' (a fine stratified sum of the reference's
  // ray weights that reach the sensor), and the image must converge with the
  // cells: at first order in the cell size here, where cells fold (second
  // order where the map is smooth).
  auto sys = prism::builtin_scene("prototype").optics;
  sys.lenslets = {sys.lenslets[15]};
  REQUIRE(sys.lenslets[0].focal_mm == 3.0);
  for (glm::dvec3 theta : {glm::dvec3{1.3, -0.7, 25.0}, glm::dvec3{2.0, 1.0, 10.0}}) {
    CAPTURE(theta.z);
    prism::TraceSettings rays;
    rays.rays_per_lenslet = 262144;
    const double half_w = 0.5 * sys.sensor_width_mm(), half_h = 0.5 * sys.sensor_height_mm();
    double on_sensor = 0;
    for (uint32_t k = 0; k < rays.rays(); ++k) {
      auto h = prism::ref::trace_sample(sys, rays, theta, 0, k);
      if (h.ok && std::abs(h.x_mm) <= half_w && std::abs(h.y_mm) <= half_h) on_sensor += h.weight;
    }
    REQUIRE(on_sensor > 0.1);
    auto image = [&](unsigned cells) {
      prism::ForwardVulkan fw(gpu(), sys, footprint(cells, 16));
      return fw.psf(theta);
    };
    auto finest = image(65536);
    CHECK(finest.photons() == doctest::Approx(on_sensor).epsilon(5e-4));
    auto l1 = [&](const prism::PixelImage& x) {
      double d = 0;
      auto p = channel(x, 0), q = channel(finest, 0);
      for (size_t i = 0; i < p.size(); ++i) d += std::abs(p[i] - q[i]);
      return d / finest.photons();
    };
    const double e1 = l1(image(1024)), e4 = l1(image(4096)), e16 = l1(image(16384));
    MESSAGE("L1 to 65536 cells: 1024 cells " << e1 << ", 4096 " << e4 << ", 16384 " << e16);
    CHECK(e4 < 0.7 * e1);
    CHECK(e16 < 0.7 * e4);
    CHECK(e16 < 0.02);
    for (float v : finest.data) CHECK(std::isfinite(v));
  }
  prism::test::check_validation_clean();
}

TEST_CASE("footprint splat: an f = 3 mm lens's faint near-face annulus converges with the cells, kernels and reference alike") {
  // A source 6 mm deep under the f = 3 mm lenslet, 3.6 mm off its axis: its
  // rim cells land as pieces still larger than LARGE_TRIANGLE_PX after the
  // last split, around a faint annulus 2e-4..1e-2 of the peak. Those pieces
  // are rasterised (the kernels: in tiles, the large pass); given to their
  // centroids' pixels instead, the annulus was 190% RMS off at 4096 cells
  // and 60% at 16384 (docs/calibration.md), not converging.
  auto sys = prism::builtin_scene("prototype").optics;
  sys.lenslets = {sys.lenslets[15]};
  REQUIRE(sys.lenslets[0].focal_mm == 3.0);
  const glm::dvec3 theta{sys.lenslets[0].x_mm + 2.0, sys.lenslets[0].y_mm - 3.0, 6.0};
  auto render = [&](unsigned cells, unsigned stratification) {
    auto t = footprint(cells, 16);
    t.stratification = stratification;
    prism::ForwardVulkan fw(gpu(), sys, t);
    auto image = fw.psf_values(theta);
    return std::make_pair(std::vector<double>(image.begin(), image.end()), fw.last_kernel_times());
  };
  const auto [finest, finest_passes] = render(65536, 0);
  CHECK(std::count_if(finest_passes.begin(), finest_passes.end(),
                      [](const auto& k) { return k.kernel == "psf_footprint_large (values)"; }) == 1);
  const double peak = prism::test::peak_abs(finest);
  // RMS relative error against 65536 cells over the pixels of a band.
  auto band_rms = [&](const std::vector<double>& b, double lo, double hi) {
    double sum = 0;
    size_t n = 0;
    for (size_t i = 0; i < b.size(); ++i)
      if (finest[i] >= lo * peak && finest[i] < hi * peak) sum += std::pow((b[i] - finest[i]) / finest[i], 2), ++n;
    REQUIRE(n > 20);
    return std::sqrt(sum / double(n));
  };
  double last_faint = INFINITY, last_dim = INFINITY;
  for (unsigned cells : {1024u, 4096u, 16384u}) {
    const auto b = render(cells, 1).first;  // another stratification than the finest's
    const double faint = band_rms(b, 2e-4, 7e-4), dim = band_rms(b, 7e-4, 1e-2);
    MESSAGE(cells << " cells: RMS relative error " << faint << " at 2e-4..7e-4 of the peak, " << dim << " at 7e-4..1e-2");
    CHECK(faint < 0.8 * last_faint);
    CHECK(dim < 0.8 * last_dim);
    last_faint = faint, last_dim = dim;
  }
  CHECK(last_faint < 0.5);
  CHECK(last_dim < 0.12);
  // The kernels' tiles against the reference's whole triangles: the light of
  // the annulus, and pixel by pixel the faint pixels too. A few pixels at
  // the ends of the slivers' streaks differ by tenths of a pixel's light:
  // which of a needle's two long edges carries its light (THIN_TRIANGLE) can
  // differ between float and double.
  const auto t = footprint(1024, 16);
  const auto want = channel(prism::ref::psf(sys, t, theta), 0);
  const auto got = render(1024, 0).first;
  double annulus_want = 0, annulus_got = 0;
  for (size_t i = 0; i < want.size(); ++i)
    if (want[i] < 1e-2 * peak) annulus_want += want[i], annulus_got += got[i];
  CHECK(annulus_got == doctest::Approx(annulus_want).epsilon(1e-4));
  auto cmp = prism::test::compare(want, got, {.abs = 1e-5 * peak, .rel = 1e-2});
  const size_t lit = size_t(std::count_if(want.begin(), want.end(), [](double v) { return v > 0; }));
  CHECK_MESSAGE(cmp.mismatches <= lit / 1000, (cmp.report("values (Vulkan vs reference)") + " (of " + std::to_string(lit) + " lit)"));
  cmp = prism::test::compare(want, got, {.abs = 1e-3 * peak});
  CHECK_MESSAGE(cmp.ok(), cmp.report("values (Vulkan vs reference)"));
  prism::test::check_validation_clean();
}

TEST_CASE("footprint splat: Fisher sums do not depend on bands and batches, and turned strata agree") {
  auto sys = prism::builtin_scene("prototype").optics;
  auto t = footprint(1024, 8);
  std::vector<glm::dvec3> sources{{0, 0, 5}, {3, -2, 20}, {-4, 1, 45}};
  prism::ForwardVulkan whole(gpu(), sys, t);
  prism::ForwardVulkan cut(gpu(), sys, t, 1ull << 20);  // 8 bands, one source per batch
  auto a = whole.fisher(sources), b = cut.fisher(sources);
  auto turned = t;
  turned.stratification = 7;
  prism::ForwardVulkan other(gpu(), sys, turned);
  auto o = other.fisher(sources);
  for (size_t i = 0; i < sources.size(); ++i) {
    CAPTURE(i);
    CHECK(b[i].photons == doctest::Approx(a[i].photons).epsilon(1e-6));
    auto c = prism::test::compare_values(a[i].poisson, b[i].poisson, {.abs = 1e-5 * a[i].poisson[0], .rel = 1e-5});
    CHECK_MESSAGE(c.ok(), c.report("Poisson Fisher entries, banded vs whole"));
    // Another stratification: other cells, the same physics to the cells' error.
    CHECK(o[i].photons == doctest::Approx(a[i].photons).epsilon(1e-4));
    CHECK(crlb_3d(o[i]) == doctest::Approx(crlb_3d(a[i])).epsilon(0.02));
    CHECK(o[i].poisson[0] != a[i].poisson[0]);
  }
  prism::test::check_validation_clean();
}

TEST_CASE("footprint splat: a masked render gives its tiles the whole render's light and nothing elsewhere") {
  // The prototype (real lenses) near the face, where the rim cells split and
  // their large pieces go to the large pass in tiles, with and without the
  // Airy square (the blur's reach); the mask: the brightest pixel's tile,
  // tiles in the faint annulus (1e-4..1e-3 of the peak), and a dark one.
  // The kernels skip pieces that reach no marked tile; what they keep must
  // be the whole render's light to float atomics' order.
  auto plain = prism::builtin_scene("prototype").optics;
  auto airy = plain;
  airy.effects.diffraction = true;
  airy.effects.wavelength_nm = 20000.0;  // a square of half side ~1.6 px at 55 um: the blur crosses tiles
  struct Case {
    std::string name;
    prism::OpticalSystem sys;
    glm::dvec3 theta;
  } cases[] = {{"real lenses, 3 mm deep", plain, {-9.0, 5.0, 3.0}}, {"with the Airy square", airy, {-9.0, 5.0, 3.0}}};
  for (const auto& k : cases) {
    CAPTURE(k.name);
    const auto t = footprint(prism::test::under_sanitizer ? 256 : 1024, 8);
    prism::ForwardVulkan fw(gpu(), k.sys, t);
    const auto whole = fw.psf(k.theta);
    REQUIRE(std::count_if(fw.last_kernel_times().begin(), fw.last_kernel_times().end(),
                          [](const auto& p) { return p.kernel == "psf_footprint_large"; }) == 1);
    const auto b = channel(whole, 0);
    const double peak = prism::test::peak_abs(b);
    prism::TileMask mask = prism::TileMask::of(fw.grid());
    const size_t brightest = size_t(std::max_element(b.begin(), b.end()) - b.begin());
    mask.mark_around(int(brightest % size_t(whole.width)), int(brightest / size_t(whole.width)), 0);
    size_t faint = 0, dark = 0;
    for (size_t i = 0; i < b.size(); i += 997)
      if (b[i] > 1e-4 * peak && b[i] < 1e-3 * peak && faint < 3)
        mask.mark_around(int(i % size_t(whole.width)), int(i / size_t(whole.width)), 0), ++faint;
      else if (b[i] == 0 && dark < 1)
        mask.mark_around(int(i % size_t(whole.width)), int(i / size_t(whole.width)), 0), ++dark;
    REQUIRE(faint == 3);
    const auto masked = fw.psf(k.theta, mask);
    // The masked render's pixels spread onto the grid (0 where it lists none).
    std::vector<double> spread[4];
    for (auto& v : spread) v.assign(b.size(), 0.0);
    size_t outside_lit = 0;
    for (size_t i = 0; i < masked.size(); ++i) {
      const auto& q = masked[i];
      REQUIRE(q.index < b.size());
      if (i > 0) REQUIRE(masked[i - 1].index < q.index);  // by index
      if (!mask.covers(int(q.index % uint32_t(whole.width)), int(q.index / uint32_t(whole.width)))) ++outside_lit;
      spread[0][q.index] = q.b;
      for (int a = 0; a < 3; ++a) spread[1 + a][q.index] = q.db[a];
    }
    double inside = 0;
    std::vector<double> want[4], got[4];
    for (int c = 0; c < 4; ++c) {
      const auto w = channel(whole, c);
      for (size_t i = 0; i < w.size(); ++i)
        if (mask.covers(int(i % size_t(whole.width)), int(i / size_t(whole.width)))) {
          want[c].push_back(w[i]), got[c].push_back(spread[c][i]);
          if (c == 0) inside += w[i];
        }
    }
    CHECK(outside_lit == 0);
    REQUIRE(inside > 0);
    MESSAGE(k.name << ": " << mask.count() << " of " << mask.tiles_w * mask.tiles_h << " tiles marked, "
                   << inside / std::accumulate(b.begin(), b.end(), 0.0) << " of the light in them");
    for (int c = 0; c < 4; ++c) {
      auto cmp = prism::test::compare(want[c], got[c], {.abs = 1e-5 * prism::test::peak_abs(want[c])});
      CHECK_MESSAGE(cmp.ok(), cmp.report("channel " + std::to_string(c) + " on the marked tiles (masked vs whole)"));
    }
    // A mask of another grid is refused, not read past its end.
    CHECK_THROWS_WITH_AS(fw.psf(k.theta, prism::TileMask::of(prism::AnalysisGrid::of(k.sys, 16))),
                         doctest::Contains("another grid"), std::invalid_argument);
  }
  prism::test::check_validation_clean();
}
