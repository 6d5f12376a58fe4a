// What reconstruction accuracy costs in time, in one run (issue 4): events per
// second and 3D error together for the CPU reference, the dense baseline (the
// paper's way) and the sparse Vulkan path on the same events; then, on the
// sparse path, the scan tier, the shift step, half vs float dictionary,
// K = 1 vs 2, and the continuous refinement (refine.h) after the search, with
// one start or all (runners-up and lattice aliases). Memory on the device and the host for each. Writes a CSV and a
// plot of error against time per event.
//
//   bench_reconstruct [--device D] [--dictionary DIR] [--native-dictionary DIR] [--out DIR]
//                     [--events-per-position N] [--native-positions N] [--dark-rate R] [--groups G,...]
//
// --dark-rate sets the likelihood's floor per click pixel for every row
// (ReconstructionSettings::dark_rate; the bound rows' pruning depends on it).
// --groups runs only those groups of rows (backend, tier, coarse, bound, layout, loads, overlap,
// step, precision, K, refine, native); the ratios print where their rows ran.
//
// native: clicks at the sensor's own 6.9 um pixels against a full-resolution
// dictionary, and the same events binned 16 x 16 (110 um) against the same
// dictionary's level 4; then the fine clicks descended on 2 host threads,
// and with the carried PSFs ranked on 27.6 um (the clicks' level + 2, the
// default before 441.6 um). Its dictionary (--native-dictionary DIR, or built once
// in /tmp: x, y in -5, 0, 5 mm, depths 15, 20, 25, binning 1, footprint at
// 1024 cells, about 3 minutes on lavapipe) is small: the rows compare the two
// click grids on the same events, not the 1210-PSF grid's accuracy. With
// --native-positions N the events lie at N positions drawn uniformly over
// the dictionary's grid instead of three inside it: for a full-resolution
// 1210-PSF dictionary, over the whole volume.
//
// Without --dictionary it builds (or resumes) the paper's 1210-PSF grid at
// 16 x 16 binning, 4096 rays per lenslet, in /tmp. Events: the ray-traced
// forward model (16384 rays per lenslet) at six off-grid positions over the
// field, 100 photons each, clicks on 110 um pixels; two-vertex events pair
// neighbouring positions at 125 + 125 photons.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <numeric>
#include <random>
#include <memory>
#include <string>

#include "bench_util.h"
#include "host/dictionary/build.h"
#include "host/events/simulate.h"
#include "host/reconstruct/match.h"
#include "host/reconstruct/reconstruct.h"
#include "host/reconstruct/refine.h"
#include "host/util/plot.h"

using namespace prism;
namespace fs = std::filesystem;

