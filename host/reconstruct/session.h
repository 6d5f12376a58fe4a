// `prism reconstruct` as one object, for the command and the Python module:
// the dictionary opened, the search pool on its backend, the continuous
// refinement's model, and a run over batches of events that gives each
// event's K vertices, refined.
#pragma once
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "engine/vk/context.h"
#include "host/events/event_file.h"
#include "host/reconstruct/pool.h"
#include "host/reconstruct/refine.h"

namespace prism {

// The command's options, with its defaults; messages name the command's options.
struct SessionOptions {
  std::string backend = "vulkan";   // vulkan, dense or cpu
  std::string precision = "float";  // the scan level on the device: float or half
  std::string model;                // scene, dictionary or none; "": the dictionary's default (choose_refine_model)
  std::string scene;                // a scene (name or file) for --model scene instead of the manifest's
  size_t batch = defaults::scan_chunk_events;  // events per device scan
  int level = -1;                   // the search's scan level; -1: default_search_level
  double budget_mib = 1024;         // host memory of the search's tables, tiles and files
  unsigned threads = 0;             // host threads (PoolOptions::threads); 0: host_threads_default()
  bool serial_scans = false;        // scan, then the host's work, instead of side by side
  double always_scan_below_mm = defaults::refine_always_scan_below_mm;  // RefineSettings'
  int always_scan_below_clicks = defaults::refine_always_scan_below_clicks;
  int refine_level = -1;            // the level the refinement renders on (Refinement); -1: refine_level()'s default
  ReconstructionSettings settings;  // vertices (K) and the search's settings
};

// The host threads when none are asked for: the cpu backend's reference
// runs on 1; the device backends descend on this machine's hardware threads
// (at most 8), since the host's descent through the tiles is their cost
// beside a coarse scan (docs/reconstruction.md "Clicks at the sensor's own pixels").
unsigned host_threads_default(ReconstructionBackend backend);

class ReconstructionSession {
 public:
  // `events`: the header of the events to come (their click binning),
  // `events_name` names them in messages. ctx: required by the device
  // backends; the refinement runs on it too, or on the CPU reference
  // without one.
  ReconstructionSession(const std::string& dictionary, const EventFileHeader& events, const std::string& events_name,
                        const SessionOptions& options, vk::Context* ctx);
  ~ReconstructionSession();

  // Per event its K vertices (rows in the order of the search's passes),
  // refined when a model is set; refined(i) after event i's refinement
  // (seconds apart on a CPU device; nothing is called without refinement).
  std::vector<std::vector<ReconstructedVertex>> run(std::span<const Event> events,
                                                    const std::function<void(size_t)>& refined = {});
  // Events per run() call that keep the device busy (several scans, so that
  // the host's work on one runs beside the next) or every CPU worker.
  size_t batch_events() const;

  bool on_device() const { return options_.backend != ReconstructionBackend::cpu; }
  const ReconstructionPool& pool() const { return *pool_; }
  const ReconstructionSettings& settings() const { return pool_->settings(); }
  int click_level() const { return click_level_; }
  RefineModel model() const { return model_; }
  const Scene& scene() const { return scene_; }
  const Refinement* refinement() const { return refinement_.get(); }  // nullptr: the search alone

 private:
  std::optional<Scene> given_;
  std::unique_ptr<DictionaryReader> reader_;
  int click_level_ = 0;
  PoolOptions options_;
  size_t batch_ = 0;
  std::unique_ptr<ReconstructionPool> pool_;
  RefineModel model_ = RefineModel::none;
  Scene scene_;
  std::unique_ptr<Refinement> refinement_;
};

}  // namespace prism
