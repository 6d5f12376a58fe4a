// prism: plenoptic imaging of scintillation events on Vulkan compute.
#include <cstdio>
#include <string>

#include "engine/vk/context.h"
#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/cmd/ranks.h"
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
  prism::cmd::add_calibrate(app);
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
  // Under mpirun simulate, reconstruct, evaluate, sweep and dictionary build split their work
  // over the ranks (host/cmd/ranks.h); the rest run as one process only.
  for (const char* name : {"simulate", "reconstruct"})
    app.get_subcommand(name)->footer("Under an MPI launcher (mpirun -n N prism " + std::string(name) +
                                     " ...) the events are split over the ranks, each on its own device; rank 0 "
                                     "writes the output, as one process would (docs/mpi.md).");
  app.get_subcommand("dictionary")->get_subcommand("build")->footer(
      "Under an MPI launcher (mpirun -n N prism dictionary build ...) rank r renders the PSFs i with i mod N = r, "
      "each on its own device; rank 0 writes the manifest first (docs/mpi.md).");
  app.get_subcommand("evaluate")->footer(
      "Under an MPI launcher (mpirun -n N prism evaluate ...) rank r reconstructs the events i with i mod N = r of "
      "those the journals lack, each rank on its own device and appending to its own part of each journal; rank 0 "
      "gathers them and writes the journals and figures, as one process would (docs/mpi.md).");
  app.get_subcommand("sweep")->footer(
      "Under an MPI launcher (mpirun -n N prism sweep ...) every rank runs the same search from the seed and scores "
      "the candidates i with i mod N = r of each batch, on its own device; the scores are shared after each batch and "
      "rank 0 writes the state and every output, as one process would (docs/mpi.md). Use a --batch of N or more.");
  for (const char* name : {"crlb", "psf", "calibrate", "devices"})
    prism::cmd::ranks::single_process_only(*app.get_subcommand(name));
  for (const char* name : {"merge-hdr", "info"})
    prism::cmd::ranks::single_process_only(*app.get_subcommand("dictionary")->get_subcommand(name));
#ifdef PRISM_WITH_CAMERA
  prism::cmd::ranks::single_process_only(*app.get_subcommand("camera"));
#endif
  prism::install_interrupt_cleanup();
  namespace ranks = prism::cmd::ranks;
  try {
    ranks::start(argc, argv);
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // Every rank parses the same line: rank 0 speaks for them.
    if (ranks::root()) {
      if (auto missing = prism::cmd::missing_command(app, e))
        std::fprintf(stderr, "prism: %s\n", missing->c_str());
      else
        app.exit(e);
    }
    ranks::stop();
    return e.get_exit_code();
  } catch (const prism::cmd::Interrupted& e) {
    std::fprintf(stderr, "prism: %s\n", e.what());
    return prism::cmd::interrupted_exit_status;
  } catch (const std::exception& e) {
    if (ranks::size() > 1) ranks::fail(e.what());  // ends every rank
    std::fprintf(stderr, "prism: %s\n", e.what());
    return 1;
  }
  ranks::stop();
  return 0;
}
