// prism: plenoptic imaging of scintillation events on Vulkan compute.
#include <cstdio>

#include "engine/vk/context.h"
#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/util/output_file.h"

int main(int argc, char** argv) {
  CLI::App app{"prism: plenoptic imaging of particle interactions in scintillation detectors, on Vulkan compute"};
  app.require_subcommand(1);
  prism::cmd::add_crlb(app);
  prism::cmd::add_psf(app);
  prism::cmd::add_dictionary(app);
  prism::cmd::add_sweep(app);
  prism::cmd::add_simulate(app);
  prism::cmd::add_reconstruct(app);
  prism::cmd::add_evaluate(app);
#ifdef PRISM_WITH_CAMERA
  prism::cmd::add_camera(app);
#endif
  app.add_subcommand("devices", "list the Vulkan devices that --device can choose")->callback([] {
    for (const auto& d : prism::vk::Context::list_devices()) std::printf("%s\n", d.c_str());
  });
  // The commands whose large allocations are estimated (host/util/memory.h);
  // crlb and sweep hold the forward model's bounded buffers only.
  prism::cmd::add_memory_limit(*app.get_subcommand("psf"));
  prism::cmd::add_memory_limit(*app.get_subcommand("dictionary")->get_subcommand("build"));
  prism::cmd::add_memory_limit(*app.get_subcommand("dictionary")->get_subcommand("merge-hdr"));
  for (const char* name : {"simulate", "reconstruct", "evaluate"}) prism::cmd::add_memory_limit(*app.get_subcommand(name));
  prism::cmd::require_finite_numbers(app);
  prism::install_interrupt_cleanup();
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    if (auto missing = prism::cmd::missing_command(app, e)) {
      std::fprintf(stderr, "prism: %s\n", missing->c_str());
      return e.get_exit_code();
    }
    return app.exit(e);
  } catch (const prism::cmd::Interrupted& e) {
    std::fprintf(stderr, "prism: %s\n", e.what());
    return prism::cmd::interrupted_exit_status;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "prism: %s\n", e.what());
    return 1;
  }
  return 0;
}
