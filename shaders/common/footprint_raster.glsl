// What the footprint kernels share (GLSL only: buffers and atomics): the cut
// list, the traced corners, and exact box-pixel coverage of a polygon from its
// edges (the rest in splat_image.glsl).
//
// Coverage by edges. Along any row of the sensor, a polygon's indicator is a
// sum over its edges of steps, 1_poly(x, y) = -sign(A) sum_e s_e H(x - x_e(y)),
// with s_e the sign of the edge's dy and A the polygon's signed area. So the
// area of the polygon inside pixel (c, r) is -sign(A) sum_e dy_e m_e, where
// dy_e is the edge's signed extent within the row and m_e the mean over it of
// clamp(c + 1 - x_e, 0, 1): 1 for an edge left of the column, 0 right of it,
// a closed form in its x range otherwise. Since the dy of a closed polygon's
// strip sum to zero, the area is equally +sign(A) sum_e dy_e (1 - m_e). Each
// pixel takes the form from its nearer end of the row, where the terms are
// small: the other would cancel the row's large terms in float and leave a
// sliver pixel the rounding of its neighbours. The closed forms divide only
// where they are well conditioned (an edge crossing a column line gives
// 1 - (x_r - c)^2 / (2 dx), bounded as dx -> 0): splitting a nearly vertical
// edge where it crosses the line would not be, and its derivatives would
// cancel by large amounts. Work: the polygon's rows times columns times
// edges, no clipping. (Exact-area font rasterisers start from the same sum.)
#ifndef PRISM_FOOTPRINT_RASTER_GLSL
#define PRISM_FOOTPRINT_RASTER_GLSL

#include "footprint.glsl"
#include "splat_image.glsl"

// Triangles the common path leaves to the later passes, each list a count,
// its capacity, then (source in dispatch, lens index, cell index, piece
// code) per entry; the code names one of the cell's two triangles and the
// piece of its split (piece_code). Splits: large triangles and those over
// the sensor's far edge, then the large pieces of each level of the split
// (psf_footprint_split.comp). Cuts: triangles and pieces some of whose
// corners' rays are stopped (psf_footprint_cut.comp).
layout(std430, binding = 5) buffer Splits {
  uint split_count;
  uint split_capacity;
  uint split_pad0;
  uint split_pad1;
  uvec4 splits[];
};
layout(std430, binding = 6) buffer Cuts {
  uint cut_count;
  uint cut_capacity;
  uint cut_pad0;
  uint cut_pad1;
  uvec4 cuts[];
};

// A piece of triangle `t` (0 or 1) of a cell: split `depth` times, taking
// child `path & 3` at the first split, `(path >> 2) & 3` at the second, and
// so on (child_piece, footprint_pieces.glsl).
uint piece_code(uint t, uint path, uint depth) { return t | (path << 1u) | (depth << (1u + 2u * uint(SPLIT_DEPTH))); }
uint piece_triangle(uint code) { return code & 1u; }
uint piece_path(uint code) { return (code >> 1u) & ((1u << (2u * uint(SPLIT_DEPTH))) - 1u); }
uint piece_depth(uint code) { return code >> (1u + 2u * uint(SPLIT_DEPTH)); }

// A traced corner: landing point in grid pixels (u, v from the sensor's
// top-left corner), weight density (photons per mm^2 of aperture), and
// whether the ray got through.
struct Corner {
  Dual u;
  Dual v;
  Dual w;
  bool ok;
};

Corner trace_corner(vec3 theta, Lenslet lens, vec2 unit) {
  Hit hit = trace_aperture_point(theta, lens, unit, 1.0f, P, LENS_MODEL, SCINT_REFRACTION, HOLDER);
  float inv_px = 1.0f / P.pixel_mm;
  return Corner(d_scale(d_addc(hit.x_mm, P.sensor_half_w_mm), inv_px),
                d_scale(d_addc(hit.y_mm, P.sensor_half_h_mm), inv_px), hit.weight, hit.ok);
}

// The point cell `cell` of lenslet `lens_index` (index within its design)
// leaves from: the source, or with source_extent the cell's own offset.
vec3 cell_source(vec3 theta, uint lens_index, uint cell) {
  if (!SOURCE_EXTENT) return theta;
  return theta + source_offset(lens_index, cell, P.source_sigma_mm, P.stratification);
}

