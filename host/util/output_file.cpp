#include "host/util/output_file.h"

#include <signal.h>
#include <unistd.h>

#include <array>
#include <atomic>
#include <cerrno>
#include <csignal>
#include <cstring>
#include <filesystem>
#include <stdexcept>
#include <string_view>

namespace prism {

namespace {

// The live temporaries, in slots a signal handler can read without locks: a
// slot is claimed with an atomic flag and its path written before it is
// published. More than kSlots at once are not tracked (still removed on
// errors and by later runs).
constexpr size_t kSlots = 64, kPathBytes = 4096;
struct Slot {
  std::atomic<int> state{0};  // 0 free, 1 being written, 2 live
  char path[kPathBytes];
};
std::array<Slot, kSlots> slots;

void track(const std::string& tmp) {
  if (tmp.size() >= kPathBytes) return;
  for (auto& s : slots) {
    int free = 0;
    if (!s.state.compare_exchange_strong(free, 1)) continue;
    std::memcpy(s.path, tmp.c_str(), tmp.size() + 1);
    s.state.store(2);
    return;
  }
}

void untrack(const std::string& tmp) {
  for (auto& s : slots)
    if (s.state.load() == 2 && tmp == s.path) {
      s.state.store(0);
      return;
    }
}

constexpr std::string_view kSuffix = ".partial-";

// PATH.partial-PID of a process that no longer runs.
void remove_stale(const std::string& path) {
  namespace fs = std::filesystem;
  const fs::path p(path);
  const fs::path folder = p.parent_path().empty() ? fs::path(".") : p.parent_path();
  const std::string prefix = p.filename().string() + std::string(kSuffix);
  std::error_code ec;
  for (fs::directory_iterator it(folder, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string name = it->path().filename().string();
    if (name.size() <= prefix.size() || name.compare(0, prefix.size(), prefix) != 0) continue;
    const std::string digits = name.substr(prefix.size());
    if (digits.find_first_not_of("0123456789") != std::string::npos || digits.size() > 9) continue;
    const pid_t pid = pid_t(std::stol(digits));
    if (pid == ::getpid() || (::kill(pid, 0) == 0 || errno == EPERM)) continue;  // alive (or not ours to judge)
    std::error_code ignored;
    fs::remove(it->path(), ignored);
  }
}

}  // namespace

void check_writable(const std::string& path) {
  namespace fs = std::filesystem;
  std::error_code ec;
  if (path.empty()) throw std::runtime_error("cannot write a file with an empty name");
  if (fs::is_directory(path, ec))
    throw std::runtime_error("cannot write " + path + ": it is a directory; give a file name");
  const fs::path folder = fs::path(path).parent_path().empty() ? fs::path(".") : fs::path(path).parent_path();
  if (!fs::is_directory(folder, ec))
    throw std::runtime_error("cannot write " + path + ": the folder " + folder.string() +
                             " does not exist; create it or choose another path");
  if (::access(folder.c_str(), W_OK) != 0)
    throw std::runtime_error("cannot write " + path + ": the folder " + folder.string() + " is not writable");
}

void check_not_input(const std::string& path, const char* option, std::initializer_list<NamedInput> inputs) {
  namespace fs = std::filesystem;
  std::error_code ec;
  const fs::path out = fs::weakly_canonical(fs::absolute(path, ec), ec);
  for (const NamedInput& in : inputs) {
    if (in.path.empty() || !fs::exists(in.path, ec)) continue;  // nothing there to destroy (a built-in scene's name)
    const fs::path p = fs::weakly_canonical(fs::absolute(in.path, ec), ec);
    if (out == p)
      throw std::runtime_error(std::string(option) + " " + path + " is the input given by " + in.option +
                               "; writing it would destroy that input: choose another path (nothing written)");
    if (fs::is_directory(p, ec)) {
      const auto rel = out.lexically_relative(p);
      if (!rel.empty() && *rel.begin() != "..")
        throw std::runtime_error(std::string(option) + " " + path + " lies inside " + in.path + ", the folder given by " +
                                 in.option + "; write outside it (nothing written)");
    }
  }
}

std::string begin_temporary(const std::string& path) {
  remove_stale(path);
  std::string tmp = path + std::string(kSuffix) + std::to_string(::getpid());
  track(tmp);
  return tmp;
}

void rename_into_place(const std::string& tmp, const std::string& path) {
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) {
    const std::string why = ec.message();  // before remove_temporary reuses errno
    remove_temporary(tmp);
    throw std::runtime_error("cannot write " + path + ": " + why);
  }
  untrack(tmp);
}

void remove_temporary(const std::string& tmp) noexcept {
  std::error_code ignored;
  std::filesystem::remove(tmp, ignored);
  untrack(tmp);
}

extern "C" void remove_temporaries_and_die(int signal) {
  for (auto& s : slots)
    if (s.state.load() == 2) ::unlink(s.path);  // async-signal-safe
  std::signal(signal, SIG_DFL);
  std::raise(signal);
}

void install_interrupt_cleanup() {
  for (int sig : {SIGINT, SIGTERM})
    if (std::signal(sig, remove_temporaries_and_die) == SIG_IGN)
      std::signal(sig, SIG_IGN);  // started ignoring it (nohup, a background job): keep ignoring it
}

}  // namespace prism
