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

// Text that is not JSON; the message says where and why in the parser's
// words ("parse error at line 3, column 7: syntax error ..."), without the
// library's exception tag.
struct JsonSyntaxError : std::runtime_error {
  JsonSyntaxError(const std::string& what, size_t byte) : std::runtime_error(what), byte(byte) {}
  size_t byte;  // where the parser stopped, from the start of the text
};

// Deepest nesting of objects and arrays parse_json_file accepts.
inline constexpr int max_json_depth = 256;

// As nlohmann::json::parse(in), but malformed text (a number beyond a
// double, nesting deeper than max_json_depth) throws JsonSyntaxError, never
// one of nlohmann's exceptions, and a repeated key JsonDuplicateKey.
nlohmann::json parse_json_file(std::istream& in);

}  // namespace prism
