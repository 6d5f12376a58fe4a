// Trace explicit rays (origin, direction) through one lenslet to the sensor
// plane: the device side of the landing-point check against an independent
// optics library (tests/engine/test_lens_landing.cpp).
#version 460
#extension GL_GOOGLE_include_directive : require
#define PRISM_FN
#include "optics.glsl"

layout(local_size_x = 64) in;
layout(constant_id = 0) const int LENS_MODEL = LENS_REAL;

layout(push_constant) uniform Push {
  float lens_to_sensor_mm;
  uint ray_count;
};
layout(std430, binding = 0) readonly buffer Lenses { Lenslet lens; };
layout(std430, binding = 1) readonly buffer Rays { vec4 rays[]; };  // origin, direction pairs
layout(std430, binding = 2) writeonly buffer Hits { vec4 hits[]; };  // (x, y, ok, 0)

void main() {
  uint i = gl_GlobalInvocationID.x;
  if (i >= ray_count) return;
  Ray ray = Ray(dv_const(rays[2u * i].xyz), dv_const(rays[2u * i + 1u].xyz), d_const(1.0f));
  LensShape g = lens_shape(lens, vec3(0.0f), vec3(0.0f), vec3(0.0f));
  Dual to_sensor = d_const(lens_to_sensor_mm);
  Hit hit = (LENS_MODEL == LENS_REAL) ? trace_real(ray, g, 0.0f, to_sensor, true) : trace_thin(ray, g, 0.0f, to_sensor, true);
  hits[i] = vec4(hit.x_mm.v, hit.y_mm.v, hit.ok ? 1.0f : 0.0f, 0.0f);
}
