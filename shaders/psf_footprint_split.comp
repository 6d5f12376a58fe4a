// Footprint splatting, the split pass, one level of the split per dispatch:
// the pieces psf_footprint.comp (level 0) or the previous level left in the
// split list, entries [split_first, split_end). A large piece is split in
// four (footprint.glsl); each child still large goes back on the list for
// the next level, the others are given to the pixels here. So only pieces
// that exist are traced, and one invocation rasterises at most four, which
// keeps its loops short (lavapipe ends a shader's loops, silently, after
// 65535 iterations in all per batch of invocations). Pieces over the
// sensor's far edge are clipped to it (footprint_pieces.glsl); a piece with
// stopped corners goes on to the cut list (psf_footprint_cut.comp); one still
// large after the last split is listed as tiles for psf_footprint_large.comp.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_shader_atomic_float : require
#define PRISM_FN
#include "footprint_pieces.glsl"
layout(local_size_x = 64) in;

// A piece not split further: clipped and rasterised, or listed for the cut
// pass when some of its corners' rays are stopped.
void give_piece(uvec4 entry, Piece t, uint image_base, float blur_half_px, uint half_offset) {
  int passed = int(t.a.ok) + int(t.b.ok) + int(t.c.ok);
  if (passed == 0) return;
  if (passed < 3) {
    uint at = atomicAdd(cut_count, 1u);
    if (at < cut_capacity) cuts[at] = entry;
    return;
  }
  // (Still large after the last split: its tiles listed for the large pass, in rasterise_clipped.)
  rasterise_clipped(image_base, t.a, t.b, t.c, d_scale(d_add(d_add(t.a.w, t.b.w), t.c.w), t.area_mm2 / 3.0f),
                    blur_half_px, half_offset, entry, 0u);
}

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
    uint depth = piece_depth(entry.w);
    // A piece not split (listed for the far edge only) is given as it is;
    // one split gives four children. One give_piece call site for both (why:
    // shaders/CMakeLists.txt).
    bool whole = !is_split(t, int(depth));
    Corner ab = t.a, bc = t.b, ca = t.c;
    if (!whole) trace_three(from, lens, 0.5f * (t.pa + t.pb), 0.5f * (t.pb + t.pc), 0.5f * (t.pc + t.pa), ab, bc, ca);
    uint tri = piece_triangle(entry.w);
    uint path = piece_path(entry.w);
    for (uint k = 0u; k < (whole ? 1u : 4u); ++k) {
      Piece child = whole ? t : child_piece(t, ab, bc, ca, k);
      uvec4 child_entry = whole ? entry : uvec4(entry.xyz, piece_code(tri, path | (k << (2u * depth)), depth + 1u));
      if (!whole && is_split(child, int(depth) + 1)) {
        if (child.a.ok && child.b.ok && child.c.ok && !triangle_reaches_mask(child.a, child.b, child.c, blur_half_px, true))
          continue;  // a masked render's other tiles
        uint at = atomicAdd(split_count, 1u);
        if (at < split_capacity) splits[at] = child_entry;
      } else {
        give_piece(child_entry, child, image_base, blur_half_px, half_offset);
      }
    }
  }
}
