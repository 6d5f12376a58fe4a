// Trace every aperture sample of every lenslet from a batch of sources and
// splat the hits, with their derivatives, into one (b, db/dx, db/dy, db/ddepth)
// image per source. Grid x: rays (strided), grid y: sources in this dispatch.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_shader_atomic_float : require
#define PRISM_FN
#include "optics.glsl"

layout(local_size_x = 64) in;

// Effects are compile-time: a scene that does not name one compiles it out.
layout(constant_id = 0) const int LENS_MODEL = LENS_THIN;
layout(constant_id = 1) const bool SCINT_REFRACTION = false;
layout(constant_id = 2) const bool HOLDER = false;
// Without derivatives a pixel is just b (dictionary synthesis, event simulation).
layout(constant_id = 3) const bool DERIVATIVES = true;
layout(constant_id = 4) const bool SOURCE_EXTENT = false;
const uint PIXEL_FLOATS = DERIVATIVES ? 8u : 1u;

layout(push_constant) uniform Push { TraceParams P; };
layout(std430, binding = 0) readonly buffer Lenses { Lenslet lenses[]; };
layout(std430, binding = 1) readonly buffer Sources { vec4 sources[]; };  // xyz = (x, y, depth) mm
// Per pixel 8 floats: b, grad b from ray half A (x2), grad b from half B (x2), unused;
// or b alone without DERIVATIVES.
layout(std430, binding = 2) buffer Images { float images[]; };  // [source][row][col][PIXEL_FLOATS]
layout(std430, binding = 3) readonly buffer SourceDesigns { uint source_design[]; };  // design of each source
layout(std430, binding = 4) readonly buffer Designs { DesignRange designs[]; };

void add_tap(uint image_base, ivec2 px, vec4 tap, uint half_offset) {
  int row = px.y - P.band_row0;
  if (px.x < 0 || px.x >= P.grid_w || row < 0 || row >= P.band_rows || px.y >= P.grid_h) return;
  uint i = image_base + PIXEL_FLOATS * (uint(row) * uint(P.grid_w) + uint(px.x));
  atomicAdd(images[i], tap.x);
  if (!DERIVATIVES) return;
  // Each half estimates the whole gradient: its rays count double.
  atomicAdd(images[i + half_offset], 2.0f * tap.y);
  atomicAdd(images[i + half_offset + 1u], 2.0f * tap.z);
  atomicAdd(images[i + half_offset + 2u], 2.0f * tap.w);
}

// The lenslet of design d that ray r belongs to: the last whose first_ray <= r.
uint lens_of_ray(DesignRange d, uint r) {
  uint lo = d.first_lens;
  uint hi = d.first_lens + d.lens_count - 1u;
  while (lo < hi) {
    uint mid = (lo + hi + 1u) / 2u;
    if (lenses[mid].first_ray <= r) lo = mid;
    else hi = mid - 1u;
  }
  return lo;
}

void main() {
  uint s = gl_GlobalInvocationID.y;
  if (s >= P.source_count) return;
  DesignRange design = designs[source_design[P.source_offset + s]];
  uint total = design.total_rays;
  vec3 theta = sources[P.source_offset + s].xyz;
  uint image_base = s * uint(P.grid_w) * uint(P.band_rows) * PIXEL_FLOATS;
  uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
  for (uint r = gl_GlobalInvocationID.x; r < total; r += stride) {
    uint lens_index = lens_of_ray(design, r);
    uint sample_index = r - lenses[lens_index].first_ray;
    // Hash by the lens's index within its design: a design traces the same
    // rays batched with others as alone.
    Hit hit = trace_sample(theta, lenses[lens_index], lens_index - design.first_lens, sample_index, P, LENS_MODEL,
                           SCINT_REFRACTION, HOLDER, SOURCE_EXTENT);
    Splat sp = splat_bilinear(hit, P);
    if (!sp.ok) continue;
    uint half_offset = 1u + 3u * ray_half(sample_index, lenses[lens_index].strata);
    add_tap(image_base, sp.base, sp.tap00, half_offset);
    add_tap(image_base, sp.base + ivec2(1, 0), sp.tap10, half_offset);
    add_tap(image_base, sp.base + ivec2(0, 1), sp.tap01, half_offset);
    add_tap(image_base, sp.base + ivec2(1, 1), sp.tap11, half_offset);
  }
}
