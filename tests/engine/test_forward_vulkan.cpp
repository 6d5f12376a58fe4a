// The Vulkan forward model (lavapipe) against the double-precision reference:
// images pixel by pixel, Fisher information, and hard inputs.
//
// Tolerances. Hit positions agree to float precision (~2e-6 mm at 25 mm off
// axis, 4e-5 of a 55 um pixel); rays focused on one spot shift together, so
// a pixel value agrees to 3e-4 of the image peak. Derivative channels jump
// where a hit crosses a pixel-centre line (the kink of the bilinear tent):
// 1e-3 of their peak. Fisher sums
// weigh each pixel by 1/b: a pixel reached by one ray with a tiny bilinear
// fraction f adds w (df)^2 / f, and float's ~1e-4 px error in f changes such
// a term by a large factor. The Fisher comparison is therefore made where
// every lit pixel holds many rays (coarse binning), to 1e-3 relative; at few
// rays per pixel both backends show the same upward sampling bias but not
// the same digits (see docs/model.md "Convergence").
#include <algorithm>
#include <cmath>
#include <string>
#include <utility>

#include "compare.h"
#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "engine/vk/compute.h"
#include "support.h"

namespace {

using prism::test::channel;
using prism::test::gpu;

// Channel c of the device image against the reference, to `tol` of the reference's peak.
void check_channel(const prism::PixelImage& v, const prism::ref::SparseImage& r, int c, double tol) {
  auto expect = channel(r, c);
  auto cmp = prism::test::compare(expect, channel(v, c), {.abs = tol * prism::test::peak_abs(expect)});
  CHECK_MESSAGE(cmp.ok(), cmp.report("channel " + std::to_string(c) + " (Vulkan vs reference)"));
}

void compare_images(const prism::OpticalSystem& sys, const prism::TraceSettings& t, const glm::dvec3& theta) {
  prism::ForwardVulkan fw(gpu(), sys, t);
  auto v = fw.psf(theta);
  auto r = prism::ref::psf(sys, t, theta);
  CAPTURE(theta.x);
  CAPTURE(theta.y);
  CAPTURE(theta.z);
  REQUIRE(r.photons() > 0);
  CHECK(v.photons() == doctest::Approx(r.photons()).epsilon(1e-5));
  check_channel(v, r, 0, 3e-4);
  for (int c = 1; c < 4; ++c) check_channel(v, r, c, 1e-3);
}

void compare_fisher(const prism::OpticalSystem& sys, const prism::TraceSettings& t, const glm::dvec3& theta,
                    double tol) {
  prism::ForwardVulkan fw(gpu(), sys, t);
  auto v = fw.fisher(std::vector<glm::dvec3>{theta}).front();
  auto r = prism::ref::fisher(sys, t, theta);
  CHECK(v.photons == doctest::Approx(r.photons).epsilon(1e-5));
  // The six entries of each matrix, to tol of the largest diagonal entry.
  const double scale = std::max({r.poisson[0], r.poisson[3], r.poisson[5]});
  auto p = prism::test::compare_values(r.poisson, v.poisson, {.abs = tol * scale, .rel = tol});
  CHECK_MESSAGE(p.ok(), p.report("Poisson Fisher entries (xx xy xz yy yz zz)"));
  auto b = prism::test::compare_values(r.binary, v.binary, {.abs = tol * scale, .rel = tol});
  CHECK_MESSAGE(b.ok(), b.report("binary Fisher entries (xx xy xz yy yz zz)"));
  auto cv = prism::crlb_from_fisher(v.poisson, v.photons), cr = prism::crlb_from_fisher(r.poisson, r.photons);
  CHECK(cv.r3_mm == doctest::Approx(cr.r3_mm).epsilon(tol));
}

}  // namespace

TEST_CASE("Vulkan PSF equals the reference pixel by pixel (thin and real lenses)") {
  prism::TraceSettings t;
  t.rays_per_lenslet = 400;
  t.binning = 8;
  for (auto model : {prism::LensModel::thin, prism::LensModel::real}) {
    std::string model_name = prism::to_string(model);
    CAPTURE(model_name);
    auto sys = prism::test::small_system(model);
    compare_images(sys, t, {1.7, -2.3, 21.0});
    compare_images(sys, t, {-6.0, -1.0, 0.0});
  }
  prism::test::check_validation_clean();
}

