#include "engine/forward.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <memory>

#include "engine/shared_math.h"
#include "engine/vk/error.h"
#include "spv/fisher_reduce.spv.h"
#include "spv/landing_points.spv.h"
#include "spv/psf_footprint.spv.h"
#include "spv/psf_footprint_blur.spv.h"
#include "spv/psf_footprint_as_built.spv.h"
#include "spv/psf_footprint_as_built_blur.spv.h"
#include "spv/psf_footprint_calibrate.spv.h"
#include "spv/psf_footprint_calibrate_blur.spv.h"
#include "spv/psf_footprint_cut.spv.h"
#include "spv/psf_footprint_cut_blur.spv.h"
#include "spv/psf_footprint_cut_as_built.spv.h"
#include "spv/psf_footprint_cut_as_built_blur.spv.h"
#include "spv/psf_footprint_cut_calibrate.spv.h"
#include "spv/psf_footprint_cut_calibrate_blur.spv.h"
#include "spv/psf_footprint_large.spv.h"
#include "spv/psf_footprint_large_blur.spv.h"
#include "spv/psf_footprint_large_as_built.spv.h"
#include "spv/psf_footprint_large_as_built_blur.spv.h"
#include "spv/psf_footprint_large_calibrate.spv.h"
#include "spv/psf_footprint_large_calibrate_blur.spv.h"
#include "spv/psf_footprint_split.spv.h"
#include "spv/psf_footprint_split_blur.spv.h"
#include "spv/psf_footprint_split_as_built.spv.h"
#include "spv/psf_footprint_split_as_built_blur.spv.h"
#include "spv/psf_footprint_split_calibrate.spv.h"
#include "spv/psf_footprint_split_calibrate_blur.spv.h"
#include "spv/psf_splat.spv.h"
#include "spv/psf_splat_blur.spv.h"
#include "spv/psf_splat_as_built.spv.h"
#include "spv/psf_splat_as_built_blur.spv.h"
#include "spv/psf_splat_calibrate.spv.h"
#include "spv/psf_splat_calibrate_blur.spv.h"

