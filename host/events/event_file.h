// Event files: a versioned header, then one record per event (its vertices'
// truth and its clicked pixels), streamed in both directions so that millions
// of events never sit in memory. Layout, field by field: host/EVENTS.md.
#pragma once
#include <cstdint>
#include <cstdio>
#include <span>
#include <stdexcept>
#include <string>
#include <vector>

namespace prism {

inline constexpr uint32_t event_format_version = 1;

// Bytes of one event record (EVENTS.md): tag, id, vertex count, 5 f64 per
// vertex, click count, a u32 per click.
inline constexpr uint64_t event_record_bytes(uint64_t vertices, uint64_t clicks) {
  return 4 + 8 + 4 + 40 * vertices + 4 + 4 * clicks;
}

// A file that cannot be read or written; the message names the file, the
// byte offset where reading stopped, and what to do.
struct EventFileError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

enum class TruthModel : uint8_t { forward = 0, dictionary = 1 };
const char* to_string(TruthModel m);

struct EventFileHeader {
  uint32_t sensor_width_px = 0;   // the physical sensor, unbinned
  uint32_t sensor_height_px = 0;
  double pixel_um = 0;            // physical pixel pitch
  uint32_t binning = 1;           // click coordinates are on the sensor binned B x B
  std::string scene;              // scene name
  TruthModel truth = TruthModel::forward;
  uint64_t seed = 0;
  std::string provenance;         // free text: rays per lenslet, dictionary path, jitter
  uint64_t event_count = 0;       // filled in by the writer on close

  // The click grid: ceil(sensor / binning); a click is row * grid_width + col.
  uint32_t grid_width() const { return (sensor_width_px + binning - 1) / binning; }
  uint32_t grid_height() const { return (sensor_height_px + binning - 1) / binning; }
  uint64_t grid_pixels() const { return uint64_t(grid_width()) * grid_height(); }
};

// The truth of one vertex of an event.
struct EventVertex {
  double x_mm = 0, y_mm = 0, depth_mm = 0;
  double alpha = 0;            // expected photons (EVENTS.md, "alpha and P")
  double sensor_fraction = 0;  // S = sum_i P_i: the part of alpha that can reach the sensor
};

struct Event {
  uint64_t id = 0;
  std::vector<EventVertex> vertices;
  std::vector<uint32_t> clicks;  // strictly increasing pixel indices on the click grid
};

// The index of the first click that lies off a grid of `grid_pixels` or is
// not above the one before (clicks are strictly increasing pixel indices);
// clicks.size() when there is none. The writer, the reader and the Python
// module's events in memory check with it.
size_t first_bad_click(std::span<const uint32_t> clicks, uint64_t grid_pixels);

// `clicks` on a grid `width` pixels wide, binned 2^shift x 2^shift onto a
// grid `binned_width` pixels wide (ceil(width / 2^shift)): a binned pixel
// clicks when any of its pixels does, which is the binary sensor's own
// likelihood for the summed rate. Strictly increasing, as clicks are.
std::vector<uint32_t> binned_clicks(std::span<const uint32_t> clicks, uint32_t width, int shift, uint32_t binned_width);

// Appends the record of event `e` (EVENTS.md) to `out`, its clicks checked
// against a grid of `grid_pixels`; `file` names the file in the error. The
// writer writes these; an MPI rank sends them to the rank that writes.
void append_event_record(const Event& e, uint64_t grid_pixels, const std::string& file, std::vector<uint8_t>& out);

// Writes DEST.tmp.PID, then renames it to DEST on close(): a file at DEST is
// always whole. Destroying an unclosed writer removes the temporary file.
class EventWriter {
 public:
  EventWriter(std::string path, EventFileHeader header);
  ~EventWriter();
  EventWriter(const EventWriter&) = delete;
  EventWriter& operator=(const EventWriter&) = delete;

  void write(const Event& e);  // clicks must be strictly increasing and on the grid
  // `events` whole records made by append_event_record for this header's grid.
  void write_records(std::span<const uint8_t> records, uint64_t events);
  void close();                // trailer, event count, rename
  uint64_t events() const { return count_; }
  uint64_t bytes() const { return bytes_; }

 private:
  std::string path_, temp_;
  EventFileHeader header_;
  std::FILE* f_ = nullptr;
  uint64_t count_ = 0, bytes_ = 0;
  uint64_t count_offset_ = 0;  // where the header's event count lies, patched on close
  std::vector<uint8_t> buf_;
};

// Reads one event at a time into a caller-owned Event whose storage is reused:
// constant memory however long the file.
class EventReader {
 public:
  explicit EventReader(std::string path);
  ~EventReader();
  EventReader(const EventReader&) = delete;
  EventReader& operator=(const EventReader&) = delete;

  const EventFileHeader& header() const { return header_; }
  // False after the last event (the trailer was read and checked). Throws
  // EventFileError for truncation or corruption.
  bool next(Event& e);
  uint64_t offset() const { return offset_; }  // bytes consumed so far

 private:
  void read(void* dst, size_t n, const char* what);
  [[noreturn]] void fail(const std::string& why) const;
  std::string path_;
  std::FILE* f_ = nullptr;
  EventFileHeader header_;
  uint64_t offset_ = 0, read_events_ = 0;
  uint64_t size_ = 0;  // the file's bytes: a count is checked against what is left before it is allocated
  void require_left(uint64_t bytes, const char* what);  // before allocating for a count
  [[noreturn]] void truncated(const char* what) const;
  void read_header();
  bool done_ = false;
};

}  // namespace prism
