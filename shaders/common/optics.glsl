// Device math of the forward model: ray emission through a lenslet aperture,
// refraction (ideal thin lens or real plano-convex lens), optional effects,
// transport to the sensor, bilinear splatting and per-pixel Fisher terms.
//
// Coordinates (millimetres): z along the optical axis; the lens plane is z = 0,
// the sensor is at z = lens_to_sensor_mm, the scintillator face at
// z = -working_distance_mm. A source theta = (x, y, depth) sits at
// (x, y, -(depth + working_distance_mm)). Every dual carries d/d(x, y, depth),
// or in the calibrate kernels d/d(three scene parameters) (seed below).
//
// Same GLSL/C++ subset as dual.glsl. Layouts are std430 and checked by
// static_assert on the C++ side (engine/shared_math.h).
#ifndef PRISM_OPTICS_GLSL
#define PRISM_OPTICS_GLSL

#include "dual.glsl"

// The as-built path (tilted lenslets, a moved sensor) is compiled only into
// the splat kernels' as-built variants (PRISM_AS_BUILT=1, shaders/CMakeLists.txt)
// and into the C++ side (engine/shared_math.h, where a bool chooses it): in a
// nominal kernel, dead as it is there, it still cost lavapipe's JIT a third more.
#ifndef PRISM_AS_BUILT
#define PRISM_AS_BUILT 1
#endif
// Calibration (issue 18): the splat kernels' calibrate variants
// (PRISM_CALIBRATE=1, always with the as-built path) take the duals' three
// slots with respect to the scene parameters the push constants name
// (TraceParams.tangent0..2) instead of the source position. Elsewhere the
// scene's parameters enter as duals of constant zero gradient, which the
// compiler folds away.
#ifndef PRISM_CALIBRATE
#define PRISM_CALIBRATE 0
#endif

const int LENS_THIN = 0;  // ideal thin lens: paraxial deflection by -h/f
const int LENS_REAL = 1;  // plano-convex: spherical front face, flat back face

// One lenslet as the kernels see it (std430, 56 bytes).
struct Lenslet {
  vec2 center_mm;             // lateral centre on the lens plane
  float radius_mm;            // clear aperture radius of both faces
  float focal_mm;             // focal length (thin model)
  float curvature_radius_mm;  // R of the front face, R = f (n - 1) (real model)
  float thickness_mm;         // centre thickness (real model)
  float sag_mm;               // front-face sag at the rim (real model)
  float glass_index;          // refractive index of the glass (real model)
  int curved_toward_sensor;   // real model: 0 = curved face toward the source, 1 = flipped
  uint strata;                // aperture samples = strata^2 (equal density over lens sizes)
  uint first_ray;             // index of its first ray (or footprint cell) among its design's
  float tilt_x_rad;           // as built: turned about its centre, about x, then
  float tilt_y_rad;           //   about y (tilt_matrix; traced with AS_BUILT only)
  uint index;                 // its index within its design (calibration's slots name lenslets by it)
};

// One optical design's lenslets within the lens buffer (std430, 16 bytes):
// a dispatch may trace several designs that share sensor, distances and effects.
struct DesignRange {
  uint first_lens;  // index of its first lenslet in the lens buffer
  uint lens_count;
  uint total_rays;  // rays (or footprint cells) per source through all its lenslets
  uint pad_;
};

// Per-dispatch constants (push constants, std430, 120 bytes).
struct TraceParams {
  float pixel_mm;             // analysis pixel pitch (sensor pixel x binning)
  float sensor_half_w_mm;     // half the physical sensor width (x)
  float sensor_half_h_mm;     // half the physical sensor height (y)
  float lens_to_sensor_mm;    // lens plane to sensor plane
  float working_distance_mm;  // lens plane to scintillator face
  float photons_per_sr;       // emitted / (4 pi) * detection efficiency
  float scint_index;          // effect: refractive index of the scintillator
  float holder_bore_mm;       // effect: holder bore length behind the lens plane
  int grid_w;                 // analysis grid width in pixels
  int grid_h;                 // analysis grid height in pixels
  int band_row0;              // first grid row this pass keeps
  int band_rows;              // rows this pass keeps (chunking of large sensors)
  uint lens_count;            // lenslets in the lens buffer (all designs)
  uint total_rays;            // rays per source of the design with the most
  uint source_offset;         // first source of this dispatch
  uint source_count;          // sources in this dispatch
  float source_sigma_mm;      // effect: Gaussian extent of the source (per axis)
  uint stratification;        // 0: the default strata; another value: other jitter (point) and cells turned (footprint)
  float airy_half_side_mm_times_diameter;  // effect diffraction: half side of a lenslet's Airy square times its diameter (mm^2)
  uint cell_first;            // footprint: the cells of this pass, [cell_first, cell_first + cell_count)
  uint cell_count;
  uint split_first;           // footprint split pass: its level's list entries, [split_first, split_end)
  uint split_end;
  float sensor_offset_x_mm;   // as built (AS_BUILT only): the sensor's centre moved within its plane,
  float sensor_offset_y_mm;
  float sensor_tilt_x_rad;    //   and the sensor turned about it (tilt_matrix)
  float sensor_tilt_y_rad;
  uint tangent0;              // calibrate variants: what each dual slot differentiates by,
  uint tangent1;              //   PARAM_* | (lenslet index + 1) << 8, lenslet 0 for every
  uint tangent2;              //   lenslet's own (tangent_code, engine/shared_math.h)
  uint mask_tiles_w;          // footprint: tiles per row of the tile mask (TileMask), 0: every pixel
};

