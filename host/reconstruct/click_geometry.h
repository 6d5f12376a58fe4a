// Where a point source lies, read from where its clicks fall (a Hough
// transform), for the refinement's lattice scan (refine.h).
//
// Through the centre of lenslet i at l_i, a source at lateral position s and
// depth d lands at c = l_i (1 + m) - m s on the sensor, m the magnification
// (OpticalSystem::magnification: the chief ray, undeviated). So at a trial
// depth every click, paired with every lenslet, votes for the source
// position s = (l_i (1 + m) - c) / m. At the right depth the clicks of each
// lenslet image gather on the source and, shifted by the lenslet lattice
// times (1 + m) / m (OpticalSystem::alias_scale), on its lattice aliases,
// which collect nearly as many votes; at a wrong depth the images' spacing
// does not match and the votes spread. The votes give the depth and the
// lattice of the aliases, not which site of it is the source: the
// likelihood decides that.
//
// The votes favour shallow depths: bins are fixed in source mm, and where the
// magnification is large an image's clicks vote into fewer of them, while
// one lenslet's image agrees with itself at every depth. A few clicks from
// one bright image can outvote a source seen through many lenslets, so the
// best-voted depth is a place to start, not a measurement.
//
// Near the scintillator face this finds what the dictionary search misses:
// only a few lenslet images reach the sensor, a source shifted by a few mm
// shows other ones, and the nearest node's PSF moved laterally (the search's
// model) no longer resembles the event.
#pragma once
#include <cstdint>
#include <span>
#include <vector>

#include <glm/glm.hpp>

#include "engine/optical_system.h"

namespace prism {

struct VotePeak {
  glm::dvec3 position_mm;  // x, y, depth
  double votes;            // clicks voting within the peak's 3 x 3 bins, per click (a click votes once per lenslet)
};

// The best-voted position at each trial depth in [depth_lo, depth_hi] (steps
// that move the outer lenslet images by about a click-grid pixel), x and y
// in [lo, hi], best first, each at least `min_depth_apart_mm` in depth from
// the ones before it; at most `count`. Clicks are pixel indices on `grid`.
std::vector<VotePeak> vote_source_positions(const OpticalSystem& sys, const AnalysisGrid& grid,
                                            std::span<const uint32_t> clicks, glm::dvec3 lo, glm::dvec3 hi,
                                            size_t count, double min_depth_apart_mm = 0.5);

}  // namespace prism
