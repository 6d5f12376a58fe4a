// `mpirun -n N prism ...` (host/cmd/ranks.h): the commands that split their
// work over MPI ranks write the files of one process, with even and uneven
// shares, and resume what a job of another size left, byte for byte but
// for the times measured (evaluate and sweep render on the device, whose
// float sums repeat only on one lavapipe thread: they run so here). A failing
// rank stops the job with its message and leaves no output; the other
// commands refuse to run under several ranks.
// Built when MPI is (PRISM_WITH_MPI); the ranks run on lavapipe with the
// validation layer on, as every test does (the environment is inherited).
#ifdef PRISM_WITH_MPI
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <regex>
#include <sstream>
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

// A CSV file without the column named `times` (seconds measured).
std::string without_column(const std::string& path, const std::string& times) {
  std::istringstream in(contents(path));
  std::string out, line;
  long skip = -1;
  for (bool header = true; std::getline(in, line); header = false) {
    std::vector<std::string> cells;
    std::istringstream row(line);
    for (std::string cell; std::getline(row, cell, ',');) cells.push_back(cell);
    if (header)
      for (size_t c = 0; c < cells.size(); ++c)
        if (cells[c] == times) skip = long(c);
    for (size_t c = 0; c < cells.size(); ++c)
      if (long(c) != skip) out += cells[c] + ",";
    out += "\n";
  }
  return out;
}

// A journal's records (the lines after its header) without their measured
// "seconds", sorted: the ranks' records reach rank 0's journal in rank order.
std::vector<std::string> records_of(const std::string& path) {
  std::vector<std::string> lines;
  std::istringstream in(contents(path));
  for (std::string line; std::getline(in, line);)
    lines.push_back(std::regex_replace(line, std::regex("\"seconds\":[^,}]*"), ""));
  if (!lines.empty()) lines.erase(lines.begin());
  std::sort(lines.begin(), lines.end());
  return lines;
}

}  // namespace