// What a dual slot can differentiate by: engine/optical_system.h's
// SceneParam, in its order. Units: mm, and degrees for tilts.
const uint PARAM_SOURCE_X = 0u;
const uint PARAM_SOURCE_Y = 1u;
const uint PARAM_SOURCE_DEPTH = 2u;
const uint PARAM_LENS_X = 3u;
const uint PARAM_LENS_Y = 4u;
const uint PARAM_LENS_FOCAL = 5u;
const uint PARAM_LENS_TILT_X = 6u;
const uint PARAM_LENS_TILT_Y = 7u;
const uint PARAM_LENS_TO_SENSOR = 8u;
const uint PARAM_WORKING_DISTANCE = 9u;
const uint PARAM_SENSOR_OFFSET_X = 10u;
const uint PARAM_SENSOR_OFFSET_Y = 11u;
const uint PARAM_SENSOR_TILT_X = 12u;
const uint PARAM_SENSOR_TILT_Y = 13u;
const uint PARAM_SOURCE_SIGMA = 14u;  // effect source_extent's sigma

// 1 when slot code `slot` names parameter `param` of lenslet `lens` (a
// lenslet's parameter: its own or every lenslet's; a global one: any).
PRISM_FN float slot_seed(uint slot, uint param, uint lens) {
  bool lens_param = param >= PARAM_LENS_X && param <= PARAM_LENS_TILT_Y;
  uint named = slot >> 8u;
  return ((slot & 255u) == param && (!lens_param || named == 0u || named == lens + 1u)) ? 1.0f : 0.0f;
}

// The gradient a parameter starts with in the three slots: the source's
// position in the plain kernels (constant, so the rest folds away), the
// push constants' choice in the calibrate ones.
PRISM_FN vec3 seed(uint param, uint lens, TraceParams P) {
#if PRISM_CALIBRATE
  return vec3(slot_seed(P.tangent0, param, lens), slot_seed(P.tangent1, param, lens), slot_seed(P.tangent2, param, lens));
#else
  return vec3(param == PARAM_SOURCE_X ? 1.0f : 0.0f, param == PARAM_SOURCE_Y ? 1.0f : 0.0f,
              param == PARAM_SOURCE_DEPTH ? 1.0f : 0.0f);
#endif
}

const float RADIANS_PER_DEGREE = 0.0174532925199f;

// A lenslet's place and shape as duals: its centre and focal length, and
// what moves with the focal length (R = f (n - 1); the sag at the rim,
// R - sqrt(R^2 - a^2); the centre thickness, sag + edge). Values are the
// Lenslet's own.
struct LensShape {
  Dual cx;
  Dual cy;
  Dual focal;
  Dual R;          // curvature radius of the curved face
  Dual thickness;  // centre thickness
  Dual sag;        // sag at the rim
  float radius;    // clear aperture radius
  float n;         // glass index
  int curved_toward_sensor;
};

PRISM_FN LensShape lens_shape(Lenslet lens, vec3 d_cx, vec3 d_cy, vec3 d_focal) {
  float R = lens.curvature_radius_mm;
  vec3 dR = d_focal * (lens.glass_index - 1.0f);
  vec3 dsag = dR * (1.0f - R / sqrt(max(R * R - lens.radius_mm * lens.radius_mm, 1e-12f)));
  return LensShape(Dual(lens.center_mm.x, d_cx), Dual(lens.center_mm.y, d_cy), Dual(lens.focal_mm, d_focal),
                   Dual(R, dR), Dual(lens.thickness_mm, dsag), Dual(lens.sag_mm, dsag), lens.radius_mm,
                   lens.glass_index, lens.curved_toward_sensor);
}
// Lenslet `lens` with the slots' gradients of its position and focal length.
PRISM_FN LensShape seeded_shape(Lenslet lens, TraceParams P) {
  return lens_shape(lens, seed(PARAM_LENS_X, lens.index, P), seed(PARAM_LENS_Y, lens.index, P),
                    seed(PARAM_LENS_FOCAL, lens.index, P));
}
PRISM_FN vec2 shape_centre(LensShape g) { return vec2(g.cx.v, g.cy.v); }
// The lens's centre on the lens plane, the pivot of its tilt (as built: its
// own frame is the lens as designed turned about it, local -> world as
// c + m (p - c)).
PRISM_FN DVec3 lens_pivot(LensShape g) { return DVec3(g.cx, g.cy, d_const(0.0f)); }

// A ray on its way to the sensor, with the photons it carries.
struct Ray {
  DVec3 origin;
  DVec3 dir;     // not normalised
  Dual weight;   // expected photons carried
};

// Where a ray lands on the sensor plane, and with how many photons.
struct Hit {
  Dual x_mm;
  Dual y_mm;
  Dual weight;
  bool ok;  // false when an aperture, the holder or total internal reflection stops it
};

// ---------------------------------------------------------------------------
// Aperture sampling

// Integer hash (PCG output permutation); the stratum jitter is a fixed function
// of (lens, sample) so the CPU reference can reproduce every sample point.
PRISM_FN uint hash_u32(uint v) {
  uint state = v * 747796405u + 2891336453u;
  uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
  return (word >> 22u) ^ word;
}

