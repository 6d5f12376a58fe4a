// JSON from files people edit (scenes, sweep spaces, manifests, HDR stack
// metadata), read with one rule nlohmann's parser lacks: a key given twice in
// one object is an error. nlohmann keeps the last value silently, so an
// edited file could carry two values of a field and be read with the one its
// author did not mean.
#pragma once
#include <istream>
#include <stdexcept>

#include <nlohmann/json.hpp>

namespace prism {

// A key given twice; the message names it with its place ("volume.x_mm").
struct JsonDuplicateKey : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// As nlohmann::json::parse(in) (its parse_error for malformed text), and
// throws JsonDuplicateKey for a repeated key.
nlohmann::json parse_json_file(std::istream& in);

}  // namespace prism
