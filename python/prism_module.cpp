// The compiled half of the Python module `prism` (prism._core): thin
// bindings over the same host functions the `prism` commands call, so that a
// notebook and the command line give the same numbers and the same error
// messages. Arguments arrive already checked and broadcast by the Python half
// (python/prism/__init__.py), which holds the docstrings users read.
//
// Device work runs with the GIL released, one call at a time per Vulkan
// device (a queue is not shared between threads); large results reach NumPy
// without a copy (the C++ vector is moved into the array's owner).
#include <map>
#include <optional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include "engine/vk/context.h"
#include "engine/vk/error.h"
#include "host/dictionary/build.h"
#include "host/dictionary/store.h"
#include "host/events/event_file.h"
#include "host/events/simulate.h"
#include "host/reconstruct/ambiguity.h"
#include "host/reconstruct/refine.h"
#include "host/reconstruct/session.h"
#include "host/scene/crlb_study.h"
#include "host/scene/psf_render.h"
#include "host/scene/scene.h"
#include "host/util/image_io.h"
#include "host/util/memory.h"
#include "host/util/output_file.h"

namespace py = pybind11;

namespace prism::python {

namespace {

// One Vulkan context per device request ("" = $PRISM_DEVICE or auto), made
// on first use and kept: a context compiles each kernel once, and the
// footprint kernels take seconds to compile on a CPU device.
struct Device {
  std::unique_ptr<vk::Context> ctx;
  std::mutex busy;
};
std::map<std::string, std::unique_ptr<Device>>& devices() {
  static std::map<std::string, std::unique_ptr<Device>> all;
  return all;
}

// Called with the GIL held (the map is guarded by it).
Device& device_for(const std::string& request) {
  auto& all = devices();
  auto it = all.find(request);
  if (it == all.end()) {
    auto d = std::make_unique<Device>();
    {
      py::gil_scoped_release release;
      d->ctx = std::make_unique<vk::Context>(vk::ContextOptions{request});
    }
    it = all.emplace(request, std::move(d)).first;
  }
  return *it->second;
}

std::vector<std::string> validation_messages() {
  std::vector<std::string> out;
  for (const auto& [request, d] : devices())
    out.insert(out.end(), d->ctx->validation_messages().begin(), d->ctx->validation_messages().end());
  return out;
}

// A vector's storage handed to NumPy: the array owns the vector.
template <typename T>
py::array_t<T> to_numpy(std::vector<T>&& v, std::vector<py::ssize_t> shape) {
  auto* owner = new std::vector<T>(std::move(v));
  py::capsule free_owner(owner, [](void* p) { delete static_cast<std::vector<T>*>(p); });
  return py::array_t<T>(shape, owner->data(), free_owner);
}

Scene scene_from_json_text(const std::string& text) {
  nlohmann::json j;
  try {
    j = nlohmann::json::parse(text);
  } catch (const nlohmann::json::exception& e) {
    throw SceneError(std::string("scene dict: ") + e.what());
  }
  return parse_scene(j, "dict");
}

// The options of the forward model as the commands take them.
struct Forward {
  unsigned rays = 0, binning = 1, stratification = 0;
  std::string splat = "footprint", lens_model, backend = "vulkan", device, estimator = "auto";
  double photons = 0;