PRISM_FN float hash_unit(uint v) { return float(hash_u32(v) >> 8u) * (1.0f / 16777216.0f); }

// Shirley-Chiu concentric map: area-preserving from [-1,1]^2 to the unit disk,
// so equal strata of the square carry equal aperture area.
PRISM_FN vec2 concentric_disk(float a, float b) {
  if (a == 0.0f && b == 0.0f) return vec2(0.0f);
  const float quarter_pi = 0.78539816339f;
  float r;
  float phi;
  if (abs(a) > abs(b)) {
    r = a;
    phi = quarter_pi * (b / a);
  } else {
    r = b;
    phi = 2.0f * quarter_pi - quarter_pi * (a / b);
  }
  return vec2(r * cos(phi), r * sin(phi));
}

// How far lenslet `lens`'s strata are turned about its centre under
// stratification `seed` (radians; 0 for the default seed 0).
PRISM_FN float strata_turn(uint lens, uint seed) {
  if (seed == 0u) return 0.0f;
  return 6.28318530718f * hash_unit(lens * 3266489917u ^ seed * 2246822519u ^ 0x68e31da4u);
}

// Point on the unit disk for jittered stratum `sample_index` of lenslet `lens`
// under stratification `seed` (another seed: other jitter, strata turned).
PRISM_FN vec2 aperture_sample(uint lens, uint sample_index, uint strata, uint seed) {
  uint i = sample_index % strata;
  uint j = sample_index / strata;
  uint key = lens * 2654435761u ^ sample_index * 2246822519u ^ seed * 0x2545f491u;
  float a = (float(i) + hash_unit(key)) / float(strata);
  float b = (float(j) + hash_unit(key ^ 0x9e3779b9u)) / float(strata);
  vec2 p = concentric_disk(2.0f * a - 1.0f, 2.0f * b - 1.0f);
  float turn = strata_turn(lens, seed);
  if (turn == 0.0f) return p;
  float c = cos(turn);
  float s = sin(turn);
  return vec2(c * p.x - s * p.y, s * p.x + c * p.y);
}

// Effect "source_extent": each ray leaves from the source centre plus a
// Gaussian offset (sigma per axis), a fixed function of (lens, sample) like the
// aperture point, so the PSF is the point PSF convolved with the source's
// extent and derivatives in theta stay exact. Box-Muller on the hash. The
// offset is linear in sigma: source_offset(.., 1, ..) is its derivative by
// sigma (the calibration's blur term).
PRISM_FN vec3 source_offset(uint lens, uint sample_index, float sigma_mm, uint seed) {
  uint key = lens * 3266489917u ^ sample_index * 668265263u ^ 0x5bd1e995u ^ seed * 0x9e3779b9u;
  float u1 = max(hash_unit(key), 1.0f / 16777216.0f);
  float u2 = hash_unit(key ^ 0x27d4eb2fu);
  float u3 = max(hash_unit(key ^ 0x165667b1u), 1.0f / 16777216.0f);
  float u4 = hash_unit(key ^ 0x85ebca6bu);
  const float two_pi = 6.28318530718f;
  float r1 = sqrt(-2.0f * log(u1));
  float r3 = sqrt(-2.0f * log(u3));
  return sigma_mm * vec3(r1 * cos(two_pi * u2), r1 * sin(two_pi * u2), r3 * cos(two_pi * u4));
}

// The source theta = (x, y, depth) as a point: (x, y, -(depth + wd)), its
// coordinates seeded as the slots say (the identity Jacobian by default).
// With source_extent the ray leaves from theta + sigma * per_sigma
// (per_sigma: the sample's source_offset at sigma 1; 0 without the effect),
// which moves with sigma by per_sigma.
PRISM_FN DVec3 source_point(vec3 theta, vec3 per_sigma, Dual working_distance_mm, uint lens, TraceParams P) {
  vec3 at = theta + P.source_sigma_mm * per_sigma;
  vec3 by_sigma = seed(PARAM_SOURCE_SIGMA, lens, P);
  return DVec3(Dual(at.x, seed(PARAM_SOURCE_X, lens, P) + per_sigma.x * by_sigma),
               Dual(at.y, seed(PARAM_SOURCE_Y, lens, P) + per_sigma.y * by_sigma),
               d_neg(d_add(Dual(at.z, seed(PARAM_SOURCE_DEPTH, lens, P) + per_sigma.z * by_sigma), working_distance_mm)));
}

// ---------------------------------------------------------------------------
// Emission: join the source to a fixed point of the lenslet's entrance disk.
// The disk does not move with theta, so the integration domain is fixed and the
// weight is smooth in theta: photons = (emitted / 4 pi) * cos / r^2 * dA. (The
// point moves with its lens's parameters; its place on the disk does not.)
// (Real lens: the disk is the rim plane z = sag, which every ray that meets the
// spherical cap crosses; thin lens: the lens plane z = 0.)

// Straight line from the source (no scintillator refraction).
PRISM_FN Ray emit_direct(DVec3 src, DVec3 p, float photons_per_sample) {
  DVec3 dir = dv_sub(p, src);
  Dual r2 = dv_dot(dir, dir);
  Dual r = d_sqrt(r2);
  Dual w = d_scale(d_div(dir.z, d_mul(r2, r)), photons_per_sample);  // cos/r^2 = dz/r^3
  return Ray(src, dir, w);
}

