// Footprint splatting, the cut pass: triangles and split pieces some of
// whose corners' rays an aperture or total internal reflection stops (from
// psf_footprint.comp and psf_footprint_split.comp). The part that passes is
// found by bisection and rasterised (footprint_pieces.glsl); a part still
// large is listed as tiles for psf_footprint_large.comp. One invocation per
// entry.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_shader_atomic_float : require
#define PRISM_FN
#include "footprint_pieces.glsl"

layout(local_size_x = 64) in;

void main() {
  uint total = min(cut_count, cut_capacity);
  uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
  for (uint e = gl_GlobalInvocationID.x; e < total; e += stride) {
    Piece t;
    CellSource from;
    Lenslet lens;
    uint image_base, half_offset;
    float blur_half_px;
    listed_piece(cuts[e], t, from, lens, image_base, half_offset, blur_half_px);
    int passed = int(t.a.ok) + int(t.b.ok) + int(t.c.ok);
    if (passed == 0 || passed == 3) continue;
    rasterise_cut(image_base, from, lens, t.a, t.b, t.c, t.pa, t.pb, t.pc, t.area_mm2, blur_half_px, half_offset, cuts[e]);
  }
}