TEST_CASE("Vulkan Fisher information equals the reference where pixels hold many rays") {
  prism::TraceSettings t;
  t.rays_per_lenslet = 4096;
  t.binning = 64;
  for (auto model : {prism::LensModel::thin, prism::LensModel::real}) {
    std::string model_name = prism::to_string(model);
    CAPTURE(model_name);
    auto sys = prism::test::small_system(model);
    compare_fisher(sys, t, {0.7, 1.1, 12.0}, 1e-3);
  }
  prism::test::check_validation_clean();
}

TEST_CASE("hard inputs: a source on a lenslet edge, and one far outside the field of view") {
  prism::TraceSettings t;
  t.rays_per_lenslet = 400;
  t.binning = 8;
  // The point splat pixel by pixel (the footprint's hard inputs, cells whose
  // shape decisions flip between float and double: test_footprint.cpp).
  t.splat = prism::Splat::point;
  auto sys = prism::test::small_system(prism::LensModel::real);
  const auto& l = sys.lenslets[3];
  compare_images(sys, t, {l.x_mm + 0.5 * l.diameter_mm, l.y_mm, 0.0});

  // 0.5 m to the side: no ray reaches the sensor. Fisher is zero, the CRLB is
  // infinite and flagged in both backends.
  glm::dvec3 far{500.0, 0.0, 25.0};
  prism::ForwardVulkan fw(prism::test::gpu(), sys, t);
  auto v = fw.fisher(std::vector<glm::dvec3>{far}).front();
  auto r = prism::ref::fisher(sys, t, far);
  CHECK(v.photons == 0.0);
  CHECK(r.photons == 0.0);
  for (const auto& f : {v, r}) {
    auto c = prism::crlb_from_fisher(f.poisson, f.photons);
    CHECK_FALSE(c.identifiable);
    CHECK(c.flag == "no_photons");
    CHECK(std::isinf(c.r3_mm));
  }
  prism::test::check_validation_clean();
}

TEST_CASE("hard inputs: rays focused exactly on pixel borders and pixel centres") {
  // One thin lens imaging an on-axis source in focus: every ray lands at x = y = 0.
  // Even sensor width: x = 0 is a pixel border (fractions 0.5). Odd width: x = 0
  // is a pixel centre, so the neighbour gets b = 0 with a nonzero derivative,
  // which the Fisher sum must skip rather than divide by.
  // Footprint splat: each cell images to a triangle of float's rounding size;
  // across a border its shares are rounding noise, its light conserved to 1e-4.
  for (auto [width, splat] : {std::pair{64, prism::Splat::point}, std::pair{65, prism::Splat::point},
                              std::pair{64, prism::Splat::footprint}, std::pair{65, prism::Splat::footprint}}) {
    CAPTURE(width);
    std::string splat_name = prism::to_string(splat);
    CAPTURE(splat_name);
    prism::OpticalSystem sys;
    sys.lens_model = prism::LensModel::thin;
    sys.lenslets = {{0.0, 0.0, 3.0, 9.0}};
    sys.sensor_width_px = width;
    sys.sensor_height_px = width;
    double object_mm = 1.0 / (1.0 / 9.0 - 1.0 / sys.lens_to_sensor_mm);
    glm::dvec3 focus{0.0, 0.0, object_mm - sys.working_distance_mm};
    prism::TraceSettings t;
    t.rays_per_lenslet = 256;
    t.binning = 1;
    t.splat = splat;
    prism::ForwardVulkan fw(prism::test::gpu(), sys, t);
    auto v = fw.fisher(std::vector<glm::dvec3>{focus}).front();
    auto r = prism::ref::fisher(sys, t, focus);
    CHECK(v.photons == doctest::Approx(r.photons).epsilon(splat == prism::Splat::point ? 1e-5 : 2e-4));
    for (int k = 0; k < 6; ++k) {
      CHECK(std::isfinite(v.poisson[k]));
      CHECK(std::isfinite(v.binary[k]));
      CHECK(std::isfinite(r.poisson[k]));
    }
    auto cv = prism::crlb_from_fisher(v.poisson, v.photons);
    CHECK_FALSE(std::isnan(cv.r3_mm));
  }
  prism::test::check_validation_clean();
}