namespace {

struct Truth {
  std::vector<glm::dvec3> vertices;
};

// One configuration's measurement.
struct Row {
  std::string group, name;
  size_t events = 0;
  double seconds_per_event = 0;  // median over repeats
  double err_mean_mm = 0, err_median_mm = 0;
  size_t catastrophic = 0;       // events whose error exceeds defaults::catastrophic_error_mm
  double scan_share = 0;         // of the time, the support scans
  uint64_t device_bytes = 0, host_peak_bytes = 0;
  uint64_t rss_bytes = 0;  // the process's peak RSS after this row (monotone over the run)
  std::vector<std::vector<ReconstructedVertex>> out;
};

// Per event, the mean 3D error of its matched vertices (host/reconstruct/match.h;
// with K = 1 on two-vertex events, the one estimate against the nearer truth).
std::vector<double> errors(const std::vector<std::vector<ReconstructedVertex>>& out, const std::vector<Truth>& truth) {
  std::vector<double> e;
  for (size_t i = 0; i < out.size(); ++i) {
    const auto& t = truth[i].vertices;
    auto which = match_vertices(out[i], t);
    double sum = 0;
    int n = 0;
    for (size_t k = 0; k < t.size(); ++k)
      if (which[k] != unmatched) sum += error_3d_mm(out[i][which[k]], t[k]), ++n;
    e.push_back(sum / n);
  }
  return e;
}

// Event `id` of one source of 100 expected photons, its clicks drawn from the event's own stream.
Event one_source_event(uint64_t id, const PsfSampler* psf) {
  Event e;
  e.id = id;
  auto rng = event_rng(7, e.id);
  ClickSource one{psf, 100.0};
  sample_clicks(std::span<const ClickSource>(&one, 1), rng, e.clicks);
  return e;
}

struct Config {
  std::string group, name;
  ReconstructionBackend backend = ReconstructionBackend::vulkan;
  int scan_level = 2;  // -1: the default for the click level
  int step = 1;
  bool half = false;
  int vertices = 1;
  int repeats = 3;
  // Continuous refinement with the scene's model on the device (refine.h):
  // 0 none; 1 from the search's answer only; 2 with the runners-up and aliases.
  int refine = 0;
  ScanLayout layout = ScanLayout::automatic;  // the sparse kernel's layout (engine/support_scan.h)
  ScanLoads loads = ScanLoads::texel;         // how the sparse kernel reads its look-ups (engine/support_scan.h)
  double carry_margin_nll = ReconstructionSettings{}.carry_margin_nll;  // coarse to fine (reconstruct.h)
  bool staged_carry = true;  // the margin at every level of the descent (reconstruct.h), or at the scan's alone
  bool fit_all_weights = false;  // the scan fits every PSF's weight (the path before the NLL bound)
  int click_level = 0;           // the dictionary level the events' clicks are on
  // Device: events per scan, and the host's work on one chunk of them beside
  // the scan of the next (reconstruct.h) or after it.
  int scan_chunk_events = defaults::scan_chunk_events;
  bool overlap_scans = true;
  double dark_rate = ReconstructionSettings{}.dark_rate;  // the likelihood's floor per click pixel (--dark-rate)
  int host_threads = 1;   // device backends: threads descending events beside the scan (reconstruct.h)
  int select_level = -1;  // coarse to fine: where the carried PSFs are ranked again (-1: select_level()'s default)
};

Row measure(vk::Context& ctx, const DictionaryReader& reader, const Config& c, const std::vector<Event>& events,
            const std::vector<Truth>& truth) {
  const bool device = c.backend != ReconstructionBackend::cpu;
  ReconstructionSettings s;
  s.vertices = c.vertices;
  s.search_level = c.scan_level >= 0 ? c.scan_level : default_search_level(reader.manifest(), c.click_level, s.tau_mm);
  s.scan_step_px = c.step;
  s.scan_layout = c.layout;
  s.scan_loads = c.loads;
  s.carry_margin_nll = c.carry_margin_nll;
  s.staged_carry = c.staged_carry;
  s.fit_all_weights = c.fit_all_weights;
  s.scan_chunk_events = c.scan_chunk_events;
  s.overlap_scans = c.overlap_scans;
  s.dark_rate = c.dark_rate;
  s.select_level = c.select_level;
  // The default host budget, shared by the host threads as prism reconstruct shares it.
  ServiceBudget budget;
  budget.host_bytes /= uint64_t(std::max(1, c.host_threads));
  DictionaryService service(reader, device ? &ctx : nullptr, s.search_level, budget, c.half);
  std::vector<std::unique_ptr<DictionaryService>> helpers;
  std::vector<DictionaryService*> helper_ptrs;
  for (int t = 1; t < c.host_threads; ++t) {
    helpers.push_back(std::make_unique<DictionaryService>(service, budget));
    helper_ptrs.push_back(helpers.back().get());
  }
  Row r;
  r.group = c.group;
  r.name = c.name;
  r.events = events.size();
  std::vector<double> per_event, share;
  std::unique_ptr<SourceModel> model;
  if (c.refine) model = make_scene_model(reader.manifest().scene, refine_trace_settings(unsigned(reader.manifest().base_binning)), &ctx);
  for (int k = 0; k < c.repeats; ++k) {
    Reconstructor rec(service, c.click_level, s, c.backend, &ctx, helper_ptrs);
    auto start = std::chrono::steady_clock::now();
    r.out = rec.run(events);
    if (model) {
      RefineSettings rs;
      if (c.refine == 1) rs.aliases = false, rs.search_starts = 0, rs.ladder_starts = 0, rs.lattice_scan = false,
                        rs.reseed = false;
      Refiner refiner(*model, reader.manifest().scene, reader.manifest().level_grid(c.click_level), rs);
      for (size_t i = 0; i < events.size(); ++i) r.out[i] = refiner.refine(events[i], std::move(r.out[i]));
    }
    double t = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    per_event.push_back(t / double(events.size()));
    share.push_back(rec.timings().scan_s / t);
    r.device_bytes = service.stats().device_bytes + rec.timings().scan_device_bytes;
  }
  r.seconds_per_event = bench::median(per_event);
  r.scan_share = bench::median(share);
  r.host_peak_bytes = service.stats().host_peak_bytes;
  for (const auto& h : helpers) r.host_peak_bytes += h->stats().host_peak_bytes;
  r.rss_bytes = bench::peak_rss_bytes();
  auto e = errors(r.out, truth);
  r.err_mean_mm = std::accumulate(e.begin(), e.end(), 0.0) / double(e.size());
  r.err_median_mm = bench::median(e);
  r.catastrophic = size_t(std::count_if(e.begin(), e.end(), [](double x) { return x > defaults::catastrophic_error_mm; }));
  return r;
}

void print(const Row& r) {
  std::printf("%-10s %-26s %6zu %10.2f %10.1f %9.3f %9.3f %6zu %7.0f%% %10.1f %10.1f %10.1f\n", r.group.c_str(),
              r.name.c_str(), r.events, r.seconds_per_event * 1e3, 1.0 / r.seconds_per_event, r.err_mean_mm,
              r.err_median_mm, r.catastrophic, 100 * r.scan_share, double(r.device_bytes) / (1 << 20), double(r.host_peak_bytes) / (1 << 20),
              double(r.rss_bytes) / (1 << 20));
  std::fflush(stdout);
}

// Whether two runs chose the same PSF and shift for every vertex.
bool same_vertices(const Row& a, const Row& b) {
  for (size_t i = 0; i < std::min(a.out.size(), b.out.size()); ++i)
    for (size_t k = 0; k < a.out[i].size(); ++k)
      if (a.out[i][k].psf != b.out[i][k].psf || a.out[i][k].shift_px != b.out[i][k].shift_px) return false;
  return true;
}

}  // namespace

