#include "host/util/json_file.h"

#include <set>
#include <string>
#include <vector>

namespace prism {

nlohmann::json parse_json_file(std::istream& in) {
  using json = nlohmann::json;
  // Per open object: its place and the keys seen so far. An array is a
  // level without keys; its elements are named by their container.
  struct Level {
    std::string place;
    std::set<std::string> keys;
    bool object;
  };
  std::vector<Level> open;
  std::string last_key;  // the key whose value comes next
  auto place_of_next = [&]() {
    if (open.empty()) return std::string();
    const Level& top = open.back();
    if (!top.object) return top.place + "[]";
    return top.place.empty() ? last_key : top.place + "." + last_key;
  };
  json::parser_callback_t track = [&](int, json::parse_event_t event, json& parsed) {
    switch (event) {
      case json::parse_event_t::object_start: open.push_back({place_of_next(), {}, true}); break;
      case json::parse_event_t::array_start: open.push_back({place_of_next(), {}, false}); break;
      case json::parse_event_t::object_end:
      case json::parse_event_t::array_end:
        if (!open.empty()) open.pop_back();
        break;
      case json::parse_event_t::key: {
        last_key = parsed.get<std::string>();
        Level& top = open.back();
        if (!top.keys.insert(last_key).second)
          throw JsonDuplicateKey("key \"" + (top.place.empty() ? last_key : top.place + "." + last_key) +
                                 "\" is given twice in one object; keep one");
        break;
      }
      case json::parse_event_t::value: break;
    }
    return true;
  };
  try {
    return json::parse(in, track);
  } catch (const json::parse_error& e) {
    // what(): "[json.exception.parse_error.101] parse error at line ...": the tag is for programmers.
    const std::string what = e.what();
    const size_t tag_end = what.rfind("] ", what.find(" parse error"));
    throw JsonSyntaxError(tag_end == std::string::npos ? what : what.substr(tag_end + 2), e.byte);
  }
}

}  // namespace prism
