// Footprint splatting, the large pass: the pieces still large after the
// split's last level (from psf_footprint_split.comp and, for the parts an
// aperture cut passes, psf_footprint_cut.comp), one tile of LARGE_TILE_PX x
// LARGE_TILE_PX grid pixels per entry (footprint_raster.glsl): the piece is
// traced again from its entry, cut again where it is a cut's part, and
// rasterised exactly within the tile. Entries [split_first, split_end) of
// the split list.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_shader_atomic_float : require
#define PRISM_FN
#include "footprint_pieces.glsl"

layout(local_size_x = 64) in;

void main() {
  uint end = min(P.split_end, split_capacity);
  uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
  for (uint e = P.split_first + gl_GlobalInvocationID.x; e < end; e += stride) {
    uvec4 entry = splits[e];
    Piece t;
    CellSource from;
    Lenslet lens;
    uint image_base, half_offset;
    float blur_half_px;
    listed_piece(entry, t, from, lens, image_base, half_offset, blur_half_px);
    uint part = entry_part(entry);
    Corner a = t.a, b = t.b, c = t.c;
    float area_mm2 = t.area_mm2;
    if (part > 0u) {
      uint parts;
      if (!cut_part(from, lens, t.a, t.b, t.c, t.pa, t.pb, t.pc, t.area_mm2, int(part) - 1, parts, a, b, c, area_mm2))
        continue;
    }
    rasterise_clipped(image_base, a, b, c, d_scale(d_add(d_add(a.w, b.w), c.w), area_mm2 / 3.0f), blur_half_px,
                      half_offset, entry, part);
  }
}