// Effect "scintillator_refraction": the source sits inside a medium of index n
// whose face is the plane z = -working_distance. The path source -> face point q
// -> aperture point p obeys Snell's law; q = s + k (p - s) laterally, where k
// solves F(k) = k + w n k / sqrt(h^2 - (n^2 - 1) k^2 u) - 1 = 0 (h: source depth
// below the face, w: face to aperture plane, u = |p - s|^2 laterally). F is
// increasing and convex, so Newton from the right converges monotonically; run
// on duals it also converges the implicit derivative dk/dtheta. The weight is
// emitted/(4 pi) * Fresnel T * cos_s/L^2 * dA_q/dA_p * dA_p.
PRISM_FN Ray emit_through_face(DVec3 src, DVec3 p, float photons_per_sample, float n, Dual face_z) {
  // A source on the face itself is moved 1 um inside: the limit is smooth but
  // the Newton iteration divides by h.
  Dual h = d_sub(face_z, src.z);
  if (h.v < 1e-3f) h = Dual(1e-3f, h.d);
  Dual w = d_sub(p.z, face_z);
  Dual wn = d_scale(w, n);
  Dual px = d_sub(p.x, src.x);
  Dual py = d_sub(p.y, src.y);
  Dual u = d_add(d_mul(px, px), d_mul(py, py));
  float nn1 = n * n - 1.0f;
  Dual wn_nn1 = d_scale(wn, nn1);
  Dual h2 = d_mul(h, h);

  // Start right of the root: the paraxial k, capped below the pole of F.
  Dual k = d_div(h, d_add(h, wn));
  if (u.v > 0.0f) {
    Dual k_pole = d_div(h, d_sqrt(d_scale(u, nn1)));
    if (k.v > 0.99f * k_pole.v) k = d_scale(k_pole, 0.99f);
  }
  for (int it = 0; it < 12; ++it) {
    Dual g = d_sub(h2, d_scale(d_mul(d_mul(k, k), u), nn1));
    Dual inv_sqrt_g = d_div(d_const(1.0f), d_sqrt(g));
    Dual f = d_addc(d_add(k, d_mul(d_mul(k, inv_sqrt_g), wn)), -1.0f);
    Dual inv_g32 = d_div(inv_sqrt_g, g);
    Dual fk = d_add(d_addc(d_mul(inv_sqrt_g, wn), 1.0f), d_mul(d_mul(d_mul(d_mul(k, k), u), inv_g32), wn_nn1));
    k = d_sub(k, d_div(f, fk));
  }

  // Jacobian of the lateral map q -> p (radial): dA_q/dA_p = k (k + p_r dk/dp_r).
  Dual k2 = d_mul(k, k);
  Dual g = d_sub(h2, d_scale(d_mul(k2, u), nn1));
  Dual inv_sqrt_g = d_div(d_const(1.0f), d_sqrt(g));
  Dual inv_g32 = d_div(inv_sqrt_g, g);
  Dual fk = d_add(d_addc(d_mul(inv_sqrt_g, wn), 1.0f), d_mul(d_mul(d_mul(k2, u), inv_g32), wn_nn1));
  Dual fu = d_mul(d_mul(d_mul(k2, k), inv_g32), d_scale(wn_nn1, 0.5f));
  Dual area_ratio = d_mul(k, d_sub(k, d_div(d_scale(d_mul(u, fu), 2.0f), fk)));

  // Solid angle per face area inside the scintillator, and Fresnel transmission
  // (unpolarised) from index n into air.
  Dual len2 = d_add(d_mul(k2, u), h2);
  Dual len = d_sqrt(len2);
  Dual cos_i = d_div(h, len);
  Dual sin_t2 = d_scale(d_sub(d_const(1.0f), d_mul(cos_i, cos_i)), n * n);
  Dual cos_t = d_sqrt(d_sub(d_const(1.0f), sin_t2));
  Dual ncos_i = d_scale(cos_i, n);
  Dual ncos_t = d_scale(cos_t, n);
  Dual rs = d_div(d_sub(ncos_i, cos_t), d_add(ncos_i, cos_t));
  Dual rp = d_div(d_sub(ncos_t, cos_i), d_add(ncos_t, cos_i));
  Dual transmit = d_sub(d_const(1.0f), d_scale(d_add(d_mul(rs, rs), d_mul(rp, rp)), 0.5f));

  Dual weight = d_mul(d_mul(transmit, d_div(h, d_mul(len2, len))), area_ratio);
  DVec3 q = DVec3(d_add(src.x, d_mul(k, px)), d_add(src.y, d_mul(k, py)), face_z);
  return Ray(q, dv_sub(p, q), d_scale(weight, photons_per_sample));
}

// ---------------------------------------------------------------------------
// Refraction and transport to the sensor

PRISM_FN bool inside_aperture(Dual x, Dual y, vec2 center, float radius) {
  float dx = x.v - center.x;
  float dy = y.v - center.y;
  return dx * dx + dy * dy <= radius * radius;
}

// Rays sampled on a lenslet's entrance disk are inside it by construction:
// re-testing them would only let float rounding at the rim clip a few.
// Explicit rays (landing_points.comp) are tested.

// Where the ray leaves the last surface, its direction, and whether it got there.
struct Exit {
  DVec3 p;
  DVec3 d;
  bool ok;
};

