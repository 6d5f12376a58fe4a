// The footprint splat's later passes (psf_footprint_split.comp,
// psf_footprint_cut.comp): the pieces of a listed triangle, and how a cut or
// clipped piece gives its light to the pixels.
//
// A piece still large after the last split: listed as tiles for the large
// pass (footprint_raster.glsl, LARGE_TILE_PX), which rasterises it exactly,
// one tile per invocation.
//
// An aperture cut: the boundary is found by bisection along each edge between
// a corner whose ray passes and one whose ray does not, stopped by an
// aperture, total internal reflection or the band around the sensor
// (lands_by_sensor, footprint.glsl) (CUT_STEPS halvings of
// the aperture segment), and the part that passes (a triangle, or a quad as
// two triangles) carries its share of the aperture area. The cut's aperture
// point is held fixed in theta: its motion, like a point ray crossing an
// aperture edge, is not in the derivatives. The far edge: each triangle is
// clipped to the sensor and the part on it rasterised with the light per
// image area of the whole triangle (light beyond is lost).
#ifndef PRISM_FOOTPRINT_PIECES_GLSL
#define PRISM_FOOTPRINT_PIECES_GLSL

#include "footprint_raster.glsl"

const int CUT_STEPS = 8;  // the cut within 1/256 of the cell edge: boundary cells only

// The tiles of large piece (a, b, c), part `part` of list entry `entry`,
// within the sensor, this band and a blur's reach, listed for the large
// pass after the split's entries.
void list_tiles(uvec4 entry, uint part, Corner a, Corner b, Corner c, float blur_half_px) {
  float reach = DIFFRACTION ? blur_half_px + 1.0f : 0.0f;
  vec2 lo = min(min(vec2(a.u.v, a.v.v), vec2(b.u.v, b.v.v)), vec2(c.u.v, c.v.v)) - reach;
  vec2 hi = max(max(vec2(a.u.v, a.v.v), vec2(b.u.v, b.v.v)), vec2(c.u.v, c.v.v)) + reach;
  // Clamped in float: a near-grazing corner can land further off than an int holds.
  vec2 first_px = max(floor(lo), vec2(0.0f, float(max(P.band_row0, 0))));
  vec2 last_px = min(floor(hi), vec2(float(P.grid_w - 1), float(min(P.band_row0 + P.band_rows, P.grid_h) - 1)));
  if (!all(lessThanEqual(first_px, last_px))) return;
  ivec2 first = ivec2(first_px) / LARGE_TILE_PX;
  ivec2 last = ivec2(last_px) / LARGE_TILE_PX;
  uint tiles = uint((last.x - first.x + 1) * (last.y - first.y + 1));
  uint columns = uint(last.x - first.x + 1);
  if (P.mask_tiles_w == 0u) {
    uint at = atomicAdd(split_count, tiles);
    for (uint k = 0u; k < tiles && at + k < split_capacity; ++k)
      splits[at + k] = with_tile(entry, part, uvec2(first) + uvec2(k % columns, k / columns));
    return;
  }
  // A masked render lists only the tiles its mask marks.
  for (uint k = 0u; k < tiles; ++k) {
    uvec2 tile = uvec2(first) + uvec2(k % columns, k / columns);
    if (!tile_marked(int(tile.x), int(tile.y))) continue;
    uint at = atomicAdd(split_count, 1u);
    if (at < split_capacity) splits[at] = with_tile(entry, part, tile);
  }
}

