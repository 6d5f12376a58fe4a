// Naive double-precision reference of the forward model. Written apart from
// the device math (shaders/common) so the two cannot share a bug: its own dual
// numbers (operator overloading), its own vector code, and its own formulation
// of the scintillator-face path (radial Snell map instead of the shader's
// implicit k). Only the choice of aperture sample points is common, because
// both backends must trace the same rays to be compared pixel by pixel.
#pragma once
#include <array>
#include <cstdint>
#include <optional>

#include <glm/glm.hpp>

#include "engine/fisher.h"
#include "engine/optical_system.h"
#include "engine/ref/dual_ref.h"
#include "engine/ref/pixel_map.h"

namespace prism::ref {

// What the three derivatives of a reference trace are taken with respect to
// (engine/optical_system.h).
using Param = SceneParam;
using prism::source_tangents;
using prism::Tangent;
using prism::Tangents;

// Per touched pixel, keyed by row * grid_width + col: expected photons b, and
// d b/d(x, y, depth) (or the tangents') estimated from each half of the rays (checkerboard of
// strata) separately: {b, gA.x, gA.y, gA.z, gB.x, gB.y, gB.z}.
struct SparseImage {
  int width = 0;
  int height = 0;
  PixelMap<std::array<double, 7>> pixels;
  // Memory per lit pixel at most, for estimates (pixel_map.h).
  static constexpr double bytes_per_pixel = PixelMap<std::array<double, 7>>::bytes_per_entry_bound;
  double photons() const;
  // b and the mean gradient of pixel `key`.
  std::array<double, 4> value(int64_t key) const;
};

// The image by settings.splat: point rays splatted bilinearly, or footprints;
// its derivatives with respect to `tangents`. With `only_lens` >= 0, the
// image of that lenslet alone, its very rays (the images of every lenslet
// alone sum to the whole; calibration's per-lenslet derivative images).
SparseImage psf(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta,
                const Tangents& tangents = source_tangents, int only_lens = -1);
// The footprint splat's image (psf() with Splat::footprint).
SparseImage psf_footprint(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta,
                          const Tangents& tangents = source_tangents, int only_lens = -1);
FisherResult fisher(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta);
FisherResult fisher_of(const SparseImage& image, double dark_counts_per_pixel, FisherEstimator estimator);

// Landing point (x, y) on the sensor plane of one explicit ray through lenslet
// `lens_index`, or nothing when an aperture or total internal reflection stops it.
std::optional<glm::dvec2> trace_ray(const OpticalSystem& sys, size_t lens_index, const glm::dvec3& origin,
                                    const glm::dvec3& direction);

// Landing point, weight and their derivatives of aperture sample `sample` of
// lenslet `lens` from source theta (for finite-difference checks).
struct SampleHit {
  bool ok = false;
  double x_mm = 0, y_mm = 0, weight = 0;
  glm::dvec3 dx{0}, dy{0}, dweight{0};  // d/d(x, y, depth), or d/d(the tangents)
};
SampleHit trace_sample(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta,
                       size_t lens, uint32_t sample);

// The ray from source theta through point `u` (unit-disk coordinates) of
// lenslet `lens`'s entrance disk, carrying the photons of `area_mm2` of
// aperture there (the footprint's corners: footprint_ref.cpp). With
// source_extent it leaves from theta + sigma per_sigma (per_sigma: the
// sample's source_offset at sigma 1, the point's derivative by sigma).
SampleHit trace_point(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta,
                      const glm::dvec3& per_sigma, size_t lens, glm::dvec2 u, double area_mm2,
                      const Tangents& tangents = source_tangents);
// Effect diffraction: `weight` at point (u, v) (grid pixels) blurred by a
// uniform square of half side h (the Airy core, shaders/common/blur.glsl):
// each box pixel gets the square's share in it, the sensor's far edges
// (u_max, v_max) bounding the last column and row; derivatives to
// checkerboard half `half`.
void add_blurred_point(SparseImage& img, D u, D v, double h, D weight, int half, double u_max, double v_max);
// Effect source_extent: sample `sample`'s offset from the source at sigma 1
// (shared sampling code); 0 without the effect.
glm::dvec3 source_offset_per_sigma(const OpticalSystem& sys, uint32_t lens, uint32_t sample, uint32_t seed);

}  // namespace prism::ref
