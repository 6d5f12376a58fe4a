// prism simulate: events (click lists) for given vertices, streamed to an
// event file (host/events/EVENTS.md).
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <optional>

#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/cmd/ranks.h"
#include "host/events/event_file.h"
#include "host/events/simulate.h"
#include "host/util/memory.h"
#include "host/util/output_file.h"
#include "host/util/progress.h"

namespace prism::cmd {

namespace {

struct SimulateArgs {
  std::string scene = "prototype";
  std::vector<std::string> vertices;
  double alpha = 100;
  uint64_t events = 1000;
  std::string out;
  std::string truth = "forward";
  std::string dictionary;
  double jitter_mm = 0;
  uint64_t seed = 1;
  unsigned binning = 1;
  bool binning_given = false;
  unsigned rays = 0;  // 0: the splat's converged default
  SplatOptions splat;
  std::string device;
};

std::vector<EventVertex> parse_vertices(const SimulateArgs& a) {
  std::vector<EventVertex> out;
  for (const auto& text : a.vertices) {
    auto v = parse_numbers(text, "--vertex", "X,Y,DEPTH[,ALPHA] (mm, mm, mm, photons)", 3, 4);
    double alpha = v.size() == 4 ? v[3] : a.alpha;
    if (!(alpha >= 0)) throw std::runtime_error("--vertex '" + text + "': ALPHA must be >= 0 expected photons");
    out.push_back({v[0], v[1], v[2], alpha, 0});
  }
  return out;
}

void run(const SimulateArgs& a) {
  check_writable(a.out);
  check_not_input(a.out, "--out", {{"--dictionary", a.dictionary}, {"--scene", a.scene}});
  Scene scene = load_scene(a.scene);
  SimulationRun run{parse_vertices(a), a.jitter_mm, a.seed};
  const auto& base = run.vertices;
  {
    // Refused before any work when even the records without their clicks
    // would not fit on the disk (a typo such as --events 18446744073709551615
    // would otherwise stream until the disk is full).
    std::error_code ec;
    const auto parent = std::filesystem::absolute(a.out, ec).parent_path();
    const auto space = std::filesystem::space(parent, ec);
    const double floor_bytes = double(a.events) * double(event_record_bytes(base.size(), 0));
    if (!ec && floor_bytes > double(space.available))
      throw std::runtime_error("--events " + std::to_string(a.events) + ": the file needs at least " +
                               format_bytes(floor_bytes) + " (" + std::to_string(event_record_bytes(base.size(), 0)) +
                               " bytes an event before its clicks), but " + parent.string() + " has " +
                               format_bytes(double(space.available)) + " free; choose fewer events or another --out");
  }
  check_simulation(scene, run, "--vertex", "--jitter-mm");

  std::optional<vk::Context> ctx;  // only the forward model needs a device
  std::optional<DictionaryReader> reader;
  std::unique_ptr<EventTruth> truth;
  if (a.truth != "dictionary" && !a.dictionary.empty())
    throw std::runtime_error("--dictionary is read only with --truth dictionary (the paper's protocol); the truth "
                             "now is the forward model, which renders the scene: add --truth dictionary or leave "
                             "--dictionary out");
  if (a.truth == "dictionary") {
    if (a.dictionary.empty()) throw std::runtime_error("--truth dictionary needs --dictionary DIR");
    reader.emplace(a.dictionary, &scene.optics);
    const auto& m = reader->manifest();
    const int level = a.binning_given ? stored_level_of_binning(m, a.binning, "--binning") : 0;
    truth = std::make_unique<DictionaryTruth>(*reader, level);
  } else {
    const TraceSettings t = trace_settings(scene, a.binning, a.rays, 0, a.splat.kind(), a.splat.stratification, "auto");
    ctx.emplace(vk::ContextOptions{a.device});
    truth = std::make_unique<ForwardTruth>(*ctx, scene, t);
  }
  const EventFileHeader h = simulation_header(scene, *truth, run);

  // Under mpirun each rank simulates its share of the ids (event i depends on
  // (seed, i) alone); rank 0 writes its own, then the others' records in rank
  // order (host/cmd/ranks.h).
  const ranks::Share mine = ranks::share(a.events);
  Progress progress(ranks::size() > 1 ? "simulate (rank 0's share)" : "simulate", mine.count(), ranks::root());
  std::optional<EventWriter> writer;
  std::vector<uint8_t> records;  // the ranks but 0: their share, sent when done
  if (ranks::root()) writer.emplace(a.out, h);
  Event e;
  uint64_t clicks = 0;
  auto start = std::chrono::steady_clock::now();
  for (uint64_t id = mine.begin; id < mine.end; ++id) {
    simulate_event(*truth, run, id, e);
    clicks += e.clicks.size();
    if (writer)
      writer->write(e);
    else
      append_event_record(e, h.grid_pixels(), a.out, records);
    progress.update(id - mine.begin + 1);
  }
  if (writer) {
    ranks::gather_in_order({}, [&](int r, std::string_view bytes) {
      const ranks::Share theirs = ranks::share_of(r, a.events);
      writer->write_records({reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size()}, theirs.count());
    });
    writer->close();
  } else {
    ranks::gather_in_order({reinterpret_cast<const char*>(records.data()), records.size()}, {});
  }
  progress.finish();
  double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  clicks = ranks::sum(clicks);
  const uint64_t renders = ranks::sum(uint64_t(truth->renders()));
  const double render_seconds = ranks::sum(truth->render_seconds());
  if (!ranks::root()) return;
  if (ranks::size() > 1)
    std::printf("# %d MPI ranks, each on its own device; renders and their times summed over them, rank 0's device:\n",
                ranks::size());
  std::printf("# device: %s\n", ctx ? ctx->describe().c_str() : "none (dictionary truth runs on the host)");
  std::printf("%s: %llu events of %zu vertices, %.1f clicks per event on average, %llu bytes\n", a.out.c_str(),
              (unsigned long long)writer->events(), base.size(), a.events ? double(clicks) / double(a.events) : 0.0,
              (unsigned long long)std::filesystem::file_size(a.out));
  double sampling_s = seconds - truth->render_seconds();
  std::printf("truth: %s\n%llu PSFs rendered or read in %.2f s; sampling and writing %.2f s (%.3g events/s); "
              "%.3g events/s overall\n",
              h.provenance.c_str(), (unsigned long long)renders, render_seconds, sampling_s,
              sampling_s > 0 ? double(a.events) / sampling_s : 0.0, seconds > 0 ? double(a.events) / seconds : 0.0);
}

}  // namespace

void add_simulate(CLI::App& app) {
  auto a = std::make_shared<SimulateArgs>();
  CLI::App* c = app.add_subcommand("simulate", "simulate binary-sensor events (click lists) and write an event file");
  c->add_option("--scene", a->scene, "built-in scene or JSON file")->capture_default_str();
  c->add_option("--vertex", a->vertices,
                "X,Y,DEPTH[,ALPHA]: a vertex in mm (depth from the scintillator face) with its expected photons; "
                "repeat for K vertices per event")
      ->required();
  c->add_option("--alpha", a->alpha, "expected photons detected per vertex where --vertex gives none")
      ->capture_default_str()->check(non_negative_number);
  c->add_option("--events", a->events, "number of events")->capture_default_str();
  c->add_option("--out", a->out, "event file to write (format: host/events/EVENTS.md)")->required();
  c->add_option("--truth", a->truth, "forward: ray-traced model at the exact positions; dictionary: shifted "
                                      "dictionary PSFs (the paper's protocol)")
      ->capture_default_str()->check(CLI::IsMember({"forward", "dictionary"}));
  c->add_option("--dictionary", a->dictionary, "dictionary directory for --truth dictionary");
  c->add_option("--jitter-mm", a->jitter_mm, "move each vertex uniformly within +-S mm in x, y and depth, per event "
                                             "(each event then renders its own PSFs)")
      ->capture_default_str();
  c->add_option("--seed", a->seed, "random seed; event i depends only on (seed, i)")->capture_default_str();
  c->add_option("--binning", a->binning, "clicks on B x B binned pixels (forward; dictionary: base binning x 2^k, "
                                         "default its base binning)")
      ->capture_default_str()->check(CLI::Range(1u, 1024u))->each([a](const std::string&) { a->binning_given = true; });
  c->add_option("--rays", a->rays, std::string("forward model: rays (footprint: cells) per 3 mm lenslet aperture, ") +
                                   rays_rounding + "; 0: the splat's converged default")
      ->capture_default_str()->check(CLI::Range(0u, 1u << 24));
  a->splat.add_to(c);
  c->add_option("--device", a->device, device_help);
  c->callback([a] { run(*a); });
}

}  // namespace prism::cmd
