// Effects: each is simulated only when the scene names it. Without it the
// kernels run the plain model (its parameters are ignored, it is compiled out
// through specialisation constants), and at neutral parameters it reduces to
// the plain model.
#include "compare.h"
#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "support.h"

namespace {

// Every test traces the source at theta on 55 um pixels. The effects are the
// same physics under either splat; the point splat's tolerances are used here
// (test_footprint.cpp compares every effect under the footprint splat).
const glm::dvec3 theta{1.0, 2.0, 15.0};
prism::TraceSettings settings(unsigned rays_per_lenslet, prism::Splat splat = prism::Splat::point) {
  prism::TraceSettings t;
  t.rays_per_lenslet = rays_per_lenslet;
  t.binning = 8;
  t.splat = splat;
  return t;
}

prism::PixelImage render(const prism::OpticalSystem& sys, prism::Splat splat = prism::Splat::point) {
  prism::ForwardVulkan fw(prism::test::gpu(), sys, settings(256, splat));
  return fw.psf(theta);
}

// Channels first..last (0: b; 1..3: its derivatives) of `got` against
// `expect`, pixel by pixel, each to `tol` of its peak in `expect`.
void check_images(const prism::PixelImage& expect, const prism::PixelImage& got, double tol, int first = 0,
                  int last = 3) {
  for (int c = first; c <= last; ++c) {
    auto e = prism::test::channel(expect, c), g = prism::test::channel(got, c);
    auto cmp = prism::test::compare(e, g, {.abs = tol * prism::test::peak_abs(e)});
    CHECK_MESSAGE(cmp.ok(), cmp.report("channel " + std::to_string(c)));
  }
}

// The b channel of a device image against the reference's.
void check_against_reference(const prism::PixelImage& v, const prism::ref::SparseImage& r, double tol) {
  auto e = prism::test::channel(r, 0), g = prism::test::channel(v, 0);
  auto cmp = prism::test::compare(e, g, {.abs = tol * prism::test::peak_abs(e)});
  CHECK_MESSAGE(cmp.ok(), cmp.report("b (Vulkan vs reference)"));
}

}  // namespace

TEST_CASE("an effect the scene does not name changes nothing, whatever its parameters") {
  auto plain = prism::test::small_system(prism::LensModel::real);
  auto odd = plain;
  odd.effects.scintillator_index = 2.5;  // named nowhere: must be ignored
  odd.effects.holder_bore_mm = 9.0;
  odd.effects.wavelength_nm = 2000.0;
  for (auto splat : {prism::Splat::point, prism::Splat::footprint}) {
    std::string splat_name = prism::to_string(splat);
    CAPTURE(splat_name);
    check_images(render(plain, splat), render(odd, splat), prism::test::same_render_tolerance);
  }
  prism::test::check_validation_clean();
}

TEST_CASE("effects at neutral parameters reduce to the plain model") {
  auto plain = prism::test::small_system(prism::LensModel::real);
  for (auto splat : {prism::Splat::point, prism::Splat::footprint}) {
    std::string splat_name = prism::to_string(splat);
    CAPTURE(splat_name);
    auto base = render(plain, splat);

    auto face = plain;
    face.effects.scintillator_refraction = true;
    face.effects.scintillator_index = 1.0;  // no index step: no refraction, no Fresnel loss
    // The face path solves Snell's law by Newton iteration in float: agreement
    // to float accuracy, not bit for bit. Point splat: derivative channels are
    // discontinuous where a hit crosses a pixel-centre line (the kink of the
    // bilinear tent), so a 1e-6 mm difference can move one ray's derivative
    // tap: 1e-3 there, as in the backend comparison (test_forward_vulkan.cpp).
    // Footprint: a cell corner within float's error of a lenslet's rim is cut
    // or not, and the sliver of light between (at most 1/2^8 of a cell, the
    // cut's bisection) can land far away at that rim: 1e-3 of the peak.
    auto refracted = render(face, splat);
    check_images(base, refracted, splat == prism::Splat::point ? 3e-4 : 1e-3, 0, 0);
    check_images(base, refracted, splat == prism::Splat::point ? 1e-3 : 2e-3, 1, 3);

    auto holder = plain;
    holder.effects.holder_vignetting = true;
    holder.effects.holder_bore_mm = 0.0;  // a bore of zero length clips nothing
    check_images(base, render(holder, splat), prism::test::same_render_tolerance);
  }
  prism::test::check_validation_clean();
}

