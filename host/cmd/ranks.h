// The processes of one `prism` job. A plain run is one process. Under an MPI
// launcher (mpirun, srun), a prism built with MPI runs the same command in
// every rank: each takes a contiguous share of the work on its own device,
// and rank 0 gathers the results in rank order and writes every output, so
// the files equal a single process's (docs/mpi.md). Only the commands that
// say so split their work; the others refuse to run under several ranks.
#pragma once
#include <cstdint>
#include <functional>
#include <string>
#include <string_view>
#include <vector>

#include <CLI/CLI.hpp>

#include "host/util/work_share.h"

namespace prism::cmd::ranks {

// Called once by main() before parsing. Starts MPI when an MPI launcher
// started this process (its environment says so; a plain run never touches
// MPI), gives the engine this rank's device slot on its node, and refuses a
// launch of several processes by a build without MPI.
void start(int& argc, char**& argv);
// MPI_Finalize after a command that returned; main() calls it.
void stop();

int rank();        // 0 in a plain run
int size();        // 1 in a plain run
inline bool root() { return rank() == 0; }
int local_rank();  // among the ranks on this node: which device it takes

// Items [begin, end) of 0..n-1 that this rank works on: contiguous, in rank
// order, their sizes differing by at most one.
struct Share {
  uint64_t begin = 0, end = 0;
  uint64_t count() const { return end - begin; }
};
Share share_of(int rank, uint64_t n);
inline Share share(uint64_t n) { return share_of(rank(), n); }

// Collective. Every rank but 0 sends `mine`; rank 0 gets each of theirs
// whole, in rank order (rank 1 first), and passes it to `consume`. Rank 0's
// own part is its own business (it writes it first).
void gather_in_order(std::string_view mine, const std::function<void(int rank, std::string_view bytes)>& consume);

// Collective: every rank's bytes, in rank order, on every rank.
std::vector<std::string> all_gather(std::string_view mine);

// This rank's place in the job, with the exchanges above, for the library's
// commands that split their own work (host/util/work_share.h).
WorkShare work_share();

// Collective: returns when every rank has called it.
void barrier();

// Collective sums and maxima over the ranks, the result on every rank.
double sum(double x);
uint64_t sum(uint64_t x);
double max(double x);

// Prints "prism: rank R of N: message" and ends the whole job (MPI_Abort):
// the other ranks are stopped, and rank 0's temporary output is removed by
// the interrupt cleanup (host/util/output_file.h) when the launcher ends it.
[[noreturn]] void fail(const std::string& message);

// Makes `command` refuse to run under several ranks, as it does not split
// its work over them yet.
void single_process_only(CLI::App& command);

}  // namespace prism::cmd::ranks