TEST_CASE("mpirun -n 2 and 3: dictionary build, simulate and reconstruct write what one process writes, byte for byte") {
  const std::string dir = scratch();
  // Under the sanitizers 3 ranks only (an uneven split, every rank's code):
  // each rank is a process that starts Vulkan and compiles its kernels.
  const std::vector<int> ranks = prism::test::under_sanitizer ? std::vector<int>{3} : std::vector<int>{2, 3};
  const std::string dict = dir + "/dict";
  REQUIRE(prism::test::run_prism("dictionary build --out " + dict + " --grid-x-mm -5,0,5 --grid-y-mm -5,0,5 "
                                 "--grid-depth-mm 20,25,30 --binning 16 --splat point --rays 256").status == 0);
  // The ranks render every N-th PSF each (27 PSFs: 14 + 13, 9 + 9 + 9);
  // the dictionary is the same files, and a rerun under other ranks
  // continues one that lost some.
  const auto files = files_under(dict);
  REQUIRE(files.size() == 28);  // the manifest and 27 PSFs
  for (int n : ranks) {
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
  for (int n : ranks) {
    CAPTURE(n);
    const std::string path = dir + "/ranks" + std::to_string(n) + ".events";
    auto r = run_ranks(n, sim + path);
    check_clean(r, "PSFs rendered or read");
    CHECK(r.output.find(std::to_string(n) + " MPI ranks") != std::string::npos);
    CHECK(contents(path) == one);
  }

  // The search alone on the device over the 7 events with 2 and 3 ranks;
  // the dictionary model's refinement on the CPU reference over the first 3
  // with 2 (1 + 2), but not under the sanitizers: it costs seconds an event
  // there, and the ranks' split is the search's code.
  struct Run {
    std::string events, options;
    std::vector<int> ranks;
    int count;
  };
  std::vector<Run> runs{{"one", "--model none", ranks, 7}};
  if (!prism::test::under_sanitizer) {
    REQUIRE(prism::test::run_prism("simulate --truth dictionary --dictionary " + dict +
                                   " --vertex 0.5,-0.5,24 --jitter-mm 3 --alpha 80 --events 3 --seed 11 --out " + dir +
                                   "/three.events").status == 0);
    runs.push_back({"three", "--model dictionary --backend cpu", {2}, 3});
  }
  for (const Run& run : runs) {
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

TEST_CASE("mpirun -n 2 and 3: evaluate and sweep give one process's figures, and resume a job of another size") {
  const std::string dir = scratch() + "/figures";
  fs::remove_all(dir);
  fs::create_directories(dir);
  const std::string dict = dir + "/dict";
  REQUIRE(prism::test::run_prism("dictionary build --out " + dict + " --grid-x-mm -5,0,5 --grid-y-mm -5,0,5 "
                                 "--grid-depth-mm 25,30,35 --binning 16 --splat point --rays 256").status == 0);
  // The device's float sums (the events' truth, the CRLB, a design's
  // scores) repeat their last bits only when one lavapipe thread does them
  // in a fixed order, and with the point splat: the footprint splat's lists
  // of split triangles interleave the sources of a dispatch, so a design's
  // sums group with those of the designs it shares a dispatch with (1e-9
  // relative: docs/mpi.md).
  const std::string one_thread = "LP_NUM_THREADS=1";
  auto ranks = [&](int n, const std::string& args) {
    return prism::test::run_prism(args, one_thread + " " + PRISM_MPIEXEC + " --allow-run-as-root --oversubscribe -n " +
                                            std::to_string(n));
  };
  // The protocol's photons experiment (2 points of 3 trials) and 7 volume
  // events: 13 events, shared 7 + 6 by 2 ranks.
  const std::string evaluate = "evaluate --dictionary " + dict +
                               " --experiments photons,volume --quick --trials 3 --volume-events 7 --model none --splat point --out ";
  auto single = prism::test::run_prism(evaluate + dir + "/one", one_thread);
  INFO(single.output);
  REQUIRE(single.status == 0);
  auto check_evaluation = [&](const std::string& out) {
    for (const char* table : {"photons.csv", "photons.png", "volume.csv", "volume.png", "volume-catastrophic.png"})
      CHECK_MESSAGE(contents(dir + "/one/" + table) == contents(out + "/" + table), table);
    CHECK(without_column(dir + "/one/volume-events.csv", "seconds") ==
          without_column(out + "/volume-events.csv", "seconds"));
    for (const char* journal : {"protocol-journal.jsonl", "volume-journal.jsonl"})
      CHECK_MESSAGE(records_of(dir + "/one/" + journal) == records_of(out + "/" + journal), journal);
    for (const auto& f : fs::directory_iterator(out))  // the ranks' parts are merged in and gone
      CHECK(f.path().filename().string().find(".part") == std::string::npos);
  };
  auto two = ranks(2, evaluate + dir + "/two");
  check_clean(two, "reconstruction: 13 events");
  CHECK(two.output.find("2 MPI ranks") != std::string::npos);
  check_evaluation(dir + "/two");

  // A stopped 2-rank job: rank 0's journals hold some events, rank 1's parts
  // others. 3 ranks resume it: the parts are merged, the 5 events neither
  // holds are done (2 + 2 + 1), and the figures are one process's.
  const std::string resumed = dir + "/resumed";
  fs::create_directories(resumed);
  for (const std::string journal : {"protocol-journal", "volume-journal"}) {
    std::istringstream in(contents(dir + "/one/" + journal + ".jsonl"));
    std::string header;
    std::getline(in, header);
    std::ofstream main(resumed + "/" + journal + ".jsonl"), part(resumed + "/" + journal + ".part1.jsonl");
    main << header << '\n';
    part << header << '\n';
    int n = 0;
    for (std::string line; n < 4 && std::getline(in, line); ++n) (n < 2 ? main : part) << line << '\n';
  }
  // A report of the stopped job reads the parts beside the journals: 4 of
  // the 7 volume events.
  auto report = prism::test::run_prism(evaluate + resumed + " --journal-only", one_thread);
  INFO(report.output);
  REQUIRE(report.status == 0);
  CHECK(report.output.find("volume: 4 events") != std::string::npos);
  CHECK(fs::exists(resumed + "/volume-journal.part1.jsonl"));  // a report changes nothing
  auto three = ranks(3, evaluate + resumed + " --resume");
  check_clean(three, "reconstruction: 5 events");
  CHECK(three.output.find("8 events read from the journals") != std::string::npos);
  check_evaluation(resumed);

  // A sweep of 12 designs in batches of 4 (2 + 2 under 2 ranks, 2 + 1 + 1
  // under 3): the first 6 under 2 ranks, the rest resumed under 3.
  std::ofstream(dir + "/space.json") << R"({"base": "prototype", "focal_mm": [9, 15], "assignment": "free",
      "samples": {"x_mm": [0], "y_mm": [0], "depth_mm": [10, 20]}})";
  const std::string sweep = "sweep --space " + dir + "/space.json --batch 4 --rays 256 --binning 64 --splat point --out ";
  auto alone = prism::test::run_prism(sweep + dir + "/sw1 --budget 12", one_thread);
  INFO(alone.output);
  REQUIRE(alone.status == 0);
  check_clean(ranks(2, sweep + dir + "/sw --budget 6"), "designs scored this run");
  auto rest = ranks(3, sweep + dir + "/sw --budget 12");
  check_clean(rest, "designs scored this run");
  CHECK(rest.output.find("6 designs scored this run, 6 replayed") != std::string::npos);
  CHECK(without_column(dir + "/sw1/ranked.csv", "seconds") == without_column(dir + "/sw/ranked.csv", "seconds"));
  CHECK(records_of(dir + "/sw1/evaluated.jsonl") == records_of(dir + "/sw/evaluated.jsonl"));
  for (const char* file : {"best-1.json", "best-2.json", "best-3.json", "pareto.png", "crlb-depth.png"})
    CHECK_MESSAGE(contents(dir + "/sw1/" + file) == contents(dir + "/sw/" + file), file);
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

  auto report = run_ranks(2, "evaluate --dictionary " + dict + " --experiments volume --journal-only --out " + dir + "/j");
  INFO(report.output);
  CHECK(report.status != 0);
  CHECK(report.output.find("--journal-only reconstructs nothing: run it as one process") != std::string::npos);

  auto crlb = run_ranks(2, "crlb --depth-mm 20 --csv " + dir + "/c.csv");
  INFO(crlb.output);
  CHECK(crlb.status != 0);
  CHECK(crlb.output.find("crlb does not split its work over MPI ranks") != std::string::npos);
  CHECK(!fs::exists(dir + "/c.csv"));
}
#endif
