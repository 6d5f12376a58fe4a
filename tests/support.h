// Shared test fixtures: one Vulkan context per test process (validation on),
// and the check that the validation layer stayed silent.
#pragma once
#include <doctest/doctest.h>

#include <filesystem>
#include <string>
#include <vector>

#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "engine/vk/context.h"
#include "host/events/event_file.h"
#include "host/events/simulate.h"
#include "host/scene/scene.h"

namespace prism::test {

// True in the sanitizer build (tests/sanitize.sh). That build looks for
// memory errors and undefined behaviour, which a smaller problem reaches
// through the same code; host-side numerics run 5-15 times slower under the
// sanitizers, so the heaviest runs take fewer events there. The normal build
// checks the numbers at full size.
#ifdef PRISM_SANITIZE
inline constexpr bool under_sanitizer = true;
#else
inline constexpr bool under_sanitizer = false;
#endif
// For a case whose size is its point (an acceptance figure at full size,
// the whole 1210-PSF grid) and whose code other cases of the suite run at
// smaller sizes: skipped in the sanitizer build, whose suite has to fit in
// CI's time after the normal one (.ci/run). TEST_CASE("..." * skip_under_sanitizer).
inline const doctest::skip skip_under_sanitizer{under_sanitizer};

vk::Context& gpu();
// Fails the current test if the validation layer printed anything.
void check_validation_clean();
// Messages the validation layer printed in this process (0 if no GPU test ran).
size_t validation_message_count();
// The running test case's own folder, prism-test-PID/case-N under the system's
// temp directory (a process runs a whole file's test cases, and one case's
// files must not meet the next's): made on first use, and removed with the
// process's folder when it exits, so that the suite leaves nothing behind.
std::filesystem::path scratch_dir();
// Called by the test runner (main.cpp) as each test case starts.
void begin_test_case();

// The allowance, per unit of a channel's peak, between two renders of the
// same inputs. Float atomic adds sum a pixel's light in the order
// invocations reach it, which varies from run to run: in the last digit on
// lavapipe when its threads contend (2 threads, a loaded machine) and on a
// GPU always (an H200: 2e-7 of the peak); the footprint's split lists are
// also appended in whatever order workgroups finish.
inline constexpr double same_render_tolerance = 1e-6;

// A scene small enough for exhaustive CPU-reference comparisons.
OpticalSystem small_system(LensModel model);

// Runs the prism binary with `args`, after the environment assignments in
// `env`; stdout and stderr together.
struct CommandResult {
  int status;
  std::string output;
};
CommandResult run_prism(const std::string& args, const std::string& env = "");

// The comma-separated fields of one CSV line (no quoting: the project's CSVs have none).
std::vector<std::string> csv_fields(const std::string& line);

// Channel c (0: b; 1..3: its derivatives) of an image, pixel by pixel, as
// doubles (the reference's derivative: the mean of its two halves).
std::vector<double> channel(const PixelImage& v, int c);

// One event from `truth`: sources (position, expected photons) sampled with
// the random stream of (seed, id), the truth recorded per vertex.
struct EventSource {
  glm::dvec3 position_mm;
  double alpha;
};
Event sample_event(EventTruth& truth, const std::vector<EventSource>& sources, uint64_t seed, uint64_t id);
std::vector<double> channel(const ref::SparseImage& r, int c);

}  // namespace prism::test
