// `mpirun -n N prism ...` (host/cmd/ranks.h): the commands that split their
// work over MPI ranks (dictionary build, simulate, reconstruct) write the
// files of one process, byte for byte, with even and uneven shares; a failing rank stops the job with its message and
// leaves no output; the other commands refuse to run under several ranks.
// Built when MPI is (PRISM_WITH_MPI); the ranks run on lavapipe with the
// validation layer on, as every test does (the environment is inherited).
#ifdef PRISM_WITH_MPI
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <string>
#include <vector>

#include "support.h"

namespace {

namespace fs = std::filesystem;

std::string scratch() {
  auto d = prism::test::scratch_dir() / "mpi";
  fs::create_directories(d);
  return d.string();
}

std::string contents(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), {}};
}

// Every file under `dir`, by its path relative to it, with its bytes.
std::map<std::string, std::string> files_under(const std::string& dir) {
  std::map<std::string, std::string> out;
  for (const auto& f : fs::recursive_directory_iterator(dir))
    if (f.is_regular_file()) out[fs::relative(f.path(), dir).string()] = contents(f.path().string());
  return out;
}

// Open MPI's launcher as CI runs it: as root, with more ranks than cores.
prism::test::CommandResult run_ranks(int n, const std::string& args) {
  return prism::test::run_prism(args, std::string(PRISM_MPIEXEC) + " --allow-run-as-root --oversubscribe -n " +
                                          std::to_string(n));
}

size_t count(const std::string& text, const std::string& what) {
  size_t n = 0;
  for (size_t at = text.find(what); at != std::string::npos; at = text.find(what, at + 1)) ++n;
  return n;
}

// Each run of a command under N ranks must say nothing of the validation
// layer and print its summary once.
void check_clean(const prism::test::CommandResult& r, const std::string& summary) {
  INFO(r.output);
  REQUIRE(r.status == 0);
  CHECK(r.output.find("vulkan validation") == std::string::npos);
  CHECK(count(r.output, summary) == 1);
}

}  // namespace