// `weight` spread over triangle (a, b, c), clipped to u <= u_max, v <= v_max
// (light beyond is lost; the rest keeps the whole triangle's light per area).
// `entry` is the list entry the triangle is (part `part` of): where it is a
// tile, only that tile's pixels are given light; where it is not and the
// triangle is large, its tiles are listed for the large pass instead.
void rasterise_clipped(uint image_base, Corner a, Corner b, Corner c, Dual weight, float blur_half_px, uint half_offset,
                       uvec4 entry, uint part) {
  if (!is_tile(entry) && is_large(a, b, c)) {
    list_tiles(entry, part, a, b, c, blur_half_px);
    return;
  }
  if (!is_tile(entry) && !triangle_reaches_mask(a, b, c, blur_half_px, false)) return;
  if (is_tile(entry)) {
    ivec2 first = ivec2(entry_tile(entry)) * LARGE_TILE_PX;
    raster_window = ivec4(first, first + (LARGE_TILE_PX - 1));
  }
#if PRISM_BLUR  // the blurred pixels end at the far edges themselves
  blur_triangle(image_base, a, b, c, weight, blur_half_px, half_offset);
  return;
#endif
  Dual area = triangle_area(a.u, a.v, b.u, b.v, c.u, c.v);
  if (is_thin(a, b, c, area)) {
    rasterise_thin(image_base, a, b, c, weight, sensor_u_max(), sensor_v_max(), 0.0f, half_offset);
    return;
  }
  // Sutherland-Hodgman against the two far edges: at most 5 vertices.
  Dual pu[MAX_SIDES];
  Dual pv[MAX_SIDES];
  Dual qu[MAX_SIDES];
  Dual qv[MAX_SIDES];
  triangle_polygon(a, b, c, pu, pv);
  int n = 3;
  for (int plane = 0; plane < 2; ++plane) {
    float limit = plane == 0 ? sensor_u_max() : sensor_v_max();
    int m = 0;
    for (int i = 0; i < n; ++i) {
      int j = (i + 1 == n) ? 0 : i + 1;
      Dual di = d_sub(d_const(limit), plane == 0 ? pu[i] : pv[i]);
      Dual dj = d_sub(d_const(limit), plane == 0 ? pu[j] : pv[j]);
      if (di.v >= 0.0f) {
        qu[m] = pu[i];
        qv[m] = pv[i];
        ++m;
      }
      if ((di.v >= 0.0f) != (dj.v >= 0.0f)) {
        Dual t = d_div(di, d_sub(di, dj));
        qu[m] = d_add(pu[i], d_mul(t, d_sub(pu[j], pu[i])));
        qv[m] = d_add(pv[i], d_mul(t, d_sub(pv[j], pv[i])));
        ++m;
      }
    }
    n = m;
    for (int k = 0; k < n; ++k) {
      pu[k] = qu[k];
      pv[k] = qv[k];
    }
    if (n < 3) return;
  }
  rasterise_polygon(image_base, pu, pv, n, weight, area, half_offset);
}

// Twice the aperture area of triangle (a, b, c), unit-disk coordinates.
float twice_area(vec2 a, vec2 b, vec2 c) { return abs((b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y)); }

// Triangle (a, b, c) with some corners stopped: the part that passes, found
// by bisection along a-b and a-c from the odd corner out, as one triangle
// or, where one corner is stopped, two (parts: 1 or 2); triangle q of it
// (p0, p1, p2), with its share of `area_mm2` of aperture. False where the
// triangle has no aperture area.
bool cut_part(CellSource from, Lenslet lens, Corner a, Corner b, Corner c, vec2 pa, vec2 pb, vec2 pc, float area_mm2, int q,
              out uint parts, out Corner p0, out Corner p1, out Corner p2, out float part_mm2) {
  int passed = int(a.ok) + int(b.ok) + int(c.ok);
  // The odd one out first, cyclic order kept: a stopped with b, c through
  // (passed == 2), or a through with b, c stopped (passed == 1).
  bool odd_ok = passed == 1;
  if (b.ok == odd_ok) {
    Corner t = a; a = b; b = c; c = t;
    vec2 q = pa; pa = pb; pb = pc; pc = q;
  } else if (c.ok == odd_ok) {
    Corner t = a; a = c; c = b; b = t;
    vec2 q = pa; pa = pc; pc = pb; pb = q;
  }
  // Bisect a-b and a-c for the last point on the through side.
  Corner cut0 = a;
  Corner cut1 = a;
  vec2 cut_p0 = pa;
  vec2 cut_p1 = pa;
  for (int side = 0; side < 2; ++side) {
    vec2 other = side == 0 ? pb : pc;
    vec2 through = odd_ok ? pa : other;
    vec2 stopped = odd_ok ? other : pa;
    Corner best = odd_ok ? a : (side == 0 ? b : c);
    for (int k = 0; k < CUT_STEPS; ++k) {
      vec2 mid = 0.5f * (through + stopped);
      Corner m = trace_corner(from, lens, mid);
      if (m.ok) {
        through = mid;
        best = m;
      } else {
        stopped = mid;
      }
    }
    if (side == 0) {
      cut0 = best;
      cut_p0 = through;
    } else {
      cut1 = best;
      cut_p1 = through;
    }
  }
  float whole = twice_area(pa, pb, pc);
  parts = odd_ok ? 1u : 2u;
  // The part that passes: triangle a, cut0, cut1; or quad cut0, b, c, cut1
  // as two triangles, each with its own aperture area.
  p0 = odd_ok ? a : cut0;
  p1 = odd_ok ? cut0 : (q == 0 ? b : c);
  p2 = odd_ok ? cut1 : (q == 0 ? c : cut1);
  vec2 q0 = odd_ok ? pa : cut_p0;
  vec2 q1 = odd_ok ? cut_p0 : (q == 0 ? pb : pc);
  vec2 q2 = odd_ok ? cut_p1 : (q == 0 ? pc : cut_p1);
  part_mm2 = area_mm2 * twice_area(q0, q1, q2) / whole;
  return whole > 0.0f;
}

