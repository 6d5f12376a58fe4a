// Line plots for science (PLplot, cairo): PNG or SVG by the file's extension.
#pragma once
#include <string>
#include <vector>

namespace prism {

struct Series {
  std::string label;
  std::vector<double> x, y;
  bool dashed = false;
  bool markers = false;  // a symbol at each point as well as the line
};

struct PlotSpec {
  std::string title, x_label, y_label;
  bool log_y = true;
  bool log_x = false;
};

void plot_lines(const std::string& path, const PlotSpec& spec, const std::vector<Series>& series);

}  // namespace prism