const int MAX_SIDES = 5;  // a triangle clipped by the sensor's two far edges

// Mean over x in [xl, xr] of clamp(c + 1 - x, 0, 1): how much of column c
// lies right of the edge there (see above).
Dual mean_right_of(Dual xl, Dual xr, float c) {
  if (xr.v <= c) return d_const(1.0f);
  if (xl.v >= c + 1.0f) return d_const(0.0f);
  bool in_l = xl.v >= c;
  bool in_r = xr.v <= c + 1.0f;
  if (in_l && in_r) return d_sub(d_const(c + 1.0f), d_scale(d_add(xl, xr), 0.5f));
  Dual dx = d_sub(xr, xl);
  if (in_r) {  // from left of the column into it
    Dual part = d_addc(xr, -c);
    return d_sub(d_const(1.0f), d_div(d_mul(part, part), d_scale(dx, 2.0f)));
  }
  if (in_l) {  // from inside the column out of its right side
    Dual part = d_sub(d_const(c + 1.0f), xl);
    return d_div(d_mul(part, part), d_scale(dx, 2.0f));
  }
  return d_div(d_add(d_sub(d_const(c), xl), d_const(0.5f)), dx);  // across it
}

// 1 - mean_right_of, formed from the column's other side.
Dual mean_left_of(Dual xl, Dual xr, float c) {
  if (xr.v <= c) return d_const(0.0f);
  if (xl.v >= c + 1.0f) return d_const(1.0f);
  bool in_l = xl.v >= c;
  bool in_r = xr.v <= c + 1.0f;
  if (in_l && in_r) return d_addc(d_scale(d_add(xl, xr), 0.5f), -c);
  Dual dx = d_sub(xr, xl);
  if (in_r) {
    Dual part = d_addc(xr, -c);
    return d_div(d_mul(part, part), d_scale(dx, 2.0f));
  }
  if (in_l) {
    Dual part = d_sub(d_const(c + 1.0f), xl);
    return d_sub(d_const(1.0f), d_div(d_mul(part, part), d_scale(dx, 2.0f)));
  }
  return d_div(d_addc(d_sub(xr, d_const(c)), -0.5f), dx);
}

