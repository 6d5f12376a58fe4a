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

#define PRISM_TILE_MASK 1  // the footprint kernels take the tile mask (splat_image.glsl)
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
uint piece_depth(uint code) { return (code >> (1u + 2u * uint(SPLIT_DEPTH))) & 7u; }

// A piece still large at the last level of the split (footprint.glsl) is
// rasterised by the large pass (psf_footprint_large.comp) one tile of
// LARGE_TILE_PX x LARGE_TILE_PX grid pixels per invocation: a rim piece can
// span hundreds of pixels, more than one invocation may loop over on
// lavapipe. Its tiles are listed after the split's entries, each entry the
// piece's (source, lens, cell, piece code) with, in the upper halves of the
// source and code words, its tile's column + 1 and row (tiles of the grid
// from pixel (0, 0); a column of 0: the piece's own entry, not a tile) and
// which part of the piece it is: the whole (0) or part 1 or 2 of what an
// aperture cut passes (rasterise_cut).
// (LARGE_TILE_PX: footprint.glsl.)
uint entry_source(uvec4 entry) { return entry.x & 0xffffu; }  // sources per dispatch < 65536 (forward.cpp)
uvec4 with_tile(uvec4 entry, uint part, uvec2 tile) {
  return uvec4(entry_source(entry) | ((tile.x + 1u) << 16u), entry.y, entry.z,
               (entry.w & 0xfffu) | (part << 12u) | (tile.y << 16u));
}
bool is_tile(uvec4 entry) { return (entry.x >> 16u) != 0u; }
uvec2 entry_tile(uvec4 entry) { return uvec2((entry.x >> 16u) - 1u, entry.w >> 16u); }
uint entry_part(uvec4 entry) { return (entry.w >> 12u) & 3u; }

// Whether light spread over grid pixels [lo, hi] (a piece's image and its
// blur's reach) may fall on a tile the mask marks: always without a mask,
// and when the box spans more than MASK_TEST_TILES tiles (not worth the
// loop; deposit drops its light off the mask).
const int MASK_TEST_TILES = 16;
bool reaches_mask(vec2 lo, vec2 hi) {
  if (P.mask_tiles_w == 0u) return true;
  // Clamped in float: a near-grazing corner can land further off than an int holds.
  vec2 first_px = max(floor(lo), vec2(0.0f));
  vec2 last_px = min(floor(hi), vec2(float(P.grid_w - 1), float(P.grid_h - 1)));
  if (!all(lessThanEqual(first_px, last_px))) return false;
  ivec2 first = ivec2(first_px) / LARGE_TILE_PX;
  ivec2 last = ivec2(last_px) / LARGE_TILE_PX;
  if ((last.x - first.x + 1) * (last.y - first.y + 1) > MASK_TEST_TILES) return true;
  for (int r = first.y; r <= last.y; ++r)
    for (int c = first.x; c <= last.x; ++c)
      if (tile_marked(c, r)) return true;
  return false;
}

// The pixels the footprint kernels may give light to, absolute grid columns
// and rows, first and last (c0, r0, c1, r1): all of them, or in the large
// pass one tile.
ivec4 raster_window = ivec4(-(1 << 30), -(1 << 30), 1 << 30, 1 << 30);
void deposit_windowed(uint image_base, int col, int row, Dual value, uint half_offset) {
  if (col < raster_window.x || row < raster_window.y || col > raster_window.z || row > raster_window.w) return;
  deposit(image_base, col, row, value, half_offset);
}

// A traced corner: landing point in grid pixels (u, v from the sensor's
// top-left corner), weight density (photons per mm^2 of aperture), whether
// the ray got through the lens (`landed`: its landing point counts where a
// piece's size is judged) and whether it also landed within the sensor's
// band (`ok`: its light counts; lands_by_sensor).
struct Corner {
  Dual u;
  Dual v;
  Dual w;
  bool ok;
  bool landed;
};

