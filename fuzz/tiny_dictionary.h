// The one-entry dictionary of a 64 x 48 px sensor whose PSF file the
// psf_exr harness fuzzes (and fuzz_seeds writes a valid file for).
#pragma once
#include "host/dictionary/store.h"

namespace prism::fuzz {

inline prism::DictionaryManifest tiny_manifest() {
  prism::DictionaryManifest m;
  m.scene = prism::parse_scene(
      {{"name", "fuzz"},
       {"lens_model", "thin"},
       {"sensor", {{"width_px", 64}, {"height_px", 48}, {"pixel_um", 110.4}}},
       {"lenslets", {{{"x_mm", 0}, {"y_mm", 0}, {"focal_mm", 9}}}}},
      "fuzz");
  m.grid.x_mm = {0};
  m.grid.y_mm = {0};
  m.grid.depth_mm = {10};
  m.base_binning = 1;
  m.width = 64;
  m.height = 48;
  m.levels = prism::DictionaryManifest::mip_levels(m.width, m.height);
  m.tile_px = 16;
  m.rays_per_lenslet = 256;
  return m;
}

}  // namespace prism::fuzz