// `weight` spread uniformly over the convex polygon (pu, pv)[0..n) (grid
// pixels), whose signed area is `area` (the light per image area is
// weight / |area| also where the polygon is a part of a larger triangle:
// pass that triangle's area). Each pixel of the band gets its exact share.
void rasterise_polygon(uint image_base, Dual pu[MAX_SIDES], Dual pv[MAX_SIDES], int n, Dual weight, Dual area,
                       uint half_offset) {
  float u_lo = pu[0].v;
  float u_hi = pu[0].v;
  float v_lo = pv[0].v;
  float v_hi = pv[0].v;
  for (int i = 1; i < n; ++i) {
    u_lo = min(u_lo, pu[i].v);
    u_hi = max(u_hi, pu[i].v);
    v_lo = min(v_lo, pv[i].v);
    v_hi = max(v_hi, pv[i].v);
  }
  // Relative to the box origin, so that differences are formed on small numbers.
  int col0 = int(floor(u_lo));
  int row0 = int(floor(v_lo));
  for (int i = 0; i < n; ++i) {
    pu[i] = d_addc(pu[i], -float(col0));
    pv[i] = d_addc(pv[i], -float(row0));
  }
  Dual scale = d_neg(d_div(weight, area));
  int rows = int(floor(v_hi)) - row0 + 1;
  int cols = int(floor(u_hi)) - col0 + 1;
  int r_first = max(0, max(P.band_row0, 0) - row0);
  int r_last = min(rows - 1, min(P.band_row0 + P.band_rows, P.grid_h) - 1 - row0);
  int k_first = max(0, -col0);
  int k_last = min(cols - 1, P.grid_w - 1 - col0);
  for (int r = r_first; r <= r_last; ++r) {
    // Each edge's part within the row: its x range and signed dy.
    Dual seg_l[MAX_SIDES];
    Dual seg_r[MAX_SIDES];
    Dual seg_dy[MAX_SIDES];
    bool seg_live[MAX_SIDES];
    float row_lo = 1e30f;
    float row_hi = -1e30f;
    for (int i = 0; i < n; ++i) {
      int j = (i + 1 == n) ? 0 : i + 1;
      seg_live[i] = false;
      if (pv[i].v == pv[j].v) continue;  // horizontal: no terms
      bool up = pv[j].v > pv[i].v;
      Dual xl = up ? pu[i] : pu[j];
      Dual yl = up ? pv[i] : pv[j];
      Dual xh = up ? pu[j] : pu[i];
      Dual yh = up ? pv[j] : pv[i];
      if (!(yh.v > float(r) && yl.v < float(r + 1))) continue;
      // Ends clamped to the row's lines, a vertex exactly on a line included:
      // every edge then sees it on the same side (the area is smooth there,
      // but mixing the two sides' pieces would mix their derivatives).
      Dual dxdy = d_div(d_sub(xh, xl), d_sub(yh, yl));
      Dual ya = (float(r) >= yl.v) ? d_const(float(r)) : yl;
      Dual yb = (float(r + 1) <= yh.v) ? d_const(float(r + 1)) : yh;
      Dual xa = d_add(xl, d_mul(d_sub(ya, yl), dxdy));
      Dual xb = d_add(xl, d_mul(d_sub(yb, yl), dxdy));
      seg_l[i] = xa.v <= xb.v ? xa : xb;
      seg_r[i] = xa.v <= xb.v ? xb : xa;
      seg_dy[i] = up ? d_sub(yb, ya) : d_sub(ya, yb);
      seg_live[i] = true;
      row_lo = min(row_lo, seg_l[i].v);
      row_hi = max(row_hi, seg_r[i].v);
    }
    if (!(row_lo < row_hi)) continue;  // no edge crosses this row
    float middle = 0.5f * (row_lo + row_hi);
    // Only the columns the row's polygon touches: a sliver's box is mostly
    // empty, and on a SIMD device every lane waits for the longest loop.
    int k_lo = max(k_first, int(floor(row_lo)));
    int k_hi = min(k_last, int(ceil(row_hi)) - 1);
    for (int k = k_lo; k <= k_hi; ++k) {
      float c = float(k);
      if (c + 1.0f <= row_lo || c >= row_hi) continue;  // the row's polygon misses this pixel
      bool from_left = c + 0.5f <= middle;
      Dual covered = d_const(0.0f);
      for (int i = 0; i < n; ++i) {
        if (!seg_live[i]) continue;
        Dual m = from_left ? mean_right_of(seg_l[i], seg_r[i], c) : mean_left_of(seg_l[i], seg_r[i], c);
        covered = d_add(covered, d_mul(seg_dy[i], m));
      }
      if (!from_left) covered = d_neg(covered);
      if (covered.v != 0.0f || covered.d != vec3(0.0f))
        deposit(image_base, col0 + k, row0 + r, d_mul(scale, covered), half_offset);
    }
  }
}

