// GenICam feature access through the camera's XML register description.
// Parsed with pugixml: a well-kept Debian package (libpugixml-dev), a small
// DOM with XPath queries, which is all a register map needs.
// Supported nodes: IntReg, MaskedIntReg, FloatReg, Integer, Float, Enumeration
// (with EnumEntry), Command, each with literal or p-referenced values.
#pragma once
#include <memory>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "hw/bytes.h"

namespace prism::hw {

// Where the register bytes live (the camera over GenCP, or a test's memory).
class RegisterPort {
 public:
  virtual ~RegisterPort() = default;
  virtual Bytes read(uint64_t address, size_t count) = 0;
  virtual void write(uint64_t address, std::span<const uint8_t> data) = 0;
};

class NodeMap {
 public:
  NodeMap(const std::string& xml, RegisterPort& port);
  ~NodeMap();
  NodeMap(const NodeMap&) = delete;
  NodeMap& operator=(const NodeMap&) = delete;

  bool has(const std::string& name) const;
  std::string type(const std::string& name) const;  // XML element name, e.g. "Float"

  int64_t get_int(const std::string& name);
  void set_int(const std::string& name, int64_t value);
  double get_float(const std::string& name);
  void set_float(const std::string& name, double value);
  std::string get_enum(const std::string& name);
  void set_enum(const std::string& name, const std::string& entry);
  std::vector<std::string> enum_entries(const std::string& name) const;
  void execute(const std::string& name);  // Command nodes
  std::pair<double, double> range(const std::string& name);  // Min/Max of Integer or Float

  // Any feature as text, and set from text (what `prism camera get/set` use).
  std::string get_string(const std::string& name);
  void set_string(const std::string& name, const std::string& value);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace prism::hw