TEST_CASE("full sensor resolution: 6696 x 4764 px in bands of at most maxStorageBufferRange") {
  // The prototype with one of its six f = 3 mm lenslets, the first (a
  // corner): at 6.9 um their discs, 10-14 mm across and rasterised to the
  // rim, were two thirds of this test's time (97 s against 34 s, one run);
  // one keeps its steep rays and the large pass in it.
  auto sys = prism::builtin_scene("prototype").optics;
  bool kept_f3 = false;
  std::erase_if(sys.lenslets, [&](const prism::LensletGeometry& l) {
    if (l.focal_mm > 3.5) return false;
    return std::exchange(kept_f3, true);
  });
  REQUIRE(sys.lenslets.size() == 37);
  prism::TraceSettings t;
  t.rays_per_lenslet = 256;
  t.binning = 1;
  // Under the sanitizers, whose double reference of a 32 Mpx image took a
  // minute: 27.6 um pixels and a budget that cuts them into bands all the same.
  uint64_t budget = prism::ForwardVulkan::default_image_budget_bytes;
  if (prism::test::under_sanitizer) t.binning = 4, budget = 8ull << 20;
  glm::dvec3 theta{2.0, -1.0, 30.0};
  prism::ForwardVulkan full(prism::test::gpu(), sys, t, budget);
  REQUIRE(full.grid().width == 6696 / t.binning);
  REQUIRE(full.grid().height == 4764 / t.binning);
  // 1 GB of (b, grad b) per source exceeds the image budget (and, on
  // lavapipe, maxStorageBufferRange): bands.
  REQUIRE(uint64_t(full.grid().width) * full.grid().height * 32 > budget);
  auto f = full.fisher(std::vector<glm::dvec3>{theta}).front();
  auto r = prism::ref::psf(sys, t, theta);
  CHECK(f.photons == doctest::Approx(r.photons()).epsilon(1e-5));
  CHECK(f.photons > 10.0);
  auto img = full.psf(theta);
  CHECK(img.photons() == doctest::Approx(r.photons()).epsilon(1e-5));
  // Pixel by pixel across the band seams. At 6.9 um pixels float's landing
  // error matters: at most 0.35 um (steep rays through the f = 3 mm corner
  // lenslets; median 0.002 um), i.e. 5% of one ray's photons in one pixel,
  // 4e-3 of this image's peak.
  check_channel(img, r, 0, 1e-2);
  for (double v : f.poisson) CHECK(std::isfinite(v));
  prism::test::check_validation_clean();
}

TEST_CASE("Fisher sums do not depend on how the sensor is cut into bands and batches") {
  auto sys = prism::builtin_scene("prototype").optics;
  prism::TraceSettings t;
  t.rays_per_lenslet = 1024;
  t.binning = 8;
  t.splat = prism::Splat::point;  // the footprint's: test_footprint.cpp
  std::vector<glm::dvec3> sources{{0, 0, 5}, {3, -2, 20}, {-4, 1, 45}};
  prism::ForwardVulkan whole(prism::test::gpu(), sys, t);
  // A 1 MiB budget forces 837 x 596 px into 8 bands and one source per batch.
  prism::ForwardVulkan cut(prism::test::gpu(), sys, t, 1ull << 20);
  auto a = whole.fisher(sources), b = cut.fisher(sources);
  for (size_t i = 0; i < sources.size(); ++i) {
    CAPTURE(i);
    CHECK(b[i].photons == doctest::Approx(a[i].photons).epsilon(1e-6));
    auto c = prism::test::compare_values(a[i].poisson, b[i].poisson, {.abs = 1e-5 * a[i].poisson[0], .rel = 1e-5});
    CHECK_MESSAGE(c.ok(), c.report("Poisson Fisher entries, cut vs whole"));
  }
  prism::test::check_validation_clean();
}

TEST_CASE("the values-only PSF kernel equals the b channel of the full one, at any band cut") {
  auto sys = prism::builtin_scene("prototype").optics;
  // Under the sanitizers 27.6 um pixels in bands of a smaller budget.
  const unsigned fine = prism::test::under_sanitizer ? 4 : 1;
  const uint64_t budget = prism::test::under_sanitizer ? 8ull << 20 : prism::ForwardVulkan::default_image_budget_bytes;
  for (unsigned binning : {16u, fine}) {
    CAPTURE(binning);
    prism::TraceSettings t;
    t.rays_per_lenslet = 256;
    t.binning = binning;
    prism::ForwardVulkan fw(prism::test::gpu(), sys, t, budget);
    glm::dvec3 theta{-3.0, 4.0, 12.0};
    auto full = fw.psf(theta);
    auto values = fw.psf_values(theta);
    REQUIRE(values.size() == size_t(full.width) * full.height);
    auto b = channel(full, 0);
    REQUIRE(prism::test::peak_abs(b) > 0);
    // Only the order of float atomic adds differs.
    auto c = prism::test::compare_values(b, values, {.abs = 1e-5 * prism::test::peak_abs(b)});
    CHECK_MESSAGE(c.ok(), c.report("values-only kernel vs the b channel"));
  }
  prism::test::check_validation_clean();
}