// Triangle (a, b, c) of list entry `entry` with some corners stopped: the
// parts that pass (cut_part) given to the pixels. The bisection runs once
// per part, a loop around one call site of each (why: shaders/CMakeLists.txt).
void rasterise_cut(uint image_base, CellSource from, Lenslet lens, Corner a, Corner b, Corner c, vec2 pa, vec2 pb, vec2 pc,
                   float area_mm2, float blur_half_px, uint half_offset, uvec4 entry) {
  uint parts = 1u;
  for (uint q = 0u; q < parts; ++q) {
    Corner p0, p1, p2;
    float part_mm2;
    if (!cut_part(from, lens, a, b, c, pa, pb, pc, area_mm2, int(q), parts, p0, p1, p2, part_mm2)) return;
    rasterise_clipped(image_base, p0, p1, p2, d_scale(d_add(d_add(p0.w, p1.w), p2.w), part_mm2 / 3.0f), blur_half_px,
                      half_offset, entry, q + 1u);
  }
}

// A triangle of the split: aperture points, traced corners, the aperture
// area it carries.
struct Piece {
  vec2 pa;
  vec2 pb;
  vec2 pc;
  Corner a;
  Corner b;
  Corner c;
  float area_mm2;
};

// Child k (0..3) of piece t, split at its aperture edges' midpoints (traced
// as ab, bc, ca): a quarter of the area each.
Piece child_piece(Piece t, Corner ab, Corner bc, Corner ca, uint k) {
  vec2 pab = 0.5f * (t.pa + t.pb);
  vec2 pbc = 0.5f * (t.pb + t.pc);
  vec2 pca = 0.5f * (t.pc + t.pa);
  float quarter = 0.25f * t.area_mm2;
  if (k == 0u) return Piece(t.pa, pab, pca, t.a, ab, ca, quarter);
  if (k == 1u) return Piece(pab, t.pb, pbc, ab, t.b, bc, quarter);
  if (k == 2u) return Piece(pca, pbc, t.pc, ca, bc, t.c, quarter);
  return Piece(pab, pbc, pca, ab, bc, ca, quarter);
}

// Whether piece t, split `depth` times so far, is split again (footprint.glsl).
bool is_split(Piece t, int depth) {
  return depth < SPLIT_DEPTH && (t.a.ok || t.b.ok || t.c.ok) && is_large(t.a, t.b, t.c);
}

// Corners traced at aperture points qa, qb, qc: a loop around one call site
// (why: shaders/CMakeLists.txt).
void trace_three(CellSource from, Lenslet lens, vec2 qa, vec2 qb, vec2 qc, out Corner a, out Corner b, out Corner c) {
  vec2 at[3] = vec2[3](qa, qb, qc);
  Corner k[3];
  for (int q = 0; q < 3; ++q) k[q] = trace_corner(from, lens, at[q]);
  a = k[0];
  b = k[1];
  c = k[2];
}

// The piece of list entry `entry` (footprint_raster.glsl): its triangle
// split along the entry's path (piece_code); `from` is the cell's source
// point.
void listed_piece(uvec4 entry, out Piece t, out CellSource from, out Lenslet lens, out uint image_base,
                  out uint half_offset, out float blur_half_px) {
  uint s = entry_source(entry);
  DesignRange design = designs[source_design[P.source_offset + s]];
  lens = lenses[entry.y];
  uint in_design = entry.y - design.first_lens;
  uint cell = entry.z;
  uint n = lens.strata;
  uint i = cell % n;
  uint j = cell / n;
  uint path = piece_path(entry.w);
  uint depth = piece_depth(entry.w);
  image_base = s * uint(P.grid_w) * uint(P.band_rows) * PIXEL_FLOATS;
  half_offset = 1u + 3u * ((i + j) & 1u);
  blur_half_px = DIFFRACTION ? airy_half_side_px(lens) : 0.0f;
  float turn = strata_turn(in_design, P.stratification);
  from = cell_source(sources[P.source_offset + s].xyz, in_design, cell);
  CellTriangle tri = cell_triangle(i, j, n, piece_triangle(entry.w));
  t.pa = aperture_corner(i + tri.ab.x, j + tri.ab.y, n, turn);
  t.pb = aperture_corner(i + tri.ab.z, j + tri.ab.w, n, turn);
  t.pc = aperture_corner(i + tri.c.x, j + tri.c.y, n, turn);
  t.area_mm2 = half_cell_area_mm2(lens.radius_mm, n);
  // Level 0 traces the triangle's corners, each level after it the midpoints
  // of the piece's edges (one call site for both).
  vec2 qa = t.pa, qb = t.pb, qc = t.pc;
  for (uint d = 0u; d <= depth; ++d) {
    Corner a, b, c;
    trace_three(from, lens, qa, qb, qc, a, b, c);
    if (d == 0u) {
      t.a = a;
      t.b = b;
      t.c = c;
    } else {
      t = child_piece(t, a, b, c, path & 3u);
      path >>= 2u;
    }
    qa = 0.5f * (t.pa + t.pb);
    qb = 0.5f * (t.pb + t.pc);
    qc = 0.5f * (t.pc + t.pa);
  }
}

#endif
