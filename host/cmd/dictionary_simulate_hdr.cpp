// prism dictionary simulate-hdr: the calibration stacks a camera would record
// of a scene's PSFs (what `prism camera capture-hdr` writes), from the forward
// model with a synthetic 12-bit sensor's noise. It rehearses a calibration:
// simulate-hdr of an as-built system, then merge-hdr, assemble or calibrate
// --merged, as on the bench (docs/calibration.md).
#include <algorithm>
#include <atomic>
#include <cstdio>
#include <filesystem>
#include <mutex>
#include <thread>

#include "host/calibrate/synthetic.h"
#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/dictionary/hdr_stack.h"
#include "host/dictionary/store.h"
#include "host/util/format.h"
#include "host/util/progress.h"

namespace fs = std::filesystem;

namespace prism::cmd {

namespace {

struct SimulateHdrArgs {
  std::string scene;
  std::string out;
  std::string grid_x = "0", grid_y = "0", grid_depth = "25";
  unsigned rays = 4096;
  uint64_t seed = 1;
  unsigned threads = std::max(1u, std::thread::hardware_concurrency());
  SyntheticCapture capture;
};

std::string stack_name(size_t index) {
  char b[32];
  std::snprintf(b, sizeof b, "p%04zu", index);
  return b;
}

void run(const SimulateHdrArgs& a) {
  if (!(a.capture.max_us > a.capture.min_us))
    throw std::invalid_argument("--max-us must exceed --min-us (" + format_number(a.capture.min_us) + ")");
  const Scene scene = load_scene(a.scene);
  DictionaryGrid grid{parse_list(a.grid_x, "--grid-x-mm"), parse_list(a.grid_y, "--grid-y-mm"),
                      parse_list(a.grid_depth, "--grid-depth-mm")};
  try {
    grid.validate();
    grid.require_in_front(scene.optics);
  } catch (const DictionaryError& e) {
    throw std::invalid_argument(std::string("--grid-*-mm: ") + e.what());
  }
  // The camera records the scene's sensor pixels as they are; bin in the
  // camera (a scene with larger pixels) to keep the stacks small.
  const OpticalSystem& optics = scene.optics;
  const uint64_t stack_bytes = uint64_t(optics.sensor_width_px) * uint64_t(optics.sensor_height_px) * 2 *
                               (a.capture.exposures + a.capture.darks);
  std::vector<size_t> missing;
  for (size_t i = 0; i < grid.size(); ++i)
    if (!fs::exists(fs::path(a.out) / stack_name(i) / "stack.json")) missing.push_back(i);
  fs::create_directories(a.out);
  const uint64_t free_bytes = fs::space(a.out).available;
  if (stack_bytes * missing.size() > free_bytes)
    throw std::runtime_error(
        std::to_string(missing.size()) + " stacks of " + std::to_string(stack_bytes >> 20) + " MiB (" +
        std::to_string(optics.sensor_width_px) + " x " + std::to_string(optics.sensor_height_px) +
        " px, " + std::to_string(a.capture.exposures + a.capture.darks) + " frames) need more than the " + std::to_string(free_bytes >> 20) + " MiB free in " + a.out +
        ": give a scene whose sensor is binned in the camera (e.g. pixel_um 110.4 and a sensor 16 times smaller "
        "in each direction), or fewer positions");

  TraceSettings truth = TraceSettings::defaults_for(Splat::footprint);
  truth.rays_per_lenslet = a.rays;
  truth.binning = 1;         // the camera's pixels
  truth.stratification = 1;  // not the strata a model renders with by default
  std::fprintf(stderr,
               "prism dictionary simulate-hdr: %zu of %zu stacks to write (%zu present), %s, %d x %d px of %.2f um, "
               "%.1f MiB each; CPU reference on %u threads\n",
               missing.size(), grid.size(), grid.size() - missing.size(), scene.name.c_str(), optics.sensor_width_px,
               optics.sensor_height_px, optics.pixel_um, double(stack_bytes) / 1048576.0, a.threads);

  Progress progress("prism dictionary simulate-hdr", missing.size());
  std::atomic<size_t> next{0}, done{0};
  std::mutex lock;
  std::exception_ptr failure;
  auto worker = [&] {
    for (size_t k; (k = next++) < missing.size();) {
      const size_t i = missing[k];
      try {
        HdrStack stack;
        stack.source_mm = grid.position(i);
        stack.camera = {{"vendor", "prism"},
                        {"model", "simulate-hdr (SyntheticSensor: 12 bit, read noise 2 DN, shot noise, dark current)"},
                        {"scene", scene.name},
                        {"rays_per_lenslet", truth.rays()},
                        {"seed", a.seed + i}};
        stack.frames = synthetic_exposures(optics, truth, stack.source_mm, a.seed + i, a.capture);
        // stack.json is written last: its presence says the stack is whole.
        write_hdr_stack((fs::path(a.out) / stack_name(i)).string(), stack);
      } catch (...) {
        std::lock_guard<std::mutex> g(lock);
        if (!failure) failure = std::current_exception();
        next = missing.size();
      }
      std::lock_guard<std::mutex> g(lock);
      progress.update(++done);
    }
  };
  std::vector<std::thread> pool;
  for (unsigned t = 0; t < std::min<size_t>(a.threads, std::max<size_t>(1, missing.size())); ++t) pool.emplace_back(worker);
  for (auto& t : pool) t.join();
  progress.finish();
  if (failure) std::rethrow_exception(failure);
  std::printf("%s: %zu stacks written, %zu already present; next: prism dictionary merge-hdr --stacks %s --out MERGED\n",
              a.out.c_str(), missing.size(), grid.size() - missing.size(), a.out.c_str());
}

}  // namespace

void add_dictionary_simulate_hdr(CLI::App& dictionary) {
  auto a = std::make_shared<SimulateHdrArgs>();
  CLI::App* c = dictionary.add_subcommand(
      "simulate-hdr",
      "write the capture-hdr stacks a camera would record of a scene's PSFs at grid positions (exposures "
      "log-spaced over --min-us .. --max-us and darks spread over those times, of a noisy 12-bit sensor, the brightest pixel "
      "at 2e6 DN/s), to rehearse a calibration");
  c->add_option("--scene", a->scene,
                "the system as built, with the camera's pixels (built-in scene or JSON file; a 6.9 um sensor makes "
                "stacks of 640 MB: bin it in the camera)")
      ->required();
  c->add_option("--out", a->out, "directory for one stack per position, p<grid index>/ (a rerun writes the missing ones)")
      ->required();
  c->add_option("--grid-x-mm", a->grid_x, "source x positions: A,B,C, FIRST:LAST:STEP or both")->capture_default_str();
  c->add_option("--grid-y-mm", a->grid_y, "source y positions")->capture_default_str();
  c->add_option("--grid-depth-mm", a->grid_depth, "source depths from the scintillator face")->capture_default_str();
  c->add_option("--rays", a->rays,
                std::string("rays per 3 mm lenslet, footprint splat at stratification 1 (box pixels, as a camera "
                            "sees them, and not a model's strata), ") + rays_rounding)
      ->capture_default_str()
      ->check(CLI::Range(4u, 1u << 24));
  c->add_option("--exposures", a->capture.exposures, "number of exposure times")
      ->capture_default_str()
      ->check(CLI::Range(2u, 64u));
  c->add_option("--darks", a->capture.darks, darks_help)->capture_default_str()->check(CLI::Range(1u, 64u));
  c->add_option("--min-us", a->capture.min_us, "shortest exposure in us")->capture_default_str()->check(positive_number);
  c->add_option("--max-us", a->capture.max_us,
                "longest exposure in us: the faintest light kept is 16 DN over the third longest exposure (the merge needs 3 "
                "valid ones), of the peak's 2e6 DN/s")
      ->capture_default_str()
      ->check(positive_number);
  c->add_option("--seed", a->seed, "noise seed of the first position; position i gets seed + i")->capture_default_str();
  c->add_option("--threads", a->threads, "positions rendered at once (CPU reference)")
      ->capture_default_str()
      ->check(CLI::Range(1u, 256u));
  c->callback([a] { run(*a); });
}

}  // namespace prism::cmd
