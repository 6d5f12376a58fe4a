// What a sweep's result is compared with: fixed designs scored at the sweep's
// settings and samples, and the double-precision reference re-scoring the
// top designs (does it rank them the same way?).
#pragma once
#include <string>
#include <vector>

#include "host/sweep/sweep.h"

namespace prism {

struct Baseline {
  std::string name;
  Objectives objectives;
};

// The prototype and the unifocal arrays (f3, f9, f15), in the space's volume.
// Under several processes (`share`) each scores those its share takes and
// every one gets them all.
std::vector<Baseline> score_baselines(const DesignSpace& space, const SweepSettings& settings, vk::Context* ctx,
                                      const WorkShare& share = {});

struct Confirmation {
  size_t rank = 0;             // 1-based, in the sweep's ranking
  double device_value = 0;     // the objective as the sweep scored it
  double reference_value = 0;  // the same design on the CPU reference
  size_t reference_rank = 0;   // its rank among the confirmed designs by the reference's values
};

// The top `count` valid designs of `ranked` re-scored on the CPU reference
// (same rays, binning and samples).
std::vector<Confirmation> confirm_with_reference(const Sweep& sweep, const std::vector<const Evaluated*>& ranked,
                                                 size_t count);

}  // namespace prism
