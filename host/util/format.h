// How numbers and text fields are written to CSV files and tables: one
// convention for every output of `prism`.
#pragma once
#include <string>

namespace prism {

// Six significant digits ("%.6g"), or `digits` (fitted parameters, whose
// uncertainties are a millionth of their values); infinities as "inf" and
// "-inf", NaN as "nan" (a CRLB with no light is infinite, never NaN; README "Commands").
std::string format_number(double v, int digits = 6);

// A CSV field, quoted when it holds a comma or a quote (quotes doubled).
std::string csv_field(const std::string& s);

// The items of a list of names, separated by ", " (for messages and --help).
template <class Names>
std::string join(const Names& names, const std::string& separator = ", ") {
  std::string out;
  bool first = true;
  for (const auto& name : names) {
    if (!first) out += separator;
    out += name;
    first = false;
  }
  return out;
}

}  // namespace prism