// Whether triangle (a, b, c), blurred by half side blur_half_px, may give
// light to a tile the mask marks (reaches_mask). Exact for a piece given to
// the pixels as it is: its light stays within its corners' box and the
// blur. A piece to be split (`splits`) is tested with its box grown by half
// its size on every side: its children's corners are traced anew at its
// aperture edges' midpoints, whose images lie off its image edges by as far
// as the map bends over one piece (the test's near-face rim: within this).
bool triangle_reaches_mask(Corner a, Corner b, Corner c, float blur_half_px, bool splits) {
  float reach = (DIFFRACTION ? blur_half_px : 0.0f) + 1.0f;
  vec2 lo = min(min(vec2(a.u.v, a.v.v), vec2(b.u.v, b.v.v)), vec2(c.u.v, c.v.v));
  vec2 hi = max(max(vec2(a.u.v, a.v.v), vec2(b.u.v, b.v.v)), vec2(c.u.v, c.v.v));
  if (splits) reach += 0.5f * max(hi.x - lo.x, hi.y - lo.y);
  return reaches_mask(lo - reach, hi + reach);
}

// Where a cell's rays leave from: the source theta and, with source_extent,
// the cell's own offset per unit sigma (source_point, optics.glsl).
struct CellSource {
  vec3 theta;
  vec3 per_sigma;
};

// The source of cell `cell` of lenslet `lens_index` (index within its design).
CellSource cell_source(vec3 theta, uint lens_index, uint cell) {
  return CellSource(theta, SOURCE_EXTENT ? source_offset(lens_index, cell, 1.0f, P.stratification) : vec3(0.0f));
}

Corner trace_corner(CellSource from, Lenslet lens, vec2 unit) {
  Hit hit = trace_aperture_point(from.theta, from.per_sigma, lens, unit, 1.0f, P, LENS_MODEL, SCINT_REFRACTION, HOLDER,
                                 AS_BUILT);
  float inv_px = 1.0f / P.pixel_mm;
  Corner k = Corner(d_scale(d_addc(hit.x_mm, P.sensor_half_w_mm), inv_px),
                    d_scale(d_addc(hit.y_mm, P.sensor_half_h_mm), inv_px), hit.weight, hit.ok, hit.ok);
  k.ok = k.landed && lands_by_sensor(k.u.v, k.v.v, sensor_u_max(), sensor_v_max(),
                                 DIFFRACTION ? airy_half_side_px(lens) : 0.0f);
  return k;
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

// The bounding box (u_lo, u_hi, v_lo, v_hi) of polygon (pu, pv)[0..n).
vec4 polygon_box(Dual pu[MAX_SIDES], Dual pv[MAX_SIDES], int n) {
  vec4 box = vec4(pu[0].v, pu[0].v, pv[0].v, pv[0].v);
  for (int i = 1; i < n; ++i) box = vec4(min(box.x, pu[i].v), max(box.y, pu[i].v), min(box.z, pv[i].v), max(box.w, pv[i].v));
  return box;
}

// Polygon (pu, pv)[0..n) moved to the pixel corner (col0, row0) at or
// below its box (u_lo, u_hi, v_lo, v_hi) widened by `reach`, so that
// differences are formed on small numbers; returns (col0, row0).
ivec2 to_origin(inout Dual pu[MAX_SIDES], inout Dual pv[MAX_SIDES], int n, vec4 box, float reach) {
  ivec2 origin = ivec2(int(floor(box.x - reach)), int(floor(box.z - reach)));
  for (int i = 0; i < n; ++i) {
    pu[i] = d_addc(pu[i], -float(origin.x));
    pv[i] = d_addc(pv[i], -float(origin.y));
  }
  return origin;
}

// The rows 0..rows - 1 after row0 that lie in this band, first and last.
ivec2 band_rows(int row0, int rows) {
  return ivec2(max(0, max(P.band_row0, 0) - row0), min(rows - 1, min(P.band_row0 + P.band_rows, P.grid_h) - 1 - row0));
}

// The part [ta, tb] of t in [0, 1] where v0 + t dv lies in [lo, hi] (ta > tb: none).
vec2 part_within(float v0, float dv, float lo, float hi) {
  if (dv == 0.0f) return v0 >= lo && v0 <= hi ? vec2(0.0f, 1.0f) : vec2(1.0f, 0.0f);
  float s0 = (lo - v0) / dv;
  float s1 = (hi - v0) / dv;
  return vec2(max(0.0f, min(s0, s1)), min(1.0f, max(s0, s1)));
}

// `weight` spread uniformly over the convex polygon (pu, pv)[0..n) (grid
// pixels), whose signed area is `area` (the light per image area is
// weight / |area| also where the polygon is a part of a larger triangle:
// pass that triangle's area). Each pixel of the band gets its exact share.
void rasterise_polygon(uint image_base, Dual pu[MAX_SIDES], Dual pv[MAX_SIDES], int n, Dual weight, Dual area,
                       uint half_offset) {
  vec4 box = polygon_box(pu, pv, n);
  ivec2 origin = to_origin(pu, pv, n, box, 0.0f);
  int col0 = origin.x;
  int row0 = origin.y;
  float u_hi = box.y;
  float v_hi = box.w;
  Dual scale = d_neg(d_div(weight, area));
  int rows = int(floor(v_hi)) - row0 + 1;
  int cols = int(floor(u_hi)) - col0 + 1;
  ivec2 band = band_rows(row0, rows);
  int k_first = max(max(0, -col0), raster_window.x - col0);
  int k_last = min(min(cols - 1, P.grid_w - 1 - col0), raster_window.z - col0);
  for (int r = max(band.x, raster_window.y - row0); r <= min(band.y, raster_window.w - row0); ++r) {
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
        deposit_windowed(image_base, col0 + k, row0 + r, d_mul(scale, covered), half_offset);
    }
  }
}

