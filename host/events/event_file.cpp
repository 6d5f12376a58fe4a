#include "host/events/event_file.h"

#include <cassert>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <cstring>
#include <filesystem>

#include "host/scene/scene.h"
#include "host/util/output_file.h"

namespace prism {

namespace {

constexpr std::array<char, 8> file_magic{'P', 'R', 'I', 'S', 'M', 'E', 'V', 'T'};
// Record tags: a reader that lands mid-record (corruption) finds no tag.
constexpr uint32_t event_tag = 0x544E5645;    // "EVNT" as little-endian bytes
constexpr uint32_t trailer_tag = 0x2E444E45;  // "END."
constexpr uint32_t max_vertices = 1u << 16;
constexpr uint32_t max_text_bytes = 1u << 20;

// Explicit little-endian encoding: the format does not depend on the host.
void put_u8(std::vector<uint8_t>& b, uint8_t v) { b.push_back(v); }
void put_u32(std::vector<uint8_t>& b, uint32_t v) {
  for (int i = 0; i < 4; ++i) b.push_back(uint8_t(v >> (8 * i)));
}
void put_u64(std::vector<uint8_t>& b, uint64_t v) {
  for (int i = 0; i < 8; ++i) b.push_back(uint8_t(v >> (8 * i)));
}
void put_f64(std::vector<uint8_t>& b, double v) { put_u64(b, std::bit_cast<uint64_t>(v)); }
void put_text(std::vector<uint8_t>& b, const std::string& s) {
  put_u32(b, uint32_t(s.size()));
  b.insert(b.end(), s.begin(), s.end());
}

uint32_t get_u32(const uint8_t* p) {
  uint32_t v = 0;
  for (int i = 0; i < 4; ++i) v |= uint32_t(p[i]) << (8 * i);
  return v;
}
uint64_t get_u64(const uint8_t* p) {
  uint64_t v = 0;
  for (int i = 0; i < 8; ++i) v |= uint64_t(p[i]) << (8 * i);
  return v;
}

}  // namespace

const char* to_string(TruthModel m) { return m == TruthModel::dictionary ? "dictionary" : "forward"; }

EventWriter::EventWriter(std::string path, EventFileHeader header) : path_(std::move(path)), header_(std::move(header)) {
  if (header_.sensor_width_px == 0 || header_.sensor_height_px == 0 || header_.binning == 0)
    throw EventFileError(path_ + ": sensor size and binning must be positive");
  if (header_.scene.size() > max_text_bytes || header_.provenance.size() > max_text_bytes)
    throw EventFileError(path_ + ": scene name or provenance longer than 1 MiB");
  try {
    check_writable(path_);
  } catch (const std::runtime_error& e) {
    throw EventFileError(e.what());
  }
  temp_ = begin_temporary(path_);
  f_ = std::fopen(temp_.c_str(), "wb");
  if (!f_) {
    const std::string why = std::strerror(errno);
    remove_temporary(temp_);
    throw EventFileError(temp_ + ": cannot create (" + why + "); check the directory exists and is writable");
  }
  std::vector<uint8_t> b(file_magic.begin(), file_magic.end());
  put_u32(b, event_format_version);
  put_u32(b, header_.sensor_width_px);
  put_u32(b, header_.sensor_height_px);
  put_f64(b, header_.pixel_um);
  put_u32(b, header_.binning);
  put_u8(b, uint8_t(header_.truth));
  put_u64(b, header_.seed);
  count_offset_ = b.size();
  put_u64(b, 0);  // event count, patched on close
  put_text(b, header_.scene);
  put_text(b, header_.provenance);
  if (std::fwrite(b.data(), 1, b.size(), f_) != b.size()) throw EventFileError(temp_ + ": write failed (disk full?)");
  bytes_ = b.size();
}

EventWriter::~EventWriter() {
  if (f_) {
    std::fclose(f_);
    remove_temporary(temp_);
  }
}

std::vector<uint32_t> binned_clicks(std::span<const uint32_t> clicks, uint32_t width, int shift, uint32_t binned_width) {
  std::vector<uint32_t> out;
  out.reserve(clicks.size());
  for (uint32_t c : clicks) out.push_back(((c / width) >> shift) * binned_width + ((c % width) >> shift));
  std::sort(out.begin(), out.end());
  out.erase(std::unique(out.begin(), out.end()), out.end());
  return out;
}

size_t first_bad_click(std::span<const uint32_t> clicks, uint64_t grid_pixels) {
  for (size_t i = 0; i < clicks.size(); ++i)
    if (clicks[i] >= grid_pixels || (i > 0 && clicks[i] <= clicks[i - 1])) return i;
  return clicks.size();
}

void append_event_record(const Event& e, uint64_t grid_pixels, const std::string& file, std::vector<uint8_t>& out) {
  if (e.vertices.size() > max_vertices) throw EventFileError(file + ": more than 65536 vertices in one event");
  if (first_bad_click(e.clicks, grid_pixels) < e.clicks.size())
    throw EventFileError(file + ": event " + std::to_string(e.id) +
                         ": clicks must be strictly increasing pixel indices below " + std::to_string(grid_pixels));
  [[maybe_unused]] const size_t start = out.size();
  put_u32(out, event_tag);
  put_u64(out, e.id);
  put_u32(out, uint32_t(e.vertices.size()));
  for (const auto& v : e.vertices) {
    put_f64(out, v.x_mm);
    put_f64(out, v.y_mm);
    put_f64(out, v.depth_mm);
    put_f64(out, v.alpha);
    put_f64(out, v.sensor_fraction);
  }
  put_u32(out, uint32_t(e.clicks.size()));
  for (uint32_t c : e.clicks) put_u32(out, c);
  assert(out.size() - start == event_record_bytes(e.vertices.size(), e.clicks.size()));
}

void EventWriter::write(const Event& e) {
  buf_.clear();
  append_event_record(e, header_.grid_pixels(), path_, buf_);
  write_records(buf_, 1);
}

void EventWriter::write_records(std::span<const uint8_t> records, uint64_t events) {
  if (!f_) throw EventFileError(path_ + ": write after close");
  if (std::fwrite(records.data(), 1, records.size(), f_) != records.size())
    throw EventFileError(temp_ + ": write failed at byte " + std::to_string(bytes_) + " (disk full?)");
  bytes_ += records.size();
  count_ += events;
}

void EventWriter::close() {
  if (!f_) return;
  buf_.clear();
  put_u32(buf_, trailer_tag);
  put_u64(buf_, count_);
  bool ok = std::fwrite(buf_.data(), 1, buf_.size(), f_) == buf_.size();
  bytes_ += buf_.size();
  buf_.clear();
  put_u64(buf_, count_);
  ok = ok && std::fseek(f_, long(count_offset_), SEEK_SET) == 0 &&
       std::fwrite(buf_.data(), 1, buf_.size(), f_) == buf_.size();
  ok = std::fflush(f_) == 0 && ok;
  ok = ::fsync(::fileno(f_)) == 0 && ok;
  ok = std::fclose(f_) == 0 && ok;
  f_ = nullptr;
  if (!ok) {
    remove_temporary(temp_);
    throw EventFileError(path_ + ": could not finish the file (write failed); nothing was written");
  }
  try {
    rename_into_place(temp_, path_);
  } catch (const std::runtime_error& e) {
    throw EventFileError(std::string(e.what()) + "; nothing was written");
  }
}

EventReader::EventReader(std::string path) : path_(std::move(path)) {
  f_ = std::fopen(path_.c_str(), "rb");
  if (!f_) throw EventFileError(path_ + ": cannot open (" + std::strerror(errno) + ")");
  try {
    read_header();
  } catch (...) {  // the destructor does not run for a constructor that throws
    std::fclose(f_);
    f_ = nullptr;
    throw;
  }
}

void EventReader::read_header() {
  std::error_code ec;
  size_ = std::filesystem::file_size(path_, ec);
  if (ec) throw EventFileError(path_ + ": cannot read its size (" + ec.message() + ")");
  std::array<char, 8> magic;
  read(magic.data(), magic.size(), "file magic");
  if (magic != file_magic) {
    offset_ = 0;
    fail("not a PRISM event file (magic is not \"PRISMEVT\")");
  }
  uint8_t b[8];
  read(b, 4, "format version");
  uint32_t version = get_u32(b);
  if (version != event_format_version) {
    offset_ -= 4;
    fail("format version " + std::to_string(version) + ", this prism reads version " +
         std::to_string(event_format_version) + "; rewrite the file with this prism's `prism simulate`");
  }
  auto u32 = [&](const char* what) { read(b, 4, what); return get_u32(b); };
  auto u64 = [&](const char* what) { read(b, 8, what); return get_u64(b); };
  auto text = [&](const char* what) {
    uint32_t n = u32(what);
    if (n > max_text_bytes) fail(std::string(what) + " length " + std::to_string(n) + " exceeds 1 MiB: corrupt header");
    std::string s(n, '\0');
    read(s.data(), n, what);
    return s;
  };
  header_.sensor_width_px = u32("sensor width");
  header_.sensor_height_px = u32("sensor height");
  header_.pixel_um = std::bit_cast<double>(u64("pixel pitch"));
  header_.binning = u32("binning");
  if (header_.sensor_width_px == 0 || header_.sensor_height_px == 0 || header_.binning == 0)
    fail("sensor size or binning is zero: corrupt header");
  if (header_.sensor_width_px > uint32_t(max_sensor_side_px) || header_.sensor_height_px > uint32_t(max_sensor_side_px) ||
      !(header_.pixel_um > 0 && std::isfinite(header_.pixel_um)) || header_.binning > header_.sensor_width_px)
    fail("sensor " + std::to_string(header_.sensor_width_px) + " x " + std::to_string(header_.sensor_height_px) +
         " px of " + std::to_string(header_.pixel_um) + " um binned " + std::to_string(header_.binning) +
         " is not a sensor a scene can describe: corrupt header");
  read(b, 1, "truth model");
  if (b[0] > uint8_t(TruthModel::dictionary)) fail("unknown truth model " + std::to_string(b[0]));
  header_.truth = TruthModel(b[0]);
  header_.seed = u64("seed");
  header_.event_count = u64("event count");
  header_.scene = text("scene name");
  header_.provenance = text("provenance");
}

EventReader::~EventReader() {
  if (f_) std::fclose(f_);
}

void EventReader::fail(const std::string& why) const {
  throw EventFileError(path_ + ": at byte offset " + std::to_string(offset_) + ": " + why);
}

void EventReader::require_left(uint64_t bytes, const char* what) {
  if (bytes > size_ - std::min(size_, offset_)) {
    offset_ = size_;  // as read() would report it, without allocating what the count asks for
    truncated(what);
  }
}

void EventReader::truncated(const char* what) const {
  fail(std::string("truncated while reading the ") + what + " (file ends here; it was cut short: re-run prism simulate)");
}

void EventReader::read(void* dst, size_t n, const char* what) {
  size_t got = std::fread(dst, 1, n, f_);
  if (got != n) {
    offset_ += got;
    truncated(what);
  }
  offset_ += n;
}

bool EventReader::next(Event& e) {
  if (done_) return false;
  uint8_t b[8];
  read(b, 4, "record tag");
  uint32_t tag = get_u32(b);
  if (tag == trailer_tag) {
    read(b, 8, "trailer event count");
    uint64_t n = get_u64(b);
    if (n != read_events_ || n != header_.event_count)
      fail("trailer says " + std::to_string(n) + " events, header says " + std::to_string(header_.event_count) +
           ", read " + std::to_string(read_events_) + ": corrupt file");
    if (std::fgetc(f_) != EOF) fail("bytes after the trailer: corrupt file");
    done_ = true;
    return false;
  }
  if (tag != event_tag) {
    offset_ -= 4;
    fail("expected an event record tag, found 0x" + [&] {
      char s[16];
      std::snprintf(s, sizeof s, "%08X", tag);
      return std::string(s);
    }() + ": corrupt file");
  }
  read(b, 8, "event id");
  e.id = get_u64(b);
  read(b, 4, "vertex count");
  uint32_t k = get_u32(b);
  if (k > max_vertices) fail("vertex count " + std::to_string(k) + " exceeds 65536: corrupt record");
  require_left(40ull * k, "vertex truth");
  e.vertices.resize(k);
  uint8_t v[40];
  for (auto& vx : e.vertices) {
    read(v, sizeof v, "vertex truth");
    vx.x_mm = std::bit_cast<double>(get_u64(v));
    vx.y_mm = std::bit_cast<double>(get_u64(v + 8));
    vx.depth_mm = std::bit_cast<double>(get_u64(v + 16));
    vx.alpha = std::bit_cast<double>(get_u64(v + 24));
    vx.sensor_fraction = std::bit_cast<double>(get_u64(v + 32));
  }
  read(b, 4, "click count");
  uint32_t n = get_u32(b);
  const uint64_t pixels = header_.grid_pixels();
  if (n > pixels) fail("click count " + std::to_string(n) + " exceeds the sensor's pixels: corrupt record");
  require_left(4ull * n, "clicks");
  e.clicks.resize(n);
  uint64_t start = offset_;
  read(e.clicks.data(), size_t(n) * 4, "clicks");
  if constexpr (std::endian::native != std::endian::little)
    for (auto& c : e.clicks) c = get_u32(reinterpret_cast<const uint8_t*>(&c));
  if (const size_t i = first_bad_click(e.clicks, pixels); i < n) {
    offset_ = start + 4ull * i;
    fail("click " + std::to_string(e.clicks[i]) + " is off the grid or out of order: corrupt record");
  }
  ++read_events_;
  return true;
}

}  // namespace prism