namespace prism {

namespace {

constexpr uint32_t kSplatGroup = 64;
constexpr uint32_t kReduceChunk = 256 * 16;  // pixels per reduce workgroup (fisher_reduce.comp)
constexpr uint32_t kPartialFloats = 16;
constexpr uint64_t kPixelBytes = 32;  // b, grad b from ray half A, from half B, unused (psf_splat.comp)
constexpr uint64_t kKeptImageBytes = 16ull << 20;  // a single source's image kept between renders up to this size

template <size_t N> std::span<const uint32_t> spirv(const uint32_t (&code)[N]) { return {code, N}; }

}  // namespace

std::vector<shared::Lenslet> device_lenslets(const OpticalSystem& sys, const TraceSettings& settings) {
  std::vector<shared::Lenslet> out(sys.lenslets.size());
  uint64_t first = 0;
  for (size_t i = 0; i < out.size(); ++i) {
    const auto& l = sys.lenslets[i];
    shared::Lenslet& d = out[i];
    d.center_mm = glm::vec2(float(l.x_mm), float(l.y_mm));
    d.radius_mm = float(0.5 * l.diameter_mm);
    d.focal_mm = float(l.focal_mm);
    d.curvature_radius_mm = float(sys.curvature_radius_mm(i));
    d.thickness_mm = float(sys.center_thickness_mm(i));
    d.sag_mm = float(sys.sag_mm(i));
    d.glass_index = float(sys.glass_index);
    d.curved_toward_sensor = sys.curved_toward_sensor ? 1 : 0;
    d.strata = settings.strata_for(l.diameter_mm);
    d.first_ray = uint32_t(first);
    d.tilt_x_rad = float(l.tilt_x_deg * M_PI / 180.0);
    d.tilt_y_rad = float(l.tilt_y_deg * M_PI / 180.0);
    d.index = uint32_t(i);
    first += uint64_t(d.strata) * d.strata;
    if (first > 0xffffffffull) throw std::invalid_argument("more than 2^32 rays per source: lower --rays");
  }
  return out;
}

double PixelImage::photons() const {
  double s = 0;
  for (size_t i = 0; i < data.size(); i += 4) s += data[i];
  return s;
}

// Which variant of the splat kernels a forward model runs
// (shaders/CMakeLists.txt): the plain one, the as-built one when a design
// traced is as built, the calibrate one for derivatives by scene parameters.
enum class Variant { plain, as_built, calibrate };
// Each variant is built twice, with the Airy blur's code (effect
// diffraction) and without it (why: shaders/CMakeLists.txt).
using KernelBuilds = std::array<std::span<const uint32_t>, 6>;  // by Variant, then the same with the blur
#define PRISM_KERNEL_BUILDS(k)                                                                                      \
  KernelBuilds {                                                                                                   \
    spirv(spv_##k), spirv(spv_##k##_as_built), spirv(spv_##k##_calibrate), spirv(spv_##k##_blur),                  \
        spirv(spv_##k##_as_built_blur), spirv(spv_##k##_calibrate_blur)                                            \
  }
std::span<const uint32_t> pick_build(const KernelBuilds& builds, Variant v, const OpticalSystem& sys) {
  return builds[size_t(v) + (sys.effects.diffraction ? 3 : 0)];
}
// The splat kernel of the settings (both take the same buffers and constants).
std::span<const uint32_t> splat_spirv(const TraceSettings& t, Variant v, const OpticalSystem& sys) {
  static const KernelBuilds footprint = PRISM_KERNEL_BUILDS(psf_footprint), point = PRISM_KERNEL_BUILDS(psf_splat);
  return pick_build(t.splat == Splat::footprint ? footprint : point, v, sys);
}
uint32_t splat_buffers(const TraceSettings& t) { return t.splat == Splat::footprint ? 8 : 5; }
std::string kernel_name(const TraceSettings& t, bool values_only) {
  return std::string(t.splat == Splat::footprint ? "psf_footprint" : "psf_splat") + (values_only ? " (values)" : "");
}

// The splat kernels' specialisation constants (splat_image.glsl): lens
// model, effects, derivatives. (Diffraction picks the build: pick_build.)
std::vector<uint32_t> specialisation(const OpticalSystem& s, bool derivatives) {
  return {uint32_t(s.lens_model == LensModel::real ? shared::LENS_REAL : shared::LENS_THIN),
          uint32_t(s.effects.scintillator_refraction), uint32_t(s.effects.holder_vignetting), uint32_t(derivatives),
          uint32_t(s.effects.source_extent)};
}

bool any_as_built(const std::vector<OpticalSystem>& designs) {
  return std::any_of(designs.begin(), designs.end(), [](const OpticalSystem& s) { return s.as_built(); });
}

// The trace constants that come from the scene's geometry (set_scene may
// change them).
void set_scene_params(shared::TraceParams& p, const OpticalSystem& s) {
  p.lens_to_sensor_mm = float(s.lens_to_sensor_mm);
  p.working_distance_mm = float(s.working_distance_mm);
  p.sensor_offset_x_mm = float(s.sensor_pose.offset_x_mm);
  p.sensor_offset_y_mm = float(s.sensor_pose.offset_y_mm);
  p.sensor_tilt_x_rad = float(s.sensor_pose.tilt_x_deg * M_PI / 180.0);
  p.sensor_tilt_y_rad = float(s.sensor_pose.tilt_y_deg * M_PI / 180.0);
  p.airy_half_side_mm_times_diameter = float(s.airy_half_side_mm_times_diameter());
}

// The lenslets of every design, one after the other, and each design's range.
struct DesignBuffers {
  std::vector<shared::Lenslet> lenses;
  std::vector<shared::DesignRange> ranges;
  uint32_t max_rays = 0;
};

DesignBuffers design_buffers(const std::vector<OpticalSystem>& designs, const TraceSettings& t) {
  DesignBuffers b;
  for (const auto& sys : designs) {
    std::vector<shared::Lenslet> dev = device_lenslets(sys, t);
    uint32_t rays = dev.back().first_ray + dev.back().strata * dev.back().strata;
    b.ranges.push_back({uint32_t(b.lenses.size()), uint32_t(dev.size()), rays, 0u});
    b.max_rays = std::max(b.max_rays, rays);
    b.lenses.insert(b.lenses.end(), dev.begin(), dev.end());
  }
  return b;
}

// Designs traced together may differ only in their lenslets.
void check_batchable(const std::vector<OpticalSystem>& designs) {
  if (designs.empty()) throw std::invalid_argument("ForwardVulkan: no design given");
  const OpticalSystem& a = designs.front();
  for (size_t k = 1; k < designs.size(); ++k) {
    const OpticalSystem& b = designs[k];
    const Effects &ea = a.effects, &eb = b.effects;
    const char* what = nullptr;
    if (a.sensor_width_px != b.sensor_width_px || a.sensor_height_px != b.sensor_height_px || a.pixel_um != b.pixel_um)
      what = "the sensor";
    else if (a.lens_to_sensor_mm != b.lens_to_sensor_mm || a.working_distance_mm != b.working_distance_mm)
      what = "the lens-to-sensor or working distance";
    else if (a.sensor_pose != b.sensor_pose)
      what = "the sensor's pose";
    else if (a.lens_model != b.lens_model)
      what = "the lens model";
    else if (ea.scintillator_refraction != eb.scintillator_refraction || ea.scintillator_index != eb.scintillator_index ||
             ea.holder_vignetting != eb.holder_vignetting || ea.holder_bore_mm != eb.holder_bore_mm ||
             ea.detection_efficiency != eb.detection_efficiency || ea.dark_counts_per_pixel != eb.dark_counts_per_pixel ||
             ea.source_extent != eb.source_extent || ea.source_sigma_mm != eb.source_sigma_mm ||
             ea.diffraction != eb.diffraction || ea.wavelength_nm != eb.wavelength_nm)
      what = "the effects";
    if (what)
      throw std::invalid_argument("design " + std::to_string(k) + " differs from design 0 in " + what +
                                  "; designs traced together may differ only in their lenslets");
  }
}

struct ForwardVulkan::Impl {
  vk::Context& ctx;
  OpticalSystem sys;
  Variant variant;  // plain; as built when any design traced is; calibrate
  TraceSettings settings;
  shared::TraceParams params{};
  DesignBuffers layout;
  vk::Buffer lenses;
  vk::Buffer designs;
  vk::Buffer design_zero;  // source_design for single-source renders: design 0
  // The footprint kernels' tile mask (binding 7): `no_mask` (never read,
  // params.mask_tiles_w 0) but while psf renders a TileMask, whose tiles'
  // slots `mask` holds.
  vk::Buffer no_mask;
  std::unique_ptr<vk::Buffer> mask;
  const vk::Buffer* tile_mask = &no_mask;
  vk::Kernel splat;
  vk::Kernel splat_values;  // b only
  vk::Kernel reduce;
  uint32_t band_rows;       // grid rows per band
  uint32_t sources_per_batch;
  uint64_t list_limit_bytes;  // the footprint's lists: at most the budget and maxStorageBufferRange

  // The footprint splat's later passes and their lists (footprint_raster.glsl):
  // the split pass (psf_footprint_split.comp), the cut pass
  // (psf_footprint_cut.comp) and the large pass (psf_footprint_large.comp,
  // the tiles of pieces still large after the split, listed after its entries).
  struct List {
    std::unique_ptr<vk::Buffer> buffer;  // header (count, capacity, 2 unused) + entries of 16 bytes
    uint32_t capacity = 0;
    void grow(vk::Context& c, uint32_t entries) {
      capacity = entries;
      buffer = std::make_unique<vk::Buffer>(c, 16 + uint64_t(entries) * 16);
      uint32_t header[4] = {0, capacity, 0, 0};
      buffer->upload(header, sizeof(header));
    }
    uint32_t count() const {
      uint32_t n = 0;
      buffer->download(&n, sizeof(n));
      return n;
    }
  };
  struct Footprint {
    vk::Kernel split, split_values, cut, cut_values, large, large_values;
    List splits, cuts;
    uint32_t chunks = 1;  // the first pass over the cells in this many chunks (record_splat)
    static std::span<const uint32_t> split_spirv(Variant v, const OpticalSystem& sys) {
      static const KernelBuilds builds = PRISM_KERNEL_BUILDS(psf_footprint_split);
      return pick_build(builds, v, sys);
    }
    static std::span<const uint32_t> cut_spirv(Variant v, const OpticalSystem& sys) {
      static const KernelBuilds builds = PRISM_KERNEL_BUILDS(psf_footprint_cut);
      return pick_build(builds, v, sys);
    }
    static std::span<const uint32_t> large_spirv(Variant v, const OpticalSystem& sys) {
      static const KernelBuilds builds = PRISM_KERNEL_BUILDS(psf_footprint_large);
      return pick_build(builds, v, sys);
    }
    Footprint(vk::Context& c, const OpticalSystem& sys, Variant v, uint32_t first_capacity)
        : split(c, "psf_footprint_split", split_spirv(v, sys), 8, sizeof(shared::TraceParams),
                specialisation(sys, true)),
          split_values(c, "psf_footprint_split (values)", split_spirv(v, sys), 8, sizeof(shared::TraceParams),
                       specialisation(sys, false)),
          cut(c, "psf_footprint_cut", cut_spirv(v, sys), 8, sizeof(shared::TraceParams), specialisation(sys, true)),
          cut_values(c, "psf_footprint_cut (values)", cut_spirv(v, sys), 8, sizeof(shared::TraceParams),
                     specialisation(sys, false)),
          large(c, "psf_footprint_large", large_spirv(v, sys), 8, sizeof(shared::TraceParams), specialisation(sys, true)),
          large_values(c, "psf_footprint_large (values)", large_spirv(v, sys), 8, sizeof(shared::TraceParams),
                       specialisation(sys, false)) {
      splits.grow(c, first_capacity);
      cuts.grow(c, first_capacity);
    }
  };
  std::unique_ptr<Footprint> footprint;

  // A single source's render (render_bands), kept between calls: its source,
  // image buffer, stream and host copy; [0] values only, [1] with
  // derivatives. Calibration renders hundreds of small images per PSF; these
  // are made once rather than for each.
  struct Scratch {
    std::unique_ptr<vk::Buffer> source, images;
    std::unique_ptr<vk::Stream> stream;
    std::vector<float> pixels;
  };
  Scratch scratch[2];
  Scratch masked;  // a masked render's (psf with a TileMask): its image holds the marked tiles

  Impl(vk::Context& c, const std::vector<OpticalSystem>& all, const TraceSettings& t, const AnalysisGrid& grid,
       uint64_t budget, Variant v)
      : Impl(c, all, t, grid, budget, v, design_buffers(all, t)) {}

  Impl(vk::Context& c, const std::vector<OpticalSystem>& all, const TraceSettings& t, const AnalysisGrid& grid,
       uint64_t budget, Variant v, DesignBuffers b)
      : ctx(c),
        sys(all.front()),
        variant(v),
        settings(t),
        layout(std::move(b)),
        lenses(c, layout.lenses.size() * sizeof(shared::Lenslet)),
        designs(c, layout.ranges.size() * sizeof(shared::DesignRange)),
        design_zero(c, sizeof(uint32_t)),
        no_mask(c, sizeof(uint32_t)),
        splat(c, kernel_name(t, false), splat_spirv(t, variant, sys), splat_buffers(t), sizeof(shared::TraceParams),
              specialisation(sys, true)),
        splat_values(c, kernel_name(t, true), splat_spirv(t, variant, sys), splat_buffers(t),
                     sizeof(shared::TraceParams), specialisation(sys, false)),
        reduce(c, "fisher_reduce", spirv(spv_fisher_reduce), 2, 3 * sizeof(uint32_t),
               {uint32_t(t.estimator == FisherEstimator::split ? shared::FISHER_SPLIT : shared::FISHER_NAIVE)}) {
    const OpticalSystem& s = sys;
    lenses.upload(std::span<const shared::Lenslet>(layout.lenses));
    designs.upload(std::span<const shared::DesignRange>(layout.ranges));
    uint32_t zero = 0;
    design_zero.upload(&zero, sizeof(zero));
    no_mask.upload(&zero, sizeof(zero));
    params.total_rays = layout.max_rays;
    params.cell_first = 0;
    params.cell_count = layout.max_rays;

    set_scene_params(params, s);
    shared::set_tangents(params, source_tangents);
    params.pixel_mm = float(grid.pixel_mm);
    params.sensor_half_w_mm = float(0.5 * s.sensor_width_mm());
    params.sensor_half_h_mm = float(0.5 * s.sensor_height_mm());
    params.photons_per_sr = float(t.photons_emitted * s.effects.detection_efficiency / (4.0 * M_PI));
    params.scint_index = float(s.effects.scintillator_index);
    params.holder_bore_mm = float(s.effects.holder_bore_mm);
    params.source_sigma_mm = float(s.effects.source_sigma_mm);
    params.stratification = t.stratification;
    params.grid_w = grid.width;
    params.grid_h = grid.height;
    params.lens_count = uint32_t(layout.lenses.size());

    // One image buffer of at most maxStorageBufferRange and the budget: bands
    // of rows when one image is larger, batches of sources when it is smaller.
    uint64_t cap = std::min<uint64_t>(budget, c.max_storage_buffer_bytes());
    uint64_t row_bytes = uint64_t(grid.width) * kPixelBytes;
    band_rows = uint32_t(std::min<uint64_t>(grid.height, cap / row_bytes));
    if (band_rows == 0) throw vk::Error("one sensor row does not fit in a storage buffer");
    uint64_t image_bytes = row_bytes * band_rows;
    sources_per_batch = uint32_t(std::clamp<uint64_t>(cap / image_bytes, 1, 65535));
    list_limit_bytes = std::max<uint64_t>(cap, 64u << 10);
    if (t.splat == Splat::footprint)
      footprint = std::make_unique<Footprint>(c, sys, variant, uint32_t(std::min<uint64_t>(1u << 14, max_list_entries())));
  }

  // Record the splat of the dispatch's sources (p.source_offset, count) into
  // `images` (zeroed), band p, of the rays (cells) [p.cell_first,
  // p.cell_first + p.cell_count); leaves every pixel's value there, ready for
  // what the caller records next. The footprint splat needs the counts of its
  // lists on the host between its passes: it submits, and returns the kernel
  // milliseconds submitted so far.
  double record_splat(vk::Stream& stream, bool derivatives, const vk::Buffer& sources,
                      const vk::Buffer& source_designs, vk::Buffer& images, const shared::TraceParams& p) {
    vk::Kernel& main = derivatives ? splat : splat_values;
    if (!footprint) {
      stream.dispatch(main, {&lenses, &sources, &images, &source_designs, &designs}, &p, splat_groups(params.total_rays),
                      p.source_count);
      return 0.0;
    }
    Footprint& f = *footprint;
    auto groups = [](uint32_t entries) { return std::min<uint32_t>((entries + kSplatGroup - 1) / kSplatGroup, 65535u); };
    // Every footprint kernel takes the same eight buffers.
    auto dispatch = [&](vk::Kernel& k, const shared::TraceParams& q, uint32_t groups_x, uint32_t groups_y) {
      stream.dispatch(k,
                      {&lenses, &sources, &images, &source_designs, &designs, f.splits.buffer.get(), f.cuts.buffer.get(),
                       tile_mask},
                      &q, groups_x, groups_y);
    };
    // The lists of a dispatch can outgrow a storage buffer (many sources, a
    // real lens's rim cells split in up to 64 pieces): then the cells are taken in
    // chunks, each with lists that fit. An overflow grows the lists (or, at
    // the limit, doubles the chunks) and starts again from a zeroed image.
    const uint64_t max_entries = max_list_entries();
    const uint32_t begin = p.cell_first, end = p.cell_first + std::min(p.cell_count, params.total_rays - p.cell_first);
    double ms = 0;
    for (;;) {
      const uint32_t per_chunk = uint32_t((uint64_t(end - begin) + f.chunks - 1) / f.chunks);
      uint64_t need = 0;  // entries a list needed and did not have
      for (uint32_t first = begin; first < end && need == 0; first += per_chunk) {
        shared::TraceParams q = p;
        q.cell_first = first;
        q.cell_count = std::min(per_chunk, end - first);
        if (first > begin) ms += submit(stream);  // the previous chunk's cut pass before the lists are reset
        stream.fill_zero(*f.splits.buffer, 0, 4);
        stream.fill_zero(*f.cuts.buffer, 0, 4);
        stream.barrier();
        dispatch(main, q, splat_groups(q.cell_count), p.source_count);
        ms += submit(stream);
        // The split, a level per pass: each pass takes the entries the one
        // before it listed and lists the large children after them.
        uint32_t split_count = f.splits.count();
        uint32_t cut_count = f.cuts.count();
        q.split_first = 0;
        for (int level = 0; level < shared::SPLIT_DEPTH && q.split_first < split_count &&
                            split_count <= f.splits.capacity && cut_count <= f.cuts.capacity;
             ++level) {
          q.split_end = split_count;
          stream.barrier();
          dispatch(derivatives ? f.split : f.split_values, q, groups(q.split_end - q.split_first), 1);
          ms += submit(stream);
          q.split_first = q.split_end;
          split_count = f.splits.count();
          cut_count = f.cuts.count();  // with the split pieces' cuts
        }
        if (split_count > f.splits.capacity || cut_count > f.cuts.capacity) {
          need = std::max(split_count, cut_count);
          break;
        }
        // The last level listed the tiles of its pieces still large, and the
        // cut pass lists those of its large parts after them.
        const uint32_t tiles_first = q.split_first;
        if (cut_count > 0) {
          stream.barrier();
          dispatch(derivatives ? f.cut : f.cut_values, q, groups(cut_count), 1);
          ms += submit(stream);
          split_count = f.splits.count();
        }
        if (split_count > f.splits.capacity) {
          need = split_count;
          break;
        }
        if (split_count > tiles_first) {
          q.split_first = tiles_first;
          q.split_end = split_count;
          stream.barrier();
          dispatch(derivatives ? f.large : f.large_values, q, groups(split_count - tiles_first), 1);
        }
      }
      if (need == 0) return ms;
      const uint64_t want = need + need / 2;
      if (want <= max_entries) {
        f.splits.grow(ctx, uint32_t(std::max<uint64_t>(want, f.splits.capacity)));
        f.cuts.grow(ctx, uint32_t(std::max<uint64_t>(want, f.cuts.capacity)));
      } else {
        f.splits.grow(ctx, uint32_t(max_entries));
        f.cuts.grow(ctx, uint32_t(max_entries));
        f.chunks *= 2;
        if (f.chunks > end - begin)
          throw vk::Error("footprint splat: one cell's triangles overflow a storage buffer; lower the sources per batch");
      }
      stream.fill_zero(images);
    }
  }

  uint64_t max_list_entries() const { return (list_limit_bytes - 16) / 16; }

  // The dispatches of the current call, each with its time (bench_forward).
  std::vector<vk::Stream::KernelTime> times;
  double submit(vk::Stream& stream) {
    const double ms = stream.submit();
    times.insert(times.end(), stream.last_times().begin(), stream.last_times().end());
    return ms;
  }

  uint32_t bands() const { return (uint32_t(params.grid_h) + band_rows - 1) / band_rows; }

  // Workgroups along x: one per 64 rays (point) or cells (footprint),
  // capped; the kernels loop over the rest.
  uint32_t splat_groups(uint32_t cells) const {
    uint64_t total = cells;
    return uint32_t(std::min<uint64_t>((total + kSplatGroup - 1) / kSplatGroup, std::min(ctx.max_group_count_x(), 65535u)));
  }
};

uint64_t ForwardVulkan::device_bytes_at_most(const AnalysisGrid& grid, Splat splat, uint64_t image_budget_bytes) {
  const uint64_t image = std::min<uint64_t>(image_budget_bytes, uint64_t(grid.width) * grid.height * kPixelBytes);
  return image + (splat == Splat::footprint ? 2 * std::max<uint64_t>(image_budget_bytes, 64u << 10) : 0);
}

ForwardVulkan::ForwardVulkan(vk::Context& ctx, const OpticalSystem& sys, const TraceSettings& settings,
                             uint64_t image_budget_bytes, Derivatives derivatives) {
  validate(sys);
  grid_ = AnalysisGrid::of(sys, settings.binning);
  const Variant v = derivatives == Derivatives::scene ? Variant::calibrate
                    : sys.as_built()                  ? Variant::as_built
                                                      : Variant::plain;
  impl_ = std::make_unique<Impl>(ctx, std::vector<OpticalSystem>{sys}, settings, grid_, image_budget_bytes, v);
}

ForwardVulkan::ForwardVulkan(vk::Context& ctx, const std::vector<OpticalSystem>& designs,
                             const TraceSettings& settings, uint64_t image_budget_bytes) {
  check_batchable(designs);
  for (const auto& d : designs) validate(d);
  grid_ = AnalysisGrid::of(designs.front(), settings.binning);
  impl_ = std::make_unique<Impl>(ctx, designs, settings, grid_, image_budget_bytes,
                                 any_as_built(designs) ? Variant::as_built : Variant::plain);
}

void ForwardVulkan::set_scene(const OpticalSystem& sys) {
  Impl& m = *impl_;
  if (m.layout.ranges.size() != 1) throw std::logic_error("set_scene: a forward model of several designs");
  const OpticalSystem& was = m.sys;
  const Effects &a = was.effects, &b = sys.effects;
  const char* what = nullptr;
  if (sys.lenslets.size() != was.lenslets.size())
    what = "the number of lenslets";
  else if (!std::equal(sys.lenslets.begin(), sys.lenslets.end(), was.lenslets.begin(),
                       [](const LensletGeometry& x, const LensletGeometry& y) { return x.diameter_mm == y.diameter_mm; }))
    what = "a lenslet's diameter";
  else if (sys.sensor_width_px != was.sensor_width_px || sys.sensor_height_px != was.sensor_height_px ||
           sys.pixel_um != was.pixel_um)
    what = "the sensor";
  else if (sys.lens_model != was.lens_model || sys.curved_toward_sensor != was.curved_toward_sensor ||
           sys.glass_index != was.glass_index || sys.edge_thickness_mm != was.edge_thickness_mm)
    what = "the lens model";
  else if (a.scintillator_refraction != b.scintillator_refraction || a.holder_vignetting != b.holder_vignetting ||
           a.source_extent != b.source_extent || a.diffraction != b.diffraction ||
           a.scintillator_index != b.scintillator_index || a.holder_bore_mm != b.holder_bore_mm ||
           a.source_sigma_mm != b.source_sigma_mm || a.detection_efficiency != b.detection_efficiency)
    what = "the effects";
  else if (sys.as_built() && m.variant == Variant::plain)
    what = "being as built (the forward model was made for a nominal scene)";
  if (what) throw std::invalid_argument(std::string("set_scene: the new scene differs in ") + what);
  validate(sys);
  m.sys = sys;
  m.layout = design_buffers({sys}, m.settings);
  m.lenses.upload(std::span<const shared::Lenslet>(m.layout.lenses));
  set_scene_params(m.params, sys);
}

ForwardVulkan::~ForwardVulkan() = default;

uint64_t ForwardVulkan::rays_per_source() const { return impl_->layout.ranges.front().total_rays; }

const std::vector<vk::Stream::KernelTime>& ForwardVulkan::last_kernel_times() const { return impl_->times; }

unsigned ForwardVulkan::footprint_cell_chunks() const { return impl_->footprint ? impl_->footprint->chunks : 0; }

std::vector<FisherResult> ForwardVulkan::fisher(std::span<const glm::dvec3> theta) {
  std::vector<uint32_t> design0(theta.size(), 0);
  return fisher(theta, design0);
}

std::vector<FisherResult> ForwardVulkan::fisher(std::span<const glm::dvec3> theta, std::span<const uint32_t> design_of) {
  Impl& m = *impl_;
  if (design_of.size() != theta.size()) throw std::invalid_argument("fisher: one design index per source");
  for (uint32_t d : design_of)
    if (d >= m.layout.ranges.size()) throw std::invalid_argument("fisher: design index " + std::to_string(d) + " out of range");
  std::vector<FisherResult> out(theta.size());
  last_kernel_ms_ = 0;
  m.times.clear();
  if (theta.empty()) return out;
  const uint32_t batch = uint32_t(std::min<size_t>(m.sources_per_batch, theta.size()));
  std::vector<glm::vec4> src(theta.size());
  for (size_t i = 0; i < theta.size(); ++i) src[i] = glm::vec4(glm::vec3(theta[i]), 0.0f);
  vk::Buffer sources(m.ctx, src.size() * sizeof(glm::vec4));
  sources.upload(std::span<const glm::vec4>(src));
  vk::Buffer source_designs(m.ctx, design_of.size() * sizeof(uint32_t));
  source_designs.upload(design_of);
  vk::Buffer images(m.ctx, uint64_t(batch) * grid_.width * m.band_rows * kPixelBytes);
  const uint32_t max_pixels = uint32_t(grid_.width) * m.band_rows;
  const uint32_t max_chunks = (max_pixels + kReduceChunk - 1) / kReduceChunk;
  vk::Buffer partials(m.ctx, uint64_t(batch) * max_chunks * kPartialFloats * sizeof(float));
  vk::Stream stream(m.ctx);

  for (uint32_t band = 0; band < m.bands(); ++band) {
    shared::TraceParams p = m.params;
    p.band_row0 = int(band * m.band_rows);
    p.band_rows = int(std::min<uint32_t>(m.band_rows, uint32_t(grid_.height) - band * m.band_rows));
    struct {
      uint32_t pixels, chunks;
      float dark;
    } rp{uint32_t(grid_.width) * uint32_t(p.band_rows), 0, float(m.sys.effects.dark_counts_per_pixel)};
    rp.chunks = (rp.pixels + kReduceChunk - 1) / kReduceChunk;
    for (size_t first = 0; first < theta.size(); first += batch) {
      p.source_offset = uint32_t(first);
      p.source_count = uint32_t(std::min<size_t>(batch, theta.size() - first));
      stream.fill_zero(images);
      stream.barrier();
      last_kernel_ms_ += m.record_splat(stream, true, sources, source_designs, images, p);
      stream.barrier();
      stream.dispatch(m.reduce, {&images, &partials}, &rp, rp.chunks, p.source_count);
      last_kernel_ms_ += m.submit(stream);
      auto part = partials.download<float>(size_t(p.source_count) * rp.chunks * kPartialFloats);
      for (uint32_t s = 0; s < p.source_count; ++s) {
        FisherResult& r = out[first + s];
        for (uint32_t c = 0; c < rp.chunks; ++c) {
          const float* q = &part[(size_t(s) * rp.chunks + c) * kPartialFloats];
          r.photons += q[0];
          for (int k = 0; k < 6; ++k) {
            r.poisson[k] += q[1 + k];
            r.binary[k] += q[7 + k];
          }
        }
      }
    }
  }
  return out;
}

// Render one source band by band with `kernel` (pixel_floats floats per
// pixel), from constants `base` (its tangents and cells); hand each band's
// pixels to consume(first_row, rows, pixels).
template <class Consume>
double render_bands(ForwardVulkan::Impl& m, const AnalysisGrid& grid, bool derivatives, const glm::dvec3& theta,
                    const shared::TraceParams& base, Consume&& consume) {
  const uint32_t pixel_floats = derivatives ? 8 : 1;
  m.times.clear();
  // Bands as tall as one buffer allows at this pixel size.
  const uint64_t band_bytes = uint64_t(m.band_rows) * grid.width * kPixelBytes;
  const uint32_t rows = uint32_t(std::min<uint64_t>(grid.height, band_bytes / (uint64_t(grid.width) * pixel_floats * 4)));
  const uint64_t image_bytes = uint64_t(grid.width) * rows * pixel_floats * sizeof(float);
  // Large images (full-resolution dictionaries) are not kept: the memory
  // estimates count one image buffer (device_bytes_at_most).
  ForwardVulkan::Impl::Scratch temporary;
  ForwardVulkan::Impl::Scratch& s = image_bytes <= kKeptImageBytes ? m.scratch[derivatives ? 1 : 0] : temporary;
  if (!s.images) {
    s.source = std::make_unique<vk::Buffer>(m.ctx, sizeof(glm::vec4));
    s.images = std::make_unique<vk::Buffer>(m.ctx, image_bytes);
    s.stream = std::make_unique<vk::Stream>(m.ctx);
    s.pixels.resize(size_t(grid.width) * rows * pixel_floats);
  }
  const glm::vec4 src(glm::vec3(theta), 0.0f);
  s.source->upload(&src, sizeof(src));
  vk::Buffer &sources = *s.source, &images = *s.images;
  vk::Stream& stream = *s.stream;
  std::vector<float>& pixels = s.pixels;
  double ms = 0;
  for (uint32_t row0 = 0; row0 < uint32_t(grid.height); row0 += rows) {
    shared::TraceParams p = base;
    p.band_row0 = int(row0);
    p.band_rows = int(std::min<uint32_t>(rows, uint32_t(grid.height) - row0));
    p.source_offset = 0;
    p.source_count = 1;
    stream.fill_zero(images);
    stream.barrier();
    ms += m.record_splat(stream, derivatives, sources, m.design_zero, images, p);
    ms += m.submit(stream);
    images.download(pixels.data(), uint64_t(p.band_rows) * grid.width * pixel_floats * sizeof(float));
    consume(row0, uint32_t(p.band_rows), pixels.data());
  }
  return ms;
}

TileMask TileMask::of(const AnalysisGrid& grid) {
  TileMask m;
  m.tiles_w = (grid.width + shared::LARGE_TILE_PX - 1) / shared::LARGE_TILE_PX;
  m.tiles_h = (grid.height + shared::LARGE_TILE_PX - 1) / shared::LARGE_TILE_PX;
  m.bits.assign((size_t(m.tiles_w) * size_t(m.tiles_h) + 31) / 32, 0u);
  return m;
}

void TileMask::mark_around(int col, int row, int reach_px) {
  const int t0 = std::max(col - reach_px, 0) / shared::LARGE_TILE_PX;
  const int t1 = std::min(col + reach_px, tiles_w * shared::LARGE_TILE_PX - 1) / shared::LARGE_TILE_PX;
  const int r0 = std::max(row - reach_px, 0) / shared::LARGE_TILE_PX;
  const int r1 = std::min(row + reach_px, tiles_h * shared::LARGE_TILE_PX - 1) / shared::LARGE_TILE_PX;
  for (int r = r0; r <= r1; ++r)
    for (int c = t0; c <= t1; ++c) {
      const size_t t = size_t(r) * size_t(tiles_w) + size_t(c);
      bits[t / 32] |= 1u << (t % 32);
    }
}

bool TileMask::marked(int tile_col, int tile_row) const {
  const size_t t = size_t(tile_row) * size_t(tiles_w) + size_t(tile_col);
  return (bits[t / 32] >> (t % 32)) & 1u;
}

size_t TileMask::count() const {
  size_t n = 0;
  for (uint32_t w : bits) n += size_t(std::popcount(w));
  return n;
}

PixelImage ForwardVulkan::psf(const glm::dvec3& theta) { return psf(theta, source_tangents, -1); }

std::vector<LitPixel> ForwardVulkan::psf(const glm::dvec3& theta, const TileMask& mask) {
  Impl& m = *impl_;
  if (!m.footprint) throw std::invalid_argument("ForwardVulkan::psf: a tile mask needs the footprint splat");
  const TileMask blank = TileMask::of(grid_);
  if (mask.tiles_w != blank.tiles_w || mask.tiles_h != blank.tiles_h || mask.bits.size() != blank.bits.size())
    throw std::invalid_argument("ForwardVulkan::psf: the tile mask is for another grid");
  // Each marked tile's slot in the image (1 + its rank; 0: unmarked).
  std::vector<uint32_t> slot(size_t(mask.tiles_w) * size_t(mask.tiles_h), 0u), tiles;
  for (int r = 0; r < mask.tiles_h; ++r)
    for (int c = 0; c < mask.tiles_w; ++c)
      if (mask.marked(c, r)) {
        const size_t t = size_t(r) * size_t(mask.tiles_w) + size_t(c);
        tiles.push_back(uint32_t(t));
        slot[t] = uint32_t(tiles.size());
      }
  if (tiles.empty()) return {};
  constexpr uint64_t tile_px = uint64_t(shared::LARGE_TILE_PX) * shared::LARGE_TILE_PX;
  constexpr uint32_t pixel_floats = 8;  // b, then the gradient from each half of the cells (render_bands)
  const uint64_t image_bytes = tiles.size() * tile_px * pixel_floats * sizeof(float);
  if (tiles.size() > max_masked_tiles())
    throw std::invalid_argument("ForwardVulkan::psf: the tile mask marks " + std::to_string(tiles.size()) +
                                " tiles, more than one image buffer holds (" + std::to_string(max_masked_tiles()) +
                                "); render the whole image instead");
  if (!m.mask || m.mask->bytes() < slot.size() * sizeof(uint32_t))
    m.mask = std::make_unique<vk::Buffer>(m.ctx, slot.size() * sizeof(uint32_t));
  m.mask->upload(slot.data(), slot.size() * sizeof(uint32_t));
  Impl::Scratch& s = m.masked;
  if (!s.source) s.source = std::make_unique<vk::Buffer>(m.ctx, sizeof(glm::vec4));
  if (!s.stream) s.stream = std::make_unique<vk::Stream>(m.ctx);
  if (!s.images || s.images->bytes() < image_bytes) s.images = std::make_unique<vk::Buffer>(m.ctx, image_bytes);
  s.pixels.resize(image_bytes / sizeof(float));
  const glm::vec4 src(glm::vec3(theta), 0.0f);
  s.source->upload(&src, sizeof(src));
  // The whole grid in one band: the image holds the marked tiles alone.
  shared::TraceParams p = m.params;
  p.mask_tiles_w = uint32_t(mask.tiles_w);
  p.band_row0 = 0;
  p.band_rows = grid_.height;
  p.source_offset = 0;
  p.source_count = 1;
  m.times.clear();
  m.tile_mask = m.mask.get();
  struct Unmask {  // back to no mask however the render ends
    Impl& m;
    ~Unmask() { m.tile_mask = &m.no_mask; }
  } unmask{m};
  s.stream->fill_zero(*s.images, 0, image_bytes);
  s.stream->barrier();
  last_kernel_ms_ = m.record_splat(*s.stream, true, *s.source, m.design_zero, *s.images, p);
  last_kernel_ms_ += m.submit(*s.stream);
  s.images->download(s.pixels.data(), image_bytes);
  // Row by row of the grid, each row's marked tiles left to right: by index.
  std::vector<LitPixel> out;
  const int tile = shared::LARGE_TILE_PX;
  for (size_t first = 0; first < tiles.size();) {
    const uint32_t tile_row = tiles[first] / uint32_t(mask.tiles_w);
    size_t end = first;
    while (end < tiles.size() && tiles[end] / uint32_t(mask.tiles_w) == tile_row) ++end;
    for (int y = 0; y < tile && int(tile_row) * tile + y < grid_.height; ++y) {
      const uint32_t row = tile_row * uint32_t(tile) + uint32_t(y);
      for (size_t k = first; k < end; ++k) {
        const int col0 = int(tiles[k] % uint32_t(mask.tiles_w)) * tile;
        const float* q = &s.pixels[(k * tile_px + size_t(y) * size_t(tile)) * pixel_floats];
        for (int x = 0; x < tile && col0 + x < grid_.width; ++x, q += pixel_floats)
          if (q[0] != 0 || q[1] != 0 || q[2] != 0 || q[3] != 0 || q[4] != 0 || q[5] != 0 || q[6] != 0)
            out.push_back({row * uint32_t(grid_.width) + uint32_t(col0 + x), q[0],
                           0.5f * (glm::vec3(q[1], q[2], q[3]) + glm::vec3(q[4], q[5], q[6]))});
      }
    }
    first = end;
  }
  return out;
}

size_t ForwardVulkan::max_masked_tiles() const {
  return size_t(impl_->list_limit_bytes / (uint64_t(shared::LARGE_TILE_PX) * shared::LARGE_TILE_PX * 8 * sizeof(float)));
}

PixelImage ForwardVulkan::psf(const glm::dvec3& theta, const Tangents& tangents, int only_lens) {
  Impl& m = *impl_;
  shared::TraceParams base = m.params;

  if (tangents != source_tangents || only_lens >= 0) {
    if (m.variant != Variant::calibrate)
      throw std::logic_error("ForwardVulkan::psf: derivatives by scene parameters need Derivatives::scene");
    shared::set_tangents(base, tangents);
  }
  if (only_lens >= 0) {
    if (size_t(only_lens) >= m.layout.lenses.size())
      throw std::invalid_argument("ForwardVulkan::psf: no lenslet " + std::to_string(only_lens));
    const shared::Lenslet& l = m.layout.lenses[size_t(only_lens)];
    base.cell_first = l.first_ray;
    base.cell_count = l.strata * l.strata;
  }
  PixelImage img{grid_.width, grid_.height, grid_.pixel_mm, std::vector<float>(size_t(grid_.width) * grid_.height * 4)};
  last_kernel_ms_ = render_bands(m, grid_, true, theta, base, [&](uint32_t row0, uint32_t rows, const float* q) {
    // Keep b and the mean of the two half-ray gradient estimates.
    float* out = &img.data[size_t(row0) * grid_.width * 4];
    for (size_t i = 0; i < size_t(rows) * grid_.width; ++i, q += 8) {
      out[4 * i] = q[0];
      for (int a = 0; a < 3; ++a) out[4 * i + 1 + a] = 0.5f * (q[1 + a] + q[4 + a]);
    }
  });
  return img;
}

std::vector<float> ForwardVulkan::psf_values(const glm::dvec3& theta) {
  std::vector<float> out(size_t(grid_.width) * grid_.height);
  last_kernel_ms_ = render_bands(*impl_, grid_, false, theta, impl_->params, [&](uint32_t row0, uint32_t rows, const float* q) {
    std::copy_n(q, size_t(rows) * grid_.width, &out[size_t(row0) * grid_.width]);
  });
  return out;
}

std::vector<glm::vec3> landing_points_vulkan(vk::Context& ctx, const OpticalSystem& sys, size_t lens_index,
                                         std::span<const glm::vec3> origin_dir_pairs) {
  if (sys.as_built())
    throw std::invalid_argument("landing points: tilted lenslets or a sensor off its nominal pose are not traced by "
                                "this check (it compares nominal lenses with an optics library)");
  size_t n = origin_dir_pairs.size() / 2;
  if (n == 0) return {};
  shared::Lenslet lens = device_lenslets(sys, TraceSettings{})[lens_index];
  vk::Buffer lens_buf(ctx, sizeof(lens));
  lens_buf.upload(&lens, sizeof(lens));
  std::vector<glm::vec4> rays(2 * n);
  for (size_t i = 0; i < 2 * n; ++i) rays[i] = glm::vec4(origin_dir_pairs[i], 0.0f);
  vk::Buffer ray_buf(ctx, rays.size() * sizeof(glm::vec4));
  ray_buf.upload(std::span<const glm::vec4>(rays));
  vk::Buffer hit_buf(ctx, n * sizeof(glm::vec4));
  vk::Kernel kernel(ctx, "landing_points", spirv(spv_landing_points), 3, 2 * sizeof(uint32_t),
                    {uint32_t(sys.lens_model == LensModel::real ? shared::LENS_REAL : shared::LENS_THIN)});
  struct {
    float lens_to_sensor_mm;
    uint32_t ray_count;
  } push{float(sys.lens_to_sensor_mm), uint32_t(n)};
  vk::Stream stream(ctx);
  stream.dispatch(kernel, {&lens_buf, &ray_buf, &hit_buf}, &push, uint32_t((n + 63) / 64));
  stream.submit();
  auto hits = hit_buf.download<glm::vec4>(n);
  std::vector<glm::vec3> out(n);
  for (size_t i = 0; i < n; ++i) out[i] = glm::vec3(hits[i]);
  return out;
}

}  // namespace prism
