// The memory limit and the estimates checked against it (host/util/memory.h):
// sizes parsed as users write them, refusals that name the parts, the limit
// and the options to change, and nothing started or written when refused.
#include <filesystem>
#include <string>

#include "host/events/simulate.h"
#include "host/util/memory.h"
#include "support.h"

namespace fs = std::filesystem;

namespace {

// The process-wide limit set for one test and put back after it.
struct LimitFor {
  explicit LimitFor(uint64_t bytes) { prism::set_memory_limit_bytes(bytes); }
  ~LimitFor() { prism::use_default_memory_limit(); }
};

}  // namespace

TEST_CASE("memory sizes: bytes, K/M/G/T as powers of 1024, and what is not a size") {
  using prism::parse_memory_size;
  CHECK(parse_memory_size("4096", "--max-memory") == 4096);
  CHECK(parse_memory_size("300k", "--max-memory") == 300ull << 10);
  CHECK(parse_memory_size("512M", "--max-memory") == 512ull << 20);
  CHECK(parse_memory_size("8G", "--max-memory") == 8ull << 30);
  CHECK(parse_memory_size("1.5GiB", "--max-memory") == 3ull << 29);
  CHECK(parse_memory_size("2TB", "--max-memory") == 2ull << 40);
  for (const char* bad : {"", "x", "1x", "12 MB", "-1", "0", "0.5", "nan", "inf", "1e30T", "G"})
    CHECK_THROWS_WITH_AS(parse_memory_size(bad, "--max-memory"), doctest::Contains("--max-memory"),
                         std::invalid_argument);
  CHECK(prism::format_bytes(900) == "900 B");
  CHECK(prism::format_bytes(1536) == "1.50 KiB");
  CHECK(prism::format_bytes(312.0 * (1 << 20)) == "312 MiB");
  // The default is a share of this machine's memory.
  CHECK(prism::machine_memory_bytes() > (64ull << 20));
  CHECK(prism::memory_limit_bytes() ==
        uint64_t(prism::default_memory_fraction * double(prism::machine_memory_bytes())));
}

TEST_CASE("a memory estimate beyond the limit is refused with its parts, the limit and what to change") {
  LimitFor limit(3 << 20);
  prism::MemoryEstimate m("psf at binning 1");
  m.add("the image", 2.0 * (1 << 20)).add("nothing", 0).add("the preview", 0.5 * (1 << 20));
  CHECK(m.total_bytes() == 2.5 * (1 << 20));
  CHECK_NOTHROW(m.require_within_limit("Use a coarser --binning"));
  m.add("the device's buffers", 1.5 * (1 << 20));
  CHECK_THROWS_WITH_AS(m.require_within_limit("Use a coarser --binning"),
                       "psf at binning 1 needs an estimated 4.00 MiB of memory (the image: 2.00 MiB; the device's "
                       "buffers: 1.50 MiB; the preview: 512 KiB), more than the limit of 3.00 MiB (set by "
                       "--max-memory). Use a coarser --binning, or raise the limit with --max-memory (on a machine "
                       "that has the memory).",
                       prism::ResourceError);
}

TEST_CASE("the events' PSF cache keeps within its share of the memory limit") {
  prism::TraceSettings t;
  t.binning = 32;
  t.rays_per_lenslet = 256;
  prism::ForwardTruth truth(prism::test::gpu(), prism::builtin_scene("prototype"), t);
  const glm::dvec3 a{1.0, -2.0, 20.0}, b{-3.0, 2.0, 30.0};
  const size_t bytes = truth.psf(a)->bytes();
  REQUIRE(bytes > 0);
  truth.psf(b);
  CHECK(truth.psf(a) != nullptr);
  CHECK(truth.renders() == 2);  // both kept under the default limit
  {
    // Room for one and a half PSFs: a third evicts the oldest.
    LimitFor limit(uint64_t(1.5 * double(bytes) / prism::EventTruth::cache_share));
    truth.psf(b);  // b is the newest now
    truth.psf({0.0, 0.0, 25.0});
    CHECK(truth.renders() == 3);
    truth.psf(b);  // evicted: rendered again
    CHECK(truth.renders() == 4);
  }
  prism::test::check_validation_clean();
}

TEST_CASE("prism refuses work beyond --max-memory before it starts, and writes nothing") {
  const fs::path dir = prism::test::scratch_dir() / "memory";
  fs::create_directories(dir);
  // A full-resolution PSF (6696 x 4764 px) with derivatives needs ~1.4 GiB.
  auto r = prism::test::run_prism("psf --scene prototype --source-mm 0,0,20 --binning 1 --max-memory 100M --out " +
                                  (dir / "psf.exr").string());
  CHECK(r.status == 1);
  CHECK_MESSAGE(r.output.find("psf at binning 1 (6696 x 4764 px) needs an estimated") != std::string::npos, r.output);
  CHECK_MESSAGE(r.output.find("more than the limit of 100 MiB (set by --max-memory). Use a coarser --binning") !=
                    std::string::npos,
                r.output);
  CHECK_FALSE(fs::exists(dir / "psf.exr"));
  CHECK_FALSE(fs::exists(dir / "psf.png"));
  // The same from the environment, for a dictionary build: no folder made.
  r = prism::test::run_prism("dictionary build --scene prototype --binning 1 --out " + (dir / "dict").string(),
                             "PRISM_MAX_MEMORY=200M");
  CHECK(r.status == 1);
  CHECK_MESSAGE(r.output.find("dictionary build at binning 1 (6696 x 4764 px per PSF) needs an estimated") !=
                    std::string::npos,
                r.output);
  CHECK_FALSE(fs::exists(dir / "dict"));
  // A size that is not one is a usage error naming the option.
  r = prism::test::run_prism("simulate --scene prototype --vertex 0,0,20 --events 1 --out " +
                             (dir / "e.events").string() + " --max-memory 1x");
  CHECK(r.status != 0);
  CHECK_MESSAGE(r.output.find("--max-memory: '1x' is not a memory size") != std::string::npos, r.output);
}
