// A source at a continuous position as a dictionary PSF moved on the sensor:
// the nearest grid node, shifted by -(source - node) * magnification(depth)
// (OpticalSystem::magnification; DESIGN.md: -dx * 18.5 / (z + 5) for the
// prototype) and rounded to whole pixels of a level. Simulation (the paper's
// protocol) and reconstruction both place sources this way, and read them back
// with source_lateral_mm; this is the one home of that convention.
#pragma once
#include <cstddef>

#include <glm/glm.hpp>

#include "host/dictionary/store.h"

namespace prism {

struct DictionaryPlacement {
  size_t index = 0;       // dictionary entry
  glm::dvec2 shift_mm{};  // on the sensor
  glm::ivec2 shift_px{};  // (columns, rows) of the level; sensor x grows with the column, y with the row
};

// The lateral position xy on depth plane `plane`, the shift scaled by the
// magnification at `depth_mm` (the plane's own depth, or the source's).
DictionaryPlacement place_on_plane(const DictionaryManifest& m, int level, glm::dvec2 xy_mm, int plane,
                                   double depth_mm);

// The nearest node in 3D, the shift at the source's own depth (the paper's
// protocol: events drawn from shifted dictionary PSFs).
DictionaryPlacement place_in_dictionary(const DictionaryManifest& m, int level, const glm::dvec3& position_mm);

// The inverse: the lateral source position that entry `index` shifted by
// `shift_px` pixels of `level` stands for, read at depth `depth_mm`.
glm::dvec2 source_lateral_mm(const DictionaryManifest& m, int level, size_t index, glm::ivec2 shift_px,
                             double depth_mm);

}  // namespace prism
