// An append-only JSON-lines file that lets long work resume where it was
// stopped (`prism sweep`'s state, `prism evaluate`'s volume events): a header
// line naming what made the file, then one record per line. Each record is
// appended with one write() and fsync, so a kill leaves at worst a torn last
// line, which reading drops.
#pragma once
#include <stdexcept>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace prism {

struct JournalError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

class Journal {
 public:
  // Creates `path` holding `header` when it does not exist. Otherwise its
  // header must have every key of `header` with the same value (else
  // JournalError naming the key, both values and `on_mismatch`, what the
  // user should do), and its records are read.
  // read_only: never created or rewritten (a torn last line is dropped in
  // memory only), for reading a journal that another process may be
  // appending to; append() then throws.
  Journal(std::string path, const nlohmann::json& header, const std::string& on_mismatch, bool read_only = false);

  const std::vector<nlohmann::json>& records() const { return records_; }
  const std::string& path() const { return path_; }
  const nlohmann::json& header() const { return header_; }  // the file's own (its first line)
  void append(const nlohmann::json& record) const;  // throws JournalError when it cannot

 private:
  std::string path_;
  std::vector<nlohmann::json> records_;
  nlohmann::json header_;
  bool read_only_ = false;
};

}  // namespace prism
