// Forward-mode dual numbers: a value and its gradient with respect to the
// source position theta = (x, y, depth), or with respect to three scene
// parameters in the calibrate kernels (optics.glsl). Written in the GLSL
// subset that also compiles as C++ with GLM (no operator overloading, no
// swizzles, float literals with an f suffix, structs returned by value), so
// the CPU side can run the very same functions (see engine/shared_math.h).
#ifndef PRISM_DUAL_GLSL
#define PRISM_DUAL_GLSL

struct Dual {
  float v;  // value
  vec3 d;   // d(value)/d(x, y, depth), or d/d(the three scene parameters)
};

PRISM_FN Dual d_const(float v) { return Dual(v, vec3(0.0f)); }
PRISM_FN Dual d_add(Dual a, Dual b) { return Dual(a.v + b.v, a.d + b.d); }
PRISM_FN Dual d_sub(Dual a, Dual b) { return Dual(a.v - b.v, a.d - b.d); }
PRISM_FN Dual d_addc(Dual a, float c) { return Dual(a.v + c, a.d); }
PRISM_FN Dual d_scale(Dual a, float c) { return Dual(a.v * c, a.d * c); }
PRISM_FN Dual d_neg(Dual a) { return Dual(-a.v, -a.d); }
PRISM_FN Dual d_mul(Dual a, Dual b) { return Dual(a.v * b.v, a.d * b.v + b.d * a.v); }
PRISM_FN Dual d_div(Dual a, Dual b) {
  float inv = 1.0f / b.v;
  return Dual(a.v * inv, (a.d - b.d * (a.v * inv)) * inv);
}
PRISM_FN Dual d_sqrt(Dual a) {
  float s = sqrt(a.v);
  // The derivative of sqrt at 0 is infinite; callers only take square roots
  // of quantities bounded away from zero (lengths, cosines of refracted rays).
  return Dual(s, a.d * (0.5f / s));
}
PRISM_FN Dual d_sin(Dual a) { return Dual(sin(a.v), a.d * cos(a.v)); }
PRISM_FN Dual d_cos(Dual a) { return Dual(cos(a.v), a.d * -sin(a.v)); }

// A point or direction whose components are duals.
struct DVec3 {
  Dual x;
  Dual y;
  Dual z;
};

PRISM_FN DVec3 dv_const(vec3 v) { return DVec3(d_const(v.x), d_const(v.y), d_const(v.z)); }
PRISM_FN DVec3 dv_add(DVec3 a, DVec3 b) { return DVec3(d_add(a.x, b.x), d_add(a.y, b.y), d_add(a.z, b.z)); }
PRISM_FN DVec3 dv_sub(DVec3 a, DVec3 b) { return DVec3(d_sub(a.x, b.x), d_sub(a.y, b.y), d_sub(a.z, b.z)); }
PRISM_FN DVec3 dv_scale(DVec3 a, Dual s) { return DVec3(d_mul(a.x, s), d_mul(a.y, s), d_mul(a.z, s)); }
PRISM_FN DVec3 dv_scalec(DVec3 a, float s) { return DVec3(d_scale(a.x, s), d_scale(a.y, s), d_scale(a.z, s)); }
PRISM_FN Dual dv_dot(DVec3 a, DVec3 b) { return d_add(d_add(d_mul(a.x, b.x), d_mul(a.y, b.y)), d_mul(a.z, b.z)); }
PRISM_FN DVec3 dv_normalize(DVec3 a) { return dv_scale(a, d_div(d_const(1.0f), d_sqrt(dv_dot(a, a)))); }
PRISM_FN vec3 dv_value(DVec3 a) { return vec3(a.x.v, a.y.v, a.z.v); }

#endif
