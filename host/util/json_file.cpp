#include "host/util/json_file.h"

#include <set>
#include <string>
#include <vector>

namespace prism {

nlohmann::json parse_json_file(std::istream& in) {
  using json = nlohmann::json;
  // Per open object or array: its name in its container (a key, or "[]" for
  // an array's element) and, for an object, the keys seen so far. A place
  // ("volume.x_mm") is spelt out only for a message: built at every level it
  // cost memory quadratic in the depth (a fuzzed 32 KB of '[' took 1.3 GB).
  struct Level {
    std::string name;
    std::set<std::string> keys;
    bool object;
  };
  std::vector<Level> open;
  std::string last_key;  // the key whose value comes next
  auto name_of_next = [&]() -> std::string {
    if (open.empty()) return "";
    return open.back().object ? last_key : "[]";
  };
  auto place = [&](const std::string& key) {
    std::string p;
    for (size_t i = 1; i < open.size(); ++i)  // the outermost level has no name
      p += (open[i].name == "[]" || p.empty() ? "" : ".") + open[i].name;
    return p.empty() ? key : p + "." + key;
  };
  json::parser_callback_t track = [&](int depth, json::parse_event_t event, json& parsed) {
    switch (event) {
      case json::parse_event_t::object_start:
      case json::parse_event_t::array_start:
        // No PRISM file nests more than a few levels; a limit keeps every
        // recursive walk of the result (dump(), the scene's parse) shallow.
        if (depth >= max_json_depth)
          throw JsonSyntaxError("objects and arrays nested deeper than " + std::to_string(max_json_depth) +
                                    " levels; no PRISM file needs more than a few",
                                0);
        open.push_back({name_of_next(), {}, event == json::parse_event_t::object_start});
        break;
      case json::parse_event_t::object_end:
      case json::parse_event_t::array_end:
        if (!open.empty()) open.pop_back();
        break;
      case json::parse_event_t::key: {
        last_key = parsed.get<std::string>();
        Level& top = open.back();
        if (!top.keys.insert(last_key).second)
          throw JsonDuplicateKey("key \"" + place(last_key) + "\" is given twice in one object; keep one");
        break;
      }
      case json::parse_event_t::value: break;
    }
    return true;
  };
  // what(): "[json.exception.parse_error.101] parse error at line ...": the
  // tag is for programmers.
  auto without_tag = [](const std::string& what) {
    const size_t tag_end = what.find("] ");
    return what.rfind("[json.exception.", 0) == 0 && tag_end != std::string::npos ? what.substr(tag_end + 2) : what;
  };
  try {
    return json::parse(in, track);
  } catch (const json::parse_error& e) {
    throw JsonSyntaxError(without_tag(e.what()), e.byte);
  } catch (const json::exception& e) {
    // Anything else the parser refuses, such as a number beyond a double
    // ("1e999": out_of_range.406), carries no position; the stream stopped
    // just past it.
    in.clear();
    const std::streamoff at = in.tellg();
    throw JsonSyntaxError(without_tag(e.what()), at > 0 ? size_t(at) : 0);
  }
}

}  // namespace prism
