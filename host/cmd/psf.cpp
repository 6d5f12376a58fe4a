// prism psf: the expected-photon image of one point source (OpenEXR + PNG).
#include <cstdio>
#include <filesystem>

#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/util/output_file.h"
#include "host/util/image_io.h"
#include "host/util/memory.h"

namespace prism::cmd {

namespace {

struct PsfArgs {
  std::string scene = "prototype";
  std::string source = "0,0,25";
  std::string out;
  bool derivatives = false;
  ForwardOptions fw;
};

// x.exr -> x.png (a dot in a folder's name is not an extension).
std::string preview_path(const std::string& exr) { return std::filesystem::path(exr).replace_extension(".png").string(); }

void run(const PsfArgs& a) {
  check_writable(a.out);
  check_writable(preview_path(a.out));
  for (const std::string& out : {a.out, preview_path(a.out)}) check_not_input(out, "--out", {{"--scene", a.scene}});
  Scene scene = load_scene(a.scene);
  a.fw.apply(scene);
  glm::dvec3 theta = parse_point(a.source, "--source-mm");
  require_in_front(scene, theta.z, "--source-mm");
  TraceSettings t = a.fw.settings(scene);
  const AnalysisGrid grid = AnalysisGrid::of(scene.optics, t.binning);
  const double px = double(grid.width) * grid.height;
  MemoryEstimate memory("psf at binning " + std::to_string(t.binning) + " (" + std::to_string(grid.width) +
                        " x " + std::to_string(grid.height) + " px)");
  memory.add("the image and its derivatives, 4 floats per pixel", 16 * px).add("the PNG preview", px);
  const bool vulkan = a.fw.backend_kind() == Backend::vulkan;
  if (!vulkan) memory.add("the CPU reference's sparse image, up to every pixel", ref::SparseImage::bytes_per_pixel * px);
  if (vulkan && !a.derivatives) memory.add("the values from the device", 4 * px);
  PixelImage img;
  std::string device = "CPU reference (double precision)";
  if (vulkan) {
    vk::Context ctx(vk::ContextOptions{a.fw.device});
    device = ctx.describe();
    memory.add_device_buffers(double(ForwardVulkan::device_bytes_at_most(grid, t.splat)), ctx.is_cpu());
    memory.require_within_limit("Use a coarser --binning");
    ForwardVulkan fw(ctx, scene.optics, t);
    if (a.derivatives) {
      img = fw.psf(theta);
    } else {
      // b alone: 4 bytes per pixel on the device instead of 32.
      auto b = fw.psf_values(theta);
      img = {fw.grid().width, fw.grid().height, fw.grid().pixel_mm, std::vector<float>(4 * b.size(), 0.0f)};
      for (size_t i = 0; i < b.size(); ++i) img.data[4 * i] = b[i];
    }
  } else {
    memory.require_within_limit("Use a coarser --binning");
    auto sparse = ref::psf(scene.optics, t, theta);
    img = {sparse.width, sparse.height, AnalysisGrid::of(scene.optics, t.binning).pixel_mm,
           std::vector<float>(size_t(sparse.width) * sparse.height * 4, 0.0f)};
    for (const auto& [k, v] : sparse.pixels) {
      auto px = sparse.value(k);
      for (int c = 0; c < 4; ++c) img.data[size_t(k) * 4 + c] = float(px[c]);
    }
  }
  std::vector<ExrChannel> channels{{"Y", img.data.data(), 4}};
  if (a.derivatives) {
    channels.push_back({"db_dx", img.data.data() + 1, 4});
    channels.push_back({"db_dy", img.data.data() + 2, 4});
    channels.push_back({"db_ddepth", img.data.data() + 3, 4});
  }
  write_exr(a.out, img.width, img.height, channels);
  const std::string png = preview_path(a.out);
  write_png_preview(png, img.width, img.height, img.data.data(), 4);
  std::printf("# device: %s\n%s: %d x %d px of %.1f um, %u rays/lenslet, %.3f expected photons detected\n",
              device.c_str(), a.out.c_str(), img.width, img.height, img.pixel_mm * 1e3, t.rays(), img.photons());
  std::printf("%s: preview (square-root scale)\n", png.c_str());
}

}  // namespace

void add_psf(CLI::App& app) {
  auto a = std::make_shared<PsfArgs>();
  CLI::App* c = app.add_subcommand("psf", "render the expected-photon image of a point source to OpenEXR and PNG");
  c->add_option("--scene", a->scene, "built-in scene or JSON file")->capture_default_str();
  c->add_option("--source-mm", a->source, "source position X,Y,DEPTH (depth from the scintillator face)")
      ->capture_default_str();
  c->add_option("--out", a->out, "output .exr (channel Y = expected photons per pixel); a .png preview goes beside it")
      ->required()
      ->check([](const std::string& out) -> std::string {
        // The image is OpenEXR whatever the name says; a .txt or .png name would mislead.
        return std::filesystem::path(out).extension() == ".exr"
                   ? ""
                   : out + ": the PSF is written as OpenEXR; give a name ending in .exr";
      });
  c->add_flag("--derivatives", a->derivatives, "also write db_dx, db_dy, db_ddepth channels");
  a->fw.add_to(c, 1);
  c->callback([a] { run(*a); });
}

}  // namespace prism::cmd
