// Effect diffraction: each lenslet's Airy core as a uniform square of half
// side h (grid pixels): the Gaussian fit's sigma times sqrt(3), the same
// variance (engine/defaults.h).
//
// Why a square and not the Gaussian itself: across each of its lines a box
// pixel blurred by the square has a piecewise-linear profile, so the light a
// blurred pixel takes from a uniform triangle (the footprint's cells), a
// segment (a cell folded flat) or a point (a ray) is, along the triangle's
// edges, a polynomial of degree three at most between known kinks: two-point
// Gauss-Legendre between them is exact, and so are its derivatives. With the
// Gaussian these are integrals of products of error functions with no closed
// form. The model before this one gave each cell's triangle one Gaussian (its
// own variance plus the core's); where the core is narrower than the cells'
// images that sum is lumpy, and the CRLB followed the lumps (docs/model.md
// "Convergence"). The Airy core is neither shape; the square keeps its width.
//
// Across a pixel's lines lo < hi, the blurred pixel's profile is
//   profile(x) = step(x - lo) - step(x - hi),
// step(u) = clamp((u + h) / 2h, 0, 1) the share of the square around u that
// lies right of a line at 0; its integral from -inf is
//   ramp(x - lo) - ramp(x - hi),
// ramp(u) = 0 below -h, (u + h)^2 / 4h within h, u above. Both have kinks at
// lo - h, lo + h, hi - h and hi + h and nowhere else.
//
// GLSL only (the CPU reference integrates the same model its own way,
// engine/ref/footprint_ref.cpp).
#ifndef PRISM_BLUR_GLSL
#define PRISM_BLUR_GLSL

#include "dual.glsl"

Dual blur_step(Dual u, float h) {
  if (u.v <= -h) return d_const(0.0f);
  if (u.v >= h) return d_const(1.0f);
  return d_scale(d_addc(u, h), 0.5f / h);
}

Dual blur_ramp(Dual u, float h) {
  if (u.v <= -h) return d_const(0.0f);
  if (u.v >= h) return u;
  Dual a = d_addc(u, h);
  return d_scale(d_mul(a, a), 0.25f / h);
}

// The blurred profile of pixel lines [lo, hi] at x: the share of the square
// around x inside them.
Dual blurred_pixel(Dual x, float lo, float hi, float h) {
  return d_sub(blur_step(d_addc(x, -lo), h), blur_step(d_addc(x, -hi), h));
}

// Its integral from -inf to x, or with `from_right` minus its integral from x
// to +inf (the same up to the pixel's width, and zero, not a difference of
// two widths, right of the pixel's reach).
Dual blurred_pixel_integral(Dual x, float lo, float hi, float h, bool from_right) {
  if (from_right) return d_sub(blur_ramp(d_sub(d_const(lo), x), h), blur_ramp(d_sub(d_const(hi), x), h));
  return d_sub(blur_ramp(d_addc(x, -lo), h), blur_ramp(d_addc(x, -hi), h));
}

// What blurred_path integrates along its path.
const int BLUR_LIGHT = 0;         // profile(u) profile(v): light along a segment
const int BLUR_EDGE = 1;          // integral(u) profile(v): a polygon's edge (Green's theorem)
const int BLUR_EDGE_RIGHT = 2;    // the same with the integral from the right

// One piece [t0, t1] of blurred_path (see there), two-point Gauss-Legendre.
Dual blurred_piece(Dual u0, Dual v0, Dual du, Dual dv, float clo, float chi, float rlo, float rhi, float h, int mode,
                   float t0, float t1) {
  float len = t1 - t0;
  if (!(len > 0.0f)) return d_const(0.0f);
  // A piece where a factor vanishes (whole pieces: the reach ends at a kink).
  float mid = 0.5f * (t0 + t1);
  float vm = v0.v + mid * dv.v;
  float um = u0.v + mid * du.v;
  if (vm <= rlo - h || vm >= rhi + h) return d_const(0.0f);
  if (mode != BLUR_EDGE_RIGHT && um <= clo - h) return d_const(0.0f);
  if (mode != BLUR_EDGE && um >= chi + h) return d_const(0.0f);
  float off = 0.28867513f * len;  // nodes at mid -+ len / (2 sqrt 3), weights len / 2
  Dual ua = d_add(u0, d_scale(du, mid - off));
  Dual va = d_add(v0, d_scale(dv, mid - off));
  Dual ub = d_add(u0, d_scale(du, mid + off));
  Dual vb = d_add(v0, d_scale(dv, mid + off));
  Dual across_a = mode == BLUR_LIGHT ? blurred_pixel(ua, clo, chi, h)
                                     : blurred_pixel_integral(ua, clo, chi, h, mode == BLUR_EDGE_RIGHT);
  Dual across_b = mode == BLUR_LIGHT ? blurred_pixel(ub, clo, chi, h)
                                     : blurred_pixel_integral(ub, clo, chi, h, mode == BLUR_EDGE_RIGHT);
  Dual sum = d_add(d_mul(across_a, blurred_pixel(va, rlo, rhi, h)), d_mul(across_b, blurred_pixel(vb, rlo, rhi, h)));
  return d_scale(sum, 0.5f * len);
}

