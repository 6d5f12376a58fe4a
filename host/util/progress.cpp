#include "host/util/progress.h"

#include <unistd.h>

#include <cstdio>

namespace prism {

Progress::Progress(std::string what, size_t total, bool shown)
    : what_(std::move(what)), total_(total), tty_(isatty(2)), shown_(shown) {}

void Progress::update(size_t done) {
  auto now = std::chrono::steady_clock::now();
  double elapsed = std::chrono::duration<double>(now - start_).count();
  double frac = total_ ? double(done) / double(total_) : 1.0;
  int decile = int(frac * 10);
  if (!shown_) return;
  bool due = tty_ ? now - last_draw_ > std::chrono::milliseconds(200) || done == total_ : decile != last_decile_;
  if (!due) return;
  last_draw_ = now;
  last_decile_ = decile;
  double eta = done ? elapsed / double(done) * double(total_ - done) : 0.0;
  const int width = 30;
  std::string bar(size_t(frac * width), '=');
  bar.resize(width, ' ');
  std::fprintf(stderr, "%s%s [%s] %zu/%zu  %.1f s elapsed, ETA %.0f s%s", tty_ ? "\r" : "", what_.c_str(), bar.c_str(),
               done, total_, elapsed, eta, tty_ ? "" : "\n");
  std::fflush(stderr);
}

void Progress::finish() {
  if (tty_ && shown_) std::fprintf(stderr, "\n");
}

}  // namespace prism
