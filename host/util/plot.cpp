#include "host/util/plot.h"

#include <plplot/plstream.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <stdexcept>

#include "host/util/image_io.h"

namespace prism {

namespace {
// PLplot's output device for a file name; throws unless it ends in .png or .svg.
const char* plot_device(const std::string& path) {
  std::string ext = path.substr(path.find_last_of('.') + 1);
  const char* device = ext == "svg" ? "svgcairo" : ext == "png" ? "pngcairo" : nullptr;
  if (!device) throw std::runtime_error("plot " + path + ": use a .png or .svg file name");
  return device;
}
}  // namespace

void check_plot_path(const std::string& path) { (void)plot_device(path); }

void plot_lines(const std::string& path, const PlotSpec& spec, const std::vector<Series>& series) {
  const char* device = plot_device(path);
  double xmin = std::numeric_limits<double>::infinity(), xmax = -xmin, ymin = xmin, ymax = -xmin;
  auto ty = [&](double v) { return spec.log_y ? std::log10(v) : v; };
  auto tx = [&](double v) { return spec.log_x ? std::log10(v) : v; };
  auto drawn = [&](const Series& s, size_t i) {
    return std::isfinite(s.y[i]) && std::isfinite(s.x[i]) && (!spec.log_y || s.y[i] > 0) && (!spec.log_x || s.x[i] > 0);
  };
  for (const auto& s : series)
    for (size_t i = 0; i < s.x.size(); ++i) {
      if (!drawn(s, i)) continue;
      xmin = std::min(xmin, tx(s.x[i]));
      xmax = std::max(xmax, tx(s.x[i]));
      ymin = std::min(ymin, ty(s.y[i]));
      ymax = std::max(ymax, ty(s.y[i]));
    }
  if (!std::isfinite(xmin)) throw std::runtime_error("plot " + path + ": no finite values to draw");
  // Whole decades on log axes, with a little room so that a value on a
  // decade is not drawn on the frame (where its marker is cut).
  constexpr double room = 0.02;
  if (spec.log_y) {
    ymin = std::floor(ymin - room);
    ymax = std::ceil(ymax + room);
  }
  if (spec.log_x) {
    xmin = std::floor(xmin - room);
    xmax = std::ceil(xmax + room);
  }
  if (ymax <= ymin) ymax = ymin + 1;
  if (xmax <= xmin) xmax = xmin + 1;

  write_atomically(path, [&](const std::string& tmp) {
    auto pls = std::make_unique<plstream>();
    pls->sdev(device);
    pls->sfnam(tmp.c_str());
    pls->spage(0, 0, 1200, 800, 0, 0);
    pls->scolbg(255, 255, 255);
    pls->init();
    pls->col0(15);  // black on white after the background swap below
    pls->scol0(15, 0, 0, 0);
    pls->col0(15);
    // Plot area on the left, legend outside it on the right: curves that fill
    // the whole range are never hidden.
    pls->adv(0);
    // Left margin: the y label sits beyond tick labels like 10^-2.
    pls->vpor(0.12, 0.64, 0.11, 0.90);
    pls->wind(xmin, xmax, ymin, ymax);
    pls->box(spec.log_x ? "bcnstl" : "bcnst", 0.0, 0, spec.log_y ? "bcnstlv" : "bcnstv", 0.0, 0);
    pls->lab(spec.x_label.c_str(), spec.y_label.c_str(), "");
    const int colours[][3] = {{0, 0, 0},     {228, 26, 28},  {55, 126, 184}, {77, 175, 74},  {152, 78, 163},
                              {255, 127, 0}, {166, 86, 40},  {247, 129, 191}, {100, 100, 100}, {23, 190, 207}};
    std::vector<int> opt, line_colors, line_styles;
    std::vector<PLFLT> widths;
    std::vector<std::string> labels;
    for (size_t k = 0; k < series.size(); ++k) {
      const auto& s = series[k];
      int c = int(1 + k % 10);
      pls->scol0(c, colours[k % 10][0], colours[k % 10][1], colours[k % 10][2]);
      pls->col0(c);
      pls->lsty(s.dashed ? 2 : 1);
      pls->width(2.0);
      std::vector<PLFLT> x, y;
      for (size_t i = 0; i < s.x.size(); ++i)
        if (drawn(s, i)) {
          x.push_back(tx(s.x[i]));
          y.push_back(ty(s.y[i]));
        }
      if (!x.empty()) pls->line(int(x.size()), x.data(), y.data());
      if (s.markers && !x.empty()) pls->poin(int(x.size()), x.data(), y.data(), 17);
      opt.push_back(s.markers ? PL_LEGEND_LINE | PL_LEGEND_SYMBOL : PL_LEGEND_LINE);
      line_colors.push_back(c);
      line_styles.push_back(s.dashed ? 2 : 1);
      widths.push_back(2.0);
      labels.push_back(s.label);
    }
    pls->lsty(1);
    pls->col0(15);
    std::vector<const char*> texts;
    for (auto& l : labels) texts.push_back(l.c_str());
    std::vector<int> zeros(series.size(), 0), text_colors(series.size(), 15);
    std::vector<PLFLT> zf(series.size(), 0.0), symbol_scales(series.size(), 1.0);
    std::vector<int> symbol_numbers(series.size(), 1);
    std::vector<const char*> symbols(series.size(), "#(728)");
    PLFLT lw, lh;
    pls->legend(&lw, &lh, PL_LEGEND_BACKGROUND | PL_LEGEND_BOUNDING_BOX, PL_POSITION_OUTSIDE | PL_POSITION_RIGHT, 0.02, 0.0,
                0.1, 0, 15, 1, 0, 0, int(series.size()), opt.data(), 1.0, 0.8, 2.0, 0.0, text_colors.data(),
                texts.data(), nullptr, nullptr, nullptr, nullptr, line_colors.data(), line_styles.data(),
                widths.data(), line_colors.data(), symbol_scales.data(), symbol_numbers.data(), symbols.data());
    // The title centred on the page, not on the plot area: a long one would
    // run off the left edge.
    pls->vpor(0.0, 1.0, 0.0, 1.0);
    pls->wind(0.0, 1.0, 0.0, 1.0);
    pls->mtex("t", -1.5, 0.5, 0.5, spec.title.c_str());
  });
}

}  // namespace prism
