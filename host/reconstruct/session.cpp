#include "host/reconstruct/session.h"

#include <algorithm>
#include <stdexcept>
#include <thread>

namespace prism {

unsigned host_threads_default(ReconstructionBackend backend) {
  if (backend == ReconstructionBackend::cpu) return 1;
  return std::clamp(std::thread::hardware_concurrency(), 1u, 8u);
}

ReconstructionSession::ReconstructionSession(const std::string& dictionary, const EventFileHeader& events,
                                             const std::string& events_name, const SessionOptions& o,
                                             vk::Context* ctx) {
  // --scene: the refinement's model instead of the manifest's scene; its
  // sensor must be the one the dictionary (and so the clicks) are for.
  if (!o.scene.empty()) given_ = load_scene(o.scene);
  reader_ = std::make_unique<DictionaryReader>(dictionary, given_ ? &given_->optics : nullptr);
  const auto& m = reader_->manifest();
  click_level_ = prism::click_level(m, events, events_name, dictionary);
  if (o.level >= 0 && (o.level < click_level_ || o.level >= m.levels))
    throw std::runtime_error("--level " + std::to_string(o.level) + ": choose a level from " +
                             std::to_string(click_level_) + " (the clicks' own) to " + std::to_string(m.levels - 1) +
                             " (the coarsest in " + dictionary + ")");
  ReconstructionSettings s = o.settings;
  s.scan_chunk_events = int(o.batch);
  s.overlap_scans = !o.serial_scans;
  s.search_level = o.level;  // -1: default_search_level

  options_.backend = backend_from_string(o.backend);
  if (o.precision != "float" && o.precision != "half")
    throw std::runtime_error("--precision " + o.precision + ": use float or half");
  if (on_device() && !ctx) throw std::logic_error("ReconstructionSession: the device backends need a Vulkan context");
  options_.ctx = ctx;
  options_.threads = o.threads ? o.threads : host_threads_default(options_.backend);
  // Saturated: a budget past 8 EiB is refused by the memory check, naming --budget-mib.
  options_.host_budget_bytes = uint64_t(std::min(o.budget_mib * double(1 << 20), 0x1p63));
  options_.device_half = o.precision == "half";
  pool_ = std::make_unique<ReconstructionPool>(*reader_, click_level_, s, options_);
  // Device: several scans' events at once, so that the host's work on one
  // batch runs beside the scan of the next (Reconstructor::run).
  batch_ = on_device() ? o.batch * size_t(defaults::scan_chunks_per_batch) : 32 * pool_->workers();

  // The continuous refinement's model: the scene's forward model, or the
  // dictionary interpolated (the default for measured dictionaries).
  model_ = choose_refine_model(o.model, m, given_.has_value(), dictionary);
  scene_ = given_ ? *given_ : m.scene;
  if (model_ != RefineModel::none) {
    RefineSettings rs;
    rs.dark_rate = s.dark_rate;
    rs.alpha_max = s.alpha_max;
    rs.always_scan_below_mm = o.always_scan_below_mm;
    rs.always_scan_below_clicks = o.always_scan_below_clicks;
    refinement_ = std::make_unique<Refinement>(model_, scene_, *reader_, click_level_,
                                               refine_level(m, click_level_, o.refine_level), ctx, rs);
  }
}

ReconstructionSession::~ReconstructionSession() = default;

size_t ReconstructionSession::batch_events() const { return batch_; }

std::vector<std::vector<ReconstructedVertex>> ReconstructionSession::run(std::span<const Event> events,
                                                                         const std::function<void(size_t)>& refined) {
  auto out = pool_->run(events);
  if (refinement_)
    for (size_t i = 0; i < events.size(); ++i) {
      out[i] = refinement_->refine(events[i], std::move(out[i]));
      if (refined) refined(i);
    }
  return out;
}

}  // namespace prism