// Ideal thin lens in the plane z = 0: the slope turns by -h/f (paraxial).
// The ray leaves the lens plane with direction (slope x, slope y, 1).
PRISM_FN Exit thin_exit(Ray ray, LensShape g, float holder_bore_mm, bool test_entrance) {
  // Cross the lens plane.
  Dual t = d_div(d_neg(ray.origin.z), ray.dir.z);
  Dual x0 = d_add(ray.origin.x, d_mul(ray.dir.x, t));
  Dual y0 = d_add(ray.origin.y, d_mul(ray.dir.y, t));
  bool ok = !test_entrance || inside_aperture(x0, y0, shape_centre(g), g.radius);
  // Deflect.
  Dual inv_f = d_div(d_const(1.0f), g.focal);
  Dual sx = d_sub(d_div(ray.dir.x, ray.dir.z), d_mul(d_sub(x0, g.cx), inv_f));
  Dual sy = d_sub(d_div(ray.dir.y, ray.dir.z), d_mul(d_sub(y0, g.cy), inv_f));
  // Holder bore: the lens sits in a cylinder of its own radius that runs
  // holder_bore_mm toward the sensor; checking the far end suffices (convex).
  if (holder_bore_mm > 0.0f) {
    Dual bx = d_add(x0, d_scale(sx, holder_bore_mm));
    Dual by = d_add(y0, d_scale(sy, holder_bore_mm));
    ok = ok && inside_aperture(bx, by, shape_centre(g), g.radius);
  }
  return Exit(DVec3(x0, y0, d_const(0.0f)), DVec3(sx, sy, d_const(1.0f)), ok);
}

PRISM_FN Hit trace_thin(Ray ray, LensShape g, float holder_bore_mm, Dual lens_to_sensor_mm, bool test_entrance) {
  Exit e = thin_exit(ray, g, holder_bore_mm, test_entrance);
  return Hit(d_add(e.p.x, d_mul(e.d.x, lens_to_sensor_mm)), d_add(e.p.y, d_mul(e.d.y, lens_to_sensor_mm)),
             ray.weight, e.ok);
}

// Snell's law in vector form for unit direction i and unit normal n facing
// against it, index ratio eta = n_before / n_after. The z of the result is
// left at 0 on total internal reflection (callers test it).
PRISM_FN DVec3 refract_dual(DVec3 i, DVec3 n, float eta) {
  Dual cos_i = d_neg(dv_dot(n, i));
  Dual k = d_sub(d_const(1.0f), d_scale(d_sub(d_const(1.0f), d_mul(cos_i, cos_i)), eta * eta));
  if (k.v <= 0.0f) return DVec3(d_const(0.0f), d_const(0.0f), d_const(0.0f));
  return dv_add(dv_scalec(i, eta), dv_scale(n, d_sub(d_scale(cos_i, eta), d_sqrt(k))));
}

// Distance along unit direction d from o to the sphere (centre c, radius r):
// the near root when `far` is false. The discriminant is formed as
// r^2 - |oc - b d|^2 rather than b^2 - (|oc|^2 - r^2): the latter loses all
// float digits when the origin is tens of millimetres away (|oc|^2 ~ 2000
// against r^2 ~ 5). Returns a negative value on a miss.
PRISM_FN Dual sphere_distance(DVec3 o, DVec3 d, DVec3 c, Dual r, bool far) {
  DVec3 oc = dv_sub(o, c);
  Dual b = dv_dot(oc, d);
  DVec3 perp = dv_sub(oc, dv_scale(d, b));
  Dual disc = d_sub(d_mul(r, r), dv_dot(perp, perp));
  if (disc.v <= 0.0f) return d_const(-1.0f);
  return far ? d_add(d_neg(b), d_sqrt(disc)) : d_sub(d_neg(b), d_sqrt(disc));
}

// Curved face toward the source (the prototype): spherical front face with its
// vertex at z = 0 and centre at z = R; flat back face at z = thickness.
PRISM_FN Exit through_convex_first(Ray ray, LensShape g, DVec3 dir, bool test_entrance) {
  Exit e = Exit(ray.origin, dir, false);
  float n = g.n;
  DVec3 centre = DVec3(g.cx, g.cy, g.R);
  // Intersect the spherical front face (the near cap).
  Dual t1 = sphere_distance(ray.origin, dir, centre, g.R, false);
  if (t1.v < 0.0f) return e;
  DVec3 p1 = dv_add(ray.origin, dv_scale(dir, t1));
  if (test_entrance && (!inside_aperture(p1.x, p1.y, shape_centre(g), g.radius) || p1.z.v > g.sag.v)) return e;
  // Refract into the glass; the outward normal faces the incoming ray.
  DVec3 d1 = refract_dual(dir, dv_scale(dv_sub(p1, centre), d_div(d_const(1.0f), g.R)), 1.0f / n);
  if (d1.z.v <= 0.0f) return e;
  // Cross the glass to the flat back face.
  DVec3 p2 = dv_add(p1, dv_scale(d1, d_div(d_sub(g.thickness, p1.z), d1.z)));
  if (!inside_aperture(p2.x, p2.y, shape_centre(g), g.radius)) return e;
  // Refract out of the flat face: tangential components scale by n.
  Dual kz = d_sub(d_const(1.0f), d_scale(d_sub(d_const(1.0f), d_mul(d1.z, d1.z)), n * n));
  if (kz.v <= 0.0f) return e;  // total internal reflection
  return Exit(p2, DVec3(d_scale(d1.x, n), d_scale(d1.y, n), d_sqrt(kz)), true);
}

