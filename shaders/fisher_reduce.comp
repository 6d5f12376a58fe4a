// Reduce per-source (b, grad b) images to partial sums of photons and of the
// Fisher matrix (Poisson and binary sensor). Each workgroup sums one chunk of
// CHUNK pixels in float with a tree in shared memory; the host adds the chunks
// in double, so no float sum ever runs over millions of pixels.
#version 460
#extension GL_GOOGLE_include_directive : require
#define PRISM_FN
#include "optics.glsl"

const uint GROUP = 256u;
const uint CHUNK = GROUP * 16u;
const uint SUMS = 13u;  // photons, Poisson xx..zz (6), binary xx..zz (6)
layout(local_size_x = 256) in;

layout(push_constant) uniform Push {
  uint pixels;        // pixels per image (this band)
  uint chunks;        // workgroups per image = ceil(pixels / CHUNK)
  float dark_counts;  // expected background counts per pixel
};
layout(std430, binding = 0) readonly buffer Images { vec4 images[]; };
layout(std430, binding = 1) writeonly buffer Partials { float partials[]; };  // [source][chunk][16]

shared float sums[SUMS][GROUP];

void main() {
  uint lid = gl_LocalInvocationID.x;
  uint chunk = gl_WorkGroupID.x;
  uint s = gl_WorkGroupID.y;
  float acc[SUMS];
  for (uint k = 0u; k < SUMS; ++k) acc[k] = 0.0f;
  uint first = chunk * CHUNK;
  uint last = min(first + CHUNK, pixels);
  for (uint i = first + lid; i < last; i += GROUP) {
    vec4 px = images[uint(s) * pixels + i];
    acc[0] += px.x;
    FisherTerms p = fisher_terms(px, dark_counts, false);
    FisherTerms b = fisher_terms(px, dark_counts, true);
    acc[1] += p.xx; acc[2] += p.xy; acc[3] += p.xz; acc[4] += p.yy; acc[5] += p.yz; acc[6] += p.zz;
    acc[7] += b.xx; acc[8] += b.xy; acc[9] += b.xz; acc[10] += b.yy; acc[11] += b.yz; acc[12] += b.zz;
  }
  for (uint k = 0u; k < SUMS; ++k) sums[k][lid] = acc[k];
  barrier();
  for (uint half_n = GROUP / 2u; half_n > 0u; half_n /= 2u) {
    if (lid < half_n)
      for (uint k = 0u; k < SUMS; ++k) sums[k][lid] += sums[k][lid + half_n];
    barrier();
  }
  if (lid < SUMS) partials[(s * chunks + chunk) * 16u + lid] = sums[lid][0];
}
