// Footprint splatting, the split pass: the triangles psf_footprint.comp
// leaves in its split list, large ones (split, footprint.glsl) and those over
// a partial last column or row at the sensor's far edge (clipped to it,
// footprint_pieces.glsl). One invocation per entry; a large triangle has an
// entry for each piece it may split into (SPLIT_ENTRIES), so that one
// invocation's work stays bounded. A piece with stopped corners goes on to
// the cut list (psf_footprint_cut.comp).
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_shader_atomic_float : require
#define PRISM_FN
#include "footprint_pieces.glsl"

layout(local_size_x = 64) in;

void main() {
  uint total = min(split_count, split_capacity);
  uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
  for (uint e = gl_GlobalInvocationID.x; e < total; e += stride) {
    Piece t;
    vec3 from;
    Lenslet lens;
    uint image_base, half_offset;
    float blur_px;
    if (!listed_piece(splits[e], t, from, lens, image_base, half_offset, blur_px)) continue;
    int passed = int(t.a.ok) + int(t.b.ok) + int(t.c.ok);
    if (passed == 0) continue;
    if (passed < 3) {
      uint at = atomicAdd(cut_count, 1u);
      if (at < cut_capacity) cuts[at] = splits[e];
      continue;
    }
    // (Still large after the last split: at its centroid, in rasterise_clipped.)
    rasterise_clipped(image_base, t.a, t.b, t.c, d_scale(d_add(d_add(t.a.w, t.b.w), t.c.w), t.area_mm2 / 3.0f),
                      blur_px, half_offset);
  }
}