// Flipped: flat front face at z = 0, spherical back face with its vertex at
// z = thickness and centre at z = thickness - R.
PRISM_FN Exit through_flat_first(Ray ray, LensShape g, DVec3 dir, bool test_entrance) {
  Exit e = Exit(ray.origin, dir, false);
  float n = g.n;
  // Cross the flat front face and refract into the glass.
  DVec3 p0 = dv_add(ray.origin, dv_scale(dir, d_div(d_neg(ray.origin.z), dir.z)));
  if (test_entrance && !inside_aperture(p0.x, p0.y, shape_centre(g), g.radius)) return e;
  float eta = 1.0f / n;
  Dual kz = d_sub(d_const(1.0f), d_scale(d_sub(d_const(1.0f), d_mul(dir.z, dir.z)), eta * eta));
  DVec3 d1 = DVec3(d_scale(dir.x, eta), d_scale(dir.y, eta), d_sqrt(kz));
  // Leave the sphere from inside: the far root.
  DVec3 centre = DVec3(g.cx, g.cy, d_sub(g.thickness, g.R));
  Dual t1 = sphere_distance(p0, d1, centre, g.R, true);
  if (t1.v < 0.0f) return e;
  DVec3 p1 = dv_add(p0, dv_scale(d1, t1));
  if (!inside_aperture(p1.x, p1.y, shape_centre(g), g.radius) || p1.z.v < g.thickness.v - g.sag.v) return e;
  // Refract out; the inward normal faces the outgoing ray.
  DVec3 d2 = refract_dual(d1, dv_scale(dv_sub(centre, p1), d_div(d_const(1.0f), g.R)), n);
  if (d2.z.v <= 0.0f) return e;  // total internal reflection
  return Exit(p1, d2, true);
}

// Real plano-convex lens, either way round: where the ray leaves the glass.
PRISM_FN Exit real_exit(Ray ray, LensShape g, bool test_entrance) {
  DVec3 dir = dv_normalize(ray.dir);
  return (g.curved_toward_sensor != 0) ? through_flat_first(ray, g, dir, test_entrance)
                                       : through_convex_first(ray, g, dir, test_entrance);
}

// Holder bore beyond the glass (see thin_exit): whether the ray leaving the
// glass passes it.
PRISM_FN bool passes_bore(Exit e, LensShape g, float holder_bore_mm) {
  if (!(holder_bore_mm > e.p.z.v)) return true;
  Dual tb = d_div(d_sub(d_const(holder_bore_mm), e.p.z), e.d.z);
  return inside_aperture(d_add(e.p.x, d_mul(e.d.x, tb)), d_add(e.p.y, d_mul(e.d.y, tb)), shape_centre(g), g.radius);
}

// Real lens, holder, and transport to the sensor plane z = lens_to_sensor_mm.
// A ray the holder stops keeps its landing point (not ok); one the glass
// stops has none.
PRISM_FN Hit trace_real(Ray ray, LensShape g, float holder_bore_mm, Dual lens_to_sensor_mm, bool test_entrance) {
  Hit hit = Hit(d_const(0.0f), d_const(0.0f), ray.weight, false);
  Exit e = real_exit(ray, g, test_entrance);
  if (!e.ok) return hit;
  bool ok = passes_bore(e, g, holder_bore_mm);
  Dual ts = d_div(d_sub(lens_to_sensor_mm, e.p.z), e.d.z);
  hit.x_mm = d_add(e.p.x, d_mul(e.d.x, ts));
  hit.y_mm = d_add(e.p.y, d_mul(e.d.y, ts));
  hit.ok = ok;
  return hit;
}

#if PRISM_AS_BUILT
// ---------------------------------------------------------------------------
// As built: tilted lenslets and a sensor off its nominal pose (AS_BUILT)

// The turn of a tilt: about the x axis by ax, then about the y axis by ay
// (radians, duals), v -> Ry(ay) Rx(ax) v. Its columns: the turned unit vectors.
struct DMat3 {
  DVec3 c0;
  DVec3 c1;
  DVec3 c2;
};
PRISM_FN DMat3 tilt_matrix(Dual ax, Dual ay) {
  Dual cx = d_cos(ax);
  Dual sx = d_sin(ax);
  Dual cy = d_cos(ay);
  Dual sy = d_sin(ay);
  return DMat3(DVec3(cy, d_const(0.0f), d_neg(sy)), DVec3(d_mul(sy, sx), cx, d_mul(cy, sx)),
               DVec3(d_mul(sy, cx), d_neg(sx), d_mul(cy, cx)));
}
// A tilt of (x_rad, y_rad) whose derivatives per degree are the slots' of
// parameters (param_x, param_y).
PRISM_FN DMat3 seeded_tilt(float x_rad, float y_rad, uint param_x, uint param_y, uint lens, TraceParams P) {
  return tilt_matrix(Dual(x_rad, seed(param_x, lens, P) * RADIANS_PER_DEGREE),
                     Dual(y_rad, seed(param_y, lens, P) * RADIANS_PER_DEGREE));
}

