#include "hw/genicam.h"

#include <pugixml.hpp>

#include <cmath>
#include <cstring>
#include <map>
#include <stdexcept>

namespace prism::hw {
namespace {

int64_t parse_int(const std::string& text, const std::string& where) {
  try {
    size_t used = 0;
    int64_t v = std::stoll(text, &used, 0);  // base 0: GenICam XML mixes "0x1C" and "42"
    if (used == text.size()) return v;
  } catch (const std::exception&) {
  }
  throw std::runtime_error("GenICam XML: '" + text + "' in " + where + " is not an integer");
}

}  // namespace

struct NodeMap::Impl {
  pugi::xml_document doc;
  std::map<std::string, pugi::xml_node> nodes;
  RegisterPort& port;

  explicit Impl(RegisterPort& p) : port(p) {}

  // p-references are followed recursively: a chain this deep is a cycle
  // (the fuzzer found a feature whose pValue names itself).
  static constexpr int kMaxReferenceDepth = 64;
  int depth = 0;
  struct Follow {
    int& d;
    Follow(int& depth, pugi::xml_node n) : d(depth) {
      if (++d > kMaxReferenceDepth)
        throw std::runtime_error(std::string("GenICam XML: references through '") + n.attribute("Name").value() +
                                 "' nest deeper than " + std::to_string(kMaxReferenceDepth) + " (a cycle?)");
    }
    ~Follow() { --d; }
  };

  pugi::xml_node node(const std::string& name) const {
    auto it = nodes.find(name);
    if (it == nodes.end()) throw std::runtime_error("camera has no feature '" + name + "' in its GenICam XML");
    return it->second;
  }
  static std::string kind(pugi::xml_node n) { return n.name(); }
  static std::string child(pugi::xml_node n, const char* tag) { return n.child(tag).text().as_string(); }

  // --- registers ---
  uint64_t address(pugi::xml_node n) {
    uint64_t a = 0;
    for (auto c : n.children("Address")) a += uint64_t(parse_int(c.text().as_string(), n.attribute("Name").value()));
    for (auto c : n.children("pAddress")) a += uint64_t(integer(node(c.text().as_string())));
    return a;
  }
  size_t length(pugi::xml_node n) { return size_t(parse_int(child(n, "Length"), n.attribute("Name").value())); }
  bool little_endian(pugi::xml_node n) { return child(n, "Endianess") == "LittleEndian"; }
  void check_writable(pugi::xml_node n) {
    if (child(n, "AccessMode") == "RO")
      throw std::runtime_error(std::string("feature '") + n.attribute("Name").value() + "' is read-only");
  }

  uint64_t read_raw(pugi::xml_node n) {
    size_t len = length(n);
    if (len == 0 || len > 8) throw std::runtime_error(std::string("register '") + n.attribute("Name").value() +
                                                      "' has unsupported length " + std::to_string(len));
    Bytes b = port.read(address(n), len);
    uint64_t v = 0;
    for (size_t i = 0; i < len; ++i) v |= uint64_t(b[little_endian(n) ? i : len - 1 - i]) << (8 * i);
    return v;
  }
  void write_raw(pugi::xml_node n, uint64_t v) {
    size_t len = length(n);
    Bytes b(len);
    for (size_t i = 0; i < len; ++i) b[little_endian(n) ? i : len - 1 - i] = uint8_t(v >> (8 * i));
    port.write(address(n), b);
  }
  // MaskedIntReg bit range, counted from the least significant bit.
  std::pair<unsigned, unsigned> bits(pugi::xml_node n) {
    unsigned total = unsigned(length(n) * 8);
    auto conv = [&](unsigned b) { return little_endian(n) ? b : total - 1 - b; };
    if (n.child("Bit")) {
      unsigned b = conv(unsigned(parse_int(child(n, "Bit"), "Bit")));
      if (b >= total)
        throw std::runtime_error(std::string("register '") + n.attribute("Name").value() + "': bit " +
                                 std::to_string(b) + " outside its " + std::to_string(total) + " bits");
      return {b, b};
    }
    unsigned lsb = conv(unsigned(parse_int(child(n, "LSB"), "LSB")));
    unsigned msb = conv(unsigned(parse_int(child(n, "MSB"), "MSB")));
    if (lsb >= total || msb >= total)
      throw std::runtime_error(std::string("register '") + n.attribute("Name").value() + "': bits " +
                               std::to_string(lsb) + ".." + std::to_string(msb) + " outside its " +
                               std::to_string(total) + " bits");
    return {std::min(lsb, msb), std::max(lsb, msb)};
  }
  static uint64_t mask(unsigned lo, unsigned hi) { return (hi - lo >= 63 ? ~0ull : ((1ull << (hi - lo + 1)) - 1)) << lo; }

