// Footprint splatting: the aperture's strata as cells whose images on the
// sensor carry the cells' light, instead of one point ray per stratum.
//
// Each lenslet's stratum grid (strata x strata cells of [-1, 1]^2, mapped to
// its entrance disk by the concentric map, as the point rays are) is traced at
// the cells' corners. A cell is two triangles; each carries the light of its
// aperture area (the mean of its corners' weight densities times half the
// cell's exact area, pi r^2 / strata^2, the map being area-preserving) spread
// uniformly over its image triangle, and a box pixel receives the part of that
// image inside it: the exact area of the triangle within the pixel. The
// corners' landing points and weights are dual numbers in theta, so b and
// grad b have exact forward-mode derivatives. The error against the true
// box-pixel image is second order in the cell size (uniform density over a
// triangle whose map is affine to first order), where the point splat's is
// shot noise.
//
// The concentric map is smooth inside each of the four wedges between the
// square's diagonals; each cell is split along the diagonal that the wedge
// boundary follows, so no triangle straddles a kink of the map.
//
// How the kernels compute the area inside each pixel is in
// footprint_raster.glsl (exact coverage from the triangle's edges); this file
// holds what the CPU side shares: the cells and their split.
//
// Same GLSL/C++ subset as dual.glsl (engine/shared_math.h compiles it).
#ifndef PRISM_FOOTPRINT_GLSL
#define PRISM_FOOTPRINT_GLSL

#include "optics.glsl"

// Corner (i, j), 0 <= i, j <= strata, of the stratum grid on the unit disk,
// turned by `turn` radians (another stratification of the same aperture).
PRISM_FN vec2 aperture_corner(uint i, uint j, uint strata, float turn) {
  float a = 2.0f * float(i) / float(strata) - 1.0f;
  float b = 2.0f * float(j) / float(strata) - 1.0f;
  vec2 p = concentric_disk(a, b);
  if (turn == 0.0f) return p;
  float c = cos(turn);
  float s = sin(turn);
  return vec2(c * p.x - s * p.y, s * p.x + c * p.y);
}

// Whether cell (i, j) is split along its main diagonal, corner (i, j) to
// (i + 1, j + 1): in the quadrants where a b > 0, where the map's kink line
// a = b runs along such diagonals; elsewhere along the other one (a = -b).
PRISM_FN bool split_main_diagonal(uint i, uint j, uint strata) {
  int ci = 2 * int(i) + 1 - int(strata);  // sign of the cell centre's a, times strata
  int cj = 2 * int(j) + 1 - int(strata);
  return (ci > 0) == (cj > 0);
}

// The three corners, as (i, j) offsets from the cell's (0, 0) corner, of
// triangle t (0 or 1) of cell (i, j); (x, y) = corner 0, (z, w) = 1, and
// corner 2 in the return's second vector.
struct CellTriangle {
  uvec4 ab;  // corner a (x, y) and corner b (z, w), offsets 0 or 1
  uvec2 c;
};
PRISM_FN CellTriangle cell_triangle(uint i, uint j, uint strata, uint t) {
  if (split_main_diagonal(i, j, strata))
    return t == 0u ? CellTriangle(uvec4(0u, 0u, 1u, 0u), uvec2(1u, 1u)) : CellTriangle(uvec4(0u, 0u, 1u, 1u), uvec2(0u, 1u));
  return t == 0u ? CellTriangle(uvec4(0u, 0u, 1u, 0u), uvec2(0u, 1u)) : CellTriangle(uvec4(1u, 0u, 1u, 1u), uvec2(0u, 1u));
}

// A triangle whose image area is below THIN_TRIANGLE times its longest edge
// squared (a cell folded near a caustic, or seen edge-on) spreads its light
// along that edge instead: the thin limit of the uniform triangle, and one
// that float can compute (the area of a sliver, and the derivative of light
// per area, lose their digits in float long before they vanish).
const float THIN_TRIANGLE = 0.01f;

// A triangle whose image spans more than LARGE_TRIANGLE_PX pixels in either
// direction (a cell where the map is far from linear: near-grazing rays at a
// strong lens's rim, a fold) is split into four at its aperture edges'
// midpoints, up to SPLIT_DEPTH times: more rays where the light needs them.
// A piece still that large at the last level is rasterised like any other,
// by the kernels in tiles (the large pass, footprint_raster.glsl): its light
// spread uniformly over its image, where giving it to its centroid's pixel
// left the faint annulus of an f = 3 mm lens's near-face image 300% off at
// any cell count (docs/calibration.md). The split pass takes one level at a
// time (one piece per invocation, its children that are still large listed
// for the next), so only the pieces that exist are traced. Piece codes hold
// 12 bits (footprint_raster.glsl): SPLIT_DEPTH at most 4.
const float LARGE_TRIANGLE_PX = 16.0f;
const int SPLIT_DEPTH = 3;

// Tiles of LARGE_TILE_PX x LARGE_TILE_PX grid pixels, from pixel (0, 0): the
// large pass rasterises a large piece one tile per invocation
// (footprint_raster.glsl), and a masked render (TileMask, engine/forward.h)
// gives light only to the tiles its mask marks. 64: a tile loops over at
// most 64 x 64 pixels times (1 + 5 edges), about 25,000 iterations, under
// llvmpipe's 65,535; 1.2-1.6x faster than 32 at 6.9 um, where each tile's
// retrace of its piece counts (docs/performance.md).
const int LARGE_TILE_PX = 64;

// A corner whose ray lands more than STOPPED_BEYOND_SENSOR_PX grid pixels
// (plus the blur's reach) beyond the sensor's edge counts as stopped, as one
// an aperture or total internal reflection stops: its triangle is cut where
// its rays leave that band. Such light is lost anyway. Traced whole, a
// triangle with a corner near the critical angle (a ray leaving the flat
// face almost grazing, landing metres away) spread its light along an image
// the linear map has nothing to do with, and that corner's landing
// derivative (of order 1 / cos^3 of the refracted angle) put an f = 3 mm
// lens's forward-mode derivatives at 2.5-14x their central differences
// (docs/calibration.md). The band's width only sets where the cut falls in
// light the sensor does not see: the part kept has the light per image area
// it had. The cut comes after the splits the corner's landing point asks
// for (is_large judges a piece by every corner that got through the lens;
// cut unsplit, the f = 3 mm near-face annulus stopped converging).
const float STOPPED_BEYOND_SENSOR_PX = 16.0f;
PRISM_FN bool lands_by_sensor(float u, float v, float u_max, float v_max, float blur_half_px) {
  float m = STOPPED_BEYOND_SENSOR_PX + blur_half_px;
  return u >= -m && v >= -m && u <= u_max + m && v <= v_max + m;  // false for NaN
}

// The aperture area (mm^2) one of a cell's two triangles carries: half of
// the cell's, which is an equal share of the disc (the concentric map
// preserves area).
PRISM_FN float half_cell_area_mm2(float radius_mm, uint strata) {
  return 0.5f * 3.14159265358979f * radius_mm * radius_mm / float(strata * strata);
}

// Signed area of triangle (a, b, c), counter-clockwise (x right, y up) positive.
PRISM_FN Dual triangle_area(Dual ax, Dual ay, Dual bx, Dual by, Dual cx, Dual cy) {
  return d_scale(d_sub(d_mul(d_sub(bx, ax), d_sub(cy, ay)), d_mul(d_sub(cx, ax), d_sub(by, ay))), 0.5f);
}

#endif
