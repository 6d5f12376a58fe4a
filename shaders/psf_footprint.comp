// Footprint splatting, the common path (shaders/common/footprint.glsl): one
// invocation per aperture cell traces the cell's four corners and gives each
// of its two triangles' light to the pixels by exact area (footprint_raster.glsl).
// Large triangles (split further, footprint.glsl) and those over a partial
// last pixel at the sensor's far edge go to the split list for
// psf_footprint_split.comp, triangles an aperture or total internal
// reflection cuts to the cut list for psf_footprint_cut.comp: rare, and on
// lavapipe every branch of a kernel is paid by every invocation, so each
// kind has a kernel of its own.
// Grid x: cells (strided), grid y: sources in this dispatch.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_shader_atomic_float : require
#define PRISM_FN
#include "footprint_raster.glsl"

layout(local_size_x = 64) in;

void main() {
  uint s = gl_GlobalInvocationID.y;
  if (s >= P.source_count) return;
  DesignRange design = designs[source_design[P.source_offset + s]];
  vec3 theta = sources[P.source_offset + s].xyz;
  uint image_base = s * uint(P.grid_w) * uint(P.band_rows) * PIXEL_FLOATS;
  uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
  float u_max = sensor_u_max();
  float v_max = sensor_v_max();
  // This pass's chunk of the cells (the host splits them when the lists would
  // outgrow a buffer).
  uint end = min(design.total_rays, P.cell_first + P.cell_count);
  for (uint r = P.cell_first + gl_GlobalInvocationID.x; r < end; r += stride) {
    uint lens_index = lens_of(design, r);
    Lenslet lens = lenses[lens_index];
    uint in_design = lens_index - design.first_lens;  // hashes by the index within the design
    uint cell = r - lens.first_ray;
    uint n = lens.strata;
    uint i = cell % n;
    uint j = cell / n;
    float turn = strata_turn(in_design, P.stratification);
    CellSource from = cell_source(theta, in_design, cell);
    // The cell's corners (i + c % 2, j + c / 2), from one call site in a loop
    // (why: shaders/CMakeLists.txt).
    Corner k[4];
    for (uint c = 0u; c < 4u; ++c) k[c] = trace_corner(from, lens, aperture_corner(i + (c & 1u), j + (c >> 1u), n, turn));
    float half_area = half_cell_area_mm2(lens.radius_mm, n);
    uint half_offset = 1u + 3u * ((i + j) & 1u);  // checkerboard halves, as ray_half
    float blur_half_px = DIFFRACTION ? airy_half_side_px(lens) : 0.0f;
    for (uint t = 0u; t < 2u; ++t) {
      CellTriangle tri = cell_triangle(i, j, n, t);
      Corner a = k[tri.ab.x + 2u * tri.ab.y];
      Corner b = k[tri.ab.z + 2u * tri.ab.w];
      Corner c = k[tri.c.x + 2u * tri.c.y];
      float u_hi = max(max(a.u.v, b.u.v), c.u.v);
      float v_hi = max(max(a.v.v, b.v.v), c.v.v);
      float u_lo = min(min(a.u.v, b.u.v), c.u.v);
      float v_lo = min(min(a.v.v, b.v.v), c.v.v);
      bool cut = !(a.ok && b.ok && c.ok);
      // Off the sensor, or off this band's rows (a large sensor is done in
      // bands), by more than a blur reaches.
      float reach = DIFFRACTION ? blur_half_px : 0.0f;
      float band_lo = float(P.band_row0);
      float band_hi = float(min(P.band_row0 + P.band_rows, P.grid_h));
      bool off = a.ok && b.ok && c.ok &&
                 (u_lo >= u_max + reach || v_lo >= v_max + reach || u_hi <= -reach || v_hi <= -reach ||
                  v_hi <= band_lo - reach || v_lo >= band_hi + reach);
      // Over a partial last column or row: the far edge cuts it.
      bool edge = !DIFFRACTION &&
                  ((u_hi > u_max && u_max < float(P.grid_w)) || (v_hi > v_max && v_max < float(P.grid_h)));
      bool large = max(u_hi - u_lo, v_hi - v_lo) > LARGE_TRIANGLE_PX;
      if (!(a.ok || b.ok || c.ok) || off) continue;
      // (A masked render skips what reaches none of its tiles: tested here
      // where the piece is whole, before the split or the raster.)
      if (!cut && !triangle_reaches_mask(a, b, c, blur_half_px, large)) continue;
      if (large || edge) {
        uint at = atomicAdd(split_count, 1u);
        if (at < split_capacity) splits[at] = uvec4(s, lens_index, cell, piece_code(t, 0u, 0u));
        continue;
      }
      if (cut) {
        uint at = atomicAdd(cut_count, 1u);
        if (at < cut_capacity) cuts[at] = uvec4(s, lens_index, cell, piece_code(t, 0u, 0u));
        continue;
      }
      Dual w = d_scale(d_add(d_add(a.w, b.w), c.w), half_area / 3.0f);
      rasterise_triangle(image_base, a, b, c, w, blur_half_px, half_offset);
    }
  }
}