TEST_CASE("several designs in one dispatch give what each gives alone") {
  std::vector<prism::OpticalSystem> designs{prism::builtin_scene("prototype").optics,
                                            prism::builtin_scene("unifocal-f9").optics,
                                            prism::test::small_system(prism::LensModel::real)};
  prism::TraceSettings t;
  t.rays_per_lenslet = 1024;
  t.binning = 16;
  std::vector<glm::dvec3> theta;
  std::vector<uint32_t> design_of;
  for (uint32_t d = 0; d < designs.size(); ++d)
    for (double depth : {5.0, 30.0}) {
      theta.push_back({1.0, -1.0, depth});
      design_of.push_back(d);
    }
  prism::ForwardVulkan batch(prism::test::gpu(), designs, t);
  auto together = batch.fisher(theta, design_of);
  for (size_t i = 0; i < theta.size(); ++i) {
    prism::ForwardVulkan alone(prism::test::gpu(), designs[design_of[i]], t);
    auto a = alone.fisher(std::span<const glm::dvec3>(&theta[i], 1)).front();
    CAPTURE(i);
    CHECK(together[i].photons == doctest::Approx(a.photons).epsilon(1e-5));
    auto c = prism::test::compare_values(a.poisson, together[i].poisson, {.abs = 1e-4 * a.poisson[0], .rel = 1e-4});
    CHECK_MESSAGE(c.ok(), c.report("Poisson Fisher entries, batched vs alone"));
  }
  auto other = designs[1];
  other.effects.holder_vignetting = true;
  CHECK_THROWS_WITH_AS(prism::ForwardVulkan(prism::test::gpu(), std::vector{designs[0], other}, t),
                       doctest::Contains("differs from design 0 in the effects"), std::invalid_argument);
  prism::test::check_validation_clean();
}

TEST_CASE("kernels compile once per context and specialisation, and a kernel never dispatched never") {
  // A context of its own: its pipeline cache starts empty.
  prism::vk::Context ctx(prism::vk::ContextOptions{"", true});
  auto sys = prism::test::small_system(prism::LensModel::thin);
  prism::TraceSettings t;
  t.binning = 64;
  t.rays_per_lenslet = 64;
  t.splat = prism::Splat::point;
  const glm::dvec3 theta(0.5, -0.5, 25);
  prism::ForwardVulkan a(ctx, sys, t);
  CHECK(ctx.pipelines().size() == 0);  // built, nothing dispatched: nothing compiled
  const auto values = a.psf_values(theta);
  const size_t after_values = ctx.pipelines().size();
  CHECK(after_values >= 1);
  // A second model of the same kernels compiles nothing and gives the same
  // image (support.h: same_render_tolerance).
  prism::ForwardVulkan b(ctx, sys, t);
  const auto again = b.psf_values(theta);
  auto same = prism::test::compare_values(values, again, {.abs = prism::test::same_render_tolerance *
                                                                 prism::test::peak_abs(std::vector<double>(values.begin(), values.end()))});
  CHECK_MESSAGE(same.ok(), same.report("second model of the same kernels"));
  CHECK(ctx.pipelines().size() == after_values);
  // The derivatives' kernel is another pipeline; another effect another one.
  const auto full = b.psf(theta);
  const size_t after_full = ctx.pipelines().size();
  CHECK(after_full > after_values);
  auto holder = sys;
  holder.effects.holder_vignetting = true;
  prism::ForwardVulkan c(ctx, holder, t);
  c.psf(theta);
  CHECK(ctx.pipelines().size() > after_full);
  // The cached pipelines trace what fresh ones do: the b channel of the full
  // kernel is the values-only image (as in the test above).
  auto bch = channel(full, 0);
  REQUIRE(prism::test::peak_abs(bch) > 0);
  auto cmp = prism::test::compare_values(bch, values, {.abs = 1e-5 * prism::test::peak_abs(bch)});
  CHECK_MESSAGE(cmp.ok(), cmp.report("values-only kernel vs the b channel, second model"));
  INFO("validation layer messages: " << ctx.validation_messages().size());
  CHECK(ctx.validation_messages().empty());
}

