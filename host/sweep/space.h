// A design space for sweeps: the free parameters of a lenslet array (focal
// lengths and their assignment to positions, diameters, hex layout,
// distances, lens model, effects) around a base scene, read from a space file
// (host/sweep/SWEEP.md). A design is a vector of choices: indices into the
// space's lists.
#pragma once
#include <cstdint>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "host/scene/scene.h"
#include "host/sweep/objectives.h"

namespace prism {

// Portable draws: std::uniform_int_distribution and std::shuffle differ
// between standard libraries, and the same seed must give the same sweep.
namespace draw {
inline size_t index(std::mt19937_64& rng, size_t n) { return size_t(rng() % n); }
template <class T> void shuffle(std::vector<T>& v, std::mt19937_64& rng) {
  for (size_t i = v.size(); i > 1; --i) std::swap(v[i - 1], v[index(rng, i)]);
}
}  // namespace draw

// One point of the space: indices into the space's lists.
struct Design {
  size_t layout = 0;
  std::vector<int> focal;     // per position, into DesignSpace::focal_mm
  std::vector<int> diameter;  // per position, into DesignSpace::diameter_mm
  size_t lens_to_sensor = 0, working_distance = 0, lens_model = 0, effects = 0;
  std::string key() const;  // unique text of the choices
  nlohmann::json to_json() const;
  static Design from_json(const nlohmann::json& j);
};

struct HexLayout {
  int rows = 0, columns = 0;  // 0: the base scene's own positions
  double pitch_mm = 0;
};

class DesignSpace {
 public:
  // `dir` resolves a relative base scene path (the space file's folder).
  static DesignSpace parse(const nlohmann::json& j, const std::string& origin, const std::string& dir = ".");
  static DesignSpace load(const std::string& path);

  // The scene of a design, not validated (see evaluate_design).
  Scene scene_of(const Design& d, const std::string& name) const;
  // The design of a scene when the space holds it (the base, usually).
  std::optional<Design> encode(const Scene& s) const;
  double size() const;                  // number of designs; may be huge
  std::vector<Design> enumerate() const;  // every design; only when size() is small
  Design random(std::mt19937_64& rng) const;
  Design neighbour(const Design& d, std::mt19937_64& rng) const;  // one or two moves
  // Parameters of a design as CSV columns (header names in parameter_columns).
  static std::vector<std::string> parameter_columns();
  std::vector<std::string> parameters(const Design& d) const;

  std::string name;
  nlohmann::json source;  // the space file as read, kept in the state file
  Scene base;
  std::vector<HexLayout> layouts;
  std::vector<double> focal_mm;
  bool focal_free = false;     // true: any focal length per position; false: balanced
  bool focal_fixed = false;    // the base scene's focal lengths, unchanged
  std::vector<double> diameter_mm;
  bool diameter_fixed = false;
  std::vector<double> lens_to_sensor_mm, working_distance_mm;
  std::vector<LensModel> lens_models;
  std::vector<Effects> effects;
  std::vector<std::string> effects_labels;
  SampleGrid samples;            // where the CRLB objectives are scored
  SampleGrid ambiguity_samples;  // where the ambiguity objectives are (fewer: each costs ~60 renders)

  std::vector<LensletGeometry> positions(size_t layout) const;  // centres only
 private:
  Design random_at(size_t layout, std::mt19937_64& rng) const;
  std::vector<int> base_genes(const std::vector<double>& values, const std::vector<double>& set) const;
};

}  // namespace prism