  TraceSettings settings(const Scene& scene) const {
    return trace_settings(scene, binning, rays, photons, splat_from_string(splat), stratification, estimator);
  }
  Backend backend_kind() const {
    if (backend != "vulkan" && backend != "cpu") throw std::invalid_argument("backend '" + backend + "': use vulkan or cpu");
    return backend == "cpu" ? Backend::cpu : Backend::vulkan;
  }
};

Forward forward_from(const py::dict& o) {
  Forward f;
  f.rays = o["rays"].cast<unsigned>();
  f.binning = o["binning"].cast<unsigned>();
  f.stratification = o["stratification"].cast<unsigned>();
  f.splat = o["splat"].cast<std::string>();
  f.lens_model = o["lens_model"].cast<std::string>();
  f.backend = o["backend"].cast<std::string>();
  f.device = o["device"].cast<std::string>();
  f.estimator = o["estimator"].cast<std::string>();
  f.photons = o["photons"].cast<double>();
  return f;
}

py::dict crlb(const std::vector<Scene>& scenes_in, const py::array_t<double, py::array::c_style>& positions_in,
              const py::dict& forward, const std::string& sensor_name, double converge, unsigned max_rays,
              bool with_ambiguity, double separation_mm) {
  if (positions_in.ndim() != 2 || positions_in.shape(1) != 3)
    throw std::invalid_argument("positions: an (N, 3) array of x_mm, y_mm, depth_mm");
  std::vector<glm::dvec3> positions;
  auto p = positions_in.unchecked<2>();
  for (py::ssize_t i = 0; i < p.shape(0); ++i) positions.push_back({p(i, 0), p(i, 1), p(i, 2)});
  if (sensor_name != "poisson" && sensor_name != "binary")
    throw std::invalid_argument("sensor '" + sensor_name + "': use poisson or binary");
  const SensorModel sensor = sensor_name == "binary" ? SensorModel::binary : SensorModel::poisson;
  const Forward fw = forward_from(forward);
  std::vector<Scene> scenes = scenes_in;
  for (Scene& s : scenes) {
    override_lens_model(s, fw.lens_model, "lens_model");
    for (const auto& q : positions) require_in_front(s, q.z, "depth_mm");
  }
  const Backend backend = fw.backend_kind();
  // As the command: the ambiguity's model on the device with the Vulkan
  // backend, on the CPU reference with the cpu one.
  Device* device = backend == Backend::vulkan ? &device_for(fw.device) : nullptr;
  AmbiguitySettings as;
  as.min_separation_mm = separation_mm;

  std::vector<CrlbRow> rows;
  std::vector<Ambiguity> ambiguities;
  {
    py::gil_scoped_release release;
    std::unique_lock<std::mutex> lock;
    if (device) lock = std::unique_lock<std::mutex>(device->busy);
    vk::Context* ctx = device ? device->ctx.get() : nullptr;
    for (const Scene& s : scenes) {
      const TraceSettings t = fw.settings(s);
      auto part = crlb_checked(s, positions, t, converge, max_rays, backend, sensor, ctx);
      if (with_ambiguity) {
        auto model = make_scene_model(s, refine_trace_settings(t.binning), ctx);
        for (const CrlbRow& r : part) ambiguities.push_back(ambiguity(*model, s, r.theta, r.photons, as));
      }
      rows.insert(rows.end(), part.begin(), part.end());
    }
  }

  const size_t n = rows.size();
  auto column = [&](auto get) {
    std::vector<double> v(n);
    for (size_t i = 0; i < n; ++i) v[i] = get(i);
    return to_numpy(std::move(v), {py::ssize_t(n)});
  };
  py::list scene_names, lens_models, flags;
  for (const auto& r : rows) {
    scene_names.append(r.scene);
    lens_models.append(to_string(r.lens_model));
    flags.append(r.crlb.flag);
  }
  py::dict out;
  out["scene"] = scene_names;
  out["x_mm"] = column([&](size_t i) { return rows[i].theta.x; });
  out["y_mm"] = column([&](size_t i) { return rows[i].theta.y; });
  out["depth_mm"] = column([&](size_t i) { return rows[i].theta.z; });
  out["photons"] = column([&](size_t i) { return rows[i].photons; });
  out["crlb_x_mm"] = column([&](size_t i) { return rows[i].crlb.x_mm; });
  out["crlb_y_mm"] = column([&](size_t i) { return rows[i].crlb.y_mm; });
  out["crlb_z_mm"] = column([&](size_t i) { return rows[i].crlb.depth_mm; });
  out["crlb_3d_mm"] = column([&](size_t i) { return rows[i].crlb.r3_mm; });
  out["lens_model"] = lens_models;
  out["rays_per_lenslet"] = column([&](size_t i) { return double(rows[i].rays_per_lenslet); });
  out["change_vs_quarter_rays"] = column([&](size_t i) { return rows[i].change; });
  out["flag"] = flags;
  if (with_ambiguity) {
    out["alias_kl"] = column([&](size_t i) { return ambiguities[i].kl; });
    out["alias_x_mm"] = column([&](size_t i) { return ambiguities[i].impostor_mm.x; });
    out["alias_y_mm"] = column([&](size_t i) { return ambiguities[i].impostor_mm.y; });
    out["alias_depth_mm"] = column([&](size_t i) { return ambiguities[i].impostor_mm.z; });
    out["p_confusion"] = column([&](size_t i) { return ambiguities[i].p_confusion; });
  }
  return out;
}

// The global ambiguity at given positions and detected photons, as `prism
// evaluate --ambiguity` computes it for each event (the scene's model at the
// clicks' binning; one model for every position).
py::dict ambiguity_at(const Scene& scene_in, const py::array_t<double, py::array::c_style>& positions_in,
                      const py::array_t<double, py::array::c_style>& photons_in, const py::dict& forward,
                      double separation_mm) {
  if (positions_in.ndim() != 2 || positions_in.shape(1) != 3)
    throw std::invalid_argument("positions: an (N, 3) array of x_mm, y_mm, depth_mm");
  if (photons_in.ndim() != 1 || photons_in.shape(0) != positions_in.shape(0))
    throw std::invalid_argument("photons: one count per position");
  const Forward fw = forward_from(forward);
  Scene scene = scene_in;
  override_lens_model(scene, fw.lens_model, "lens_model");
  auto p = positions_in.unchecked<2>();
  auto ph = photons_in.unchecked<1>();
  std::vector<glm::dvec3> positions;
  for (py::ssize_t i = 0; i < p.shape(0); ++i) {
    positions.push_back({p(i, 0), p(i, 1), p(i, 2)});
    require_in_front(scene, p(i, 2), "depth_mm");
    if (!(std::isfinite(ph(i)) && ph(i) > 0)) throw std::invalid_argument("photons: each must be a finite number > 0");
  }
  Device* device = fw.backend_kind() == Backend::vulkan ? &device_for(fw.device) : nullptr;
  AmbiguitySettings as;
  as.min_separation_mm = separation_mm;
  std::vector<Ambiguity> out(positions.size());
  {
    py::gil_scoped_release release;
    std::unique_lock<std::mutex> lock;
    if (device) lock = std::unique_lock<std::mutex>(device->busy);
    auto model = make_scene_model(scene, refine_trace_settings(fw.binning), device ? device->ctx.get() : nullptr);
    for (size_t i = 0; i < positions.size(); ++i) out[i] = ambiguity(*model, scene, positions[i], ph(py::ssize_t(i)), as);
  }
  const size_t n = out.size();
  auto column = [&](auto get) {
    std::vector<double> v(n);
    for (size_t i = 0; i < n; ++i) v[i] = get(out[i]);
    return to_numpy(std::move(v), {py::ssize_t(n)});
  };
  py::dict d;
  d["alias_kl"] = column([](const Ambiguity& a) { return a.kl; });
  d["alias_x_mm"] = column([](const Ambiguity& a) { return a.impostor_mm.x; });
  d["alias_y_mm"] = column([](const Ambiguity& a) { return a.impostor_mm.y; });
  d["alias_depth_mm"] = column([](const Ambiguity& a) { return a.impostor_mm.z; });
  d["p_confusion"] = column([](const Ambiguity& a) { return a.p_confusion; });
  return d;
}

// (height, width, 4) float32: b, db/dx, db/dy, db/ddepth per pixel; and the pixel pitch.
py::tuple psf(const Scene& scene_in, double x_mm, double y_mm, double depth_mm, const py::dict& forward,
              bool derivatives) {
  const Forward fw = forward_from(forward);
  Scene scene = scene_in;
  override_lens_model(scene, fw.lens_model, "lens_model");
  require_in_front(scene, depth_mm, "depth_mm");
  const TraceSettings t = fw.settings(scene);
  const AnalysisGrid grid = AnalysisGrid::of(scene.optics, t.binning);
  MemoryEstimate memory("psf at binning " + std::to_string(t.binning) + " (" + std::to_string(grid.width) + " x " +
                        std::to_string(grid.height) + " px)");
  const Backend backend = fw.backend_kind();
  Device* device = backend == Backend::vulkan ? &device_for(fw.device) : nullptr;
  PixelImage img;
  {
    py::gil_scoped_release release;
    std::unique_lock<std::mutex> lock;
    if (device) lock = std::unique_lock<std::mutex>(device->busy);
    img = render_psf(scene, t, {x_mm, y_mm, depth_mm}, derivatives, backend, device ? device->ctx.get() : nullptr, memory);
  }
  const double pixel_mm = img.pixel_mm;
  return py::make_tuple(to_numpy(std::move(img.data), {img.height, img.width, 4}), pixel_mm);
}


// --- events -----------------------------------------------------------------

py::dict header_dict(const EventFileHeader& h) {
  py::dict d;
  d["sensor_width_px"] = h.sensor_width_px;
  d["sensor_height_px"] = h.sensor_height_px;
  d["pixel_um"] = h.pixel_um;
  d["binning"] = h.binning;
  d["grid_width"] = h.grid_width();
  d["grid_height"] = h.grid_height();
  d["scene"] = h.scene;
  d["truth"] = std::string(to_string(h.truth));
  d["seed"] = h.seed;
  d["provenance"] = h.provenance;
  d["event_count"] = h.event_count;
  return d;
}

// (id, vertices (V, 5): x_mm, y_mm, depth_mm, alpha, sensor_fraction, clicks (uint32)).
py::tuple event_tuple(Event&& e) {
  std::vector<double> v;
  for (const auto& x : e.vertices) v.insert(v.end(), {x.x_mm, x.y_mm, x.depth_mm, x.alpha, x.sensor_fraction});
  const py::ssize_t n = py::ssize_t(e.vertices.size()), c = py::ssize_t(e.clicks.size());
  return py::make_tuple(e.id, to_numpy(std::move(v), {n, 5}), to_numpy(std::move(e.clicks), {c}));
}

py::object next_event(EventReader& r) {
  Event e;
  bool more;
  {
    py::gil_scoped_release release;
    more = r.next(e);
  }
  if (!more) return py::none();
  return event_tuple(std::move(e));
}

SimulationRun simulation_run(const py::array_t<double, py::array::c_style>& vertices, double jitter_mm, uint64_t seed) {
  if (vertices.ndim() != 2 || vertices.shape(1) != 4 || vertices.shape(0) < 1)
    throw std::invalid_argument("vertices: a (K, 4) array of x_mm, y_mm, depth_mm, alpha (expected photons), K >= 1");
  SimulationRun run;
  auto v = vertices.unchecked<2>();
  for (py::ssize_t k = 0; k < v.shape(0); ++k) run.vertices.push_back({v(k, 0), v(k, 1), v(k, 2), v(k, 3), 0});
  run.jitter_mm = jitter_mm;
  run.seed = seed;
  return run;
}

// Events of `scene` from the forward model (or a dictionary's PSFs, the
// paper's protocol), to a file (out) or returned as a list of event tuples.
py::object simulate(const Scene& scene, const py::array_t<double, py::array::c_style>& vertices, uint64_t events,
                    uint64_t seed, double jitter_mm, const py::dict& forward, const std::string& truth_name,
                    const std::string& dictionary, const std::string& out, const py::object& progress) {
  const SimulationRun run = simulation_run(vertices, jitter_mm, seed);
  check_simulation(scene, run, "vertices", "jitter_mm");
  if (!out.empty()) check_writable(out);
  const Forward fw = forward_from(forward);
  std::optional<DictionaryReader> reader;
  std::unique_ptr<EventTruth> truth;
  Device* device = nullptr;
  if (truth_name == "dictionary") {
    if (dictionary.empty()) throw std::invalid_argument("truth='dictionary' needs dictionary=DIR");
    reader.emplace(dictionary, &scene.optics);
    const int level = fw.binning ? stored_level_of_binning(reader->manifest(), fw.binning, "binning") : 0;
    truth = std::make_unique<DictionaryTruth>(*reader, level);
  } else if (truth_name == "forward") {
    device = &device_for(fw.device);
    py::gil_scoped_release release;
    std::lock_guard<std::mutex> lock(device->busy);
    truth = std::make_unique<ForwardTruth>(*device->ctx, scene, fw.settings(scene));
  } else {
    throw std::invalid_argument("truth '" + truth_name + "': use forward or dictionary");
  }
  const EventFileHeader header = simulation_header(scene, *truth, run);
  std::optional<EventWriter> writer;
  if (!out.empty()) writer.emplace(out, header);
  py::list list;
  Event e;
  for (uint64_t id = 0; id < events; ++id) {
    {
      py::gil_scoped_release release;
      std::unique_lock<std::mutex> lock;
      if (device) lock = std::unique_lock<std::mutex>(device->busy);
      simulate_event(*truth, run, id, e);
      if (writer) writer->write(e);
    }
    if (!writer) list.append(event_tuple(std::move(e)));
    if (!progress.is_none()) progress(id + 1, events);
    if (PyErr_CheckSignals() != 0) throw py::error_already_set();  // Ctrl-C: the writer removes its temporary
  }
  if (!writer) return list;
  writer->close();
  py::dict d = header_dict(header);
  d["event_count"] = writer->events();
  d["bytes"] = writer->bytes();
  return d;
}

// --- dictionaries -------------------------------------------------------------

py::array_t<double> grid_positions(const DictionaryReader& r) {
  const DictionaryGrid& g = r.manifest().grid;
  std::vector<double> v;
  v.reserve(3 * g.size());
  for (size_t i = 0; i < g.size(); ++i) {
    const glm::dvec3 p = g.position(i);
    v.insert(v.end(), {p.x, p.y, p.z});
  }
  return to_numpy(std::move(v), {py::ssize_t(g.size()), 3});
}

py::dict build(const Scene& scene, const std::string& dir, const std::vector<double>& grid_x,
               const std::vector<double>& grid_y, const std::vector<double>& grid_depth, int base_binning,
               unsigned rays, const std::string& splat, unsigned stratification, const std::string& device_request,
               const py::object& progress) {
  DictionaryBuildOptions o;
  if (!grid_x.empty()) o.grid.x_mm = grid_x;
  if (!grid_y.empty()) o.grid.y_mm = grid_y;
  if (!grid_depth.empty()) o.grid.depth_mm = grid_depth;
  o.base_binning = base_binning;
  o.rays_per_lenslet = rays;
  o.splat = splat_from_string(splat);
  o.stratification = stratification;
  check_build_options(dir, scene, o);  // before the device is set up
  Device& device = device_for(device_request);
  DictionaryBuildReport r;
  {
    py::gil_scoped_release release;
    std::lock_guard<std::mutex> lock(device.busy);
    r = build_dictionary(*device.ctx, scene, dir, o, [&](size_t done, size_t total) {
      py::gil_scoped_acquire acquire;
      if (!progress.is_none()) progress(done, total);
      if (PyErr_CheckSignals() != 0) throw py::error_already_set();  // Ctrl-C: the entries so far stay
    });
  }
  py::dict d;
  d["rendered"] = r.rendered;
  d["reused"] = r.reused;
  d["seconds"] = r.seconds;
  d["seconds_per_psf"] = r.seconds_per_psf;
  return d;
}

// --- reconstruction -------------------------------------------------------------

Event event_from(const py::handle& item) {
  auto t = item.cast<py::tuple>();
  if (t.size() != 3) throw std::invalid_argument("events: each event is (id, vertices, clicks), as prism.Event");
  Event e;
  e.id = t[0].cast<uint64_t>();
  if (!t[1].is_none()) {
    auto v = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(t[1]);
    if (!v || (v.size() > 0 && (v.ndim() != 2 || v.shape(1) != 5)))
      throw std::invalid_argument("event " + std::to_string(e.id) + ": vertices must be a (K, 5) array or None");
    for (py::ssize_t k = 0; v.size() > 0 && k < v.shape(0); ++k)
      e.vertices.push_back({v.at(k, 0), v.at(k, 1), v.at(k, 2), v.at(k, 3), v.at(k, 4)});
  }
  auto c = py::array_t<int64_t, py::array::c_style | py::array::forcecast>::ensure(t[2]);
  if (!c || c.ndim() != 1) throw std::invalid_argument("event " + std::to_string(e.id) + ": clicks must be a 1-D array");
  for (py::ssize_t i = 0; i < c.shape(0); ++i) {
    const int64_t x = c.at(i);
    if (x < 0 || x > int64_t(UINT32_MAX))
      throw std::invalid_argument("event " + std::to_string(e.id) + ": click " + std::to_string(i) + " is " +
                                  std::to_string(x) + ", not a pixel index on the click grid");
    e.clicks.push_back(uint32_t(x));
  }
  return e;  // checked against the grid (first_bad_click) once its binning is known
}

SessionOptions session_options(const py::dict& o) {
  SessionOptions s;
  s.backend = o["backend"].cast<std::string>();
  s.precision = o["precision"].cast<std::string>();
  s.model = o["model"].cast<std::string>();
  s.scene = o["scene"].cast<std::string>();
  s.batch = o["batch"].cast<size_t>();
  s.level = o["level"].cast<int>();
  s.budget_mib = o["budget_mib"].cast<double>();
  s.threads = o["threads"].cast<unsigned>();
  s.serial_scans = o["serial_scans"].cast<bool>();
  s.settings.vertices = o["vertices"].cast<int>();
  s.settings.scan_step_px = o["scan_step"].cast<int>();
  s.settings.carry_margin_nll = o["carry_margin"].cast<double>();
  s.settings.tau_mm = o["tau_mm"].cast<double>();
  s.settings.dark_rate = o["dark_rate"].cast<double>();
  s.settings.search_dark_rate = o["search_dark_rate"].cast<double>();
  return s;
}

// The vertices of every event, as the rows of `prism reconstruct`'s CSV in
// columns. `events`: an event file's path (read a batch at a time) or a
// sequence of (id, vertices, clicks) on a grid of `binning` (0: the
// dictionary's base binning).
py::dict reconstruct_events(const std::string& dictionary, const py::object& events, unsigned binning, const py::dict& options,
                     const std::string& device_request, const py::object& progress) {
  const SessionOptions so = session_options(options);
  std::optional<EventReader> file;
  EventFileHeader header;
  std::string events_name;
  std::vector<Event> given;
  if (py::isinstance<py::str>(events)) {
    events_name = events.cast<std::string>();
    file.emplace(events_name);
    header = file->header();
  } else {
    events_name = "the events given";
    for (const auto& item : events) given.push_back(event_from(item));
    const DictionaryManifest m = DictionaryReader(dictionary).manifest();
    header.sensor_width_px = uint32_t(m.scene.optics.sensor_width_px);
    header.sensor_height_px = uint32_t(m.scene.optics.sensor_height_px);
    header.pixel_um = m.scene.optics.pixel_um;
    header.binning = binning ? binning : uint32_t(m.base_binning);
    header.scene = m.scene.name;
    header.event_count = given.size();
    const uint64_t pixels = header.grid_pixels();
    for (const Event& e : given)
      if (const size_t i = first_bad_click(e.clicks, pixels); i < e.clicks.size())
        throw std::invalid_argument(
            "event " + std::to_string(e.id) + ": click " + std::to_string(i) + " (" + std::to_string(e.clicks[i]) +
            (e.clicks[i] >= pixels ? ") lies beyond the " + std::to_string(header.grid_width()) + " x " +
                                         std::to_string(header.grid_height()) + " click grid of binning " +
                                         std::to_string(header.binning)
                                   : ") is not above the one before: clicks must be strictly increasing"));
  }
  // As the command: the device backends and the refinement on the device,
  // or the CPU reference throughout.
  Device* device =
      backend_from_string(so.backend) != ReconstructionBackend::cpu ? &device_for(device_request) : nullptr;
  std::vector<uint64_t> event_id;
  std::vector<int64_t> vertex, clicks;
  std::vector<double> x, y, depth, alpha, nll, cx, cy, cz, c3, pvalue;
  std::vector<uint32_t> flag_bits;
  {
    py::gil_scoped_release release;
    std::unique_lock<std::mutex> lock;
    if (device) lock = std::unique_lock<std::mutex>(device->busy);
    ReconstructionSession session(dictionary, header, events_name, so, device ? device->ctx.get() : nullptr);
    const size_t batch = session.batch_events();
    std::vector<Event> in(file ? batch : 0);
    uint64_t done = 0;
    const uint64_t total = header.event_count;
    auto report = [&](uint64_t n) {
      py::gil_scoped_acquire acquire;
      if (!progress.is_none()) progress(n, total);
      if (PyErr_CheckSignals() != 0) throw py::error_already_set();
    };
    for (size_t first = 0;;) {
      std::span<const Event> part;
      if (file) {
        size_t n = 0;
        while (n < batch && file->next(in[n])) ++n;
        part = std::span<const Event>(in.data(), n);
      } else {
        part = std::span<const Event>(given).subspan(first, std::min(batch, given.size() - first));
        first += part.size();
      }
      if (part.empty()) break;
      auto out = session.run(part, [&](size_t i) { report(done + i + 1); });
      for (size_t i = 0; i < part.size(); ++i)
        for (size_t k = 0; k < out[i].size(); ++k) {
          const ReconstructedVertex& v = out[i][k];
          event_id.push_back(part[i].id);
          vertex.push_back(int64_t(k));
          x.push_back(v.x_mm), y.push_back(v.y_mm), depth.push_back(v.depth_mm), alpha.push_back(v.alpha);
          nll.push_back(v.nll), clicks.push_back(v.clicks);
          cx.push_back(v.crlb_x_mm), cy.push_back(v.crlb_y_mm), cz.push_back(v.crlb_z_mm), c3.push_back(v.crlb_3d_mm);
          pvalue.push_back(v.fit_pvalue);
          flag_bits.push_back(v.flags);
        }
      done += part.size();
      report(done);
    }
  }
  py::list flags;
  for (uint32_t f : flag_bits) flags.append(flags_to_string(f));
  const py::ssize_t n = py::ssize_t(x.size());
  py::dict d;
  d["event"] = to_numpy(std::move(event_id), {n});
  d["vertex"] = to_numpy(std::move(vertex), {n});
  d["x_mm"] = to_numpy(std::move(x), {n});
  d["y_mm"] = to_numpy(std::move(y), {n});
  d["depth_mm"] = to_numpy(std::move(depth), {n});
  d["alpha"] = to_numpy(std::move(alpha), {n});
  d["nll"] = to_numpy(std::move(nll), {n});
  d["clicks"] = to_numpy(std::move(clicks), {n});
  d["flags"] = flags;
  d["crlb_x_mm"] = to_numpy(std::move(cx), {n});
  d["crlb_y_mm"] = to_numpy(std::move(cy), {n});
  d["crlb_z_mm"] = to_numpy(std::move(cz), {n});
  d["crlb_3d_mm"] = to_numpy(std::move(c3), {n});
  d["fit_pvalue"] = to_numpy(std::move(pvalue), {n});
  return d;
}

py::array_t<float> read_exr(const std::string& path, const std::string& channel) {
  int width = 0, height = 0;
  std::vector<float> v;
  {
    py::gil_scoped_release release;
    v = read_exr_channel(path, channel, width, height);
  }
  return to_numpy(std::move(v), {height, width});
}

}  // namespace

}  // namespace prism::python