PRISM_FN DVec3 dv_turn(DMat3 m, DVec3 v) {  // m v
  return dv_add(dv_add(dv_scale(m.c0, v.x), dv_scale(m.c1, v.y)), dv_scale(m.c2, v.z));
}
PRISM_FN DVec3 dv_unturn(DMat3 m, DVec3 v) {  // m^T v: m's inverse
  return DVec3(dv_dot(m.c0, v), dv_dot(m.c1, v), dv_dot(m.c2, v));
}

// The world ray `ray` through a lenslet turned by m (tilt_matrix; traced in
// its own frame) and onto the sensor as built: the plane through (offset_x,
// offset_y, lens_to_sensor) turned by the sensor's tilt, the landing point in
// the sensor's own axes from its centre.
PRISM_FN Hit trace_as_built(Ray ray, LensShape g, DMat3 m, int lens_model, float holder_bore_mm, TraceParams P,
                            Dual lens_to_sensor_mm, bool test_entrance) {
  Hit hit = Hit(d_const(0.0f), d_const(0.0f), ray.weight, false);
  DVec3 c = lens_pivot(g);
  Ray local = Ray(dv_add(c, dv_unturn(m, dv_sub(ray.origin, c))), dv_unturn(m, ray.dir), ray.weight);
  Exit e;
  bool ok;
  if (lens_model == LENS_REAL) {
    e = real_exit(local, g, test_entrance);
    if (!e.ok) return hit;  // as trace_real
    ok = passes_bore(e, g, holder_bore_mm);
  } else {
    e = thin_exit(local, g, holder_bore_mm, test_entrance);
    ok = e.ok;
  }
  DVec3 p = dv_add(c, dv_turn(m, dv_sub(e.p, c)));
  DVec3 d = dv_turn(m, e.d);
  DMat3 s = seeded_tilt(P.sensor_tilt_x_rad, P.sensor_tilt_y_rad, PARAM_SENSOR_TILT_X, PARAM_SENSOR_TILT_Y, 0u, P);
  DVec3 s0 = DVec3(Dual(P.sensor_offset_x_mm, seed(PARAM_SENSOR_OFFSET_X, 0u, P)),
                   Dual(P.sensor_offset_y_mm, seed(PARAM_SENSOR_OFFSET_Y, 0u, P)), lens_to_sensor_mm);
  Dual t = d_div(dv_dot(dv_sub(s0, p), s.c2), dv_dot(d, s.c2));
  DVec3 on_sensor = dv_sub(dv_add(p, dv_scale(d, t)), s0);
  hit.x_mm = dv_dot(on_sensor, s.c0);
  hit.y_mm = dv_dot(on_sensor, s.c1);
  hit.ok = ok;
  return hit;
}
#endif  // PRISM_AS_BUILT

// Trace the ray from source theta (with source_extent: moved by sigma times
// per_sigma, source_point) through point `unit` of the lenslet's
// entrance disk (unit-disk coordinates). Its weight is the photons per mm^2
// of aperture there times `area_mm2`. The effect switches are compile-time
// constants in the kernels (specialisation constants), so an effect the scene
// does not name is compiled out.
PRISM_FN Hit trace_aperture_point(vec3 theta, vec3 per_sigma, Lenslet lens, vec2 unit, float area_mm2, TraceParams P, int lens_model,
                                  bool scint_refraction, bool holder, bool as_built) {
  LensShape g = seeded_shape(lens, P);
  // The entrance disk: the rim plane of a front sphere, else the plane z = 0.
  Dual aperture_z = (lens_model == LENS_REAL && lens.curved_toward_sensor == 0) ? g.sag : d_const(0.0f);
  DVec3 on_disk = DVec3(d_const(lens.radius_mm * unit.x), d_const(lens.radius_mm * unit.y), aperture_z);
#if PRISM_AS_BUILT
  DMat3 m;
  if (as_built) {
    // The disk turns with its lens.
    m = seeded_tilt(lens.tilt_x_rad, lens.tilt_y_rad, PARAM_LENS_TILT_X, PARAM_LENS_TILT_Y, lens.index, P);
    on_disk = dv_turn(m, on_disk);
  }
#endif
  DVec3 p = dv_add(lens_pivot(g), on_disk);
  float photons = P.photons_per_sr * area_mm2;
  Dual working_distance = Dual(P.working_distance_mm, seed(PARAM_WORKING_DISTANCE, lens.index, P));
  DVec3 src = source_point(theta, per_sigma, working_distance, lens.index, P);
  Ray ray = scint_refraction ? emit_through_face(src, p, photons, P.scint_index, d_neg(working_distance))
                             : emit_direct(src, p, photons);
  float bore = holder ? P.holder_bore_mm : 0.0f;
  Dual lens_to_sensor = Dual(P.lens_to_sensor_mm, seed(PARAM_LENS_TO_SENSOR, lens.index, P));
#if PRISM_AS_BUILT
  if (as_built) {
    // The emitters weigh the ray by the disk's area seen along z; a turned
    // disk is seen along its own normal: times (d . normal) / d.z.
    ray.weight = d_mul(ray.weight, d_div(dv_dot(ray.dir, m.c2), ray.dir.z));
    return trace_as_built(ray, g, m, lens_model, bore, P, lens_to_sensor, false);
  }
#endif
  return (lens_model == LENS_REAL) ? trace_real(ray, g, bore, lens_to_sensor, false)
                                   : trace_thin(ray, g, bore, lens_to_sensor, false);
}

