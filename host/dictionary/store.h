// The PSF dictionary on disk: a directory with manifest.json and one tiled
// OpenEXR file per grid position (psf/NNNN.exr). Each file holds every
// resolution level as an OpenEXR mip level: level 0 is the sensor binned by
// the dictionary's base binning, level k sums 2^k x 2^k level-0 pixels, so
// every level of a PSF sums to 1 over the sensor. Values are half floats,
// ZIP-compressed, scaled by a power of two per file (attribute prismScaleLog2)
// so that small probabilities do not underflow half precision.
#pragma once
#include <cstdint>
#include <memory>
#include <span>
#include <stdexcept>
#include <string>
#include <vector>

#include <glm/glm.hpp>
#include <nlohmann/json.hpp>

#include "host/scene/scene.h"

namespace prism {

inline constexpr int dictionary_format_version = 1;

// A dictionary that cannot be used; the message names the file and why.
struct DictionaryError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// The grid of source positions the PSFs were taken at. Entry i is node
// (ix, iy, iz) with i = ix + nx (iy + ny iz): x varies fastest, then y, then
// depth (the file names follow it). The one home of that convention.
struct DictionaryGrid {
  std::vector<double> x_mm, y_mm, depth_mm;
  size_t size() const { return x_mm.size() * y_mm.size() * depth_mm.size(); }
  size_t index(glm::ivec3 node) const {
    return size_t(node.x) + x_mm.size() * (size_t(node.y) + y_mm.size() * size_t(node.z));
  }
  glm::ivec3 node(size_t i) const {
    const size_t nx = x_mm.size(), ny = y_mm.size();
    return {int(i % nx), int(i / nx % ny), int(i / (nx * ny))};
  }
  glm::dvec3 position(size_t i) const;
  // The node nearest to a position, axis by axis (ties to the lower index).
  glm::ivec3 nearest_node(const glm::dvec3& position_mm) const;
  static DictionaryGrid paper();  // 11 x 11 x 10: x, y in -25..25, depth 5..50, 5 mm steps
  // The default: the paper's nodes, depth planes dense near the face
  // (defaults::dictionary_depth_planes_mm, 23 planes, 2783 PSFs).
  static DictionaryGrid fine_near_face();
  // Throws DictionaryError naming the axis (callers add the file) unless every axis is non-empty,
  // finite and strictly increasing (the search and the dictionary model
  // bracket positions between neighbouring nodes).
  void validate() const;
  // Throws DictionaryError unless every depth lies in front of lenses
  // `working_distance_mm` before the scintillator face (depth > -that).
  void require_in_front(const OpticalSystem& optics) const;
};

struct DictionaryManifest {
  int version = dictionary_format_version;
  Scene scene;
  DictionaryGrid grid;
  int base_binning = 4;   // level 0 = sensor pixels binned base_binning x base_binning
  int width = 0;          // level-0 size in pixels
  int height = 0;
  int levels = 0;         // mip levels in every file (OpenEXR ROUND_UP chain down to 1 x 1)
  int tile_px = 64;
  unsigned rays_per_lenslet = 0;  // synthesis; 0 for a calibrated dictionary
  Splat splat = Splat::point;     // synthesis: how rays became pixel values (manifests before it: point)
  unsigned stratification = 0;    // synthesis
  std::string source = "synthesised";  // or "calibrated"

  std::string file_of(size_t i) const;  // relative to the directory
  // OpenEXR's ROUND_UP mip chain of a w x h level 0, down to 1 x 1.
  static int mip_levels(int width, int height);
  double pixel_mm(int level) const;
  int level_width(int level) const;
  int level_height(int level) const;
  AnalysisGrid level_grid(int level) const { return {level_width(level), level_height(level), pixel_mm(level)}; }
  nlohmann::json to_json() const;
  static DictionaryManifest from_json(const nlohmann::json& j, const std::string& path);
};

// A PSF at one level, as stored values converted back to probabilities.
struct PsfLevel {
  int level = 0, width = 0, height = 0;
  std::vector<float> p;  // row-major, sums to ~1 over the sensor
};

// A rectangular window of one level: pixels [x0, x0 + width) x [y0, y0 + height).
struct PsfWindow {
  int level = 0, x0 = 0, y0 = 0, width = 0, height = 0;
  std::vector<float> p;
};

// Level k from level 0 by summing 2^k x 2^k blocks (the rule the files obey).
PsfLevel bin_level(const PsfLevel& level0, int k);

// Writes one PSF (level 0 as probabilities summing to 1) with all its levels,
// atomically: a file that exists is whole.
void write_psf_file(const std::string& path, const DictionaryManifest& m, size_t index, const PsfLevel& level0,
                    double photons_on_sensor);

// Writes DIR/manifest.json atomically (DIR must exist).
void write_manifest(const std::string& dir, const DictionaryManifest& m);

class DictionaryReader {
 public:
  // Opens DIR/manifest.json; checks version and, when `expect` is given,
  // that the dictionary is for that sensor.
  explicit DictionaryReader(std::string dir, const OpticalSystem* expect = nullptr);