PYBIND11_MODULE(_core, m) {
  using namespace prism;
  using namespace prism::python;
  m.doc() = "PRISM engine bindings (compiled half; use the package `prism`)";

  py::register_exception<SceneError>(m, "SceneError", PyExc_ValueError);
  py::register_exception<ResourceError>(m, "ResourceError", PyExc_MemoryError);
  py::register_exception<vk::Error>(m, "DeviceError", PyExc_RuntimeError);

  py::class_<Scene>(m, "Scene")
      .def_readonly("name", &Scene::name)
      .def_readonly("photons_emitted", &Scene::photons_emitted)
      .def_property_readonly("lens_model", [](const Scene& s) { return std::string(to_string(s.optics.lens_model)); })
      .def_property_readonly("lenslet_count", [](const Scene& s) { return s.optics.lenslets.size(); })
      .def("json_text", [](const Scene& s) { return to_json(s).dump(); });
  m.def("load_scene", &load_scene);
  m.def("scene_from_json_text", &scene_from_json_text);
  m.def("builtin_scene_names", &builtin_scene_names);
  m.def("list_devices", &vk::Context::list_devices);
  m.def("describe_device", [](const std::string& request) { return device_for(request).ctx->describe(); });
  m.def("validation_messages", &validation_messages);
  // The contexts go while the interpreter and the Vulkan driver are whole:
  // left to static destructors at exit, they outlived lavapipe's own and
  // crashed the process after a clean run.
  m.def("release_devices", [] { devices().clear(); });
  py::module_::import("atexit").attr("register")(m.attr("release_devices"));
  m.def("crlb", &crlb);
  m.def("ambiguity", &ambiguity_at);
  m.def("psf", &psf);
  m.def("read_exr", &read_exr);

  py::class_<EventReader>(m, "EventReader")
      .def(py::init<std::string>())
      .def("header", [](const EventReader& r) { return header_dict(r.header()); })
      .def("next", &next_event)
      .def("offset", &EventReader::offset);
  m.def("simulate", &simulate);

  py::class_<DictionaryReader>(m, "DictionaryReader")
      .def(py::init([](const std::string& dir) { return std::make_unique<DictionaryReader>(dir); }))
      .def("manifest_json", [](const DictionaryReader& r) { return r.manifest().to_json().dump(); })
      .def("scene", [](const DictionaryReader& r) { return r.manifest().scene; })
      .def("size", [](const DictionaryReader& r) { return r.manifest().grid.size(); })
      .def("present", &DictionaryReader::present)
      .def("has", &DictionaryReader::has)
      .def("path_of", &DictionaryReader::path_of)
      .def("positions", &grid_positions)
      .def("grid", [](const DictionaryReader& r) {
        const auto& g = r.manifest().grid;
        return py::make_tuple(g.x_mm, g.y_mm, g.depth_mm);
      })
      .def("levels", [](const DictionaryReader& r) { return r.manifest().levels; })
      .def("base_binning", [](const DictionaryReader& r) { return r.manifest().base_binning; })
      .def("pixel_mm", [](const DictionaryReader& r, int level) { return r.manifest().pixel_mm(level); })
      .def("level_shape", [](const DictionaryReader& r, int level) {
        return py::make_tuple(r.manifest().level_height(level), r.manifest().level_width(level));
      })
      .def("read_level", [](const DictionaryReader& r, size_t i, int level) {
        PsfLevel l;
        {
          py::gil_scoped_release release;
          l = r.read_level(i, level);
        }
        return to_numpy(std::move(l.p), {l.height, l.width});
      })
      .def("read_window", [](const DictionaryReader& r, size_t i, int level, int x0, int y0, int width, int height) {
        PsfWindow w;
        {
          py::gil_scoped_release release;
          w = r.read_window(i, level, x0, y0, width, height);
        }
        const int wx = w.x0, wy = w.y0;
        return py::make_tuple(to_numpy(std::move(w.p), {w.height, w.width}), wx, wy);
      });
  m.def("build_dictionary", &build);
  m.def("reconstruct", &reconstruct_events);
  m.def("reconstruction_defaults", [] {
    const SessionOptions s;
    py::dict d;
    d["batch"] = s.batch;
    d["carry_margin"] = s.settings.carry_margin_nll;
    d["tau_mm"] = s.settings.tau_mm;
    d["dark_rate"] = s.settings.dark_rate;
    d["search_dark_rate"] = s.settings.search_dark_rate;
    return d;
  });
  m.def("set_max_memory", [](const std::string& text) {
    set_memory_limit_bytes(parse_memory_size(text, "max_memory"));
  });
  m.def("max_memory_bytes", &memory_limit_bytes);
  m.attr("analysis_binning") = defaults::analysis_binning;
  m.attr("crlb_convergence_tol") = defaults::crlb_convergence_tol;
  m.attr("min_separation_mm") = AmbiguitySettings{}.min_separation_mm;
  m.attr("max_rays_converge") = 1u << 20;
}
