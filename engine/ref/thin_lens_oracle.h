// Exact images of ideal thin lenses on box pixels: the oracle the splats are
// tested against (no rays, no sampling).
//
// For an ideal thin lens and a fixed point source the landing point is affine
// in the aperture point p (lateral coordinates):
//   q = k p + t,   k = 1 + L/h - L/f,   t = c L/f - s L/h,
// with L the lens-to-sensor distance, h = depth + working distance the
// source's distance to the lens plane, c the lenslet centre and s the source's
// lateral position. So each lenslet's image is its aperture disc scaled by k
// and moved, and a box pixel's expected photons are the ray weight
//   w(p) = Phi / (4 pi) * h / |p - s|^3      (cos / r^2 per aperture area)
// integrated over the part of the disc whose image falls in the pixel: the
// disc intersected with the pixel's preimage rectangle. Over a rectangle the
// integral has a closed form, the solid angle atan(u v / (h sqrt(u^2 + v^2 +
// h^2))) at its corners; where the disc's edge crosses the rectangle it is a
// 1D integral along the edge's angle, by Gauss-Legendre on pieces split where
// the edge meets the rectangle's sides (smooth on each piece).
//
// Every quantity is a dual number in theta (engine/ref/dual_ref.h), so the
// derivatives are those of the exact integral (the quadrature's own
// derivative, with its moving end points), not finite differences: a pixel
// that holds a sliver of a disc has a tiny b and a large derivative, where
// finite differences fail.
//
// Plain thin lenses only (detection efficiency and dark counts allowed);
// other effects are refused. Sensor clipping as in the kernels: light beyond
// the physical sensor is lost, the last column and row hold only their part
// on the sensor.
#pragma once
#include <glm/glm.hpp>

#include "engine/optical_system.h"
#include "engine/ref/forward_ref.h"

namespace prism::ref {

// The image of a point source at theta = (x, y, depth) on the analysis grid of
// settings.binning, with exact b and grad b per pixel (both "halves" of the
// SparseImage hold the exact gradient, so fisher_of gives the same with either
// estimator). Throws std::invalid_argument for a real lens or an effect other
// than detection efficiency and dark counts.
SparseImage thin_lens_image(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta);

// Fisher information of the exact image (sensor model by fisher_of's rules).
FisherResult thin_lens_fisher(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta);

}  // namespace prism::ref
