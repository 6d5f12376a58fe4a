// Test runner: doctest, with the tests' environment, plus two checks after the run: the Vulkan validation
// layer printed nothing, and a run asked for named test cases ran at least
// one (a filter that matches nothing would otherwise pass without testing
// anything).
#define DOCTEST_CONFIG_IMPLEMENT
#include <doctest/doctest.h>

#include <cstdio>
#include <cstdlib>
#include <cstring>

#include "support.h"

namespace {

unsigned g_cases_run = 0;

// Counts the test cases that passed the filters, and gives each its own
// scratch folder (support.h).
struct RunCounter : doctest::IReporter {
  explicit RunCounter(const doctest::ContextOptions&) {}
  void report_query(const doctest::QueryData&) override {}
  void test_run_start() override {}
  void test_run_end(const doctest::TestRunStats& s) override { g_cases_run = s.numTestCasesPassingFilters; }
  void test_case_start(const doctest::TestCaseData&) override { prism::test::begin_test_case(); }
  void test_case_reenter(const doctest::TestCaseData&) override {}
  void test_case_end(const doctest::CurrentTestCaseStats&) override {}
  void test_case_exception(const doctest::TestCaseException&) override {}
  void subcase_start(const doctest::SubcaseSignature&) override {}
  void subcase_end() override {}
  void log_assert(const doctest::AssertData&) override {}
  void log_message(const doctest::MessageData&) override {}
  void test_case_skipped(const doctest::TestCaseData&) override {}
};
REGISTER_LISTENER("run-counter", 1, RunCounter);

}  // namespace

int main(int argc, char** argv) {
  // Every test on lavapipe with the validation layer on, unless the caller's
  // environment says otherwise; `prism` run by a test inherits both.
  ::setenv("PRISM_DEVICE", "cpu", 0);
  ::setenv("PRISM_VALIDATION", "1", 0);
  doctest::Context context(argc, argv);
  int rc = context.run();
  if (context.shouldExit()) return rc;
  bool filtered = false;
  for (int i = 1; i < argc; ++i)
    for (const char* option : {"-tc=", "--test-case=", "-sf=", "--source-file="})
      filtered = filtered || std::strncmp(argv[i], option, std::strlen(option)) == 0;
  if (filtered && g_cases_run == 0) {
    std::fprintf(stderr, "FAILED: no test case matched the filter (-tc takes test names, -sf source paths; "
                         "',' separates patterns, '*' matches anything)\n");
    return 1;
  }
  // ctest runs each test file in its own process, so this covers every test,
  // also those that do not call check_validation_clean() themselves.
  if (size_t n = prism::test::validation_message_count()) {
    std::fprintf(stderr, "FAILED: the Vulkan validation layer printed %zu message(s) (above)\n", n);
    return 1;
  }
  return rc;
}
