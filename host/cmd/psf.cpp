// prism psf: the expected-photon image of one point source (OpenEXR + PNG).
#include <cstdio>
#include <filesystem>

#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/util/output_file.h"
#include "host/util/image_io.h"
#include "host/util/memory.h"
#include "host/scene/psf_render.h"

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
  MemoryEstimate memory("psf at binning " + std::to_string(t.binning) + " (" + std::to_string(grid.width) +
                        " x " + std::to_string(grid.height) + " px)");
  memory.add("the PNG preview", double(grid.width) * grid.height);
  std::unique_ptr<vk::Context> ctx;
  std::string device = "CPU reference (double precision)";
  if (a.fw.backend_kind() == Backend::vulkan) {
    ctx = std::make_unique<vk::Context>(vk::ContextOptions{a.fw.device});
    device = ctx->describe();
  }
  const PixelImage img = render_psf(scene, t, theta, a.derivatives, a.fw.backend_kind(), ctx.get(), memory);
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