int main(int argc, char** argv) {
  std::string device, dict_dir, native_dir, out_dir = "bench-reconstruct";
  int per_position = 8;
  int native_positions = 0;  // 0: three fixed positions inside the small native grid
  double dark_rate = ReconstructionSettings{}.dark_rate;
  std::string only;  // --groups: comma-separated, empty for all
  for (int i = 1; i < argc; ++i) {
    std::string a = argv[i];
    auto value = [&]() -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "bench_reconstruct: %s needs a value\n", a.c_str());
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--device") device = value();
    else if (a == "--dictionary") dict_dir = value();
    else if (a == "--native-dictionary") native_dir = value();
    else if (a == "--out") out_dir = value();
    else if (a == "--events-per-position") per_position = std::max(2, std::stoi(value()));
    else if (a == "--native-positions") native_positions = std::max(1, std::stoi(value()));
    else if (a == "--groups") only = "," + value() + ",";
    else if (a == "--dark-rate") dark_rate = std::stod(value());
    else {
      std::fprintf(stderr, "usage: bench_reconstruct [--device D] [--dictionary DIR] [--native-dictionary DIR] [--out DIR] "
                           "[--events-per-position N] [--native-positions N] [--dark-rate R] [--groups backend,tier,coarse,bound,layout,"
                           "loads,overlap,step,precision,K,refine,native]\n");
      return a == "--help" || a == "-h" ? 0 : 2;
    }
  }
  vk::Context ctx(vk::ContextOptions{device});
  Scene scene = builtin_scene("prototype");
  if (dict_dir.empty()) {
    dict_dir = (fs::temp_directory_path() / "prism-bench-reconstruct-dict").string();
    DictionaryBuildOptions o;
    o.grid = DictionaryGrid::paper();  // the grid its figures in docs/ were measured on (not the default's 2783)
    o.base_binning = 16;
    o.rays_per_lenslet = 4096;
    o.splat = Splat::point;  // as the README's demo, and the figures in docs/ measured with it
    std::fprintf(stderr, "bench_reconstruct: building (or reusing) the 1210-PSF dictionary in %s\n", dict_dir.c_str());
    build_dictionary(ctx, scene, dict_dir, o);
  }
  DictionaryReader reader(dict_dir);
  const auto& m = reader.manifest();

  TraceSettings t;
  t.binning = unsigned(m.base_binning);
  t.rays_per_lenslet = 16384;
  t.splat = Splat::point;
  ForwardTruth truth_model(ctx, m.scene, t, 16);
  const std::vector<glm::dvec3> positions{{1, 1, 31},     {-12, 7, 12}, {9, -14, 44},
                                          {17, 18, 22.5}, {-6, -3, 7},  {3, -9, 38}};
  std::vector<Event> single, pairs;
  std::vector<Truth> single_truth, pair_truth;
  uint64_t id = 0;
  for (size_t p = 0; p < positions.size(); ++p) {
    auto a = truth_model.psf(positions[p]), b = truth_model.psf(positions[(p + 1) % positions.size()]);
    for (int k = 0; k < per_position; ++k) {
      Event e = one_source_event(id++, a.get());
      single.push_back(e);
      single_truth.push_back({{positions[p]}});
      if (k < per_position / 2) {
        Event e2;
        e2.id = id++;
        auto rng2 = event_rng(7, e2.id);
        ClickSource two[2] = {{a.get(), 125.0}, {b.get(), 125.0}};
        sample_clicks(two, rng2, e2.clicks);
        pairs.push_back(e2);
        pair_truth.push_back({{positions[p], positions[(p + 1) % positions.size()]}});
      }
    }
  }
  // The slow backends see one event per position: the same events for all three.
  std::vector<Event> few;
  std::vector<Truth> few_truth;
  for (size_t i = 0; i < single.size(); i += size_t(per_position)) few.push_back(single[i]), few_truth.push_back(single_truth[i]);

  std::printf("# bench_reconstruct\n# machine: %s\n# device: %s\n", bench::machine_line().c_str(), ctx.describe().c_str());
  std::printf("# dictionary: %zu PSFs, level 0 %d x %d px (%.0f um), %d levels; clicks on level 0\n", m.grid.size(),
              m.width, m.height, m.pixel_mm(0) * 1e3, m.levels);
  std::printf("# likelihood floor (--dark-rate): %g expected counts per click pixel and event\n", dark_rate);
  std::printf("# events: forward model at %zu off-grid positions, 100 photons (pairs: 125 + 125); times: medians of "
              "3 repeats; error: 3D, against the truth\n\n",
              positions.size());
  std::printf("%-10s %-26s %6s %10s %10s %9s %9s %6s %8s %10s %10s %10s\n", "group", "configuration", "events", "ms/event",
              "events/s", "err mean", "err med", ">3 mm", "scan", "device MiB", "host MiB", "RSS MiB");

  using B = ReconstructionBackend;
  std::vector<Row> rows;
  rows.reserve(64);  // rows are referred to by reference below
  const Row not_run;
  auto run = [&](const Config& c, const std::vector<Event>& ev, const std::vector<Truth>& tr) -> const Row& {
    if (!only.empty() && only.find("," + c.group + ",") == std::string::npos) return not_run;
    Config at_floor = c;
    at_floor.dark_rate = dark_rate;
    rows.push_back(measure(ctx, reader, at_floor, ev, tr));
    print(rows.back());
    return rows.back();
  };
  // 1. Backends on the same events.
  const Row cpu = run({"backend", "cpu reference (double)", B::cpu, 2, 1, false, 1, 3}, few, few_truth);
  const Row dense = run({"backend", "dense baseline (device)", B::dense, 2, 1, false, 1, 3}, few, few_truth);
  const Row sparse = run({"backend", "sparse vulkan", B::vulkan, 2, 1, false, 1, 3}, few, few_truth);
  // The default path: the budget's scan level, coarse to fine (reconstruct.h).
  const int default_level = default_search_level(m, 0, ReconstructionSettings{}.tau_mm);
  const Row sparse_default =
      run({"backend", "sparse, default level " + std::to_string(default_level), B::vulkan, default_level, 1, false, 1, 3}, few,
          few_truth);
  // 2. The sparse path: tier, step, precision, K.
  std::map<int, const Row*> tier;
  for (int level : {1, 2, 3, 4})
    tier[level] = &run({"tier", "scan level " + std::to_string(level) + " (" + std::to_string(int(m.pixel_mm(level) * 1e3)) + " um)",
                        B::vulkan, level, 1, false, 1, 3},
                       single, single_truth);
  // Coarse to fine: the tier rows above carry every PSF within the NLL
  // margin from a coarse scan down to level 2 and rank them again there;
  // these carry the 8 best of the coarse scan alone (the margin 0).
  std::map<int, const Row*> fixed8;
  for (int level : {3, 4}) {
    Config c{"coarse", "level " + std::to_string(level) + ", 8 best carried", B::vulkan, level, 1, false, 1, 3};
    c.carry_margin_nll = 0;
    c.staged_carry = false;  // all 8 to the clicks, as these rows always measured
    fixed8[level] = &run(c, single, single_truth);
  }
  // The carry margin at every level of the descent (the default) against at
  // the scan alone, every carried PSF taken down to the select level and all
  // 8 candidates to the clicks (before). With the scans serial, the host's
  // work after each scan: by default it runs beside the next scan, and
  // where the scan takes longer, what it saves does not show.
  std::map<int, std::pair<const Row*, const Row*>> staging;
  for (int level : {3, 4}) {
    Config c{"coarse", "level " + std::to_string(level) + " serial, staged", B::vulkan, level, 1, false, 1, 3};
    c.overlap_scans = false;
    const Row* staged = &run(c, single, single_truth);
    c.name = "level " + std::to_string(level) + " serial, carry once";
    c.staged_carry = false;
    staging[level] = {staged, &run(c, single, single_truth)};
  }
  // Weights fitted only where the NLL bound can still win (the tier rows)
  // against every PSF's weight fitted, as before the bound.
  std::map<int, const Row*> every_weight;
  for (int level : {2, 3, 4}) {
    Config c{"bound", "level " + std::to_string(level) + ", every weight fitted", B::vulkan, level, 1, false, 1, 3};
    c.fit_all_weights = true;
    every_weight[level] = &run(c, single, single_truth);
  }
  // The kernel's layouts (engine/support_scan.h): the tier rows ran the
  // default for this device; these force workgroups throughout (a GPU's).
  std::map<int, const Row*> workgroups;
  for (int level : {2, 3, 4}) {
    Config c{"layout", "level " + std::to_string(level) + ", workgroup layout", B::vulkan, level, 1, false, 1, 3};
    c.layout = ScanLayout::group;
    workgroups[level] = &run(c, single, single_truth);
  }
  // The sparse kernel's look-ups through storage buffers (the way before the
  // texel buffers; engine/support_scan.h, ScanLoads) against the tier rows.
  std::map<int, const Row*> storage_loads;
  for (int level : {2, 3, 4}) {
    Config c{"loads", "level " + std::to_string(level) + ", storage-buffer loads", B::vulkan, level, 1, false, 1, 3};
    c.loads = ScanLoads::storage;
    storage_loads[level] = &run(c, single, single_truth);
  }
  // The host's work on each chunk of events beside the scan of the next, or
  // after it: chunks of 16 of the 48 events (the CLI's are 64 of 256).
  std::map<int, std::pair<const Row*, const Row*>> overlap;
  for (int level : {2, 3, 4}) {
    Config c{"overlap", "level " + std::to_string(level) + ", 16 per scan, serial", B::vulkan, level, 1, false, 1, 3};
    c.scan_chunk_events = 16;
    c.overlap_scans = false;
    const Row* serial = &run(c, single, single_truth);
    c.name = "level " + std::to_string(level) + ", 16 per scan, overlapped";
    c.overlap_scans = true;
    overlap[level] = {serial, &run(c, single, single_truth)};
  }
  for (int step : {2, 3}) run({"step", "level 2, shift step " + std::to_string(step), B::vulkan, 2, step, false, 1, 3}, single, single_truth);
  run({"step", "level 1, shift step 2", B::vulkan, 1, 2, false, 1, 3}, single, single_truth);
  run({"precision", "level 2, half dictionary", B::vulkan, 2, 1, true, 1, 3}, single, single_truth);
  run({"K", "K = 1 on two-vertex events", B::vulkan, 2, 1, false, 1, 3}, pairs, pair_truth);
  run({"K", "K = 2 on two-vertex events", B::vulkan, 2, 1, false, 2, 3}, pairs, pair_truth);
  // 3. The continuous refinement (scene model, footprint, on the device): one
  // repeat, on the slow backends' six events (seconds per event on a CPU device).
  const Row refined_one = run({"refine", "sparse + refine, one start", B::vulkan, 2, 1, false, 1, 1, 1}, few, few_truth);
  const Row refined = run({"refine", "sparse + refine, all starts", B::vulkan, 2, 1, false, 1, 1, 2}, few, few_truth);
  std::vector<Event> few_pairs;
  std::vector<Truth> few_pair_truth;
  for (size_t i = 0; i < pairs.size(); i += size_t(std::max(1, per_position / 2)))
    few_pairs.push_back(pairs[i]), few_pair_truth.push_back(pair_truth[i]);
  run({"K", "K = 2 + refine, all starts", B::vulkan, 2, 1, false, 2, 1, 2}, few_pairs, few_pair_truth);
  // The refinement's model per source: device against the double reference.
  double device_s = 0, reference_s = 0;
  const bool refine_rows = only.empty() || only.find(",refine,") != std::string::npos;
  if (refine_rows) {
    auto t = refine_trace_settings(unsigned(m.base_binning));
    auto dev = make_scene_model(m.scene, t, &ctx), ref_model = make_scene_model(m.scene, t, nullptr);
    std::vector<double> d, c;
    for (const auto& p : positions) {
      auto a = std::chrono::steady_clock::now();
      dev->render(std::span(&p, 1));
      auto b = std::chrono::steady_clock::now();
      ref_model->render(std::span(&p, 1));
      auto e = std::chrono::steady_clock::now();
      d.push_back(std::chrono::duration<double>(b - a).count());
      c.push_back(std::chrono::duration<double>(e - b).count());
    }
    device_s = bench::median(d);
    reference_s = bench::median(c);
  }

  // 4. Clicks at the sensor's own pixels (6.9 um) against a full-resolution
  // dictionary, and the same events binned to 110 um against its level 4.
  Row native_fine, native_binned, native_threads, native_select;
  if (only.empty() || only.find(",native,") != std::string::npos) {
    if (native_dir.empty()) {
      native_dir = (fs::temp_directory_path() / "prism-bench-reconstruct-native").string();
      DictionaryBuildOptions o;
      o.grid = {{-5.0, 0.0, 5.0}, {-5.0, 0.0, 5.0}, {15.0, 20.0, 25.0}};
      o.base_binning = 1;
      o.rays_per_lenslet = 1024;
      o.splat = Splat::footprint;  // a full-resolution tier worth reading (docs/dictionary.md)
      std::fprintf(stderr, "bench_reconstruct: building (or reusing) the full-resolution dictionary in %s\n",
                   native_dir.c_str());
      build_dictionary(ctx, scene, native_dir, o);
    }
    DictionaryReader native(native_dir);
    const auto& nm = native.manifest();
    if (nm.base_binning != 1) {
      std::fprintf(stderr, "bench_reconstruct: %s: --native-dictionary needs a full-resolution dictionary (binning 1)\n",
                   native_dir.c_str());
      return 2;
    }
    // Truth: 4x the model's cells, another stratification.
    TraceSettings nt;
    nt.binning = 1;
    nt.rays_per_lenslet = 4096;
    nt.splat = Splat::footprint;
    nt.stratification = 1;
    ForwardTruth native_truth(ctx, nm.scene, nt, 4);
    // Three positions inside the small grid, or --native-positions drawn
    // uniformly over the dictionary's grid (for a 1210-PSF one: the volume).
    std::vector<glm::dvec3> inner{{1, 1, 21}, {-2, 1.5, 18}, {2.5, -1.5, 23}};
    if (native_positions > 0) {
      inner.clear();
      std::mt19937_64 rng(5);
      auto uniform = [&](const std::vector<double>& axis) {
        return std::uniform_real_distribution<double>(axis.front(), axis.back())(rng);
      };
      for (int k = 0; k < native_positions; ++k) {
        const double x = uniform(nm.grid.x_mm), y = uniform(nm.grid.y_mm);
        inner.push_back({x, y, uniform(nm.grid.depth_mm)});
      }
    }
    std::printf("# native: %zu positions x %d events%s\n", inner.size(), per_position,
                native_positions > 0 ? ", uniform over the dictionary's grid" : "");
    const int binned_level = 4;  // 110 um (16 x 16 sensor pixels): level 4 of a full-resolution dictionary
    const uint32_t w0 = uint32_t(nm.width), wb = uint32_t(nm.level_width(binned_level));
    std::vector<Event> fine, binned;
    std::vector<Truth> native_truths;
    for (const auto& p : inner) {
      auto psf = native_truth.psf(p);
      for (int k = 0; k < per_position; ++k) {
        Event e = one_source_event(id++, psf.get());
        // The same photons on 16 x 16 blocks: a block clicks when any of its pixels does.
        Event b = e;
        b.clicks = binned_clicks(e.clicks, w0, binned_level, wb);
        fine.push_back(std::move(e));
        binned.push_back(std::move(b));
        native_truths.push_back({{p}});
      }
    }
    auto run_native = [&](const Config& c, const std::vector<Event>& ev) {
      Config at_floor = c;
      at_floor.dark_rate = dark_rate;
      Row r = measure(ctx, native, at_floor, ev, native_truths);
      print(r);
      rows.push_back(r);
      return r;
    };
    Config fine_c{"native", "6.9 um clicks, default scan", B::vulkan, -1};
    fine_c.click_level = 0;
    Config binned_c{"native", "110 um (binned), default scan", B::vulkan, -1};
    binned_c.click_level = binned_level;
    native_fine = run_native(fine_c, fine);
    native_binned = run_native(binned_c, binned);
    // The host's descent through the tiles takes most of the fine clicks'
    // time where the scan is coarse: on two host threads, and (one thread)
    // with the carried PSFs ranked on the clicks' level + 2 (27.6 um), the
    // default before 441.6 um.
    Config threads_c = fine_c;
    threads_c.name = "6.9 um clicks, 2 threads";
    threads_c.host_threads = 2;
    native_threads = run_native(threads_c, fine);
    Config select_c = fine_c;
    select_c.name = "6.9 um, ranked on 27.6 um";
    select_c.select_level = 2;
    native_select = run_native(select_c, fine);
  }

  auto ran = [](const Row& r) { return r.events > 0; };
  if (ran(cpu) && ran(dense) && ran(sparse)) {
    std::printf("\nratios (same %zu events, same vertices chosen: cpu %s, dense %s):\n", few.size(),
                same_vertices(cpu, sparse) ? "yes" : "NO", same_vertices(dense, sparse) ? "yes" : "NO");
    std::printf("  sparse vulkan vs cpu reference:  %.1fx faster\n", cpu.seconds_per_event / sparse.seconds_per_event);
    std::printf("  sparse vulkan vs dense baseline: %.1fx faster\n", dense.seconds_per_event / sparse.seconds_per_event);
  }
  if (ran(dense) && ran(sparse_default))
    std::printf("  sparse at the default level %d (coarse to fine) vs the dense baseline: %.1fx faster, same vertices %s\n",
                default_level, dense.seconds_per_event / sparse_default.seconds_per_event,
                same_vertices(dense, sparse_default) ? "yes" : "NO");
  for (auto [level, f] : fixed8)
    if (ran(*f) && ran(*tier[level]) && ran(*tier[2]))
      std::printf("  level %d coarse to fine (margin %.0f) vs exhaustive level 2: %.1fx faster, error mean %.2f vs %.2f mm, "
                  "median %.2f vs %.2f mm (8 best carried alone: %.2f / %.2f mm)\n",
                  level, ReconstructionSettings{}.carry_margin_nll, tier[2]->seconds_per_event / tier[level]->seconds_per_event,
                  tier[level]->err_mean_mm, tier[2]->err_mean_mm, tier[level]->err_median_mm, tier[2]->err_median_mm,
                  f->err_mean_mm, f->err_median_mm);
  for (auto [level, pair] : staging)
    if (ran(*pair.first) && ran(*pair.second))
      std::printf("  level %d, the carry margin at every level vs at the scan alone (scans serial): %.2fx faster, same "
                  "vertices %s\n",
                  level, pair.second->seconds_per_event / pair.first->seconds_per_event,
                  same_vertices(*pair.first, *pair.second) ? "yes" : "NO");
  for (auto [level, a] : every_weight)
    if (ran(*a) && ran(*tier[level]))
      std::printf("  level %d, weights fitted where the NLL bound can win vs every weight fitted: %.2fx faster, same "
                  "vertices %s\n",
                  level, a->seconds_per_event / tier[level]->seconds_per_event, same_vertices(*a, *tier[level]) ? "yes" : "NO");
  for (auto [level, w] : workgroups)
    if (ran(*w) && ran(*tier[level]))
      std::printf("  level %d, this device's layout vs workgroups throughout: %.2fx faster, same vertices %s\n", level,
                  w->seconds_per_event / tier[level]->seconds_per_event, same_vertices(*w, *tier[level]) ? "yes" : "NO");
  for (auto [level, s] : storage_loads)
    if (ran(*s) && ran(*tier[level]))
      std::printf("  level %d, texel-buffer look-ups vs storage buffers: %.2fx faster, same vertices %s\n", level,
                  s->seconds_per_event / tier[level]->seconds_per_event, same_vertices(*s, *tier[level]) ? "yes" : "NO");
  for (auto [level, rows2] : overlap)
    if (ran(*rows2.first) && ran(*rows2.second))
      std::printf("  level %d, the host's work on a chunk beside the scan of the next vs after it: %.2fx faster, same "
                  "vertices %s\n",
                  level, rows2.first->seconds_per_event / rows2.second->seconds_per_event,
                  same_vertices(*rows2.first, *rows2.second) ? "yes" : "NO");
  if (ran(sparse) && ran(refined_one))
    std::printf("  refinement (one start) vs search alone: %.1fx the time, mean error %.2f -> %.2f mm, median %.2f -> %.2f mm\n",
                refined_one.seconds_per_event / sparse.seconds_per_event, sparse.err_mean_mm, refined_one.err_mean_mm,
                sparse.err_median_mm, refined_one.err_median_mm);
  if (ran(refined) && ran(refined_one))
    std::printf("  refinement (all starts) vs one start: %.1fx the time, mean error %.2f -> %.2f mm\n",
                refined.seconds_per_event / refined_one.seconds_per_event, refined_one.err_mean_mm, refined.err_mean_mm);
  if (ran(native_fine) && ran(native_binned))
    std::printf("  6.9 um clicks vs the same events binned to 110 um (full-resolution dictionary, %zu events): %.2fx "
                "the time per event (%.1f vs %.1f events/s), error mean %.3f vs %.3f mm, median %.3f vs %.3f mm\n",
                native_fine.events, native_fine.seconds_per_event / native_binned.seconds_per_event,
                1 / native_fine.seconds_per_event, 1 / native_binned.seconds_per_event, native_fine.err_mean_mm,
                native_binned.err_mean_mm, native_fine.err_median_mm, native_binned.err_median_mm);
  if (ran(native_fine) && ran(native_threads) && ran(native_select))
    std::printf("  6.9 um clicks on 2 host threads vs 1: %.2fx faster, same vertices %s; carried PSFs ranked on 441.6 um "
                "(default) vs 27.6 um: %.2fx faster, error mean %.3f vs %.3f mm, median %.3f vs %.3f mm, > 3 mm %zu vs %zu\n",
                native_fine.seconds_per_event / native_threads.seconds_per_event,
                same_vertices(native_fine, native_threads) ? "yes" : "NO",
                native_select.seconds_per_event / native_fine.seconds_per_event, native_fine.err_mean_mm,
                native_select.err_mean_mm, native_fine.err_median_mm, native_select.err_median_mm, native_fine.catastrophic,
                native_select.catastrophic);
  if (refine_rows)
    std::printf("  refinement model per source (footprint, %u cells per lenslet, median of %zu positions): device %.3f s, "
              "double reference %.3f s (%.1fx)\n",
              defaults::refine_rays_per_lenslet, positions.size(), device_s, reference_s, reference_s / device_s);
  std::printf("scan = share of the time in the support scans (the rest: refinement from disk tiles, weights, "
              "descent, depth, on the host). device MiB: resident scan level + event/result buffers; host MiB: "
              "peak of summed-area tables and tile cache; RSS MiB: the process's peak resident set so far (it "
              "only grows: a row's own peak shows where it rises).\n");

  fs::create_directories(out_dir);
  {
    std::ofstream csv(out_dir + "/reconstruct.csv");
    csv << "group,configuration,events,ms_per_event,events_per_s,err_mean_mm,err_median_mm,beyond_3mm,scan_share,device_mib,"
           "host_mib,peak_rss_mib\n";
    for (const auto& r : rows)
      csv << r.group << ',' << r.name << ',' << r.events << ',' << r.seconds_per_event * 1e3 << ','
          << 1 / r.seconds_per_event << ',' << r.err_mean_mm << ',' << r.err_median_mm << ',' << r.catastrophic << ',' << r.scan_share << ','
          << double(r.device_bytes) / (1 << 20) << ',' << double(r.host_peak_bytes) / (1 << 20) << ','
          << double(r.rss_bytes) / (1 << 20) << '\n';
  }
  std::map<std::string, Series> groups;
  std::vector<std::string> order;
  for (const auto& r : rows) {
    if (r.group == "K") continue;  // other events: not on the same axis
    if (!groups.count(r.group)) order.push_back(r.group), groups[r.group] = {r.group, {}, {}, false, true};
    groups[r.group].x.push_back(r.seconds_per_event * 1e3);
    groups[r.group].y.push_back(r.err_mean_mm);
  }
  std::vector<Series> series;
  for (const auto& g : order) series.push_back(groups[g]);
  plot_lines(out_dir + "/reconstruct.png",
             {"3D error against time per event (" + ctx.describe() + ")", "time per event (ms)", "mean 3D error (mm)",
              false, true},
             series);
  std::fprintf(stderr, "bench_reconstruct: wrote %s/reconstruct.csv and reconstruct.png\n", out_dir.c_str());
  return 0;
}