// `weight` spread uniformly along segment (x0, y0) -> (x1, y1), grid pixels,
// up to the sensor's far edges (u_max, v_max): each pixel gets the share of
// the segment's length inside it. A walk through the pixels it crosses.
void rasterise_segment(uint image_base, Dual x0, Dual y0, Dual x1, Dual y1, Dual weight, float u_max, float v_max,
                       uint half_offset) {
  Dual dx = d_sub(x1, x0);
  Dual dy = d_sub(y1, y0);
  // The part on the sensor's side of its far edges (light beyond is lost).
  Dual t_end = d_const(1.0f);
  if (x1.v > u_max && dx.v > 0.0f) t_end = d_div(d_sub(d_const(u_max), x0), dx);
  if (y1.v > v_max && dy.v > 0.0f) {
    Dual t = d_div(d_sub(d_const(v_max), y0), dy);
    if (t.v < t_end.v) t_end = t;
  }
  if (!(t_end.v > 0.0f)) return;
  int cx = int(floor(x0.v));
  int cy = int(floor(y0.v));
  int step_x = dx.v > 0.0f ? 1 : -1;
  int step_y = dy.v > 0.0f ? 1 : -1;
  // Parameters where the segment next crosses a column line and a row line.
  Dual tx = dx.v != 0.0f ? d_div(d_sub(d_const(float(step_x > 0 ? cx + 1 : cx)), x0), dx) : d_const(2.0f);
  Dual ty = dy.v != 0.0f ? d_div(d_sub(d_const(float(step_y > 0 ? cy + 1 : cy)), y0), dy) : d_const(2.0f);
  Dual t_prev = d_const(0.0f);
  int cells = abs(int(floor(x1.v)) - cx) + abs(int(floor(y1.v)) - cy) + 1;
  for (int k = 0; k < cells && t_prev.v < t_end.v; ++k) {
    bool along_x = tx.v <= ty.v;
    Dual t_next = along_x ? tx : ty;
    if (t_next.v > t_end.v) t_next = t_end;
    deposit(image_base, cx, cy, d_mul(weight, d_sub(t_next, t_prev)), half_offset);
    t_prev = t_next;
    if (along_x) {
      cx += step_x;
      tx = d_div(d_sub(d_const(float(step_x > 0 ? cx + 1 : cx)), x0), dx);
    } else {
      cy += step_y;
      ty = d_div(d_sub(d_const(float(step_y > 0 ? cy + 1 : cy)), y0), dy);
    }
  }
}

// A thin triangle's light along its longest edge (see THIN_TRIANGLE).
void rasterise_thin(uint image_base, Corner a, Corner b, Corner c, Dual weight, float u_max, float v_max,
                    uint half_offset) {
  float ab = (b.u.v - a.u.v) * (b.u.v - a.u.v) + (b.v.v - a.v.v) * (b.v.v - a.v.v);
  float bc = (c.u.v - b.u.v) * (c.u.v - b.u.v) + (c.v.v - b.v.v) * (c.v.v - b.v.v);
  float ca = (a.u.v - c.u.v) * (a.u.v - c.u.v) + (a.v.v - c.v.v) * (a.v.v - c.v.v);
  if (ab >= bc && ab >= ca) rasterise_segment(image_base, a.u, a.v, b.u, b.v, weight, u_max, v_max, half_offset);
  else if (bc >= ca) rasterise_segment(image_base, b.u, b.v, c.u, c.v, weight, u_max, v_max, half_offset);
  else rasterise_segment(image_base, c.u, c.v, a.u, a.v, weight, u_max, v_max, half_offset);
}

// Whether the image of triangle (a, b, c), over its corners that got through,
// spans more than LARGE_TRIANGLE_PX in either direction.
bool is_large(Corner a, Corner b, Corner c) {
  float u_lo = 1e30f;
  float u_hi = -1e30f;
  float v_lo = 1e30f;
  float v_hi = -1e30f;
  if (a.ok) u_lo = min(u_lo, a.u.v), u_hi = max(u_hi, a.u.v), v_lo = min(v_lo, a.v.v), v_hi = max(v_hi, a.v.v);
  if (b.ok) u_lo = min(u_lo, b.u.v), u_hi = max(u_hi, b.u.v), v_lo = min(v_lo, b.v.v), v_hi = max(v_hi, b.v.v);
  if (c.ok) u_lo = min(u_lo, c.u.v), u_hi = max(u_hi, c.u.v), v_lo = min(v_lo, c.v.v), v_hi = max(v_hi, c.v.v);
  return max(u_hi - u_lo, v_hi - v_lo) > LARGE_TRIANGLE_PX;
}

// All of `weight` in the pixel of the centroid of (a, b, c), if on the sensor.
void deposit_at_centroid(uint image_base, Corner a, Corner b, Corner c, Dual weight, uint half_offset) {
  float cu = (a.u.v + b.u.v + c.u.v) / 3.0f;
  float cv = (a.v.v + b.v.v + c.v.v) / 3.0f;
  if (cu >= 0.0f && cv >= 0.0f && cu < sensor_u_max() && cv < sensor_v_max())
    deposit(image_base, int(floor(cu)), int(floor(cv)), weight, half_offset);
}

