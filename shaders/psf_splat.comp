// Trace every aperture sample of every lenslet from a batch of sources and
// splat the hits, with their derivatives, into one (b, db/dx, db/dy, db/ddepth)
// image per source. Grid x: rays (strided), grid y: sources in this dispatch.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_shader_atomic_float : require
#define PRISM_FN
#include "splat_image.glsl"

layout(local_size_x = 64) in;

void add_tap(uint image_base, ivec2 px, vec4 tap, uint half_offset) {
  deposit(image_base, px.x, px.y, Dual(tap.x, tap.yzw), half_offset);
}

void main() {
  uint s = gl_GlobalInvocationID.y;
  if (s >= P.source_count) return;
  DesignRange design = designs[source_design[P.source_offset + s]];
  uint total = design.total_rays;
  vec3 theta = sources[P.source_offset + s].xyz;
  uint image_base = s * uint(P.grid_w) * uint(P.band_rows) * PIXEL_FLOATS;
  uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
  // This pass's rays (the host takes one lenslet's alone for calibration).
  uint end = min(total, P.cell_first + P.cell_count);
  for (uint r = P.cell_first + gl_GlobalInvocationID.x; r < end; r += stride) {
    uint lens_index = lens_of(design, r);
    uint sample_index = r - lenses[lens_index].first_ray;
    // Hash by the lens's index within its design: a design traces the same
    // rays batched with others as alone.
    Hit hit = trace_sample(theta, lenses[lens_index], lens_index - design.first_lens, sample_index, P, LENS_MODEL,
                           SCINT_REFRACTION, HOLDER, SOURCE_EXTENT, AS_BUILT);
    uint half_offset = 1u + 3u * ray_half(sample_index, lenses[lens_index].strata);
#if PRISM_BLUR
    // Effect diffraction: the ray's light blurred by its lenslet's Airy
    // square over box pixels (blur.glsl; the sensor's far edges bound it).
    if (!hit.ok) continue;
    float inv_px = 1.0f / P.pixel_mm;
    Dual u = d_scale(d_addc(hit.x_mm, P.sensor_half_w_mm), inv_px);
    Dual v = d_scale(d_addc(hit.y_mm, P.sensor_half_h_mm), inv_px);
    deposit_blurred_point(image_base, u, v, airy_half_side_px(lenses[lens_index]), hit.weight, half_offset);
    continue;
#endif
    Splat sp = splat_bilinear(hit, P);
    if (!sp.ok) continue;
    add_tap(image_base, sp.base, sp.tap00, half_offset);
    add_tap(image_base, sp.base + ivec2(1, 0), sp.tap10, half_offset);
    add_tap(image_base, sp.base + ivec2(0, 1), sp.tap01, half_offset);
    add_tap(image_base, sp.base + ivec2(1, 1), sp.tap11, half_offset);
  }
}
