// The calibration's blur term: a Gaussian source of sigma per axis (effect
// source_extent), modelled smoothly.
//
// To first order in the source's offset delta, a lenslet's image of a moved
// source is its image moved rigidly by J delta, J the image's motion by the
// source (x, y, depth) (for a thin lens exactly so sideways: the defocus disc
// keeps its shape and moves with the chief ray; the calibration takes J from
// the chief ray, calibrate.cpp, or from the centroid where it has none, below).
// So the lenslet's image of the
// Gaussian source is its point image convolved with a Gaussian of covariance
// sigma^2 J J^T: smooth in sigma and in every other parameter, and its
// derivative by sigma is that of the kernel. The engine's own source_extent
// samples a random offset per footprint cell instead: right on average, but
// speckled at the pixel scale, and a fit cannot tell that speckle from the
// measurement's noise (docs/calibration.md, the blur term).
//
// What first order leaves out: a deeper or shallower source changes a
// defocus disc's size, not only where it lies (for a near-face source the
// disc's edge moves by a pixel over 0.3 mm of depth), and the kernel is
// sampled at pixel centres, so a sub-pixel image blurred by about a pixel is
// modelled coarsely. The kernel's shape J holds still where derivatives by
// the other parameters are taken (it changes with the magnification: about
// 1% for 0.2 mm of lens-to-sensor distance); chi2 itself uses the exact
// kernel.
#pragma once
#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

#include <glm/glm.hpp>

#include "engine/optical_system.h"

namespace prism {

// One lenslet's image on a grid of width x height pixels, sparse: keys
// (row * width + column) and, per key, `channels` values; channel 0 the
// image b, channels 1..3 db/d(source x, y, depth) per mm, the rest whatever
// derivative images ride along (blurred as b is).
struct LensImage {
  int width = 0, height = 0;
  std::size_t channels = 4;
  std::vector<int64_t> keys;
  std::vector<double> values;  // keys.size() x channels
};

// J as the motion of lenslet `lens`'s chief ray (through its entrance disk's
// centre) on the sensor, from the double reference, in pixels of
// settings.binning per mm: how a thin lens's image moves (above). Nothing
// where the chief ray is stopped. The image centroid's motion (below), taken
// from derivative images, was not a steady measure of it: for the defocus
// disc of an f = 12 mm lens, source 15 mm deep, it came out 7.4 and 9.6 px /
// mm along x and y on 110 um pixels, 10.3 and 8.7 (per 110 um) on 55 um
// pixels; the chief ray's is 8.3 and 8.3 on both.
std::optional<std::array<double, 6>> chief_ray_motion(const OpticalSystem& sys, const TraceSettings& settings,
                                                      const glm::dvec3& theta, std::size_t lens);

// J as the image centroid's derivative by the source (x, y, depth), in
// pixels per mm, row-major 2 x 3 (from channels 0..3); zero for an empty
// image. A noisy measure of the motion for a large disc rendered with few
// cells (its edges' lever arm): the calibration uses it only where the chief
// ray misses.
std::array<double, 6> centroid_jacobian(const LensImage& image);

// The Gaussian kernel of covariance sigma^2 J J^T (pixels^2), sampled at
// integer offsets within `radius` and normalised to sum 1, and its exact
// derivative by sigma: (2 radius + 1)^2 values each, row by row from
// offset (-radius, -radius).
struct BlurKernel {
  int radius = 0;
  std::vector<double> g, dg_dsigma;
};
BlurKernel source_blur_kernel(const std::array<double, 6>& jacobian, double sigma_mm);

// `image` convolved with `kernel` (every channel), light blurred beyond the
// grid lost as the sensor's edge loses it; with `sigma_channel`, one more
// channel last: d(blurred b)/d sigma. Keys in the same form, only pixels
// with some value.
LensImage blur(const LensImage& image, const BlurKernel& kernel, bool sigma_channel);

}  // namespace prism
