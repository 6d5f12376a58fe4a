// prism reconstruct: vertices of every event of an event file, one CSV row per
// vertex (host/reconstruct/reconstruct.h). The device backends (vulkan: sparse,
// dense: the paper's dense correlation) scan --batch events per dispatch; the
// CPU reference runs on --threads workers (host/reconstruct/pool.h).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <memory>
#include <span>
#include <sstream>

#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/cmd/ranks.h"
#include "host/reconstruct/match.h"
#include "host/reconstruct/session.h"
#include "host/util/output_file.h"
#include "host/util/progress.h"

namespace prism::cmd {

namespace {

struct ReconstructArgs {
  std::string dictionary, events, out;
  std::string device;
  SessionOptions session;
};

void run(const ReconstructArgs& a) {
  check_writable(a.out);
  check_not_input(a.out, "--out",
                  {{"--events", a.events}, {"--dictionary", a.dictionary}, {"--scene", a.session.scene}});
  EventReader events(a.events);
  std::unique_ptr<vk::Context> ctx;
  if (backend_from_string(a.session.backend) != ReconstructionBackend::cpu)
    ctx = std::make_unique<vk::Context>(vk::ContextOptions{a.device});
  ReconstructionSession session(a.dictionary, events.header(), a.events, a.session, ctx.get());
  const ReconstructionPool& pool = session.pool();
  const ReconstructionSettings& s = session.settings();
  const bool on_device = session.on_device();
  const Refinement* refinement = session.refinement();

  // Under mpirun each rank takes its share of the events (host/cmd/ranks.h);
  // rank 0 writes the CSV, its own rows first, then the others' in rank order.
  const ranks::Share mine = ranks::share(events.header().event_count);
  Progress progress(ranks::size() > 1 ? "reconstruct (rank 0's share)" : "reconstruct", mine.count(), ranks::root());
  const size_t batch = session.batch_events();
  std::vector<Event> in(batch);
  uint64_t done = 0, flagged = 0, clicks = 0, scored = 0;
  double error_sum_mm = 0;
  auto start = std::chrono::steady_clock::now();
  auto reconstruct_share = [&](std::ostream& csv) {
    csv.precision(10);
    for (uint64_t i = 0; i < mine.begin; ++i) events.next(in[0]);
    while (done < mine.count()) {
      size_t n = 0;
      while (n < batch && done + n < mine.count() && events.next(in[n])) ++n;
      if (n == 0) break;
      // Refinement takes seconds per event: progress as each is done.
      auto out = session.run(std::span<const Event>(in.data(), n), [&](size_t i) { progress.update(done + i + 1); });
      for (size_t i = 0; i < n; ++i) {
        const Event& e = in[i];
        clicks += e.clicks.size();
        for (size_t k = 0; k < out[i].size(); ++k) {
          const auto& v = out[i][k];
          flagged += v.flags != vertex_ok;
          csv << e.id << ',' << k << ',' << v.x_mm << ',' << v.y_mm << ',' << v.depth_mm << ',' << v.alpha << ','
              << v.nll << ',' << v.clicks << ',' << flags_to_string(v.flags);
          // Without refinement the CRLB and p-value fields stay empty.
          for (double x : {v.crlb_x_mm, v.crlb_y_mm, v.crlb_z_mm, v.crlb_3d_mm, v.fit_pvalue}) {
            csv << ',';
            if (!std::isnan(x)) csv << x;
          }
          csv << '\n';
        }
        // Single-vertex truth: the 3D error, for the summary line.
        if (e.vertices.size() == 1 && out[i].size() == 1 && out[i][0].flags == vertex_ok) {
          const auto& t = e.vertices[0];
          error_sum_mm += error_3d_mm(out[i][0], {t.x_mm, t.y_mm, t.depth_mm});
          ++scored;
        }
      }
      done += n;
      progress.update(done);
    }
    // The last share ends at the trailer, which checks the count.
    if (mine.end == events.header().event_count && events.next(in[0]))
      throw std::runtime_error(a.events + ": more events than its header's " +
                               std::to_string(events.header().event_count) + ": corrupt file");
  };
  if (ranks::root()) {
    // Written aside and renamed when whole: a failure (a corrupt PSF, a
    // truncated event file, another rank's) leaves an earlier CSV as it was.
    write_atomically(a.out, [&](const std::string& tmp) {
      std::ofstream csv(tmp);
      if (!csv) throw std::runtime_error(a.out + ": cannot open for writing; check the directory exists and is writable");
      csv << "event,vertex,x_mm,y_mm,depth_mm,alpha,nll,clicks,flags,crlb_x_mm,crlb_y_mm,crlb_z_mm,crlb_3d_mm,fit_pvalue\n";
      reconstruct_share(csv);
      ranks::gather_in_order({}, [&](int, std::string_view rows) { csv.write(rows.data(), std::streamsize(rows.size())); });
      csv.close();
      if (!csv) throw std::runtime_error(a.out + ": write failed (disk full?)");
    });
  } else {
    std::ostringstream rows;
    reconstruct_share(rows);
    ranks::gather_in_order(rows.view(), {});
  }
  progress.finish();
  double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  // The summary is of every rank's events; rank 0 prints it.
  done = ranks::sum(done);
  flagged = ranks::sum(flagged);
  clicks = ranks::sum(clicks);
  scored = ranks::sum(scored);
  error_sum_mm = ranks::sum(error_sum_mm);
  auto t = pool.timings();
  for (double* x : {&t.scan_s, &t.scan_kernel_ms, &t.host_s, &t.scan_wait_s}) *x = ranks::sum(*x);
  for (uint64_t* x : {&t.scan_fits, &t.scan_candidates}) *x = ranks::sum(*x);
  RefineStats r = refinement ? refinement->stats() : RefineStats{};
  r.seconds = ranks::sum(r.seconds);
  for (uint64_t* x : {&r.starts, &r.iterations, &r.rescues, &r.lattice_scans, &r.lattice_depths, &r.reseeds,
                      &r.continuations_kept, &r.continuations})
    *x = ranks::sum(*x);
  ServiceStats d = pool.dictionary_stats();
  for (uint64_t* x : {&d.tile_misses, &d.bytes_read, &d.file_opens, &d.tile_hits, &d.dark_pixels}) *x = ranks::sum(*x);
  const uint64_t renders = ranks::sum(uint64_t(refinement ? refinement->renders() : 0));
  if (!ranks::root()) return;
  const unsigned threads = pool.workers();
  if (ranks::size() > 1)
    std::printf("# %d MPI ranks, each on its own device; the times below are summed over them, rank 0's device:\n",
                ranks::size());
  if (on_device)
    std::printf("# device: %s; %s scan, %s dictionary on the device, batches of %zu events, %s (%u host thread%s)\n",
                ctx->describe().c_str(), a.session.backend.c_str(), a.session.precision.c_str(), a.session.batch,
                a.session.serial_scans ? "each scanned, then the host's work on it" : "the host's work on one beside the scan of the next",
                pool.host_threads(), pool.host_threads() == 1 ? "" : "s");
  else
    std::printf("# device: CPU reference (double precision, %u thread%s)\n", threads, threads == 1 ? "" : "s");
  std::printf("%s: %llu events, K = %d, %.1f clicks per event; clicks on level %d, search on level %d, tau %.2f mm\n",
              a.out.c_str(), (unsigned long long)done, s.vertices, done ? double(clicks) / double(done) : 0.0, session.click_level(),
              pool.search_level(), s.tau_mm);
  std::printf("likelihood floors: --dark-rate %g per click pixel (weights, refinement), --search-dark-rate %g per "
              "sensor pixel (the search's choice of PSFs)\n",
              s.dark_rate, s.search_dark_rate);
  std::printf("%.2f s, %.1f events/s; %llu vertices flagged\n", seconds, seconds > 0 ? double(done) / seconds : 0.0,
              (unsigned long long)flagged);
  if (on_device)  // the scans ran beside the host's work (ReconstructionSettings::overlap_scans)
    std::printf("time: support scans %.2f s (kernels %.2f s), the search's host work %.2f s; the host waited %.2f s "
                "for scans\n",
                t.scan_s, t.scan_kernel_ms / 1e3, t.host_s, t.scan_wait_s);
  else
    std::printf("time: support scans %.2f s, the rest on the host %.2f s%s\n", t.scan_s, t.host_s,
                threads > 1 ? " (summed over threads)" : "");
  std::printf("dictionary tiles below the scan level: %llu read (%.0f MiB decoded, %llu file opens), %llu from the "
              "cache; %llu pixels asked for were dark on the scan level, not read; tables and tiles at most %.0f MiB (--budget-mib)\n",
              (unsigned long long)d.tile_misses, double(d.bytes_read) / (1 << 20), (unsigned long long)d.file_opens,
              (unsigned long long)d.tile_hits, (unsigned long long)d.dark_pixels, double(d.host_peak_bytes) / (1 << 20));
  if (t.scan_candidates > 0)
    std::printf("weights fitted in the scans: %llu of %llu (event, PSF) candidates (%.1f%%; the rest bounded out)\n",
                (unsigned long long)t.scan_fits, (unsigned long long)t.scan_candidates,
                100.0 * double(t.scan_fits) / double(t.scan_candidates));
  if (refinement && refinement->staged())
    std::printf("refinement on level %d (the clicks binned; --refine-level), then fitted again on the clicks' level "
                "from its answer\n",
                refinement->refine_level());
  if (refinement)
    std::printf("refinement (%s): %.2f s, %.1f starts and %.1f LM steps per event, %llu renders; %llu poor fits "
                "sent to the far aliases, %llu poor, marginal or shallow ones had the clicks' votes counted (%llu voted depths scanned); "
                "%llu events of K > 1 re-seeded from their unclaimed clicks; %llu of %llu blurred refits lowered the NLL\n",
                describe(session.model(), session.scene()).c_str(), r.seconds,
                double(r.starts) / double(std::max<uint64_t>(1, done)),
                double(r.iterations) / double(std::max<uint64_t>(1, done)),
                (unsigned long long)renders, (unsigned long long)r.rescues,
                (unsigned long long)r.lattice_scans, (unsigned long long)r.lattice_depths,
                (unsigned long long)r.reseeds, (unsigned long long)r.continuations_kept, (unsigned long long)r.continuations);
  else
    std::printf("refinement: none (--model none): positions from the dictionary search alone\n");
  if (scored)
    std::printf("single-vertex truth: mean 3D error %.3f mm over %llu unflagged events\n",
                error_sum_mm / double(scored), (unsigned long long)scored);
}

}  // namespace

void add_reconstruct(CLI::App& app) {
  auto a = std::make_shared<ReconstructArgs>();
  CLI::App* c = app.add_subcommand("reconstruct", "find the vertices of each event (ADCG on the sparse likelihood)");
  c->add_option("--dictionary", a->dictionary, "PSF dictionary directory")->required();
  c->add_option("--events", a->events, "event file (host/events/EVENTS.md)")->required();
  c->add_option("--vertices", a->session.settings.vertices, "K: vertices per event")
      ->capture_default_str()->check(CLI::Range(1, 8));
  c->add_option("--out", a->out, "CSV: event,vertex,x_mm,y_mm,depth_mm,alpha,nll,clicks,flags,crlb_x_mm,crlb_y_mm,"
                 "crlb_z_mm,crlb_3d_mm,fit_pvalue (the last five empty without refinement)")->required();
  c->add_option("--model", a->session.model, "continuous refinement after the search: scene (the scene's forward model, "
                 "default for synthesised dictionaries), dictionary (the dictionary's PSFs interpolated, default for "
                 "calibrated ones) or none (the search's grid positions alone)")
      ->check(CLI::IsMember({"scene", "dictionary", "none"}));
  add_always_scan_options(c, a->session.always_scan_below_mm, a->session.always_scan_below_clicks);
  add_refine_level_option(c, a->session.refine_level);
  c->add_option("--scene", a->session.scene, "scene for --model scene (default: the one the dictionary was built from)");
  c->add_option("--backend", a->session.backend,
                 "vulkan: sparse scan on the device; dense: the paper's dense correlation on the device (baseline); "
                 "cpu: the double-precision reference")
      ->capture_default_str()->check(CLI::IsMember({"vulkan", "dense", "cpu"}));
  c->add_option("--device", a->device, device_help);
  c->add_option("--precision", a->session.precision, "the scan level's values on the device: float or half")
      ->capture_default_str()->check(CLI::IsMember({"float", "half"}));
  c->add_option("--batch", a->session.batch, "events per device scan; the host's work on one batch runs while the device "
                 "scans the next")
      ->capture_default_str()->check(CLI::Range(1, 65535));
  c->add_flag("--serial-scans", a->session.serial_scans,
              "scan a batch, then do the host's work on it, then scan the next, instead of the two side by side "
              "(the same results; for comparison)");
  c->add_option("--scan-step", a->session.settings.scan_step_px, "the scan tries shifts on multiples of this (pixels of the "
                 "scan level); the best candidates are re-searched around theirs")
      ->capture_default_str()->check(CLI::Range(1, 64));
  c->add_option("--level", a->session.level, "dictionary level of the scan over all PSFs (default: the finest from the clicks' level + 2 up "
                 "whose shifts over all PSFs stay within a budget per click; level 4 for the default dictionary at "
                 "110 um clicks); one coarser than --select-level is searched coarse to fine: every PSF "
                 "within --carry-margin of its best NLL goes down to --select-level and is ranked again there")
      ->check(non_negative_number);
  c->add_option("--select-level", a->session.settings.select_level,
                "coarse to fine: the level where the carried PSFs are ranked again before the best 8 go on to the "
                "clicks (-1: pixels of 64 x 64 sensor pixels, 441.6 um, or the clicks' level + 2 where coarser)")
      ->capture_default_str()->check(CLI::Range(-1, 63));
  c->add_option("--rank-level", a->session.settings.rank_level,
                "the level where the 8 candidates from --select-level are ranked by their NLL before the best alone "
                "goes on to the clicks (-1: pixels of 4 x 4 sensor pixels, 27.6 um, or the clicks' level where "
                "coarser)")
      ->capture_default_str()->check(CLI::Range(-1, 63));
  c->add_option("--carry-margin", a->session.settings.carry_margin_nll,
                "coarse to fine: NLL margin of the PSFs carried from a coarse scan, and again at each level on the way "
                "to the clicks (0: the scan's 8 best alone, and of them the best alone on to the clicks)")
      ->capture_default_str()->check(non_negative_number);
  c->add_flag_callback("--carry-once", [a] { a->session.settings.staged_carry = false; },
                       "coarse to fine: apply --carry-margin to the scan alone, carrying every PSF within it down to "
                       "--select-level and all 8 candidates to --rank-level, instead of again at every level (the "
                       "way before; for comparison)");
  c->add_option("--tau-mm", a->session.settings.tau_mm, "lateral search half-width around each grid node, source mm")
      ->capture_default_str()->check(non_negative_number);
  c->add_option("--dark-rate", a->session.settings.dark_rate, dark_rate_help)->capture_default_str()->check(positive_number);
  c->add_option("--search-dark-rate", a->session.settings.search_dark_rate, search_dark_rate_help)
      ->capture_default_str()
      ->check(non_negative_number);
  c->add_option("--budget-mib", a->session.budget_mib, "host memory for summed-area tables, tiles and open PSF files, all threads together")
      ->capture_default_str()->check(positive_number);
  c->add_option("--threads", a->session.threads, "host threads: the cpu backend's workers; with vulkan or dense, the "
                 "threads that descend events beside the device's scan (sharing one tile cache within --budget-mib). 0: 1 for "
                 "the cpu backend, this machine's hardware threads (at most 8) for vulkan and dense")->capture_default_str()->check(CLI::Range(0u, 256u));
  c->callback([a] { run(*a); });
}

}  // namespace prism::cmd
