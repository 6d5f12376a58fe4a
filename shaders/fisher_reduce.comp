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
layout(constant_id = 0) const int ESTIMATOR = FISHER_SPLIT;

layout(push_constant) uniform Push {
  uint pixels;        // pixels per image (this band)
  uint chunks;        // workgroups per image = ceil(pixels / CHUNK)
  float dark_counts;  // expected background counts per pixel
};
layout(std430, binding = 0) readonly buffer Images { vec4 images[]; };  // 2 per pixel (psf_splat.comp)
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
    vec4 lo = images[2u * (uint(s) * pixels + i)];
    vec4 hi = images[2u * (uint(s) * pixels + i) + 1u];
    vec3 ga = vec3(lo.y, lo.z, lo.w);
    vec3 gb = vec3(hi.x, hi.y, hi.z);
    acc[0] += lo.x;
    FisherTerms p = fisher_terms(lo.x, ga, gb, dark_counts, false, ESTIMATOR);
    FisherTerms b = fisher_terms(lo.x, ga, gb, dark_counts, true, ESTIMATOR);
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