// Whether triangle (a, b, c) of signed area `area` is thin (THIN_TRIANGLE).
bool is_thin(Corner a, Corner b, Corner c, Dual area) {
  float ab = (b.u.v - a.u.v) * (b.u.v - a.u.v) + (b.v.v - a.v.v) * (b.v.v - a.v.v);
  float bc = (c.u.v - b.u.v) * (c.u.v - b.u.v) + (c.v.v - b.v.v) * (c.v.v - b.v.v);
  float ca = (a.u.v - c.u.v) * (a.u.v - c.u.v) + (a.v.v - c.v.v) * (a.v.v - c.v.v);
  return !(abs(area.v) >= THIN_TRIANGLE * max(ab, max(bc, ca)));
}

// Effect diffraction: `weight` spread over triangle (a, b, c) and blurred by
// the lenslet's Airy core (sigma blur_px), as one Gaussian: its mean the
// centroid, its variance the triangle's own (uniform light over it: the sum
// of the corners' squared offsets over 12) plus the core's. It tends to the
// exactly blurred image as the cells shrink (second order in their size), and
// it is smooth where a sharp geometric edge would leave a sliver of light in
// a pixel with a large derivative (whose g^2 / b the CRLB would follow).
void blur_triangle(uint image_base, Corner a, Corner b, Corner c, Dual weight, float blur_px, uint half_offset) {
  Dual mu = d_scale(d_add(d_add(a.u, b.u), c.u), 1.0f / 3.0f);
  Dual mv = d_scale(d_add(d_add(a.v, b.v), c.v), 1.0f / 3.0f);
  Dual au = d_sub(a.u, mu);
  Dual bu = d_sub(b.u, mu);
  Dual cu = d_sub(c.u, mu);
  Dual av = d_sub(a.v, mv);
  Dual bv = d_sub(b.v, mv);
  Dual cv = d_sub(c.v, mv);
  Dual var_u = d_addc(d_scale(d_add(d_add(d_mul(au, au), d_mul(bu, bu)), d_mul(cu, cu)), 1.0f / 12.0f), blur_px * blur_px);
  Dual var_v = d_addc(d_scale(d_add(d_add(d_mul(av, av), d_mul(bv, bv)), d_mul(cv, cv)), 1.0f / 12.0f), blur_px * blur_px);
  deposit_gaussian(image_base, mu, mv, d_sqrt(var_u), d_sqrt(var_v), weight, half_offset);
}

// Triangle (a, b, c) as the first three vertices of a polygon.
void triangle_polygon(Corner a, Corner b, Corner c, inout Dual pu[MAX_SIDES], inout Dual pv[MAX_SIDES]) {
  pu[0] = a.u;
  pv[0] = a.v;
  pu[1] = b.u;
  pv[1] = b.v;
  pu[2] = c.u;
  pv[2] = c.v;
}

// `weight` spread uniformly over triangle (a, b, c), every pixel given its
// exact share (the caller has checked it lies within the sensor's far edges),
// or with diffraction blurred (blur_px, blur_triangle).
void rasterise_triangle(uint image_base, Corner a, Corner b, Corner c, Dual weight, float blur_px, uint half_offset) {
  if (DIFFRACTION) {
    blur_triangle(image_base, a, b, c, weight, blur_px, half_offset);
    return;
  }
  int col = int(floor(a.u.v));
  int row = int(floor(a.v.v));
  bool one_pixel = int(floor(b.u.v)) == col && int(floor(c.u.v)) == col && int(floor(b.v.v)) == row &&
                   int(floor(c.v.v)) == row;
  if (one_pixel) {
    // Wholly inside one pixel: all of it there, no positional derivative.
    deposit(image_base, col, row, weight, half_offset);
    return;
  }
  Dual area = triangle_area(a.u, a.v, b.u, b.v, c.u, c.v);
  if (is_thin(a, b, c, area)) {
    rasterise_thin(image_base, a, b, c, weight, 1e30f, 1e30f, half_offset);
    return;
  }
  Dual pu[MAX_SIDES];
  Dual pv[MAX_SIDES];
  triangle_polygon(a, b, c, pu, pv);
  rasterise_polygon(image_base, pu, pv, 3, weight, area, half_offset);
}

#endif