TEST_CASE("mpirun -n 2 and 3: dictionary build, simulate and reconstruct write what one process writes, byte for byte") {
  const std::string dir = scratch();
  const std::string dict = dir + "/dict";
  REQUIRE(prism::test::run_prism("dictionary build --out " + dict + " --grid-x-mm -5,0,5 --grid-y-mm -5,0,5 "
                                 "--grid-depth-mm 20,25,30 --binning 16 --splat point --rays 256").status == 0);
  // The ranks render every N-th PSF each (27 PSFs: 14 + 13, 9 + 9 + 9);
  // the dictionary is the same files, and a rerun under other ranks
  // continues one that lost some.
  const auto files = files_under(dict);
  REQUIRE(files.size() == 28);  // the manifest and 27 PSFs
  for (int n : {2, 3}) {
    CAPTURE(n);
    const std::string other = dir + "/dict" + std::to_string(n);
    auto r = run_ranks(n, "dictionary build --out " + other + " --grid-x-mm -5,0,5 --grid-y-mm -5,0,5 "
                          "--grid-depth-mm 20,25,30 --binning 16 --splat point --rays 256");
    check_clean(r, "PSFs rendered");
    CHECK(r.output.find("27 PSFs rendered, 0 already present") != std::string::npos);
    CHECK(files_under(other) == files);
  }
  int removed = 0;
  for (const auto& f : fs::directory_iterator(dir + "/dict3/psf"))
    if (removed < 5 && ++removed) fs::remove(f.path());
  auto resumed = run_ranks(2, "dictionary build --out " + dir + "/dict3 --grid-x-mm -5,0,5 --grid-y-mm -5,0,5 "
                              "--grid-depth-mm 20,25,30 --binning 16 --splat point --rays 256");
  check_clean(resumed, "PSFs rendered");
  CHECK(resumed.output.find("5 PSFs rendered, 22 already present") != std::string::npos);
  CHECK(files_under(dir + "/dict3") == files);

  // 7 events: shares of 3 + 4 and 2 + 2 + 3. Dictionary truth runs on the
  // host in double, so the events of one seed repeat exactly (the forward
  // model's device sums need not: host/events/simulate.h).
  const std::string sim = "simulate --truth dictionary --dictionary " + dict +
                          " --vertex 0.5,-0.5,24 --jitter-mm 3 --alpha 80 --events 7 --seed 11 --out ";
  REQUIRE(prism::test::run_prism(sim + dir + "/one.events").status == 0);
  const std::string one = contents(dir + "/one.events");
  REQUIRE(one.size() > 100);
  for (int n : {2, 3}) {
    CAPTURE(n);
    const std::string path = dir + "/ranks" + std::to_string(n) + ".events";
    auto r = run_ranks(n, sim + path);
    check_clean(r, "PSFs rendered or read");
    CHECK(r.output.find(std::to_string(n) + " MPI ranks") != std::string::npos);
    CHECK(contents(path) == one);
  }

  // The search alone on the device over the 7 events with 2 and 3 ranks;
  // the dictionary model's refinement on the CPU reference over the first 3
  // with 2 (1 + 2: it costs seconds an event under the sanitizers).
  REQUIRE(prism::test::run_prism("simulate --truth dictionary --dictionary " + dict +
                                 " --vertex 0.5,-0.5,24 --jitter-mm 3 --alpha 80 --events 3 --seed 11 --out " + dir +
                                 "/three.events").status == 0);
  struct Run {
    std::string events, options;
    std::vector<int> ranks;
    int count;
  };
  for (const Run& run : {Run{"one", "--model none", {2, 3}, 7}, Run{"three", "--model dictionary --backend cpu", {2}, 3}}) {
    CAPTURE(run.options);
    const std::string rec =
        "reconstruct --dictionary " + dict + " --events " + dir + "/" + run.events + ".events " + run.options + " --out ";
    auto single = prism::test::run_prism(rec + dir + "/one.csv");
    INFO(single.output);
    REQUIRE(single.status == 0);
    const std::string csv = contents(dir + "/one.csv");
    REQUIRE(std::count(csv.begin(), csv.end(), '\n') == run.count + 1);  // header and a vertex per event
    for (int n : run.ranks) {
      CAPTURE(n);
      const std::string path = dir + "/ranks" + std::to_string(n) + ".csv";
      auto r = run_ranks(n, rec + path);
      check_clean(r, "events/s");
      // The summary counts every rank's events.
      CHECK(r.output.find(": " + std::to_string(run.count) + " events") != std::string::npos);
      CHECK(contents(path) == csv);
    }
  }
}

TEST_CASE("mpirun: a rank that fails stops the job with its message and no output, and the other commands refuse ranks") {
  const std::string dir = scratch();
  const std::string dict = dir + "/dict";
  REQUIRE(prism::test::run_prism("dictionary build --out " + dict + " --grid-x-mm 0 --grid-y-mm 0 "
                                 "--grid-depth-mm 20,25 --binning 16 --splat point --rays 256").status == 0);
  REQUIRE(prism::test::run_prism("simulate --truth dictionary --dictionary " + dict +
                                 " --vertex 0,0,22 --events 6 --out " + dir + "/e.events").status == 0);
  // Cut the file inside its last event: rank 1 of 2 reads to the cut and
  // fails; rank 0's share is whole and it waits for rank 1's rows.
  const std::string whole = contents(dir + "/e.events");
  {
    std::ofstream cut(dir + "/cut.events", std::ios::binary);
    cut.write(whole.data(), std::streamsize(whole.size() - 30));
  }
  auto r = run_ranks(2, "reconstruct --dictionary " + dict + " --events " + dir + "/cut.events --model none --out " +
                            dir + "/v.csv");
  INFO(r.output);
  CHECK(r.status != 0);
  CHECK(r.output.find("prism: rank 1 of 2: ") != std::string::npos);
  CHECK(r.output.find("cut.events") != std::string::npos);
  for (const auto& f : fs::directory_iterator(dir))  // neither the CSV nor a temporary of it
    CHECK(f.path().filename().string().rfind("v.csv", 0) != 0);

  auto crlb = run_ranks(2, "crlb --depth-mm 20 --csv " + dir + "/c.csv");
  INFO(crlb.output);
  CHECK(crlb.status != 0);
  CHECK(crlb.output.find("crlb does not split its work over MPI ranks") != std::string::npos);
  CHECK(!fs::exists(dir + "/c.csv"));
}
#endif
