// host/util/json_file.h: files people edit, read with repeated keys refused.
#include <sstream>

#include "host/util/json_file.h"
#include "support.h"

namespace {
nlohmann::json parse(const std::string& text) {
  std::istringstream in(text);
  return prism::parse_json_file(in);
}
}  // namespace

TEST_CASE("json files: a key given twice in one object is refused, named with its place") {
  CHECK(parse(R"({"a": 1, "b": {"a": 2}})")["b"]["a"] == 2);  // the same key in another object is fine
  CHECK(parse(R"([{"x": 1}, {"x": 2}])")[1]["x"] == 2);       // and in sibling objects
  CHECK(parse(R"({"a": [{"b": {"c": 1}}, {"b": {"c": 2}}]})")["a"][1]["b"]["c"] == 2);
  CHECK_THROWS_WITH_AS(parse(R"({"a": 1, "a": 2})"), doctest::Contains("key \"a\" is given twice"),
                       prism::JsonDuplicateKey);
  CHECK_THROWS_WITH_AS(parse(R"({"v": {"x": [0, 1], "y": 2, "x": 3}})"), doctest::Contains("\"v.x\""),
                       prism::JsonDuplicateKey);
  CHECK_THROWS_WITH_AS(parse(R"({"l": [{"x": 1}, {"x": 1, "y": 0, "x": 2}]})"), doctest::Contains("\"l[].x\""),
                       prism::JsonDuplicateKey);
  // Nesting: a place is spelt out only for a message (it once was at every
  // level, memory quadratic in the depth: 1.3 GB for a fuzzed 32 KB of '['),
  // and deeper than max_json_depth is refused.
  auto nested = [](int depth, const std::string& inner) {
    return std::string(size_t(depth), '[') + inner + std::string(size_t(depth), ']');
  };
  CHECK(parse(nested(prism::max_json_depth - 2, R"({"a": 1})")).is_array());
  CHECK_THROWS_WITH_AS(parse(nested(prism::max_json_depth + 1, "1")), doctest::Contains("nested deeper than 256"),
                       prism::JsonSyntaxError);
  CHECK_THROWS_WITH_AS(parse(nested(40000, "")), doctest::Contains("nested deeper than"), prism::JsonSyntaxError);
  CHECK_THROWS_WITH_AS(parse("[" + nested(3, R"({"v": {"x": 1, "x": 2}})") + "]"), doctest::Contains("\"[][][][].v.x\""),
                       prism::JsonDuplicateKey);
  // Malformed: where and why in the parser's words, without the library's tag.
  CHECK_THROWS_WITH_AS(parse(R"({"a": 1,})"), doctest::Contains("parse error at line 1, column 9"), prism::JsonSyntaxError);
  try {
    parse("[1,\n 2,,]");
    FAIL("a second comma in a row was read as JSON");
  } catch (const prism::JsonSyntaxError& e) {
    CHECK(std::string(e.what()).find("json.exception") == std::string::npos);
    CHECK(e.byte == 8);
  }
  // A number beyond a double is nlohmann's out_of_range, not a parse error;
  // it too is a JsonSyntaxError (it once ended the fuzz harnesses, and the
  // commands printed the library's tag), with the byte past the number.
  try {
    parse("{\"a\":\n 8888e44844}");
    FAIL("a number beyond a double was read as JSON");
  } catch (const prism::JsonSyntaxError& e) {
    CHECK_MESSAGE(std::string(e.what()).find("number overflow") != std::string::npos, e.what());
    CHECK(std::string(e.what()).find("json.exception") == std::string::npos);
    CHECK(e.byte >= 7);  // on the second line
    CHECK(e.byte <= 18);
  }
}
