#include "host/cmd/ranks.h"

#include <cstdio>
#include <cstdlib>
#include <stdexcept>
#include <vector>

#include "engine/vk/context.h"

#ifdef PRISM_WITH_MPI
// The C interface only: mpi.h would otherwise bring in the C++ bindings
// (removed from MPI 3), which libmpi does not link.
#define OMPI_SKIP_MPICXX 1
#define MPICH_SKIP_MPICXX 1
#include <mpi.h>
#endif

namespace prism::cmd::ranks {

namespace {

int rank_ = 0, size_ = 1, local_rank_ = 0;
bool started_ = false;

// The process count an MPI launcher announces in the environment (Open MPI's
// mpirun; MPICH's hydra and Slurm's PMI), or 0 when none started this process.
long launcher_size() {
  for (const char* name : {"OMPI_COMM_WORLD_SIZE", "PMI_SIZE"})
    if (const char* v = std::getenv(name)) return std::atol(v);
  return 0;
}

// Whether an MPI launcher started this process (PMIx, as under `srun
// --mpi=pmix`, announces the rank alone).
bool launched_by_mpi() { return launcher_size() > 0 || std::getenv("PMI_RANK") || std::getenv("PMIX_RANK"); }

#ifdef PRISM_WITH_MPI
// Messages are cut into pieces of at most this many bytes (MPI counts are int).
constexpr uint64_t max_piece_bytes = uint64_t(1) << 30;
constexpr int tag_length = 1, tag_bytes = 2;

void check(int status, const char* what) {
  if (status != MPI_SUCCESS) fail(std::string(what) + " failed (MPI error " + std::to_string(status) + ")");
}
#endif

}  // namespace

void start(int& argc, char**& argv) {
  (void)argc;
  (void)argv;
#ifdef PRISM_WITH_MPI
  if (!launched_by_mpi()) return;
  check(MPI_Init(&argc, &argv), "MPI_Init");
  started_ = true;
  check(MPI_Comm_rank(MPI_COMM_WORLD, &rank_), "MPI_Comm_rank");
  check(MPI_Comm_size(MPI_COMM_WORLD, &size_), "MPI_Comm_size");
  MPI_Comm node;
  check(MPI_Comm_split_type(MPI_COMM_WORLD, MPI_COMM_TYPE_SHARED, rank_, MPI_INFO_NULL, &node), "MPI_Comm_split_type");
  check(MPI_Comm_rank(node, &local_rank_), "MPI_Comm_rank");
  MPI_Comm_free(&node);
  vk::set_device_slot(unsigned(local_rank_));
#else
  if (const long n = launcher_size(); n > 1)
    throw std::runtime_error("started as one of " + std::to_string(n) + " MPI processes, but this prism was built "
                             "without MPI: each would do the whole job and write the same files. Install "
                             "libopenmpi-dev and build again (docs/mpi.md), or run prism without mpirun");
#endif
}

void stop() {
#ifdef PRISM_WITH_MPI
  if (started_) MPI_Finalize();
#endif
  started_ = false;
}

int rank() { return rank_; }
int size() { return size_; }
int local_rank() { return local_rank_; }

Share share_of(int rank, uint64_t n) {
  // Rank r takes [r n / N, (r + 1) n / N): 128-bit products, so no n overflows.
  auto edge = [&](int r) { return uint64_t((unsigned __int128)n * unsigned(r) / unsigned(size_)); };
  return {edge(rank), edge(rank + 1)};
}

void gather_in_order(std::string_view mine, const std::function<void(int, std::string_view)>& consume) {
  if (size_ == 1) return;
#ifdef PRISM_WITH_MPI
  if (rank_ != 0) {
    // Rank 0 receives the ranks one after another: a length, then pieces.
    uint64_t length = mine.size();
    check(MPI_Send(&length, 1, MPI_UINT64_T, 0, tag_length, MPI_COMM_WORLD), "MPI_Send");
    for (uint64_t at = 0; at < length; at += max_piece_bytes)
      check(MPI_Send(mine.data() + at, int(std::min(max_piece_bytes, length - at)), MPI_BYTE, 0, tag_bytes,
                     MPI_COMM_WORLD),
            "MPI_Send");
    return;
  }
  std::string bytes;
  for (int r = 1; r < size_; ++r) {
    uint64_t length = 0;
    check(MPI_Recv(&length, 1, MPI_UINT64_T, r, tag_length, MPI_COMM_WORLD, MPI_STATUS_IGNORE), "MPI_Recv");
    bytes.resize(length);
    for (uint64_t at = 0; at < length; at += max_piece_bytes)
      check(MPI_Recv(bytes.data() + at, int(std::min(max_piece_bytes, length - at)), MPI_BYTE, r, tag_bytes,
                     MPI_COMM_WORLD, MPI_STATUS_IGNORE),
            "MPI_Recv");
    consume(r, bytes);
  }
#else
  (void)mine;
  (void)consume;
#endif
}

std::vector<std::string> all_gather(std::string_view mine) {
  std::vector<std::string> all(static_cast<size_t>(size_));
  all[size_t(rank_)] = mine;
  if (size_ == 1) return all;
#ifdef PRISM_WITH_MPI
  std::vector<uint64_t> lengths(static_cast<size_t>(size_));
  uint64_t length = mine.size();
  check(MPI_Allgather(&length, 1, MPI_UINT64_T, lengths.data(), 1, MPI_UINT64_T, MPI_COMM_WORLD), "MPI_Allgather");
  // Each rank's bytes from that rank to all, in pieces (MPI counts are int).
  for (int r = 0; r < size_; ++r) {
    std::string& bytes = all[size_t(r)];
    bytes.resize(lengths[size_t(r)]);
    for (uint64_t at = 0; at < bytes.size(); at += max_piece_bytes)
      check(MPI_Bcast(bytes.data() + at, int(std::min(max_piece_bytes, bytes.size() - at)), MPI_BYTE, r,
                      MPI_COMM_WORLD),
            "MPI_Bcast");
  }
#endif
  return all;
}

WorkShare work_share() {
  WorkShare s;
  s.index = size_t(rank_);
  s.count = size_t(size_);
  s.all_gather = all_gather;
  s.barrier = barrier;
  return s;
}

void barrier() {
#ifdef PRISM_WITH_MPI
  if (size_ > 1) check(MPI_Barrier(MPI_COMM_WORLD), "MPI_Barrier");
#endif
}

double sum(double x) {
#ifdef PRISM_WITH_MPI
  if (size_ > 1) check(MPI_Allreduce(MPI_IN_PLACE, &x, 1, MPI_DOUBLE, MPI_SUM, MPI_COMM_WORLD), "MPI_Allreduce");
#endif
  return x;
}

uint64_t sum(uint64_t x) {
#ifdef PRISM_WITH_MPI
  if (size_ > 1) check(MPI_Allreduce(MPI_IN_PLACE, &x, 1, MPI_UINT64_T, MPI_SUM, MPI_COMM_WORLD), "MPI_Allreduce");
#endif
  return x;
}

double max(double x) {
#ifdef PRISM_WITH_MPI
  if (size_ > 1) check(MPI_Allreduce(MPI_IN_PLACE, &x, 1, MPI_DOUBLE, MPI_MAX, MPI_COMM_WORLD), "MPI_Allreduce");
#endif
  return x;
}

void fail(const std::string& message) {
  std::fprintf(stderr, "prism: rank %d of %d: %s\n", rank_, size_, message.c_str());
  std::fflush(stderr);
#ifdef PRISM_WITH_MPI
  if (started_) MPI_Abort(MPI_COMM_WORLD, 1);
#endif
  std::exit(1);
}

void single_process_only(CLI::App& command) {
  command.preparse_callback([name = command.get_name()](size_t) {
    if (size_ > 1)
      throw std::runtime_error(name + " does not split its work over MPI ranks (docs/mpi.md lists the commands that "
                               "do): run it as one process, without mpirun");
  });
}

}  // namespace prism::cmd::ranks
