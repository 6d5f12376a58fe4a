#include "host/dictionary/store.h"

#include <Imath/half.h>
#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFloatAttribute.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfIntAttribute.h>
#include <OpenEXR/ImfStringAttribute.h>
#include <OpenEXR/ImfTiledInputFile.h>
#include <OpenEXR/ImfTiledOutputFile.h>
#include <OpenEXR/ImfVecAttribute.h>
#include <OpenEXR/openexr.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>

#include "engine/defaults.h"
#include "host/dictionary/exr_zip.h"
#include "host/util/format.h"
#include "host/util/image_io.h"
#include "host/util/json_file.h"

namespace prism {

namespace {

// Every level of a PSF sums to 1, so no stored value exceeds 1: scaling by 2^15
// keeps the largest below half's maximum (65504) and puts half's smallest
// normal (6.1e-5) at a probability of 1.9e-9, its relative precision 1e-3.
constexpr int kScaleLog2 = 15;


int ceil_div(int a, int b) { return (a + b - 1) / b; }

template <class F> auto exr_call(const std::string& path, F&& f) {
  try {
    return f();
  } catch (const DictionaryError&) {
    throw;
  } catch (const std::exception& e) {
    throw DictionaryError(path + ": cannot read the PSF file (" + e.what() +
                          "); it may be truncated or corrupt: delete it and run `prism dictionary build` again to "
                          "re-render it");
  }
}

}  // namespace

glm::dvec3 DictionaryGrid::position(size_t i) const {
  glm::ivec3 n = node(i);
  return {x_mm[size_t(n.x)], y_mm[size_t(n.y)], depth_mm[size_t(n.z)]};
}

glm::ivec3 DictionaryGrid::nearest_node(const glm::dvec3& position_mm) const {
  auto nearest = [](const std::vector<double>& nodes, double v) {
    size_t best = 0;
    for (size_t i = 1; i < nodes.size(); ++i)
      if (std::abs(nodes[i] - v) < std::abs(nodes[best] - v)) best = i;
    return int(best);
  };
  return {nearest(x_mm, position_mm.x), nearest(y_mm, position_mm.y), nearest(depth_mm, position_mm.z)};
}

DictionaryGrid DictionaryGrid::paper() {
  DictionaryGrid g;
  for (int i = 0; i <= 10; ++i) g.x_mm.push_back(-25.0 + 5.0 * i);
  g.y_mm = g.x_mm;
  for (int i = 1; i <= 10; ++i) g.depth_mm.push_back(5.0 * i);
  return g;
}

DictionaryGrid DictionaryGrid::fine_near_face() {
  DictionaryGrid g = paper();
  g.depth_mm.assign(std::begin(defaults::dictionary_depth_planes_mm), std::end(defaults::dictionary_depth_planes_mm));
  return g;
}

void DictionaryGrid::validate() const {
  auto str = [](double v) {
    char b[32];
    std::snprintf(b, sizeof b, "%g", v);
    return std::string(b);
  };
  for (const auto& [name, v] : {std::pair{"x", &x_mm}, {"y", &y_mm}, {"depth", &depth_mm}}) {
    if (v->empty()) throw DictionaryError(std::string("no ") + name + " positions");
    for (size_t i = 0; i < v->size(); ++i) {
      if (!std::isfinite((*v)[i]))
        throw DictionaryError(name + std::string(" position ") + std::to_string(i + 1) + " is not a number");
      if (i > 0 && !((*v)[i] > (*v)[i - 1]))
        throw DictionaryError(name + std::string(" positions must increase, but ") +
                              str((*v)[i]) + " follows " + str((*v)[i - 1]));
    }
  }
}

void DictionaryGrid::require_in_front(const OpticalSystem& optics) const {
  const double wd = optics.working_distance_mm;
  if (!depth_mm.empty() && !optics.in_front(depth_mm.front()))
    throw DictionaryError("depth " + format_number(depth_mm.front()) + " mm is not in front of the lenses, which lie " +
                          format_number(wd) + " mm before the scintillator face: every depth must be > " +
                          format_number(-wd) + " mm");
}

std::string DictionaryManifest::file_of(size_t i) const {
  char b[32];
  std::snprintf(b, sizeof b, "psf/%05zu.exr", i);
  return b;
}

int DictionaryManifest::mip_levels(int width, int height) {
  int levels = 1;
  for (int s = std::max(width, height); s > 1; s = (s + 1) / 2) ++levels;
  return levels;
}

double DictionaryManifest::pixel_mm(int level) const {
  return scene.optics.pixel_um * 1e-3 * base_binning * double(1 << level);
}
int DictionaryManifest::level_width(int level) const { return ceil_div(width, 1 << level); }
int DictionaryManifest::level_height(int level) const { return ceil_div(height, 1 << level); }

nlohmann::json DictionaryManifest::to_json() const {
  return {{"format", "prism-psf-dictionary"},
          {"version", version},
          {"source", source},
          {"scene", prism::to_json(scene)},
          {"sensor",
           {{"width_px", scene.optics.sensor_width_px},
            {"height_px", scene.optics.sensor_height_px},
            {"pixel_um", scene.optics.pixel_um}}},
          {"grid", {{"x_mm", grid.x_mm}, {"y_mm", grid.y_mm}, {"depth_mm", grid.depth_mm}}},
          {"entries", grid.size()},
          {"files", "psf/NNNNN.exr, N = ix + nx (iy + ny iz)"},
          {"levels",
           {{"count", levels},
            {"base_binning", base_binning},
            {"level0_px", {width, height}},
            {"rule", "level k pixel = sum of its 2^k x 2^k level-0 pixels (OpenEXR mip levels, ROUND_UP)"}}},
          {"storage", {{"pixel", "half"}, {"compression", "zip"}, {"tile_px", tile_px}, {"scale_log2", kScaleLog2}}},
          {"normalisation", "every level of every PSF sums to 1 over the sensor"},
          {"rays_per_lenslet", rays_per_lenslet},
          {"splat", to_string(splat)},
          {"stratification", stratification}};
}

DictionaryManifest DictionaryManifest::from_json(const nlohmann::json& j, const std::string& path) {
  auto fail = [&](const std::string& field, const std::string& why) -> DictionaryError {
    return DictionaryError(path + ": " + field + ": " + why);
  };
  if (!j.is_object() || !j.contains("format") || j["format"] != "prism-psf-dictionary")
    throw fail("format", "not a PRISM PSF dictionary manifest");
  const int version = j.contains("version") && j["version"].is_number_integer() && j["version"].get<double>() > 0 &&
                              j["version"].get<double>() < 1e6
                          ? j["version"].get<int>()
                          : -1;
  if (version != dictionary_format_version)
    throw fail("version", "is " + std::to_string(version) + ", this prism reads version " +
                              std::to_string(dictionary_format_version) + "; rebuild the dictionary with this prism");
  DictionaryManifest m;
  try {
    // Each field read names itself when it is missing or of the wrong type.
    auto field = [&](const std::string& name, auto&& read) {
      try {
        return read();
      } catch (const nlohmann::json::exception&) {
        throw fail(name, "missing or of the wrong type");
      }
    };
    m.source = field("source", [&] { return j.at("source").get<std::string>(); });
    m.scene = parse_scene(field("scene", [&] { return j.at("scene"); }), path + " (scene)");
    auto axis = [&](const char* name) {
      return field(std::string("grid.") + name + " (a list of numbers)",
                   [&] { return j.at("grid").at(name).get<std::vector<double>>(); });
    };
    m.grid.x_mm = axis("x_mm");
    m.grid.y_mm = axis("y_mm");
    m.grid.depth_mm = axis("depth_mm");
    // Integers read checked: a wrapped 2^40 or a 0 would divide by zero later.
    auto integer = [&](const std::string& name, auto&& read, double lo, double hi) {
      const nlohmann::json v = field(name, read);
      if (!v.is_number() || v.get<double>() != std::floor(v.get<double>()) || v.get<double>() < lo ||
          v.get<double>() > hi)
        throw fail(name, "must be an integer in " + format_number(lo) + ".." + format_number(hi) + ", got " + v.dump());
      return int(v.get<double>());
    };
    const auto& sensor = m.scene.optics;
    m.base_binning = integer("levels.base_binning", [&] { return j.at("levels").at("base_binning"); }, 1,
                             std::min(sensor.sensor_width_px, sensor.sensor_height_px));
    m.width = integer("levels.level0_px[0]", [&] { return j.at("levels").at("level0_px").at(0); }, 1,
                      sensor.sensor_width_px);
    m.height = integer("levels.level0_px[1]", [&] { return j.at("levels").at("level0_px").at(1); }, 1,
                       sensor.sensor_height_px);
    m.levels = integer("levels.count", [&] { return j.at("levels").at("count"); }, 1, 64);
    m.tile_px = integer("storage.tile_px", [&] { return j.at("storage").at("tile_px"); }, 1, 1 << 16);
    m.rays_per_lenslet = unsigned(
        j.contains("rays_per_lenslet") ? integer("rays_per_lenslet", [&] { return j.at("rays_per_lenslet"); }, 0, 1 << 30)
                                       : 0);
    if (j.contains("splat") && !(j["splat"] == "point" || j["splat"] == "footprint"))
      throw fail("splat", "must be \"point\" or \"footprint\", got " + j["splat"].dump());
    m.splat = splat_from_string(j.contains("splat") ? j["splat"].get<std::string>() : std::string("point"));
    m.stratification = unsigned(
        j.contains("stratification") ? integer("stratification", [&] { return j.at("stratification"); }, 0, 1 << 30) : 0);
  } catch (const SceneError&) {
    throw;
  } catch (const DictionaryError&) {
    throw;
  } catch (const std::exception& e) {
    throw fail("(fields)", std::string("missing or malformed: ") + e.what());
  }
  try {
    m.grid.validate();
    m.grid.require_in_front(m.scene.optics);
  } catch (const DictionaryError& e) {
    throw fail("grid", e.what());
  }
  // A count that disagrees with the grid: an edited grid or a mixed-up folder.
  if (j.contains("entries") && !(j["entries"].is_number() && j["entries"].get<double>() == double(m.grid.size())))
    throw fail("entries", "is " + j["entries"].dump() + ", but the grid has " + std::to_string(m.grid.x_mm.size()) +
                              " x " + std::to_string(m.grid.y_mm.size()) + " x " +
                              std::to_string(m.grid.depth_mm.size()) + " = " + std::to_string(m.grid.size()) +
                              " positions");
  // Fields that repeat what the scene or this format version already fixes
  // must agree with it: an edit there would describe files that do not exist.
  const auto& optics = m.scene.optics;
  if (j.contains("sensor")) {
    const auto& sj = j["sensor"];
    for (const auto& [field, want] : {std::pair<const char*, double>{"width_px", optics.sensor_width_px},
                                      {"height_px", optics.sensor_height_px},
                                      {"pixel_um", optics.pixel_um}})
      if (!sj.is_object() || !sj.contains(field) || !sj[field].is_number() || sj[field].get<double>() != want)
        throw fail(std::string("sensor.") + field,
                   "is " + (sj.is_object() && sj.contains(field) ? sj[field].dump() : std::string("missing")) +
                       ", but the manifest's scene has " + format_number(want) +
                       "; the two describe the same sensor and must agree");
  }
  const nlohmann::json storage = j.at("storage");
  for (const auto& [field, want] : {std::pair<const char*, nlohmann::json>{"pixel", "half"},
                                    {"compression", "zip"},
                                    {"scale_log2", kScaleLog2}})
    if (storage.contains(field) && storage[field] != want)
      throw fail(std::string("storage.") + field, "is " + storage[field].dump() + "; format version " +
                                                      std::to_string(dictionary_format_version) + " stores " +
                                                      want.dump());
  if (m.source != "synthesised" && m.source != "calibrated")
    throw fail("source", "must be \"synthesised\" or \"calibrated\", got \"" + m.source + "\"");
  if ((m.source == "synthesised") != (m.rays_per_lenslet > 0))
    throw fail("source", "is \"" + m.source + "\" with rays_per_lenslet " + std::to_string(m.rays_per_lenslet) +
                             ": a synthesised dictionary was rendered with rays (> 0), a calibrated one was not (0)");
  if (m.width != ceil_div(m.scene.optics.sensor_width_px, m.base_binning) ||
      m.height != ceil_div(m.scene.optics.sensor_height_px, m.base_binning))
    throw fail("levels.level0_px", "does not match the sensor binned by levels.base_binning");
  if (m.levels != DictionaryManifest::mip_levels(m.width, m.height))
    throw fail("levels.count", "is " + std::to_string(m.levels) + ", but a " + std::to_string(m.width) + " x " +
                                   std::to_string(m.height) + " level 0 has " +
                                   std::to_string(DictionaryManifest::mip_levels(m.width, m.height)) + " mip levels");
  return m;
}

PsfLevel bin_level(const PsfLevel& l0, int k) {
  int f = 1 << k;
  PsfLevel out{l0.level + k, ceil_div(l0.width, f), ceil_div(l0.height, f), {}};
  out.p.assign(size_t(out.width) * out.height, 0.0f);
  std::vector<double> acc(out.p.size(), 0.0);
  for (int y = 0; y < l0.height; ++y)
    for (int x = 0; x < l0.width; ++x) acc[size_t(y / f) * out.width + x / f] += l0.p[size_t(y) * l0.width + x];
  for (size_t i = 0; i < acc.size(); ++i) out.p[i] = float(acc[i]);
  return out;
}

void write_manifest(const std::string& dir, const DictionaryManifest& m) {
  std::string path = dir + "/manifest.json";
  write_atomically(path, [&](const std::string& tmp) {
    std::ofstream out(tmp);
    out << m.to_json().dump(2) << '\n';
    if (!out) throw DictionaryError(path + ": cannot write");
  });
}

void write_psf_file(const std::string& path, const DictionaryManifest& m, size_t index, const PsfLevel& level0,
                    double photons_on_sensor) {
  if (level0.width != m.width || level0.height != m.height)
    throw DictionaryError(path + ": level 0 is " + std::to_string(level0.width) + " x " + std::to_string(level0.height) +
                          ", the manifest says " + std::to_string(m.width) + " x " + std::to_string(m.height));
  std::filesystem::create_directories(std::filesystem::path(path).parent_path());
  const float scale = float(1 << kScaleLog2);
  glm::dvec3 pos = m.grid.position(index);
  write_atomically(path, [&](const std::string& tmp) {
    Imf::Header header(m.width, m.height);
    header.setTileDescription(Imf::TileDescription(m.tile_px, m.tile_px, Imf::MIPMAP_LEVELS, Imf::ROUND_UP));
    header.compression() = Imf::ZIP_COMPRESSION;
    header.channels().insert("Y", Imf::Channel(Imf::HALF));
    header.insert("prismFormatVersion", Imf::IntAttribute(dictionary_format_version));
    header.insert("prismIndex", Imf::IntAttribute(int(index)));
    header.insert("prismPositionMm", Imf::V3fAttribute(Imath::V3f(float(pos.x), float(pos.y), float(pos.z))));
    header.insert("prismScaleLog2", Imf::IntAttribute(kScaleLog2));
    header.insert("prismPhotonsOnSensor", Imf::FloatAttribute(float(photons_on_sensor)));
    header.insert("prismScene", Imf::StringAttribute(m.scene.name));
    try {
      Imf::TiledOutputFile file(tmp.c_str(), header);
      for (int l = 0; l < file.numLevels(); ++l) {
        PsfLevel binned;  // level 0 is written from the caller's copy
        const PsfLevel& lv = l == 0 ? level0 : (binned = bin_level(level0, l));
        std::vector<half> data(lv.p.size());
        for (size_t i = 0; i < data.size(); ++i) data[i] = half(lv.p[i] * scale);
        Imf::FrameBuffer fb;
        fb.insert("Y", Imf::Slice(Imf::HALF, (char*)data.data(), sizeof(half), sizeof(half) * size_t(lv.width)));
        file.setFrameBuffer(fb);
        file.writeTiles(0, file.numXTiles(l) - 1, 0, file.numYTiles(l) - 1, l);
      }
    } catch (const std::exception& e) {
      std::remove(tmp.c_str());
      throw DictionaryError(path + ": cannot write (" + e.what() + ")");
    }
  });
}

DictionaryReader::DictionaryReader(std::string dir, const OpticalSystem* expect) : dir_(std::move(dir)) {
  std::error_code ec;
  if (!std::filesystem::is_directory(dir_, ec))
    throw DictionaryError(dir_ + (std::filesystem::exists(dir_, ec) ? ": a file, not a dictionary" : ": no such folder") +
                          "; a dictionary is the folder that `prism dictionary build --out` wrote (it holds manifest.json)");
  std::string path = dir_ + "/manifest.json";
  std::ifstream in(path);
  if (!in) throw DictionaryError(path + ": no dictionary manifest here; build one with `prism dictionary build`");
  nlohmann::json j;
  try {
    j = parse_json_file(in);
  } catch (const JsonDuplicateKey& e) {
    throw DictionaryError(path + ": " + e.what());
  } catch (const std::exception& e) {
    throw DictionaryError(path + ": not valid JSON (" + e.what() + ")");
  }
  m_ = DictionaryManifest::from_json(j, path);
  if (expect) {
    const OpticalSystem& s = m_.scene.optics;
    if (s.sensor_width_px != expect->sensor_width_px || s.sensor_height_px != expect->sensor_height_px ||
        s.pixel_um != expect->pixel_um)
      throw DictionaryError(path + ": the dictionary is for a " + std::to_string(s.sensor_width_px) + " x " +
                            std::to_string(s.sensor_height_px) + " px sensor of " + format_number(s.pixel_um) +
                            " um pixels, not the " + std::to_string(expect->sensor_width_px) + " x " +
                            std::to_string(expect->sensor_height_px) + " px sensor of " +
                            format_number(expect->pixel_um) + " um pixels of the scene given");
  }
}

std::string DictionaryReader::path_of(size_t i) const { return dir_ + "/" + m_.file_of(i); }
bool DictionaryReader::has(size_t i) const { return std::filesystem::exists(path_of(i)); }
size_t DictionaryReader::present() const {
  size_t n = 0;
  for (size_t i = 0; i < m_.grid.size(); ++i) n += has(i);
  return n;
}

namespace {

// OpenEXR 3.1 allocates what a header attribute declares before reading it
// (a damaged size field asked for gigabytes; fuzz/README.md): the attribute
// list is walked here first, each size checked against the bytes the file
// has. Layout (OpenEXR file layout): magic and version (8 bytes), then
// attributes (name NUL, type NUL, int32 size, value) up to an empty name;
// in a multi-part file, headers so until an empty one.
// OpenEXR reads a value of these types by its structure, whatever its size
// field says; 0 for any other type (read by its size).
int64_t exr_fixed_value_bytes(const std::string& type) {
  static const std::map<std::string, int64_t> fixed{
      {"box2i", 16},      {"box2f", 16},   {"compression", 1}, {"lineOrder", 1}, {"envmap", 1},
      {"deepImageState", 1}, {"int", 4},   {"float", 4},       {"double", 8},    {"rational", 8},
      {"timecode", 8},    {"keycode", 28}, {"v2i", 8},         {"v2f", 8},       {"v2d", 16},
      {"v3i", 12},        {"v3f", 12},     {"v3d", 24},        {"m33f", 36},     {"m33d", 72},
      {"m44f", 64},       {"m44d", 128},   {"tiledesc", 9},    {"chromaticities", 32}};
  auto it = fixed.find(type);
  return it == fixed.end() ? 0 : it->second;
}

// The file's first bytes, read in blocks as the walk below asks for them:
// one read for a PSF's header (a few hundred bytes), not one per byte.
class HeaderBytes {
 public:
  explicit HeaderBytes(const std::string& path) : in_(path, std::ios::binary) {
    in_.seekg(0, std::ios::end);
    size_ = in_ ? int64_t(in_.tellg()) : 0;
  }
  int64_t size() const { return size_; }
  int64_t tell() const { return pos_; }
  bool good() const { return pos_ <= size_; }
  void seek(int64_t pos) { pos_ = pos; }
  // False past the end (and from then on, good() is false).
  bool get(char& c) {
    if (!have(1)) return ++pos_, false;
    c = char(buf_[size_t(pos_++)]);
    return true;
  }
  int64_t int32() {
    uint8_t b[4] = {};
    for (uint8_t& x : b) {
      char c = 0;
      get(c);
      x = uint8_t(c);
    }
    return int64_t(int32_t(uint32_t(b[0]) | uint32_t(b[1]) << 8 | uint32_t(b[2]) << 16 | uint32_t(b[3]) << 24));
  }

