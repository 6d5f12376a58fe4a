// Test runner: doctest, plus a final check that the Vulkan validation layer
// printed nothing during the whole run.
#define DOCTEST_CONFIG_IMPLEMENT
#include <doctest/doctest.h>

#include <cstdio>

#include "support.h"

int main(int argc, char** argv) {
  doctest::Context context(argc, argv);
  int rc = context.run();
  if (context.shouldExit()) return rc;
  // ctest runs each test case in its own process, so this covers every test,
  // also those that do not call check_validation_clean() themselves.
  if (size_t n = prism::test::validation_message_count()) {
    std::fprintf(stderr, "FAILED: the Vulkan validation layer printed %zu message(s) (above)\n", n);
    return 1;
  }
  return rc;
}