// Trace aperture sample `sample_index` of lenslet `lens_index` from source
// theta: its jittered stratum's point, carrying an equal share of the area.
PRISM_FN Hit trace_sample(vec3 theta, Lenslet lens, uint lens_index, uint sample_index, TraceParams P,
                          int lens_model, bool scint_refraction, bool holder, bool source_extent, bool as_built) {
  vec3 per_sigma = source_extent ? source_offset(lens_index, sample_index, 1.0f, P.stratification) : vec3(0.0f);
  vec2 unit = aperture_sample(lens_index, sample_index, lens.strata, P.stratification);
  float area = 3.14159265358979f * lens.radius_mm * lens.radius_mm / float(lens.strata * lens.strata);
  return trace_aperture_point(theta, per_sigma, lens, unit, area, P, lens_model, scint_refraction, holder, as_built);
}

// ---------------------------------------------------------------------------
// Bilinear splatting

// The four pixels a hit touches: base pixel (column, row) and per tap
// (photons, d/dx, d/dy, d/ddepth). Taps outside the grid are left to the caller.
struct Splat {
  ivec2 base;
  vec4 tap00;
  vec4 tap10;
  vec4 tap01;
  vec4 tap11;
  bool ok;  // false when the hit misses the physical sensor
};

PRISM_FN vec4 tap_value(Dual a, Dual b, Dual w) {
  Dual t = d_mul(d_mul(a, b), w);
  return vec4(t.v, t.d.x, t.d.y, t.d.z);
}

// Pixel centres sit at (i + 0.5) * pixel from the sensor's left/top edge. A hit
// exactly on a pixel centre line puts zero weight, with a one-sided derivative,
// on the neighbour: the Fisher reduction skips such b = 0 pixels.
PRISM_FN Splat splat_bilinear(Hit hit, TraceParams P) {
  Splat s;
  s.ok = hit.ok && abs(hit.x_mm.v) <= P.sensor_half_w_mm && abs(hit.y_mm.v) <= P.sensor_half_h_mm;
  float inv_px = 1.0f / P.pixel_mm;
  Dual u = d_addc(d_scale(d_addc(hit.x_mm, P.sensor_half_w_mm), inv_px), -0.5f);
  Dual v = d_addc(d_scale(d_addc(hit.y_mm, P.sensor_half_h_mm), inv_px), -0.5f);
  float iu = floor(u.v);
  float iv = floor(v.v);
  s.base = ivec2(int(iu), int(iv));
  Dual fx = d_addc(u, -iu);
  Dual fy = d_addc(v, -iv);
  Dual gx = d_sub(d_const(1.0f), fx);
  Dual gy = d_sub(d_const(1.0f), fy);
  s.tap00 = tap_value(gx, gy, hit.weight);
  s.tap10 = tap_value(fx, gy, hit.weight);
  s.tap01 = tap_value(gx, fy, hit.weight);
  s.tap11 = tap_value(fx, fy, hit.weight);
  return s;
}

// ---------------------------------------------------------------------------
// Fisher information per pixel

// exp(x) - 1 without cancellation for small x.
PRISM_FN float expm1_small(float x) {
  if (abs(x) < 1e-2f) return x * (1.0f + x * (0.5f + x * (1.0f / 6.0f + x * (1.0f / 24.0f))));
  return exp(x) - 1.0f;
}

// Information a pixel holds, as (xx, xy, xz, yy, yz, zz), for a Poisson pixel
// (divide by b) or a binary single-photon pixel (divide by exp(b) - 1).
// The pixel stores b and two independent estimates of grad b, one from each
// half of the rays (checkerboard strata). The naive estimate uses their mean
// g and g g^T, whose expectation is grad b grad b^T + Var(g): sampling noise
// adds information that is not there, without bound where one ray grazes a
// pixel (w (df)^2 / f). The split estimate (gA gB^T + gB gA^T) / 2 has
// expectation grad b grad b^T exactly, because the halves are independent.
// Empty pixels hold none; `dark` is the background in every pixel.
struct FisherTerms {
  float xx;
  float xy;
  float xz;
  float yy;
  float yz;
  float zz;
};

const int FISHER_NAIVE = 0;
const int FISHER_SPLIT = 1;

PRISM_FN FisherTerms fisher_terms(float b_signal, vec3 ga, vec3 gb, float dark, bool binary, int estimator) {
  float b = b_signal + dark;
  FisherTerms f = FisherTerms(0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f);
  if (!(b > 0.0f)) return f;
  float inv = 1.0f / (binary ? expm1_small(b) : b);
  vec3 u = ga;
  vec3 v = gb;
  if (estimator == FISHER_NAIVE) {
    u = 0.5f * (ga + gb);
    v = u;
  }
  f.xx = u.x * v.x * inv;
  f.xy = 0.5f * (u.x * v.y + u.y * v.x) * inv;
  f.xz = 0.5f * (u.x * v.z + u.z * v.x) * inv;
  f.yy = u.y * v.y * inv;
  f.yz = 0.5f * (u.y * v.z + u.z * v.y) * inv;
  f.zz = u.z * v.z * inv;
  return f;
}

// Which half of the rays a sample belongs to: the checkerboard of strata, so
// each half is itself stratified over the aperture.
PRISM_FN uint ray_half(uint sample_index, uint strata) {
  return ((sample_index % strata) + (sample_index / strata)) & 1u;
}

#endif
