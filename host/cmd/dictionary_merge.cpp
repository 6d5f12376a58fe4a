// prism dictionary merge-hdr: per-pixel HDR merge of calibration stacks
// (paper Sec. III.A.2) into normalised PSFs, one OpenEXR + JSON sidecar each.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <set>

#include "engine/hdr_merge.h"
#include "engine/ref/hdr_merge_ref.h"
#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/dictionary/hdr_stack.h"
#include "host/util/image_io.h"

namespace fs = std::filesystem;

namespace prism::cmd {

namespace {

struct MergeArgs {
  std::vector<std::string> stacks;
  std::string parent;
  std::string out;
  std::string backend = "vulkan";
  std::string device;
  bool skip_existing = false;
  HdrOptions hdr;
};

nlohmann::json sidecar(const HdrStack& s, const HdrResult& r, const MergeArgs& a, const std::string& device) {
  const HdrFrames& f = s.frames;
  const HdrOptions& o = a.hdr;
  nlohmann::json j = {
      {"format_version", 1},
      {"stack", fs::absolute(s.dir).string()},
      {"source", {{"x_mm", s.source_mm.x}, {"y_mm", s.source_mm.y}, {"depth_mm", s.source_mm.z}}},
      {"width", f.width},
      {"height", f.height},
      {"bit_depth", f.bit_depth},
      {"pixel_format", s.pixel_format},
      {"backend", a.backend},
      {"device", device},
      {"exposures", nlohmann::json::array()},
      {"darks", nlohmann::json::array()},
      {"dark_model", r.limits.dark_linear ? "linear" : "constant"},
      {"dark_stats",
       {{"median_dn", r.dark.median_dn}, {"spread_dn", r.dark.spread_dn}, {"read_noise_dn", r.dark.read_noise_dn}}},
      {"limits_dn",
       {{"saturation", r.limits.saturation_dn}, {"floor", r.limits.floor_dn}, {"hot_dark", r.limits.hot_dark_dn}}},
      {"options",
       {{"min_valid_exposures", o.min_valid_exposures},
        {"min_correlation", o.min_correlation},
        {"saturation_margin", o.saturation_margin},
        {"floor_sigmas", o.floor_sigmas},
        {"floor_min_dn", o.floor_min_dn},
        {"hot_dark_spreads", o.hot_dark_spreads},
        {"dark_model", o.dark_model}}},
      {"normalisation", {{"sum_dn_per_s", r.sum_dn_per_s}, {"psf_sum", 1.0}}}};
  for (size_t i = 0; i < f.exposures.size(); ++i)
    j["exposures"].push_back({{"exposure_us", f.exposure_s[i] * 1e6},
                              {"file", s.exposure_files[i]},
                              {"kept_pixels_using", r.kept_using_exposure[i]}});
  for (size_t i = 0; i < f.darks.size(); ++i)
    j["darks"].push_back({{"exposure_us", f.dark_s[i] * 1e6}, {"file", s.dark_files[i]}});
  nlohmann::json rejected;
  for (size_t k = 1; k < kHdrReasons; ++k) rejected[to_string(HdrReason(k))] = r.pixels_by_reason[k];
  j["pixels"] = {{"kept", r.pixels_by_reason[0]}, {"rejected", rejected}};
  return j;
}

void run(const MergeArgs& a) {
  a.hdr.validate();
  std::vector<std::string> dirs = a.stacks;
  if (!a.parent.empty())
    for (const auto& d : find_hdr_stacks(a.parent)) dirs.push_back(d);
  if (dirs.empty()) throw std::invalid_argument("merge-hdr: give --stack DIR (repeatable) or --stacks PARENT");
  // Outputs are named after the stack directories, so those must differ.
  std::map<std::string, std::string> names;
  for (const auto& d : dirs) {
    std::string name = fs::path(d).lexically_normal().filename().string();
    if (name.empty() || name == ".") name = fs::absolute(d).lexically_normal().parent_path().filename().string();
    if (!names.emplace(name, d).second)
      throw std::invalid_argument("merge-hdr: stacks " + names[name] + " and " + d + " would both write " + name +
                                  ".exr: rename one directory");
  }
  // Every stack's stack.json and file sizes before any output: a bad one
  // named now, not after the others were merged.
  for (const auto& [name, dir] : names) (void)read_hdr_stack_header(dir);
  fs::create_directories(a.out);

  std::unique_ptr<vk::Context> ctx;
  std::unique_ptr<HdrMergeVulkan> merger;
  std::string device = "CPU reference (double precision)";
  if (a.backend == "vulkan") {
    ctx = std::make_unique<vk::Context>(vk::ContextOptions{a.device});
    merger = std::make_unique<HdrMergeVulkan>(*ctx);
    device = ctx->describe();
  }
  std::fprintf(stderr, "prism merge-hdr: %zu stack(s), device: %s\n", dirs.size(), device.c_str());
  std::printf("%-24s %8s %8s %8s %10s %10s %10s %8s %9s %12s\n", "stack", "x_mm", "y_mm", "depth", "kept",
              "saturated", "faint", "hot", "nonlinear", "sum_dn_per_s");
  size_t index = 0;
  bool warned_constant_dark = false;
  for (const auto& [name, dir] : names) {
    ++index;
    std::string exr = (fs::path(a.out) / (name + ".exr")).string();
    std::string json = (fs::path(a.out) / (name + ".json")).string();
    if (a.skip_existing && fs::exists(json) && fs::exists(exr)) {
      std::fprintf(stderr, "prism merge-hdr: [%zu/%zu] %s: exists, skipped\n", index, dirs.size(), name.c_str());
      continue;
    }
    auto start = std::chrono::steady_clock::now();
    HdrStack stack = read_hdr_stack(dir);
    HdrResult r = merger ? merger->merge(stack.frames, a.hdr) : ref::hdr_merge(stack.frames, a.hdr);
    const auto& dark_s = stack.frames.dark_s;
    const bool one_dark_time = std::all_of(dark_s.begin(), dark_s.end(), [&](double t) { return t == dark_s.front(); });
    if (!r.limits.dark_linear && one_dark_time && !warned_constant_dark) {
      warned_constant_dark = true;
      std::fprintf(stderr,
                   "prism merge-hdr: note: %s's darks lie at one exposure time, so their level is subtracted from "
                   "every exposure and each pixel's dark current is over-subtracted from the shorter ones by rate x "
                   "(T_dark - T), which puts errors of a few per cent on the faint pixels (engine/hdr_times.h). Capture darks at two or "
                   "more times (capture-hdr and simulate-hdr spread --darks over the exposures).\n",
                   name.c_str());
    }
    std::vector<float> valid(r.status.size());
    for (size_t i = 0; i < valid.size(); ++i) valid[i] = HdrResult::reason(r.status[i]) == HdrReason::kept;
    write_exr(exr, r.width, r.height, {{"Y", r.psf.data()}, {"valid", valid.data()}});
    // The sidecar goes last: its presence says the PSF beside it is whole.
    std::string text = sidecar(stack, r, a, device).dump(2);
    write_atomically(json, [&](const std::string& tmp) {
      std::ofstream out(tmp);
      out << text << '\n';
      if (!out) throw std::runtime_error("cannot write " + json);
    });
    double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    const auto& n = r.pixels_by_reason;
    std::printf("%-24s %8.2f %8.2f %8.2f %10llu %10llu %10llu %8llu %9llu %12.6g\n", name.c_str(), stack.source_mm.x,
                stack.source_mm.y, stack.source_mm.z, (unsigned long long)n[0], (unsigned long long)n[2],
                (unsigned long long)n[3], (unsigned long long)n[1], (unsigned long long)n[4], r.sum_dn_per_s);
    std::fflush(stdout);
    std::fprintf(stderr, "prism merge-hdr: [%zu/%zu] %s: %.1f%% of pixels kept, %.2f s -> %s\n", index, dirs.size(),
                 name.c_str(), 100.0 * double(n[0]) / double(r.status.size()), s, exr.c_str());
  }
}

}  // namespace

void add_dictionary_merge_hdr(CLI::App& dictionary) {
  auto a = std::make_shared<MergeArgs>();
  HdrOptions& o = a->hdr;
  CLI::App* c = dictionary.add_subcommand(
      "merge-hdr", "merge capture-hdr exposure stacks into normalised PSFs (paper Sec. III.A.2): OpenEXR + JSON");
  c->add_option("--stack", a->stacks, "a capture-hdr stack directory (holds stack.json); repeatable");
  c->add_option("--stacks", a->parent, "a directory holding one stack per subdirectory");
  c->add_option("--out", a->out, "output directory: <stack name>.exr (channels Y, valid) and <stack name>.json")
      ->required();
  c->add_option("--backend", a->backend, "vulkan (the kernel) or cpu (the double-precision reference)")
      ->capture_default_str()
      ->check(CLI::IsMember({"vulkan", "cpu"}));
  c->add_option("--device", a->device, device_help);
  c->add_flag("--skip-existing", a->skip_existing, "skip stacks whose .exr and .json are already written (resume)");
  c->add_option("--min-valid", o.min_valid_exposures, "valid exposures a kept pixel needs (paper: 3)")
      ->capture_default_str()
      ->check(CLI::Range(2, 16));
  c->add_option("--min-correlation", o.min_correlation,
                "keep a pixel only if Pearson r of (raw - dark) against T exceeds this (paper: 0.95)")
      ->capture_default_str()
      ->check(CLI::Range(-1.0, 1.0));
  c->add_option("--saturation-margin", o.saturation_margin,
                "raw >= (1 - margin) * (2^bit_depth - 1) counts as saturated")
      ->capture_default_str()
      ->check(CLI::Range(0.0, 0.5));
  c->add_option("--floor-sigmas", o.floor_sigmas, "valid only if raw - dark > this many dark-noise sigmas")
      ->capture_default_str()
      ->check(non_negative_number);
  c->add_option("--floor-min-dn", o.floor_min_dn, "... and raw - dark > this many DN (quantisation)")
      ->capture_default_str()
      ->check(non_negative_number);
  c->add_option("--hot-dark-spreads", o.hot_dark_spreads,
                "reject pixels whose dark level exceeds the frame median by this many robust spreads")
      ->capture_default_str()
      ->check(positive_number);
  c->add_option("--dark-model", o.dark_model,
                "dark level against T: linear (offset + rate*T, needs darks at 2+ times), constant, or auto")
      ->capture_default_str()
      ->check(CLI::IsMember({"auto", "linear", "constant"}));
  c->callback([a] { run(*a); });
}

}  // namespace prism::cmd