 private:
  // Bytes [pos_, pos_ + n) loaded; false where the file ends first.
  bool have(int64_t n) {
    if (pos_ < 0 || pos_ + n > size_) return false;
    if (pos_ + n <= int64_t(buf_.size())) return true;
    const int64_t end = std::min(size_, std::max(pos_ + n, int64_t(buf_.size()) + kBlock));
    const size_t from = buf_.size();
    buf_.resize(size_t(end));
    in_.seekg(int64_t(from));
    in_.read(reinterpret_cast<char*>(buf_.data() + from), std::streamsize(end - int64_t(from)));
    if (in_.gcount() != std::streamsize(end - int64_t(from))) size_ = int64_t(from) + in_.gcount();
    return pos_ + n <= size_;
  }
  static constexpr int64_t kBlock = 4096;
  std::ifstream in_;
  std::vector<uint8_t> buf_;
  int64_t size_ = 0, pos_ = 0;
};

const std::string& checked_exr_header(const std::string& path, const DictionaryManifest& m) {
  HeaderBytes in(path);
  const int64_t size = in.size();
  in.seek(4);
  const int64_t version = in.int32();
  const bool multipart = (version & 0x1000) != 0;  // headers follow one another, up to an empty one
  auto text = [&](const char* what) {
    std::string s;
    for (char c; in.get(c) && c != '\0';)
      if (s.size() < 256) s += c;
      else throw DictionaryError(path + ": corrupt OpenEXR header (" + what + " longer than 255 bytes)");
    return s;
  };
  for (int attributes = 0; in.good();) {
    const std::string name = text("attribute name");
    if (!in.good()) break;
    if (name.empty()) {  // the end of a header
      if (!multipart || attributes == 0) break;
      attributes = 0;
      continue;
    }
    ++attributes;
    const std::string type = text("attribute type");
    auto corrupt = [&](const std::string& why) {
      return DictionaryError(path + ": corrupt OpenEXR header (attribute '" + name + "' " + why + ")");
    };
    const int64_t bytes = in.int32();
    const int64_t start = in.tell(), left = size - start;
    if (!in.good() || bytes < 0 || bytes > left)
      throw corrupt("declares " + std::to_string(bytes) + " bytes, the file has " +
                    std::to_string(std::max<int64_t>(0, left)) + " left");
    // Values OpenEXR reads by their own structure, not by the size: they must
    // end where the size says, or its reading goes out of step with the file.
    if (auto fixed = exr_fixed_value_bytes(type); fixed && bytes != fixed)
      throw corrupt("of type " + type + " declares " + std::to_string(bytes) + " bytes; its value has " +
                    std::to_string(fixed));
    if (type == "chlist") {
      while (!text("channel name").empty() && in.good()) in.seek(in.tell() + 16);  // type, linear, reserved, sampling
      if (!in.good() || in.tell() - start != bytes) throw corrupt("holds channels that do not fill its size");
    } else if (type == "preview") {
      const int64_t w = in.int32(), h = in.int32();
      // w h pixels of 4 bytes after the two sizes; h bounded first, since
      // 4 w h of two damaged sizes overflows (a long fuzz run's finding).
      const bool fits = w >= 0 && h >= 0 && bytes >= 8 && (w == 0 || h <= (bytes - 8) / 4 / w);
      if (!in.good() || !fits || 8 + 4 * w * h != bytes) throw corrupt("is a preview image of another size");
    } else if (type == "tiledesc") {
      // OpenEXR sizes its tile buffers by these before reading a pixel (a
      // 16 x 2.8e8 px tile asked for 1.1 GB): they must be the manifest's.
      const int64_t tx = uint32_t(in.int32()), ty = uint32_t(in.int32());
      if (!in.good() || tx != m.tile_px || ty != m.tile_px)
        throw corrupt("declares tiles of " + std::to_string(tx) + " x " + std::to_string(ty) + " px; the manifest's are " +
                      std::to_string(m.tile_px) + " x " + std::to_string(m.tile_px));
    } else if (type == "box2i" && name == "dataWindow") {
      // Its tile offset tables follow from the data window: it must be the manifest's level 0.
      const int64_t x0 = in.int32(), y0 = in.int32(), x1 = in.int32(), y1 = in.int32();
      if (!in.good() || x0 != 0 || y0 != 0 || x1 != m.width - 1 || y1 != m.height - 1)
        throw corrupt("is (" + std::to_string(x0) + ", " + std::to_string(y0) + ") - (" + std::to_string(x1) + ", " +
                      std::to_string(y1) + "); the manifest's level 0 is " + std::to_string(m.width) + " x " +
                      std::to_string(m.height) + " px");
    }
    in.seek(start + bytes);
  }
  return path;
}

// Opens a PSF file with OpenEXR's C core and checks it belongs to this
// dictionary. The core reads the header and, at the first tile, the offset
// table; nothing else (PsfFile reopens a file for each event's tiles, and
// opening it with OpenEXR's C++ reader after a byte-by-byte header walk
// took 7x as long as the core's own open, by perf).
struct CorePsf {
  exr_context_t core = nullptr;
  float inv_scale = 1;
  CorePsf(const std::string& path, const DictionaryManifest& m, size_t index) {
    checked_exr_header(path, m);
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    init.error_handler_fn = [](exr_const_context_t, exr_result_t, const char*) {};  // reported by the calls' results
    if (const exr_result_t r = exr_start_read(&core, path.c_str(), &init); r != EXR_ERR_SUCCESS) {
      exr_finish(&core);
      throw std::runtime_error(exr_get_default_error_message(r));  // exr_call names the file and says what to do
    }
    try {
      check(path, m, index);
    } catch (...) {
      exr_finish(&core);
      throw;
    }
  }
  ~CorePsf() { exr_finish(&core); }
  CorePsf(const CorePsf&) = delete;
  CorePsf& operator=(const CorePsf&) = delete;

