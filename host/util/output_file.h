// Output files that exist only whole. Every command writes a file through a
// temporary beside it (PATH.partial-PID), renamed over PATH when complete:
// an error removes the temporary, an interrupt (SIGINT, SIGTERM) removes every
// temporary of the process before it dies with the signal (exit status 130
// for Ctrl-C), and a later write of the same PATH removes temporaries left by
// processes no longer running (a kill -9, a crash).
#pragma once
#include <string>

namespace prism {

// Throws "cannot write PATH: ..." when `path` cannot become a file: it is a
// directory, or its folder does not exist or is not writable. Commands call
// it for their output files before any work.
void check_writable(const std::string& path);

// An input of a command: the option that named it and its path (a file, or a
// folder such as a dictionary; an empty path, or one where nothing exists
// such as a built-in scene's name, is skipped).
struct NamedInput {
  const char* option;
  std::string path;
};
// Throws unless the output `path` (named by `option`) is none of `inputs`
// and lies in none of the input folders: an output written over an input
// would destroy it (the events a run reads, a dictionary's manifest).
// Commands call it with check_writable, before any work.
void check_not_input(const std::string& path, const char* option, std::initializer_list<NamedInput> inputs);

// The temporary for `path`, registered for removal on an interrupt; stale
// temporaries of `path` from dead processes are removed first.
std::string begin_temporary(const std::string& path);
// Renames the temporary over `path` (throws "cannot write PATH: why", the
// temporary removed), or removes it; either way it is no longer registered.
void rename_into_place(const std::string& tmp, const std::string& path);
void remove_temporary(const std::string& tmp) noexcept;

// Write `path` through a temporary: the callback writes to the temporary's
// path, renamed over `path` only when it returns.
template <class F> void write_atomically(const std::string& path, F&& write) {
  check_writable(path);
  const std::string tmp = begin_temporary(path);
  try {
    write(tmp);
  } catch (...) {
    remove_temporary(tmp);
    throw;
  }
  rename_into_place(tmp, path);
}

// SIGINT and SIGTERM remove the registered temporaries, then end the process
// with the signal's default action. Installed once, by main().
void install_interrupt_cleanup();
// The handler itself, for a command that catches SIGINT for a while (to stop
// gracefully) and gives the next one back to it.
extern "C" void remove_temporaries_and_die(int signal);

}  // namespace prism
