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
// Throws unless `path` names a file plot_lines can draw (.png or .svg): for
// commands to check before their work, as check_writable.
void check_plot_path(const std::string& path);

}  // namespace prism
