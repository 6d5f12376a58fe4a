#include "host/util/memory.h"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <optional>

namespace prism {

namespace {

// A control group's memory limit (cgroup v2 memory.max, else v1's
// limit_in_bytes); nullopt when there is none or it reads "max".
std::optional<uint64_t> cgroup_memory_limit() {
  for (const char* path : {"/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"}) {
    std::ifstream in(path);
    std::string text;
    if (!(in >> text) || text == "max") continue;
    try {
      size_t used = 0;
      uint64_t v = std::stoull(text, &used);
      if (used == text.size() && v > 0) return v;
    } catch (const std::exception&) {
    }
  }
  return std::nullopt;
}

std::optional<uint64_t> limit_set;

uint64_t physical_memory_bytes() {
  const long pages = ::sysconf(_SC_PHYS_PAGES), page = ::sysconf(_SC_PAGESIZE);
  return pages > 0 && page > 0 ? uint64_t(pages) * uint64_t(page) : 0;
}

bool limited_by_cgroup() {
  const auto cg = cgroup_memory_limit();
  return cg && (physical_memory_bytes() == 0 || *cg < physical_memory_bytes());
}

}  // namespace

uint64_t machine_memory_bytes() { return limited_by_cgroup() ? *cgroup_memory_limit() : physical_memory_bytes(); }

uint64_t memory_limit_bytes() {
  if (limit_set) return *limit_set;
  return uint64_t(default_memory_fraction * double(machine_memory_bytes()));
}

void set_memory_limit_bytes(uint64_t bytes) { limit_set = bytes; }
void use_default_memory_limit() { limit_set.reset(); }

std::string memory_limit_origin() {
  if (limit_set) return "set by --max-memory";
  char share[32];
  std::snprintf(share, sizeof share, "%.0f%%", 100 * default_memory_fraction);
  return std::string(share) + (limited_by_cgroup() ? " of this control group's limit of " : " of this machine's ") +
         format_bytes(double(machine_memory_bytes()));
}

uint64_t parse_memory_size(const std::string& text, const std::string& option) {
  auto fail = [&] {
    return std::invalid_argument(option + ": '" + text +
                                 "' is not a memory size; write bytes or a number with K, M, G or T (powers of "
                                 "1024), for example 512M or 8G");
  };
  size_t used = 0;
  double v = 0;
  try {
    v = std::stod(text, &used);
  } catch (const std::exception&) {
    throw fail();
  }
  std::string unit = text.substr(used);
  for (auto& c : unit) c = char(std::toupper(static_cast<unsigned char>(c)));
  if (unit.size() >= 2 && unit.substr(unit.size() - 2) == "IB") unit.resize(unit.size() - 2);
  else if (!unit.empty() && unit.back() == 'B') unit.pop_back();
  const std::string units = "KMGT";
  double scale = 1;
  if (unit.size() == 1 && units.find(unit[0]) != std::string::npos)
    scale = std::ldexp(1.0, 10 * int(units.find(unit[0]) + 1));
  else if (!unit.empty())
    throw fail();
  const double bytes = v * scale;
  if (!std::isfinite(bytes) || bytes < 1 || bytes >= 0x1p64)
    throw std::invalid_argument(option + ": '" + text + "' must be at least one byte and below 16 EiB");
  return uint64_t(bytes);
}

std::string format_bytes(double bytes) {
  const char* unit[] = {"B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"};
  int u = 0;
  while (bytes >= 1024 && u < 6) bytes /= 1024, ++u;
  char buf[48];
  if (u == 0) std::snprintf(buf, sizeof buf, "%.0f B", bytes);
  else std::snprintf(buf, sizeof buf, bytes < 10 ? "%.2f %s" : bytes < 100 ? "%.1f %s" : "%.0f %s", bytes, unit[u]);
  return buf;
}

MemoryEstimate& MemoryEstimate::add(std::string part, double bytes) {
  if (bytes > 0) parts_.emplace_back(std::move(part), bytes);
  return *this;
}

double MemoryEstimate::total_bytes() const {
  double t = 0;
  for (const auto& p : parts_) t += p.second;
  return t;
}

void MemoryEstimate::require_within_limit(const std::string& to_reduce) const {
  const double total = total_bytes();
  const uint64_t limit = memory_limit_bytes();
  if (total <= double(limit)) return;
  auto parts = parts_;
  std::stable_sort(parts.begin(), parts.end(), [](const auto& a, const auto& b) { return a.second > b.second; });
  std::string msg = work_ + " needs an estimated " + format_bytes(total) + " of memory (";
  for (size_t i = 0; i < parts.size(); ++i) msg += (i ? "; " : "") + parts[i].first + ": " + format_bytes(parts[i].second);
  msg += "), more than the limit of " + format_bytes(double(limit)) + " (" + memory_limit_origin() + "). " + to_reduce +
         ", or raise the limit with --max-memory (on a machine that has the memory).";
  throw ResourceError(msg);
}

}  // namespace prism
