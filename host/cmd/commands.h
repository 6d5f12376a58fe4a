// One function per `prism` subcommand; each lives in host/cmd/<name>.cpp and
// registers its options and callback on the top-level CLI11 app.
#pragma once
#include <stdexcept>

#include <CLI/CLI.hpp>

namespace prism::cmd {
// A command stopped by Ctrl-C after saving what it could: prism exits 130,
// as a shell reports a process ended by SIGINT.
struct Interrupted : std::runtime_error {
  using std::runtime_error::runtime_error;
};
inline constexpr int interrupted_exit_status = 130;

void add_crlb(CLI::App& app);
void add_psf(CLI::App& app);
void add_camera(CLI::App& app);
void add_sweep(CLI::App& app);
// `prism dictionary ...`; its subcommands live in host/cmd/dictionary_*.cpp.
void add_dictionary(CLI::App& app);
void add_dictionary_merge_hdr(CLI::App& dictionary);
void add_dictionary_build(CLI::App& dictionary);
void add_dictionary_info(CLI::App& dictionary);
void add_dictionary_assemble(CLI::App& dictionary);
void add_dictionary_simulate_hdr(CLI::App& dictionary);
void add_simulate(CLI::App& app);
void add_reconstruct(CLI::App& app);
void add_evaluate(CLI::App& app);
void add_calibrate(CLI::App& app);
}  // namespace prism::cmd