// The part [t.x, t.y] of segment x0 + t dx, t in `t`, within [0, hi]
// (Liang-Barsky, one axis); an empty part has t.x.v >= t.y.v.
void clip_segment(Dual x0, Dual dx, float hi, inout Dual t[2]) {
  if (dx.v == 0.0f) {
    if (x0.v < 0.0f || x0.v > hi) t[1] = t[0];
    return;
  }
  Dual at_lo = d_div(d_neg(x0), dx);
  Dual at_hi = d_div(d_sub(d_const(hi), x0), dx);
  Dual enter = dx.v > 0.0f ? at_lo : at_hi;
  Dual leave = dx.v > 0.0f ? at_hi : at_lo;
  if (enter.v > t[0].v) t[0] = enter;
  if (leave.v < t[1].v) t[1] = leave;
}

// `weight` spread uniformly along segment (x0, y0) -> (x1, y1), grid pixels,
// within the sensor (up to its far edges u_max, v_max; light off it is
// lost): each pixel gets the share of the segment's length inside it. A walk
// through the pixels it crosses, from where it enters the sensor to where it
// leaves (a rim piece's sliver can reach far beyond it).
void rasterise_segment(uint image_base, Dual x0, Dual y0, Dual x1, Dual y1, Dual weight, float u_max, float v_max,
                       uint half_offset) {
  Dual dx = d_sub(x1, x0);
  Dual dy = d_sub(y1, y0);
  Dual t[2] = Dual[2](d_const(0.0f), d_const(1.0f));
  clip_segment(x0, dx, u_max, t);
  clip_segment(y0, dy, v_max, t);
  Dual t_end = t[1];
  if (!(t_end.v > t[0].v)) return;
  int cx = int(floor(x0.v + t[0].v * dx.v));
  int cy = int(floor(y0.v + t[0].v * dy.v));
  int step_x = dx.v > 0.0f ? 1 : -1;
  int step_y = dy.v > 0.0f ? 1 : -1;
  // Parameters where the segment next crosses a column line and a row line.
  Dual tx = dx.v != 0.0f ? d_div(d_sub(d_const(float(step_x > 0 ? cx + 1 : cx)), x0), dx) : d_const(2.0f);
  Dual ty = dy.v != 0.0f ? d_div(d_sub(d_const(float(step_y > 0 ? cy + 1 : cy)), y0), dy) : d_const(2.0f);
  Dual t_prev = t[0];
  int cells = abs(int(floor(x0.v + t_end.v * dx.v)) - cx) + abs(int(floor(y0.v + t_end.v * dy.v)) - cy) + 2;
  for (int k = 0; k < cells && t_prev.v < t_end.v; ++k) {
    bool along_x = tx.v <= ty.v;
    Dual t_next = along_x ? tx : ty;
    if (t_next.v > t_end.v) t_next = t_end;
    deposit_windowed(image_base, cx, cy, d_mul(weight, d_sub(t_next, t_prev)), half_offset);
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

// Effect diffraction (blur.glsl): `weight` spread uniformly over the convex
// polygon (pu, pv)[0..n) of signed area `area`, blurred by the Airy square of
// half side h; each box pixel within its reach gets its exact share. By
// Green's theorem the polygon's light in a pixel is weight / area times the
// sum over its edges of the integral of integral(u) profile(v) dv; a column
// left of the row's middle takes the integral from the right, so that edges
// far from it add zeros rather than terms that cancel.
void blur_polygon(uint image_base, Dual pu[MAX_SIDES], Dual pv[MAX_SIDES], int n, Dual weight, Dual area, float h,
                  uint half_offset) {
  vec4 box = polygon_box(pu, pv, n);
  ivec2 origin = to_origin(pu, pv, n, box, h);
  int col0 = origin.x;
  int row0 = origin.y;
  float u_max = sensor_u_max() - float(col0);
  float v_max = sensor_v_max() - float(row0);
  Dual scale = d_div(weight, area);
  int rows = int(floor(box.w + h)) - row0 + 1;
  ivec2 band = band_rows(row0, rows);
  for (int r = max(band.x, raster_window.y - row0); r <= min(band.y, raster_window.w - row0); ++r) {
    float rlo = float(r);
    float rhi = min(float(r + 1), v_max);
    // The polygon's extent along the row's reach [rlo - h, rhi + h].
    float row_lo = 1e30f;
    float row_hi = -1e30f;
    for (int i = 0; i < n; ++i) {
      int j = (i + 1 == n) ? 0 : i + 1;
      float y0 = pv[i].v;
      float y1 = pv[j].v;
      vec2 part = part_within(y0, y1 - y0, rlo - h, rhi + h);
      if (part.x > part.y) continue;
      float xa = pu[i].v + part.x * (pu[j].v - pu[i].v);
      float xb = pu[i].v + part.y * (pu[j].v - pu[i].v);
      row_lo = min(row_lo, min(xa, xb));
      row_hi = max(row_hi, max(xa, xb));
    }
    if (!(row_lo <= row_hi)) continue;
    float middle = 0.5f * (row_lo + row_hi);
    int k_first = max(max(int(floor(row_lo - h)), -col0), raster_window.x - col0);
    int k_last = min(min(int(floor(row_hi + h)), P.grid_w - 1 - col0), raster_window.z - col0);
    for (int k = k_first; k <= k_last; ++k) {
      float clo = float(k);
      float chi = min(float(k + 1), u_max);
      int mode = float(k) + 0.5f <= middle ? BLUR_EDGE_RIGHT : BLUR_EDGE;
      Dual light = d_const(0.0f);
      for (int i = 0; i < n; ++i) {
        int j = (i + 1 == n) ? 0 : i + 1;
        Dual dv = d_sub(pv[j], pv[i]);
        if (dv.v == 0.0f || max(pv[i].v, pv[j].v) <= rlo - h || min(pv[i].v, pv[j].v) >= rhi + h) continue;
        Dual du = d_sub(pu[j], pu[i]);
        light = d_add(light, d_mul(blurred_path(pu[i], pv[i], du, dv, clo, chi, rlo, rhi, h, mode), dv));
      }
      if (light.v != 0.0f || light.d != vec3(0.0f))
        deposit_windowed(image_base, col0 + k, row0 + r, d_mul(scale, light), half_offset);
    }
  }
}

// Effect diffraction: `weight` spread uniformly along segment (x0, y0) ->
// (x1, y1) (a cell folded flat, THIN_TRIANGLE) and blurred by the Airy square.
void blur_segment(uint image_base, Dual x0, Dual y0, Dual x1, Dual y1, Dual weight, float h, uint half_offset) {
  int col0 = int(floor(min(x0.v, x1.v) - h));
  int row0 = int(floor(min(y0.v, y1.v) - h));
  Dual u0 = d_addc(x0, -float(col0));
  Dual v0 = d_addc(y0, -float(row0));
  Dual du = d_sub(x1, x0);
  Dual dv = d_sub(y1, y0);
  float u_max = sensor_u_max() - float(col0);
  float v_max = sensor_v_max() - float(row0);
  int rows = int(floor(max(y0.v, y1.v) + h)) - row0 + 1;
  ivec2 band = band_rows(row0, rows);
  for (int r = band.x; r <= band.y; ++r) {
    float rlo = float(r);
    float rhi = min(float(r + 1), v_max);
    // The segment's part within the row's reach, and its columns.
    vec2 part = part_within(v0.v, dv.v, rlo - h, rhi + h);
    if (part.x > part.y) continue;
    float xa = u0.v + part.x * du.v;
    float xb = u0.v + part.y * du.v;
    int k_first = max(int(floor(min(xa, xb) - h)), -col0);
    int k_last = min(int(floor(max(xa, xb) + h)), P.grid_w - 1 - col0);
    for (int k = k_first; k <= k_last; ++k) {
      Dual share = blurred_path(u0, v0, du, dv, float(k), min(float(k + 1), u_max), rlo, rhi, h, BLUR_LIGHT);
      if (share.v != 0.0f || share.d != vec3(0.0f))
        deposit_windowed(image_base, col0 + k, row0 + r, d_mul(weight, share), half_offset);
    }
  }
}

// A thin triangle's light along its longest edge (see THIN_TRIANGLE); with
// diffraction blurred by the Airy square (half side blur_half_px).
void rasterise_thin(uint image_base, Corner a, Corner b, Corner c, Dual weight, float u_max, float v_max,
                    float blur_half_px, uint half_offset) {
  float ab = (b.u.v - a.u.v) * (b.u.v - a.u.v) + (b.v.v - a.v.v) * (b.v.v - a.v.v);
  float bc = (c.u.v - b.u.v) * (c.u.v - b.u.v) + (c.v.v - b.v.v) * (c.v.v - b.v.v);
  float ca = (a.u.v - c.u.v) * (a.u.v - c.u.v) + (a.v.v - c.v.v) * (a.v.v - c.v.v);
  Corner p = a;
  Corner q = b;
  if (!(ab >= bc && ab >= ca)) {
    p = bc >= ca ? b : c;
    q = bc >= ca ? c : a;
  }
#if PRISM_BLUR
  blur_segment(image_base, p.u, p.v, q.u, q.v, weight, blur_half_px, half_offset);
#else
  rasterise_segment(image_base, p.u, p.v, q.u, q.v, weight, u_max, v_max, half_offset);
#endif
}

// Whether the image of triangle (a, b, c), over its corners that got through,
// spans more than LARGE_TRIANGLE_PX in either direction.
bool is_large(Corner a, Corner b, Corner c) {
  float u_lo = 1e30f;
  float u_hi = -1e30f;
  float v_lo = 1e30f;
  float v_hi = -1e30f;
  if (a.landed) u_lo = min(u_lo, a.u.v), u_hi = max(u_hi, a.u.v), v_lo = min(v_lo, a.v.v), v_hi = max(v_hi, a.v.v);
  if (b.landed) u_lo = min(u_lo, b.u.v), u_hi = max(u_hi, b.u.v), v_lo = min(v_lo, b.v.v), v_hi = max(v_hi, b.v.v);
  if (c.landed) u_lo = min(u_lo, c.u.v), u_hi = max(u_hi, c.u.v), v_lo = min(v_lo, c.v.v), v_hi = max(v_hi, c.v.v);
  return max(u_hi - u_lo, v_hi - v_lo) > LARGE_TRIANGLE_PX;
}

// Whether triangle (a, b, c) of signed area `area` is thin (THIN_TRIANGLE).
bool is_thin(Corner a, Corner b, Corner c, Dual area) {
  float ab = (b.u.v - a.u.v) * (b.u.v - a.u.v) + (b.v.v - a.v.v) * (b.v.v - a.v.v);
  float bc = (c.u.v - b.u.v) * (c.u.v - b.u.v) + (c.v.v - b.v.v) * (c.v.v - b.v.v);
  float ca = (a.u.v - c.u.v) * (a.u.v - c.u.v) + (a.v.v - c.v.v) * (a.v.v - c.v.v);
  return !(abs(area.v) >= THIN_TRIANGLE * max(ab, max(bc, ca)));
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

// Effect diffraction: `weight` spread over triangle (a, b, c) and blurred by
// the lenslet's Airy square (half side h, grid pixels); a triangle folded
// flat, along its longest edge.
void blur_triangle(uint image_base, Corner a, Corner b, Corner c, Dual weight, float h, uint half_offset) {
  float u_lo = min(min(a.u.v, b.u.v), c.u.v);
  float u_hi = max(max(a.u.v, b.u.v), c.u.v);
  float v_lo = min(min(a.v.v, b.v.v), c.v.v);
  float v_hi = max(max(a.v.v, b.v.v), c.v.v);
  int col = int(floor(u_lo - h));
  int row = int(floor(v_lo - h));
  if (u_hi + h <= min(float(col + 1), sensor_u_max()) && v_hi + h <= min(float(row + 1), sensor_v_max())) {
    // Blurred, still inside one pixel: all of it there.
    deposit(image_base, col, row, weight, half_offset);
    return;
  }
  Dual area = triangle_area(a.u, a.v, b.u, b.v, c.u, c.v);
  if (is_thin(a, b, c, area)) {
    rasterise_thin(image_base, a, b, c, weight, 0.0f, 0.0f, h, half_offset);
    return;
  }
  Dual pu[MAX_SIDES];
  Dual pv[MAX_SIDES];
  triangle_polygon(a, b, c, pu, pv);
  blur_polygon(image_base, pu, pv, 3, weight, area, h, half_offset);
}

// `weight` spread uniformly over triangle (a, b, c), every pixel given its
// exact share (the caller has checked it lies within the sensor's far edges),
// or with diffraction blurred (blur_half_px, blur_triangle).
void rasterise_triangle(uint image_base, Corner a, Corner b, Corner c, Dual weight, float blur_half_px,
                        uint half_offset) {
#if PRISM_BLUR
  blur_triangle(image_base, a, b, c, weight, blur_half_px, half_offset);
  return;
#endif
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
    rasterise_thin(image_base, a, b, c, weight, 1e30f, 1e30f, 0.0f, half_offset);
    return;
  }
  Dual pu[MAX_SIDES];
  Dual pv[MAX_SIDES];
  triangle_polygon(a, b, c, pu, pv);
  rasterise_polygon(image_base, pu, pv, 3, weight, area, half_offset);
}

#endif