// Where a path at `from` moving by `delta` per unit t crosses `kink`, within [0, 1].
float kink_crossing(float from, float delta, float kink) {
  return delta == 0.0f ? 0.0f : clamp((kink - from) / delta, 0.0f, 1.0f);
}

// Where the path crosses the four kinks of a profile of lines [lo, hi]
// (lo - h <= lo + h and hi - h <= hi + h, ordered pairwise), in order along it.
vec4 kink_crossings(float from, float delta, float lo, float hi, float h) {
  vec4 t = vec4(kink_crossing(from, delta, lo - h), kink_crossing(from, delta, min(lo + h, hi - h)),
                kink_crossing(from, delta, max(lo + h, hi - h)), kink_crossing(from, delta, hi + h));
  return delta < 0.0f ? t.wzyx : t;
}

// Order two values.
void order(inout float a, inout float b) {
  float lo = min(a, b);
  b = max(a, b);
  a = lo;
}

// The integral over t in [0, 1] along the path (u0 + t du, v0 + t dv) of the
// `mode`'s product for pixel columns [clo, chi] and rows [rlo, rhi], blurred
// by half side h: split at every kink of both profiles, each piece a
// polynomial of degree <= 3 in t (two-point Gauss-Legendre: exact). The
// split points are held fixed in theta: the integrand is continuous across
// them, so their motion adds nothing (and 1 / du would, in float, where an
// edge is nearly parallel to a pixel line). Written without loops: lavapipe
// ends a shader's loops after 65535 iterations in all per batch of
// invocations (footprint.glsl), and this runs for every edge of every pixel.
Dual blurred_path(Dual u0, Dual v0, Dual du, Dual dv, float clo, float chi, float rlo, float rhi, float h, int mode) {
  // The crossings of each profile's kinks in order along the path, merged.
  vec4 a = kink_crossings(u0.v, du.v, clo, chi, h);
  vec4 b = kink_crossings(v0.v, dv.v, rlo, rhi, h);
  float a0 = a.x;
  float a1 = a.y;
  float a2 = a.z;
  float a3 = a.w;
  float b0 = b.x;
  float b1 = b.y;
  float b2 = b.z;
  float b3 = b.w;
  // Batcher's odd-even merge of the two sorted fours.
  order(a0, b0); order(a1, b1); order(a2, b2); order(a3, b3);
  order(a2, b0); order(a3, b1);
  order(a1, a2); order(a3, b0); order(b1, b2);
  Dual sum = blurred_piece(u0, v0, du, dv, clo, chi, rlo, rhi, h, mode, 0.0f, a0);
  sum = d_add(sum, blurred_piece(u0, v0, du, dv, clo, chi, rlo, rhi, h, mode, a0, a1));
  sum = d_add(sum, blurred_piece(u0, v0, du, dv, clo, chi, rlo, rhi, h, mode, a1, a2));
  sum = d_add(sum, blurred_piece(u0, v0, du, dv, clo, chi, rlo, rhi, h, mode, a2, a3));
  sum = d_add(sum, blurred_piece(u0, v0, du, dv, clo, chi, rlo, rhi, h, mode, a3, b0));
  sum = d_add(sum, blurred_piece(u0, v0, du, dv, clo, chi, rlo, rhi, h, mode, b0, b1));
  sum = d_add(sum, blurred_piece(u0, v0, du, dv, clo, chi, rlo, rhi, h, mode, b1, b2));
  sum = d_add(sum, blurred_piece(u0, v0, du, dv, clo, chi, rlo, rhi, h, mode, b2, b3));
  sum = d_add(sum, blurred_piece(u0, v0, du, dv, clo, chi, rlo, rhi, h, mode, b3, 1.0f));
  return sum;
}

#endif
