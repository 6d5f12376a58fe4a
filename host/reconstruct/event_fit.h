// One event being reconstructed (internal to host/reconstruct): its clicks on
// every level, the model built so far (vertices = dictionary PSFs moved by
// whole click-grid pixels, with weights), and the steps of the paper's
// algorithm after the support scan. The Reconstructor (reconstructor.cpp)
// drives a batch of these through the K passes; the scan itself runs on a
// backend (engine/ref/support_scan_ref.h or the device).
//
// Where each step lives:
//   event_fit.cpp  the event at each level, the model's rates, weights, output
//   search.cpp     pruning: the scan's best candidates carried down to the click level
//   descent.cpp    ADCG's joint local descent on the grid, and the depth parabola
#pragma once
#include <cstdint>
#include <map>
#include <optional>
#include <tuple>
#include <vector>

#include <glm/glm.hpp>

#include "engine/ref/support_scan_ref.h"
#include "engine/support_scan.h"
#include "host/dictionary/service.h"
#include "host/events/event_file.h"
#include "host/reconstruct/reconstruct.h"

namespace prism::detail {

using Shift = glm::ivec2;

// A vertex of the model: a dictionary PSF moved by whole click-grid pixels.
struct Vertex {
  size_t psf = 0;
  Shift shift{};
  double alpha = 0;
};

// A PSF at one shift seen at the click level: P at each click, and S.
struct Column {
  std::vector<double> p;
  double s = 0;
};

// tau on the sensor in pixels of `level` for the depth plane of PSF `psf`,
// rounded to the nearest pixel as place_on_plane rounds a source's offset:
// exactly the shifts a source within tau of the node can be given (the ring
// beyond is the neighbouring node's; tests/host/reconstruct).
int scan_radius_px(const DictionaryManifest& m, double tau_mm, size_t psf, int level);
// The level the scan runs on: settings.search_level, or the service's coarse
// level when it is -1; never finer than the clicks.
int search_level_of(const DictionaryService& d, const ReconstructionSettings& s, int click_level);
// The level the carried PSFs are ranked on (select_level(), between the
// clicks' level and the search level): coarse to fine when it is finer than
// the search level. The device scan's choice of which weights to fit
// (reconstructor.cpp) rests on the same level as the pruning (search.cpp).
int select_level_of(int search_level, const ReconstructionSettings& s, const DictionaryManifest& m, int click_level);
// The level the candidates are ranked on before the best goes on to the
// clicks (rank_level(), between the clicks' level and the select level).
int rank_level_of(int select_level, const ReconstructionSettings& s, const DictionaryManifest& m, int click_level);

class EventFit {
 public:
  EventFit(const Event& e, int level, DictionaryService& d, const ReconstructionSettings& s);

  // Another vertex to add (the event has clicks and fewer than K so far).
  bool wants_vertex() const { return !clicks_.at(level_).empty() && vs_.size() < size_t(s_.vertices); }

  // The support scan's input for the next vertex: the clicks on the search
  // level and the current model's rate there (dense: at every pixel).
  ScanEvent scan_input(bool dense);
  // The scan on the CPU reference (engine/ref/support_scan_ref.h).
  std::vector<SupportScore> scan_cpu();

  // Steps 3-6 for the next vertex from the scan's results: pruning down to
  // the click level, all weights, then the joint local descent.
  void add_vertex(std::vector<SupportScore> scored);

  // K rows: refined depth, lateral position, flags (no_clicks rows for an
  // empty event).
  std::vector<ReconstructedVertex> result();

 private:
  // --- geometry on the dictionary grid (event_fit.cpp) ---
  double depth_of(size_t psf) const { return m_.grid.depth_mm[size_t(m_.grid.node(psf).z)]; }
  int radius_px(size_t psf, int level) const { return scan_radius_px(m_, s_.tau_mm, psf, level); }
  // Lateral source position of a vertex, its shift read at depth `depth_mm`.
  glm::dvec2 source_xy(const Vertex& v, double depth_mm) const;
  // The vertex for a lateral source position on depth plane iz: nearest node,
  // shift rounded; none when the position lies beyond tau of every node.
  std::optional<Vertex> place(glm::dvec2 xy, int iz, double alpha) const;

  // --- the event at each level (event_fit.cpp) ---
  const std::vector<glm::ivec2>& clicks_at(int level);
  double sensor_mass(size_t psf, int level, Shift shift) const;
  // P of a PSF at `level` at every click of that level minus `shift`.
  std::vector<float> values_at(size_t psf, int level, Shift shift);
  const Column& column(size_t psf, Shift shift);
  // lambda at the clicks of `level` of the vertices `vs` (shifts on the
  // click grid), the floor `floor` (per click-level pixel) included; vertex
  // `skip` left out.
  std::vector<double> rates(int level, const std::vector<Vertex>& vs, double floor, int skip = -1);
  std::vector<double> dense_rates(int level);  // at every pixel (the dense baseline's input)
  // The floor the search chooses PSFs with, per click-level pixel
  // (ReconstructionSettings::search_dark_rate, per sensor pixel, times the
  // sensor pixels in a click pixel; never below dark_rate).
  double search_floor() const;

  // --- weights (event_fit.cpp) ---
  double fit(std::vector<Vertex>& vs);  // all weights jointly at the click level; the event's NLL
  // One weight against a fixed background; returns the NLL of that vertex's part.
  double fit_one(const std::vector<double>& p, double s, const std::vector<double>& background, double& alpha) const;

  // --- pruning (search.cpp) ---
  // The best candidate; the others, best first, go to `runners_up`.
  Vertex refine(std::vector<SupportScore> scored, std::vector<Vertex>& runners_up);

  // --- joint descent and depth (descent.cpp) ---
  std::vector<Vertex> moves(const Vertex& v) const;
  void descend(std::vector<Vertex>& vs);
  struct DepthFit {
    double depth_mm;
    bool at_edge;
  };
  DepthFit refine_depth(const Vertex& v, const std::vector<double>& background);

  std::vector<ReconstructedVertex> finish(std::vector<Vertex>& vs);

  // A level of the dictionary seen from this event, for the shared shift search.
  class LevelSource;

  DictionaryService& d_;
  const DictionaryManifest& m_;
  const ReconstructionSettings& s_;
  int level_, search_level_ = 0;
  std::map<int, std::vector<glm::ivec2>> clicks_;  // per level
  std::vector<double> dark_;                       // dark rate at each click-level click
  std::map<std::tuple<size_t, int, int>, Column> columns_;
  std::vector<Vertex> vs_;  // the model so far
  // Per vertex, the pruning's runners-up (click-level NLL order): starting
  // points for the continuous refinement (host/reconstruct/refine.h).
  std::vector<std::vector<Vertex>> runners_up_;
};

// A level of the dictionary seen from this event: values through the
// service's tiles, S from the coarse summed-area table, radii from tau.
class EventFit::LevelSource : public ref::ScanSource {
 public:
  LevelSource(EventFit& fit, int level) : f_(fit), level_(level) {}
  size_t psf_count() const override { return f_.m_.grid.size(); }
  std::vector<float> values(size_t psf, std::span<const glm::ivec2> pixels) override {
    return f_.d_.values(psf, level_, pixels);
  }
  double mass_shifted(size_t psf, glm::ivec2 shift) override { return f_.sensor_mass(psf, level_, shift); }
  int radius_px(size_t psf) const override { return f_.radius_px(psf, level_); }

 private:
  EventFit& f_;
  int level_;
};

}  // namespace prism::detail