 private:
  void check(const std::string& path, const DictionaryManifest& m, size_t index) {
    int32_t version = 0, idx = 0, scale = 0;
    if (exr_attr_get_int(core, 0, "prismFormatVersion", &version) != EXR_ERR_SUCCESS ||
        exr_attr_get_int(core, 0, "prismIndex", &idx) != EXR_ERR_SUCCESS ||
        exr_attr_get_int(core, 0, "prismScaleLog2", &scale) != EXR_ERR_SUCCESS)
      throw DictionaryError(path + ": not a PRISM dictionary PSF (attributes missing)");
    if (version != dictionary_format_version)
      throw DictionaryError(path + ": PSF format version " + std::to_string(version) + ", expected " +
                            std::to_string(dictionary_format_version));
    if (idx != int(index)) throw DictionaryError(path + ": holds entry " + std::to_string(idx));
    // The manifest's grid must still say where the file's source was (an
    // edited grid would put every PSF at a wrong position).
    if (exr_attr_v3f_t got; exr_attr_get_v3f(core, 0, "prismPositionMm", &got) == EXR_ERR_SUCCESS) {
      const glm::dvec3 want = m.grid.position(index);
      if (glm::length(glm::dvec3(got.x, got.y, got.z) - want) > 1e-3 * (1 + glm::length(want)))
        throw DictionaryError(path + ": holds the PSF of a source at (" + format_number(got.x) + ", " +
                              format_number(got.y) + ", " + format_number(got.z) + ") mm, but the manifest's grid " +
                              "puts entry " + std::to_string(index) + " at (" + format_number(want.x) + ", " +
                              format_number(want.y) + ", " + format_number(want.z) + ") mm");
    }
    exr_attr_box2i_t dw;
    if (exr_get_data_window(core, 0, &dw) != EXR_ERR_SUCCESS || dw.max.x - dw.min.x + 1 != m.width ||
        dw.max.y - dw.min.y + 1 != m.height)
      throw DictionaryError(path + ": level 0 size differs from the manifest's");
    // The scale's range: ldexp of any int is defined, but a damaged one would
    // make every value 0 or inf.
    if (scale < -126 || scale > 126) throw DictionaryError(path + ": prismScaleLog2 " + std::to_string(scale));
    inv_scale = std::ldexp(1.0f, -scale);
  }
};

}  // namespace

PsfLevel DictionaryReader::read_level(size_t i, int level) const {
  PsfWindow w = read_window(i, level, 0, 0, m_.level_width(level), m_.level_height(level));
  return {level, w.width, w.height, std::move(w.p)};
}

PsfWindow DictionaryReader::read_window(size_t i, int level, int x0, int y0, int width, int height) const {
  return PsfFile(*this, i).read_window(level, x0, y0, width, height);
}

// The C core serves read_tile a tile's chunk as stored, which exr_zip
// decodes; OpenEXR's C++ reader, opened at its first use, serves
// read_window and tiles of another codec.
struct PsfFile::Open : CorePsf {
  std::string path;
  std::unique_ptr<Imf::TiledInputFile> file;
  std::vector<uint8_t> packed, bytes;
  Open(const std::string& p, const DictionaryManifest& m, size_t index) : CorePsf(p, m, index), path(p) {}
  Imf::TiledInputFile& imf() {
    if (!file) {
      // The header was walked when the core opened the file.
      auto f = std::make_unique<Imf::TiledInputFile>(path.c_str());
      if (!f->isComplete()) throw DictionaryError(path + ": incomplete file (missing tiles)");
      file = std::move(f);
    }
    return *file;
  }
};

PsfFile::PsfFile(const DictionaryReader& reader, size_t i)
    : m_(&reader.manifest()), path_(reader.path_of(i)), index_(i) {
  f_ = exr_call(path_, [&] { return std::make_unique<Open>(path_, *m_, i); });
}
PsfFile::~PsfFile() = default;
PsfFile::PsfFile(PsfFile&&) noexcept = default;
PsfFile& PsfFile::operator=(PsfFile&&) noexcept = default;

uint64_t PsfFile::bytes(const DictionaryManifest& m) {
  uint64_t tiles = 0;
  for (int l = 0; l < m.levels; ++l)
    tiles += uint64_t(ceil_div(m.level_width(l), m.tile_px)) * uint64_t(ceil_div(m.level_height(l), m.tile_px));
  // 8-byte offsets per tile in each of the two readers (the core's, and
  // OpenEXR's C++ reader's once read_window opens it); a tile's compressed
  // and decoded buffers (half).
  return 2 * 8 * tiles + 3 * uint64_t(m.tile_px) * uint64_t(m.tile_px) * sizeof(half);
}

PsfWindow PsfFile::read_window(int level, int x0, int y0, int width, int height) {
  if (level < 0 || level >= m_->levels)
    throw DictionaryError(path_ + ": level " + std::to_string(level) + " of " + std::to_string(m_->levels));
  return exr_call(path_, [&] {
    Imf::TiledInputFile& file = f_->imf();
    int lw = file.levelWidth(level), lh = file.levelHeight(level);
    int x1 = std::min(x0 + width, lw), y1 = std::min(y0 + height, lh);
    x0 = std::max(x0, 0);
    y0 = std::max(y0, 0);
    PsfWindow out{level, x0, y0, std::max(0, x1 - x0), std::max(0, y1 - y0), {}};
    out.p.assign(size_t(out.width) * out.height, 0.0f);
    if (out.p.empty()) return out;
    // OpenEXR fills whole tiles: read into a tile-aligned buffer, then crop.
    int t = m_->tile_px;
    int tx0 = x0 / t, tx1 = (x1 - 1) / t, ty0 = y0 / t, ty1 = (y1 - 1) / t;
    int bx = tx0 * t, by = ty0 * t, bw = (tx1 + 1) * t - bx, bh = (ty1 + 1) * t - by;
    std::vector<half> buf(size_t(bw) * bh);
    Imf::FrameBuffer fb;
    fb.insert("Y", Imf::Slice(Imf::HALF, (char*)(buf.data() - bx - size_t(by) * bw), sizeof(half),
                              sizeof(half) * size_t(bw)));
    file.setFrameBuffer(fb);
    file.readTiles(tx0, tx1, ty0, ty1, level, level);
    for (int y = y0; y < y1; ++y)
      for (int x = x0; x < x1; ++x)
        out.p[size_t(y - y0) * out.width + (x - x0)] = float(buf[size_t(y - by) * bw + (x - bx)]) * f_->inv_scale;
    return out;
  });
}

float PsfFile::value_scale() const { return f_->inv_scale; }

void PsfFile::read_tile(int level, int tx, int ty, std::span<uint16_t> out) {
  const int t = m_->tile_px;
  if (level < 0 || level >= m_->levels)
    throw DictionaryError(path_ + ": level " + std::to_string(level) + " of " + std::to_string(m_->levels));
  if (out.size() != size_t(t) * size_t(t))
    throw std::invalid_argument("PsfFile::read_tile: the buffer holds " + std::to_string(out.size()) + " values, not " +
                                std::to_string(t) + " x " + std::to_string(t));
  exr_call(path_, [&] {
    int32_t lw = 0, lh = 0;
    if (exr_get_level_sizes(f_->core, 0, level, level, &lw, &lh) != EXR_ERR_SUCCESS)
      throw DictionaryError(path_ + ": no level " + std::to_string(level));
    if (tx < 0 || ty < 0 || tx * t >= lw || ty * t >= lh)
      throw DictionaryError(path_ + ": no tile (" + std::to_string(tx) + ", " + std::to_string(ty) + ") on level " +
                            std::to_string(level));
    // Edge tiles are partial: zeros where the level ends.
    std::fill(out.begin(), out.end(), uint16_t(0));
    exr_chunk_info_t chunk;
    auto check = [&](exr_result_t r) {
      if (r != EXR_ERR_SUCCESS) throw std::runtime_error(exr_get_default_error_message(r));
    };
    check(exr_read_tile_chunk_info(f_->core, 0, tx, ty, level, level, &chunk));
    const bool zip = chunk.compression == EXR_COMPRESSION_ZIP || chunk.compression == EXR_COMPRESSION_ZIPS;
    const size_t w = size_t(chunk.width), h = size_t(chunk.height), n = w * h * sizeof(half);
    if ((!zip && chunk.compression != EXR_COMPRESSION_NONE) || w > size_t(t) || h > size_t(t) ||
        chunk.unpacked_size != n) {
      // Another codec, from another writer: OpenEXR's own decoder.
      const int bx = tx * t, by = ty * t;
      Imf::FrameBuffer fb;
      fb.insert("Y", Imf::Slice(Imf::HALF, (char*)(out.data() - bx - size_t(by) * t), sizeof(half),
                                sizeof(half) * size_t(t)));
      Imf::TiledInputFile& file = f_->imf();
      file.setFrameBuffer(fb);
      file.readTile(tx, ty, level, level);
      return;
    }
    static_assert(std::endian::native == std::endian::little, "tiles are copied as OpenEXR stores them, little-endian");
    const std::string what = "tile (" + std::to_string(tx) + ", " + std::to_string(ty) + ") of level " +
                             std::to_string(level);
    // A writer stores a chunk as it is when deflating would not shrink it.
    if (chunk.packed_size > n || (!zip && chunk.packed_size != n))
      throw std::runtime_error(what + ": " + std::to_string(chunk.packed_size) + " bytes stored for " +
                               std::to_string(n));
    f_->packed.resize(chunk.packed_size);
    f_->bytes.resize(n);
    check(exr_read_chunk(f_->core, 0, &chunk, f_->packed.data()));
    exr_zip::decode(f_->packed, f_->bytes, what);  // as it is when packed_size == n
    for (size_t y = 0; y < h; ++y)
      std::memcpy(out.data() + y * size_t(t), f_->bytes.data() + y * w * sizeof(half), w * sizeof(half));
  });
}

double DictionaryReader::photons_on_sensor(size_t i) const {
  std::string path = path_of(i);
  return exr_call(path, [&] {
    CorePsf f(path, m_, i);
    float photons = 0;
    return exr_attr_get_float(f.core, 0, "prismPhotonsOnSensor", &photons) == EXR_ERR_SUCCESS ? double(photons) : 0.0;
  });
}

SummedArea::SummedArea(const PsfLevel& l) : width_(l.width), height_(l.height) {
  table_.assign(size_t(width_ + 1) * (height_ + 1), 0.0);
  for (int y = 0; y < height_; ++y) {
    double row = 0;
    for (int x = 0; x < width_; ++x) {
      row += l.p[size_t(y) * width_ + x];
      table_[size_t(y + 1) * (width_ + 1) + x + 1] = table_[size_t(y) * (width_ + 1) + x + 1] + row;
    }
  }
}

LitPixels::LitPixels(const PsfLevel& l) : width_(l.width), height_(l.height) {
  table_.assign(size_t(width_ + 1) * (height_ + 1), 0u);
  for (int y = 0; y < height_; ++y) {
    uint32_t row = 0;
    for (int x = 0; x < width_; ++x) {
      row += l.p[size_t(y) * width_ + x] > 0.0f ? 1u : 0u;
      table_[size_t(y + 1) * (width_ + 1) + x + 1] = table_[size_t(y) * (width_ + 1) + x + 1] + row;
    }
  }
}

namespace {
// Clips [x0, x1) x [y0, y1) to a width x height level; false when nothing is left.
bool clip_rect(int& x0, int& y0, int& x1, int& y1, int width, int height) {
  x0 = std::clamp(x0, 0, width);
  x1 = std::clamp(x1, 0, width);
  y0 = std::clamp(y0, 0, height);
  y1 = std::clamp(y1, 0, height);
  return x1 > x0 && y1 > y0;
}
}  // namespace

uint32_t LitPixels::count(int x0, int y0, int x1, int y1) const {
  if (!clip_rect(x0, y0, x1, y1, width_, height_)) return 0;
  auto at = [&](int x, int y) { return table_[size_t(y) * (width_ + 1) + x]; };
  return at(x1, y1) - at(x0, y1) - at(x1, y0) + at(x0, y0);  // exact in unsigned arithmetic
}

double SummedArea::mass(int x0, int y0, int x1, int y1) const {
  if (!clip_rect(x0, y0, x1, y1, width_, height_)) return 0.0;
  auto at = [&](int x, int y) { return table_[size_t(y) * (width_ + 1) + x]; };
  return at(x1, y1) - at(x0, y1) - at(x1, y0) + at(x0, y0);
}

}  // namespace prism
