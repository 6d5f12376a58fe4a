#include "host/sweep/baselines.h"

#include <algorithm>

namespace prism {

std::vector<Baseline> score_baselines(const DesignSpace& space, const SweepSettings& s, vk::Context* ctx,
                                      const WorkShare& share) {
  const std::vector<std::string> names{"prototype", "unifocal-f3", "unifocal-f9", "unifocal-f15"};
  std::vector<Baseline> baselines;
  nlohmann::json mine = nlohmann::json::array();
  for (size_t i = 0; i < names.size(); ++i) {
    if (!share.takes(i)) continue;
    Scene b = builtin_scene(names[i]);
    b.volume = space.base.volume;
    Objectives o = score(b, space.samples, s.trace, s.backend, ctx);
    if (s.ambiguity)
      score_ambiguity(b, space.ambiguity_samples, *s.ambiguity, s.backend == Backend::vulkan ? ctx : nullptr, o);
    baselines.push_back({names[i], o});
    mine.push_back(to_json(o));
  }
  if (share.count == 1) return baselines;
  const auto all = share.gather_items(names.size(), mine);
  baselines.clear();
  for (size_t i = 0; i < names.size(); ++i) baselines.push_back({names[i], objectives_from_json(all[i])});
  return baselines;
}

std::vector<Confirmation> confirm_with_reference(const Sweep& sweep, const std::vector<const Evaluated*>& ranked,
                                                 size_t count) {
  const auto& s = sweep.settings();
  const bool maximised = objective_is_maximised(s.objective);
  std::vector<Confirmation> out;
  for (size_t k = 0; k < ranked.size() && k < count && ranked[k]->valid; ++k) {
    Scene scene = sweep.space().scene_of(ranked[k]->design, "confirm");
    Confirmation c;
    c.rank = k + 1;
    c.device_value = objective_value(ranked[k]->objectives, s.objective);
    Objectives o = score(scene, sweep.space().samples, s.trace, Backend::cpu, nullptr);
    if (objective_is_ambiguity(s.objective))
      score_ambiguity(scene, sweep.space().ambiguity_samples, *s.ambiguity, nullptr, o);
    c.reference_value = objective_value(o, s.objective);
    out.push_back(c);
  }
  std::vector<size_t> order(out.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) {
    return maximised ? out[a].reference_value > out[b].reference_value : out[a].reference_value < out[b].reference_value;
  });
  for (size_t r = 0; r < order.size(); ++r) out[order[r]].reference_rank = r + 1;
  return out;
}

}  // namespace prism