TEST_CASE("effects change the light as the physics says, in both backends") {
  auto plain = prism::test::small_system(prism::LensModel::real);
  const auto t = settings(256);
  // The system on both backends, image against image; returns the photons.
  auto traced = [&](const prism::OpticalSystem& sys) {
    auto r = prism::ref::psf(sys, t, theta);
    prism::ForwardVulkan fw(prism::test::gpu(), sys, t);
    auto v = fw.psf(theta);
    CHECK(v.photons() == doctest::Approx(r.photons()).epsilon(1e-4));
    check_against_reference(v, r, 3e-4);
    return r.photons();
  };
  const double base = traced(plain);

  // Refraction out of n = 1.58 narrows the cone that reaches the lenses: fewer photons.
  auto face = plain;
  face.effects.scintillator_refraction = true;
  CHECK(traced(face) < 0.9 * base);

  // A long holder bore clips oblique rays.
  auto holder = plain;
  holder.effects.holder_vignetting = true;
  holder.effects.holder_bore_mm = 4.0;
  CHECK(traced(holder) < base);

  // Detection efficiency scales the photons.
  auto eff = plain;
  eff.effects.detection_efficiency = 0.5;
  CHECK(traced(eff) == doctest::Approx(0.5 * base).epsilon(1e-12));

  // Diffraction blurs each lenslet's image by its Airy core: nearly the same
  // light (rays through the real lenses' rims land near the sensor's edges,
  // and the blur takes a little of that off it), a dimmer brightest pixel.
  auto airy = plain;
  airy.effects.diffraction = true;
  airy.effects.wavelength_nm = 50000.0;  // a core sigma of ~0.13 mm (f/6): visible at 55 um pixels
  CHECK(traced(airy) == doctest::Approx(base).epsilon(1e-3));
  auto peak = [](const prism::ref::SparseImage& r) {
    double m = 0;
    for (const auto& [k, px] : r.pixels) m = std::max(m, px[0]);
    return m;
  };
  CHECK(peak(prism::ref::psf(airy, t, theta)) < 0.8 * peak(prism::ref::psf(plain, t, theta)));
  prism::test::check_validation_clean();
}

TEST_CASE("source extent: reduces to a point at tiny sigma, softens peaks, and both backends agree") {
  auto plain = prism::test::small_system(prism::LensModel::real);
  const auto t = settings(1024);
  auto point = render(plain);

  auto tiny = plain;
  tiny.effects.source_extent = true;
  tiny.effects.source_sigma_mm = 1e-6;
  auto tiny_img = render(tiny);
  check_images(point, tiny_img, 3e-4, 0, 0);

  auto wide = plain;
  wide.effects.source_extent = true;
  wide.effects.source_sigma_mm = 0.5;
  prism::ForwardVulkan fw(prism::test::gpu(), wide, t);
  auto v = fw.psf(theta);
  auto r = prism::ref::psf(wide, t, theta);
  CHECK(v.photons() == doctest::Approx(r.photons()).epsilon(1e-4));
  check_against_reference(v, r, 3e-4);

  // Same light, spread out: the brightest pixel dims.
  prism::ForwardVulkan fw_point(prism::test::gpu(), plain, t);
  auto p = fw_point.psf(theta);
  double peak_point = 0, peak_wide = 0;
  for (size_t i = 0; i < p.data.size(); i += 4) {
    peak_point = std::max(peak_point, double(p.data[i]));
    peak_wide = std::max(peak_wide, double(v.data[i]));
  }
  CHECK(v.photons() == doctest::Approx(p.photons()).epsilon(0.02));
  CHECK(peak_wide < 0.8 * peak_point);
  prism::test::check_validation_clean();
}
