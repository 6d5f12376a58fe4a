// What every splat kernel shares (GLSL only: buffers and atomics): the
// specialisation constants (lens model, effects, derivatives), the trace
// parameters, the buffers, and how light is added to the image of a source:
// at one pixel, or blurred by the Airy square over box pixels (effect
// diffraction, blur.glsl).
#ifndef PRISM_SPLAT_IMAGE_GLSL
#define PRISM_SPLAT_IMAGE_GLSL

#include "blur.glsl"
#include "optics.glsl"

// Effects are compile-time: a scene that does not name one compiles it out.
layout(constant_id = 0) const int LENS_MODEL = LENS_THIN;
layout(constant_id = 1) const bool SCINT_REFRACTION = false;
layout(constant_id = 2) const bool HOLDER = false;
// Without derivatives a pixel is just b (dictionary synthesis, event simulation).
layout(constant_id = 3) const bool DERIVATIVES = true;
layout(constant_id = 4) const bool SOURCE_EXTENT = false;
// Effect diffraction is the kernels' blur builds (PRISM_BLUR=1, why:
// shaders/CMakeLists.txt), not a constant. Calls into blur.glsl sit in #if PRISM_BLUR.
const bool DIFFRACTION = PRISM_BLUR != 0;
// Tilted lenslets or a sensor off its nominal pose (optics.glsl,
// trace_as_built): the kernels' as-built variants, compiled apart.
const bool AS_BUILT = PRISM_AS_BUILT != 0;
const uint PIXEL_FLOATS = DERIVATIVES ? 8u : 1u;

layout(push_constant) uniform Push { TraceParams P; };
layout(std430, binding = 0) readonly buffer Lenses { Lenslet lenses[]; };
layout(std430, binding = 1) readonly buffer Sources { vec4 sources[]; };  // xyz = (x, y, depth) mm
// Per pixel 8 floats: b, grad b from ray (cell) half A, from half B, unused;
// or b alone without DERIVATIVES.
layout(std430, binding = 2) buffer Images { float images[]; };  // [source][band row][col][PIXEL_FLOATS]
layout(std430, binding = 3) readonly buffer SourceDesigns { uint source_design[]; };  // design of each source
layout(std430, binding = 4) readonly buffer Designs { DesignRange designs[]; };

#ifdef PRISM_TILE_MASK
// A masked render (P.mask_tiles_w > 0; the footprint kernels only): light
// only for the pixels of the tiles of LARGE_TILE_PX pixels (footprint.glsl)
// the mask marks, each tile's pixels a block of the image of their own (in
// the order of the tiles' slots, row-major within), so the image holds the
// marked tiles alone. The kernels also skip the pieces that reach none of
// them (reaches_mask, footprint_raster.glsl): a refinement at the sensor's
// own pixels costs its clicks' neighbourhoods instead of the whole sensor.
layout(std430, binding = 7) readonly buffer TileMask { uint tile_slot[]; };  // per tile, row-major: 0 unmarked, else 1 + its slot
uint tile_slot_of(int tile_col, int tile_row) { return tile_slot[uint(tile_row) * P.mask_tiles_w + uint(tile_col)]; }
bool tile_marked(int tile_col, int tile_row) { return tile_slot_of(tile_col, tile_row) != 0u; }
#endif

// The physical sensor's far edges in grid pixels: the last column and row may
// hang over it (binning that does not divide the sensor), and light beyond is lost.
float sensor_u_max() { return 2.0f * P.sensor_half_w_mm / P.pixel_mm; }
float sensor_v_max() { return 2.0f * P.sensor_half_h_mm / P.pixel_mm; }

// The lenslet of design d that ray (footprint: cell) r belongs to: the last
// whose first_ray <= r.
uint lens_of(DesignRange d, uint r) {
  uint lo = d.first_lens;
  uint hi = d.first_lens + d.lens_count - 1u;
  while (lo < hi) {
    uint mid = (lo + hi + 1u) / 2u;
    if (lenses[mid].first_ray <= r) lo = mid;
    else hi = mid - 1u;
  }
  return lo;
}

// Add `value` (with its derivatives) to pixel (col, row) of the band.
void deposit(uint image_base, int col, int row, Dual value, uint half_offset) {
  if (col < 0 || col >= P.grid_w || row < P.band_row0 || row >= P.band_row0 + P.band_rows || row >= P.grid_h) return;
  uint i = image_base + PIXEL_FLOATS * (uint(row - P.band_row0) * uint(P.grid_w) + uint(col));
#ifdef PRISM_TILE_MASK
  if (P.mask_tiles_w != 0u) {
    uint slot = tile_slot_of(col / LARGE_TILE_PX, row / LARGE_TILE_PX);
    if (slot == 0u) return;
    i = image_base + PIXEL_FLOATS * ((slot - 1u) * uint(LARGE_TILE_PX * LARGE_TILE_PX) +
                                     uint(row % LARGE_TILE_PX) * uint(LARGE_TILE_PX) + uint(col % LARGE_TILE_PX));
  }
#endif
  atomicAdd(images[i], value.v);
  if (!DERIVATIVES) return;
  // Each half of the rays (cells; checkerboard) estimates the whole gradient.
  atomicAdd(images[i + half_offset], 2.0f * value.d.x);
  atomicAdd(images[i + half_offset + 1u], 2.0f * value.d.y);
  atomicAdd(images[i + half_offset + 2u], 2.0f * value.d.z);
}

// Effect diffraction: the half side of lenslet `lens`'s Airy square, grid pixels.
float airy_half_side_px(Lenslet lens) {
  return P.airy_half_side_mm_times_diameter / (2.0f * lens.radius_mm) / P.pixel_mm;
}

// `weight` at point (u, v) (grid pixels) blurred by a square of half side h:
// each box pixel gets the square's share inside it (the sensor's far edges
// bound the last column and row; light beyond is lost).
void deposit_blurred_point(uint image_base, Dual u, Dual v, float h, Dual weight, uint half_offset) {
  float u_max = sensor_u_max();
  float v_max = sensor_v_max();
  int c0 = max(int(floor(u.v - h)), 0);
  int c1 = min(int(floor(u.v + h)), P.grid_w - 1);
  int r0 = max(int(floor(v.v - h)), max(P.band_row0, 0));
  int r1 = min(int(floor(v.v + h)), min(P.band_row0 + P.band_rows, P.grid_h) - 1);
  for (int row = r0; row <= r1; ++row) {
    Dual fy = blurred_pixel(v, float(row), min(float(row + 1), v_max), h);
    if (fy.v == 0.0f && fy.d == vec3(0.0f)) continue;
    Dual wy = d_mul(weight, fy);
    for (int col = c0; col <= c1; ++col) {
      Dual fx = blurred_pixel(u, float(col), min(float(col + 1), u_max), h);
      if (fx.v != 0.0f || fx.d != vec3(0.0f)) deposit(image_base, col, row, d_mul(wy, fx), half_offset);
    }
  }
}

#endif
