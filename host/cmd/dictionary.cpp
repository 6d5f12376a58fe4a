// prism dictionary: the PSF dictionary's subcommands (one file each,
// host/cmd/dictionary_*.cpp).
#include "host/cmd/commands.h"

namespace prism::cmd {

void add_dictionary(CLI::App& app) {
  CLI::App* dictionary =
      app.add_subcommand("dictionary", "PSF dictionary: build, inspect; simulate and merge calibration exposures and assemble them");
  dictionary->require_subcommand(1);
  add_dictionary_build(*dictionary);
  add_dictionary_info(*dictionary);
  add_dictionary_simulate_hdr(*dictionary);
  add_dictionary_merge_hdr(*dictionary);
  add_dictionary_assemble(*dictionary);
}

}  // namespace prism::cmd
