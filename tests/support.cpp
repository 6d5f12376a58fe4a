#include "support.h"

#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cstdlib>
#include <cstdio>
#include <memory>
#include <sstream>

namespace prism::test {

namespace {
vk::Context* created = nullptr;
}

vk::Context& gpu() {
  static vk::Context ctx(vk::ContextOptions{"", true});
  created = &ctx;
  return ctx;
}

namespace {
unsigned g_test_case = 0;  // the test case this process is running, counted from 1
}

void begin_test_case() { ++g_test_case; }

std::filesystem::path scratch_dir() {
  struct Scratch {
    std::filesystem::path path =
        std::filesystem::temp_directory_path() / ("prism-test-" + std::to_string(::getpid()));
    ~Scratch() {
      std::error_code ignored;  // nothing to report from an exiting process
      std::filesystem::remove_all(path, ignored);
    }
  };
  static const Scratch process;
  auto dir = process.path / ("case-" + std::to_string(g_test_case));
  std::filesystem::create_directories(dir);
  return dir;
}

size_t validation_message_count() { return created ? created->validation_messages().size() : 0; }

void check_validation_clean() {
  const auto& m = gpu().validation_messages();
  INFO("validation layer messages: " << m.size() << (m.empty() ? "" : ", first: " + m.front()));
  CHECK(m.empty());
}

OpticalSystem small_system(LensModel model) {
  OpticalSystem s = builtin_scene("prototype").optics;
  s.lens_model = model;
  // The seven lenslets of a central row keep the reference fast; an outer row
  // would image near sources off the sensor.
  s.lenslets = std::vector<LensletGeometry>(s.lenslets.begin() + 14, s.lenslets.begin() + 21);
  return s;
}

CommandResult run_prism(const std::string& args, const std::string& env) {
  using clock = std::chrono::steady_clock;
  const auto start = clock::now();
  std::string cmd = env + " " + std::string(PRISM_BINARY) + " " + args + " 2>&1";
  std::unique_ptr<FILE, int (*)(FILE*)> pipe(popen(cmd.c_str(), "r"), &pclose);
  REQUIRE(pipe);
  std::string out;
  std::array<char, 4096> buf;
  size_t n;
  while ((n = fread(buf.data(), 1, buf.size(), pipe.get())) > 0) out.append(buf.data(), n);
  int status = pclose(pipe.release());
  // PRISM_TEST_TIMES=1: each command's seconds on stderr, for finding where a
  // slow test file spends its time (doctest -d times only whole cases).
  if (const char* times = std::getenv("PRISM_TEST_TIMES"); times && *times == '1')
    std::fprintf(stderr, "[%.1f s] prism %s\n", std::chrono::duration<double>(clock::now() - start).count(),
                 args.substr(0, 160).c_str());
  return {WEXITSTATUS(status), out};
}

std::vector<double> channel(const PixelImage& v, int c) {
  std::vector<double> out(size_t(v.width) * size_t(v.height));
  for (size_t i = 0; i < out.size(); ++i) out[i] = v.data[4 * i + size_t(c)];
  return out;
}

std::vector<double> channel(const ref::SparseImage& r, int c) {
  std::vector<double> out(size_t(r.width) * size_t(r.height), 0.0);
  for (const auto& [k, px] : r.pixels) out[size_t(k)] = r.value(k)[size_t(c)];
  return out;
}

std::vector<std::string> csv_fields(const std::string& line) {
  std::vector<std::string> fields;
  std::stringstream ss(line);
  for (std::string cell; std::getline(ss, cell, ',');) fields.push_back(cell);
  if (!line.empty() && line.back() == ',') fields.emplace_back();  // an empty last field
  return fields;
}

Event sample_event(EventTruth& truth, const std::vector<EventSource>& sources, uint64_t seed, uint64_t id) {
  Event e;
  e.id = id;
  std::vector<std::shared_ptr<const PsfSampler>> held;
  std::vector<ClickSource> cs;
  for (const auto& s : sources) {
    held.push_back(truth.psf(s.position_mm));
    cs.push_back({held.back().get(), s.alpha});
    e.vertices.push_back({s.position_mm.x, s.position_mm.y, s.position_mm.z, s.alpha, held.back()->sensor_fraction()});
  }
  auto rng = event_rng(seed, id);
  sample_clicks(cs, rng, e.clicks);
  return e;
}

}  // namespace prism::test