  const DictionaryManifest& manifest() const { return m_; }
  const std::string& dir() const { return dir_; }
  std::string path_of(size_t i) const;
  bool has(size_t i) const;   // the file exists (and, being written atomically, is whole)
  size_t present() const;     // how many entries exist

  PsfLevel read_level(size_t i, int level) const;
  PsfWindow read_window(size_t i, int level, int x0, int y0, int width, int height) const;
  double photons_on_sensor(size_t i) const;  // synthesis: expected photons reaching the sensor

 private:
  std::string dir_;
  DictionaryManifest m_;
};

// One PSF file opened and checked against the manifest once, then read many
// times: a tile read through it costs its decompression alone, where
// DictionaryReader::read_window opens the file and checks its header again
// (8x the time of a 64 px tile at 110 um). The reader must outlive it.
class PsfFile {
 public:
  PsfFile(const DictionaryReader& reader, size_t i);
  ~PsfFile();
  PsfFile(PsfFile&&) noexcept;
  PsfFile& operator=(PsfFile&&) noexcept;

  size_t index() const { return index_; }
  // Pixels [x0, x0 + width) x [y0, y0 + height) of `level`, cropped to it.
  PsfWindow read_window(int level, int x0, int y0, int width, int height);
  // Tile (tx, ty) of `level` as stored: tile_px x tile_px half floats (their
  // bits), row-major, zero beyond the level's edge; a value is the half
  // times value_scale().
  void read_tile(int level, int tx, int ty, std::span<uint16_t> out);
  float value_scale() const;
  // What an open file holds in memory (its tile offset tables and one
  // tile's buffers), for budgets.
  static uint64_t bytes(const DictionaryManifest& m);

 private:
  struct Open;  // the OpenEXR file, kept out of this header
  std::unique_ptr<Open> f_;
  const DictionaryManifest* m_ = nullptr;
  std::string path_;
  size_t index_ = 0;
};

// Summed-area table of one PSF level: the mass inside any rectangle of pixels
// in four look-ups (the on-sensor mass S of a shifted PSF).
class SummedArea {
 public:
  explicit SummedArea(const PsfLevel& level);
  // Sum over columns [x0, x1) and rows [y0, y1), clipped to the level.
  double mass(int x0, int y0, int x1, int y1) const;
  // Mass still on the sensor after shifting the PSF by (dx, dy) pixels.
  double mass_shifted(int dx, int dy) const { return mass(-dx, -dy, width_ - dx, height_ - dy); }
  size_t bytes() const { return table_.size() * sizeof(double); }
  // (width + 1) x (height + 1), row-major: entry (x, y) sums columns < x, rows < y.
  const std::vector<double>& table() const { return table_; }

 private:
  int width_, height_;
  std::vector<double> table_;  // (width + 1) x (height + 1), row-major
};

// Which pixels of a level hold light, counted over rectangles (an integer
// summed-area table of p > 0). A level-k pixel sums its level-0 pixels, all
// non-negative, so a rectangle with no lit pixel at a coarse level has none
// at any finer level: the tiles under it need not be read.
class LitPixels {
 public:
  explicit LitPixels(const PsfLevel& level);
  // Lit pixels in columns [x0, x1) and rows [y0, y1), clipped to the level.
  uint32_t count(int x0, int y0, int x1, int y1) const;
  size_t bytes() const { return table_.size() * sizeof(uint32_t); }

 private:
  int width_, height_;
  std::vector<uint32_t> table_;  // (width + 1) x (height + 1), row-major
};

}  // namespace prism