TEST_CASE("buffers the host cannot map (a discrete GPU's path) hold and render what mapped ones do") {
  // lavapipe maps every buffer; staged_buffers makes every upload and
  // download a copy through a staging buffer, as on a GPU whose memory the
  // host cannot map, with the barriers that path needs (validation on).
  prism::vk::Context staged(prism::vk::ContextOptions{"", true, true});
  std::vector<uint32_t> words(4096);
  for (size_t i = 0; i < words.size(); ++i) words[i] = uint32_t(i * 2654435761u);
  prism::vk::Buffer buffer(staged, words.size() * 4);
  buffer.upload(words.data(), words.size() * 4);
  const std::vector<uint32_t> patch{7, 8, 9};
  buffer.upload(patch.data(), patch.size() * 4, 400 * 4);
  std::copy(patch.begin(), patch.end(), words.begin() + 400);
  CHECK(buffer.download<uint32_t>(words.size()) == words);
  std::vector<uint32_t> part(10);
  buffer.download(part.data(), part.size() * 4, 398 * 4);
  CHECK(part == std::vector<uint32_t>(words.begin() + 398, words.begin() + 408));

  // Both splats (the footprint reads its lists' counts back between passes),
  // b and its derivatives, against the same render in mapped buffers.
  auto sys = prism::test::small_system(prism::LensModel::real);
  const glm::dvec3 theta(1.3, -0.7, 25.0);
  for (auto splat : {prism::Splat::point, prism::Splat::footprint}) {
    std::string name = prism::to_string(splat);
    CAPTURE(name);
    prism::TraceSettings t;
    t.binning = 16;
    t.rays_per_lenslet = 1024;
    t.splat = splat;
    const auto want = prism::ForwardVulkan(gpu(), sys, t).psf(theta);
    const auto got = prism::ForwardVulkan(staged, sys, t).psf(theta);
    REQUIRE(want.photons() > 0);
    for (int c = 0; c < 4; ++c) {
      auto w = channel(want, c);
      auto cmp = prism::test::compare(w, channel(got, c),
                                      {.abs = prism::test::same_render_tolerance * prism::test::peak_abs(w)});
      CHECK_MESSAGE(cmp.ok(), cmp.report("channel " + std::to_string(c) + " (staged vs mapped buffers)"));
    }
  }
  INFO("validation layer messages: " << staged.validation_messages().size());
  CHECK(staged.validation_messages().empty());
}

TEST_CASE("each dispatch's time is reported by pass, and the passes add up to the call's kernel time") {
  // The footprint of the real prototype lenses: the first pass over the
  // cells, one dispatch per split level, the cut; the Fisher reduction after
  // them (bench_forward's "passes" table reads these).
  auto sys = prism::builtin_scene("prototype").optics;
  prism::TraceSettings t;
  t.rays_per_lenslet = 256;
  t.binning = 32;
  t.splat = prism::Splat::footprint;
  prism::ForwardVulkan fw(gpu(), sys, t);
  const glm::dvec3 theta{2.0, -1.0, 4.0};
  auto names = [&] {
    std::vector<std::string> out;
    double sum = 0;
    for (const auto& k : fw.last_kernel_times()) {
      out.push_back(k.kernel);
      CHECK(k.ms >= 0);
      sum += k.ms;
    }
    CHECK(sum == doctest::Approx(fw.last_kernel_ms()).epsilon(1e-9));
    return out;
  };
  fw.psf(theta);
  auto psf = names();
  REQUIRE_FALSE(psf.empty());
  CHECK(psf.front() == "psf_footprint");
  CHECK(std::count(psf.begin(), psf.end(), "psf_footprint_split") >= 1);  // the f = 3 mm lenslets' rims
  fw.fisher(std::vector<glm::dvec3>{theta});
  auto fisher = names();
  CHECK(fisher.back() == "fisher_reduce");
  // A call reports its own dispatches only.
  fw.psf_values(theta);
  auto values = names();
  CHECK(values.front() == "psf_footprint (values)");
  CHECK(std::count(values.begin(), values.end(), "fisher_reduce") == 0);
  prism::test::check_validation_clean();
}
