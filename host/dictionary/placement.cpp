#include "host/dictionary/placement.h"

#include <cmath>

namespace prism {

DictionaryPlacement place_on_plane(const DictionaryManifest& m, int level, glm::dvec2 xy_mm, int plane,
                                   double depth_mm) {
  glm::ivec3 n = m.grid.nearest_node({xy_mm, 0.0});
  n.z = plane;
  DictionaryPlacement p;
  p.index = m.grid.index(n);
  const glm::dvec3 node = m.grid.position(p.index);
  // The lenslets image the source inverted: a lateral source shift moves
  // every lenslet image the other way, scaled by the magnification.
  p.shift_mm = -(xy_mm - glm::dvec2(node)) * m.scene.optics.magnification(depth_mm);
  const double px = m.pixel_mm(level);
  p.shift_px = glm::ivec2(int(std::lround(p.shift_mm.x / px)), int(std::lround(p.shift_mm.y / px)));
  return p;
}

DictionaryPlacement place_in_dictionary(const DictionaryManifest& m, int level, const glm::dvec3& position_mm) {
  return place_on_plane(m, level, glm::dvec2(position_mm), m.grid.nearest_node(position_mm).z, position_mm.z);
}

glm::dvec2 source_lateral_mm(const DictionaryManifest& m, int level, size_t index, glm::ivec2 shift_px,
                             double depth_mm) {
  const glm::dvec3 node = m.grid.position(index);
  const double source_mm_per_px = m.pixel_mm(level) / m.scene.optics.magnification(depth_mm);
  return glm::dvec2(node) - glm::dvec2(shift_px) * source_mm_per_px;
}

}  // namespace prism
