#include "host/util/journal.h"

#include <fcntl.h>
#include <unistd.h>

#include <fstream>

#include "host/util/image_io.h"

namespace prism {

using json = nlohmann::json;

Journal::Journal(std::string path, const json& header, const std::string& on_mismatch, bool read_only)
    : path_(std::move(path)), read_only_(read_only) {
  std::ifstream in(path_);
  if (!in && read_only) throw JournalError("cannot read " + path_);
  if (!in) {
    header_ = header;
    write_atomically(path_, [&](const std::string& tmp) {
      std::ofstream out(tmp);
      out << header.dump() << '\n';
      if (!out) throw JournalError("cannot write " + path_);
    });
    return;
  }
  std::string line;
  std::vector<std::string> good;
  bool torn = false;
  size_t line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    json j;
    try {
      j = json::parse(line);
    } catch (const json::parse_error&) {
      // Only a record cut short by a kill can be half written: the last line.
      if (in.peek() != EOF)
        throw JournalError(path_ + ":" + std::to_string(line_no) + ": not a JSON record; remove the file to start over");
      torn = true;
      break;
    }
    if (line_no == 1) {
      for (auto it = header.begin(); it != header.end(); ++it)
        if (!j.contains(it.key()) || j[it.key()] != it.value())
          throw JournalError(path_ + " was made with a different " + it.key() + " (" +
                             (j.contains(it.key()) ? j[it.key()].dump() : "none") + ", this run: " +
                             it.value().dump() + "); " + on_mismatch);
      header_ = j;
    } else {
      records_.push_back(std::move(j));
    }
    good.push_back(line);
  }
  if (line_no == 0) throw JournalError(path_ + " is empty; remove it to start over");
  if (torn && !read_only) {
    write_atomically(path_, [&](const std::string& tmp) {
      std::ofstream out(tmp);
      for (const auto& g : good) out << g << '\n';
      if (!out) throw JournalError("cannot write " + path_);
    });
  }
}

void Journal::append(const json& record) const {
  // One write() of a whole line with O_APPEND, then fsync: a kill leaves
  // either the line or (at worst) a torn last line, which the reader drops.
  if (read_only_) throw JournalError(path_ + " was opened to be read only");
  const std::string line = record.dump() + "\n";
  const int fd = ::open(path_.c_str(), O_WRONLY | O_APPEND);
  if (fd < 0) throw JournalError("cannot append to " + path_);
  const ssize_t n = ::write(fd, line.data(), line.size());
  ::fsync(fd);
  ::close(fd);
  if (n != ssize_t(line.size())) throw JournalError("cannot append to " + path_ + " (disk full?)");
}

}  // namespace prism