  // --- values ---
  int64_t integer(pugi::xml_node n) {
    Follow follow(depth, n);
    std::string k = kind(n);
    std::string name = n.attribute("Name").value();
    if (k == "IntReg") {
      uint64_t v = read_raw(n);
      size_t len = length(n);
      if (child(n, "Sign") == "Signed" && len < 8 && (v >> (len * 8 - 1)) & 1) v |= ~0ull << (len * 8);
      return int64_t(v);
    }
    if (k == "MaskedIntReg") {
      auto [lo, hi] = bits(n);
      return int64_t((read_raw(n) & mask(lo, hi)) >> lo);
    }
    if (k == "Integer" || k == "Enumeration" || k == "IntSwissKnife" || k == "Boolean") {
      if (n.child("pValue")) return integer(node(child(n, "pValue")));
      if (n.child("Value")) return parse_int(child(n, "Value"), name);
    }
    if (k == "Float" || k == "FloatReg") return int64_t(std::llround(number(n)));
    throw std::runtime_error("feature '" + name + "' (" + k + ") has no integer value this driver can read");
  }
  double number(pugi::xml_node n) {
    Follow follow(depth, n);
    std::string k = kind(n);
    if (k == "FloatReg") {
      uint64_t raw = read_raw(n);
      if (length(n) == 4) {
        float f;
        uint32_t r32 = uint32_t(raw);
        std::memcpy(&f, &r32, 4);
        return f;
      }
      double d;
      std::memcpy(&d, &raw, 8);
      return d;
    }
    if (k == "Float") {
      if (n.child("pValue")) return number(node(child(n, "pValue")));
      if (n.child("Value")) return n.child("Value").text().as_double();
    }
    return double(integer(n));
  }
  void set_integer(pugi::xml_node n, int64_t v) {
    Follow follow(depth, n);
    std::string k = kind(n);
    std::string name = n.attribute("Name").value();
    check_writable(n);
    if (k == "IntReg") return write_raw(n, uint64_t(v));
    if (k == "MaskedIntReg") {
      auto [lo, hi] = bits(n);
      uint64_t m = mask(lo, hi);
      if ((uint64_t(v) << lo & m) >> lo != uint64_t(v))
        throw std::runtime_error("value " + std::to_string(v) + " does not fit the bits of '" + name + "'");
      return write_raw(n, (read_raw(n) & ~m) | (uint64_t(v) << lo));
    }
    if (k == "Integer") {
      auto [lo, hi] = limits(n);  // +-inf where the XML gives none
      if (double(v) < lo || double(v) > hi)
        throw std::runtime_error(name + " = " + std::to_string(v) + " is outside [" + std::to_string(lo) + ", " +
                                 std::to_string(hi) + "]");
      if (n.child("Inc")) {
        int64_t inc = parse_int(child(n, "Inc"), name);
        // The steps start at Min when it is a representable integer, else at 0.
        const int64_t base = std::isfinite(lo) && std::abs(lo) < 9e18 ? int64_t(lo) : 0;
        if (inc > 1 && (__int128(v) - base) % inc != 0)
          throw std::runtime_error(name + " must be " + std::to_string(base) + " plus a multiple of " +
                                   std::to_string(inc));
      }
    }
    if (k == "Float" || k == "FloatReg") return set_number(n, double(v));
    if ((k == "Integer" || k == "Enumeration" || k == "Command") && n.child("pValue"))
      return set_integer(node(child(n, "pValue")), v);
    throw std::runtime_error("feature '" + name + "' (" + k + ") cannot be written by this driver");
  }
  void set_number(pugi::xml_node n, double v) {
    Follow follow(depth, n);
    std::string k = kind(n);
    std::string name = n.attribute("Name").value();
    check_writable(n);
    if (k == "FloatReg") {
      if (length(n) == 4) {
        float f = float(v);
        uint32_t r;
        std::memcpy(&r, &f, 4);
        return write_raw(n, r);
      }
      uint64_t r;
      std::memcpy(&r, &v, 8);
      return write_raw(n, r);
    }
    if (k == "Float") {
      auto [lo, hi] = limits(n);
      if (v < lo || v > hi)
        throw std::runtime_error(name + " = " + std::to_string(v) + " is outside [" + std::to_string(lo) + ", " +
                                 std::to_string(hi) + "]");
      if (n.child("pValue")) {
        pugi::xml_node target = node(child(n, "pValue"));
        return kind(target) == "FloatReg" ? set_number(target, v) : set_integer(target, std::llround(v));
      }
    }
    return set_integer(n, std::llround(v));
  }
  std::pair<double, double> limits(pugi::xml_node n) {
    auto bound = [&](const char* lit, const char* ref, double dflt) {
      if (n.child(ref)) return number(node(child(n, ref)));
      if (n.child(lit)) return n.child(lit).text().as_double();
      return dflt;
    };
    return {bound("Min", "pMin", -INFINITY), bound("Max", "pMax", INFINITY)};
  }
  pugi::xml_node entry(pugi::xml_node n, const std::string& e) {
    for (auto c : n.children("EnumEntry"))
      if (e == c.attribute("Name").value()) return c;
    std::string all;
    for (auto c : n.children("EnumEntry")) all += std::string(all.empty() ? "" : ", ") + c.attribute("Name").value();
    throw std::runtime_error("'" + e + "' is not a value of " + n.attribute("Name").value() + " (one of: " + all + ")");
  }
};

NodeMap::NodeMap(const std::string& xml, RegisterPort& port) : impl_(std::make_unique<Impl>(port)) {
  auto res = impl_->doc.load_buffer(xml.data(), xml.size());
  if (!res)
    throw std::runtime_error(std::string("camera's GenICam XML does not parse: ") + res.description() + " at byte " +
                             std::to_string(res.offset));
  for (auto x : impl_->doc.select_nodes("/RegisterDescription//*[@Name]")) {
    pugi::xml_node n = x.node();
    if (std::string(n.name()) != "EnumEntry") impl_->nodes.emplace(n.attribute("Name").value(), n);
  }
  if (impl_->nodes.empty()) throw std::runtime_error("camera's GenICam XML has no RegisterDescription features");
}
NodeMap::~NodeMap() = default;

bool NodeMap::has(const std::string& name) const { return impl_->nodes.count(name) != 0; }
std::string NodeMap::type(const std::string& name) const { return impl_->node(name).name(); }
int64_t NodeMap::get_int(const std::string& name) { return impl_->integer(impl_->node(name)); }
void NodeMap::set_int(const std::string& name, int64_t v) { impl_->set_integer(impl_->node(name), v); }
double NodeMap::get_float(const std::string& name) { return impl_->number(impl_->node(name)); }
void NodeMap::set_float(const std::string& name, double v) { impl_->set_number(impl_->node(name), v); }
std::pair<double, double> NodeMap::range(const std::string& name) { return impl_->limits(impl_->node(name)); }

std::string NodeMap::get_enum(const std::string& name) {
  auto n = impl_->node(name);
  int64_t v = impl_->integer(n);
  for (auto c : n.children("EnumEntry"))
    if (parse_int(c.child("Value").text().as_string(), name) == v) return c.attribute("Name").value();
  throw std::runtime_error("camera reports " + name + " = " + std::to_string(v) + ", which its XML does not name");
}

void NodeMap::set_enum(const std::string& name, const std::string& e) {
  auto n = impl_->node(name);
  impl_->set_integer(n, parse_int(impl_->entry(n, e).child("Value").text().as_string(), name));
}

std::vector<std::string> NodeMap::enum_entries(const std::string& name) const {
  std::vector<std::string> out;
  for (auto c : impl_->node(name).children("EnumEntry")) out.push_back(c.attribute("Name").value());
  return out;
}

void NodeMap::execute(const std::string& name) {
  auto n = impl_->node(name);
  if (std::string(n.name()) != "Command") throw std::runtime_error("feature '" + name + "' is not a command");
  int64_t v = n.child("pCommandValue") ? impl_->integer(impl_->node(Impl::child(n, "pCommandValue")))
                                       : parse_int(Impl::child(n, "CommandValue"), name);
  impl_->set_integer(impl_->node(Impl::child(n, "pValue")), v);
}

std::string NodeMap::get_string(const std::string& name) {
  std::string k = type(name);
  if (k == "Enumeration") return get_enum(name);
  if (k == "Float" || k == "FloatReg") {
    char s[64];
    snprintf(s, sizeof s, "%.6g", get_float(name));
    return s;
  }
  if (k == "Command") throw std::runtime_error("'" + name + "' is a command: use `prism camera set " + name + " 1`");
  return std::to_string(get_int(name));
}

void NodeMap::set_string(const std::string& name, const std::string& value) {
  std::string k = type(name);
  if (k == "Enumeration") return set_enum(name, value);
  if (k == "Command") return execute(name);
  if (k == "Float" || k == "FloatReg") {
    size_t used = 0;
    double v = 0;
    try {
      v = std::stod(value, &used);
    } catch (const std::exception&) {
    }
    if (used == 0 || used != value.size()) throw std::runtime_error("'" + value + "' is not a number for " + name);
    return set_float(name, v);
  }
  set_int(name, parse_int(value, name));
}

}  // namespace prism::hw
