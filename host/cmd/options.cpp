#include "host/cmd/options.h"

#include <cmath>
#include <cstdlib>
#include <sstream>
#include <tuple>

#include "host/util/format.h"
#include "host/util/memory.h"

namespace prism::cmd {

void ForwardOptions::add_to(CLI::App* app, unsigned default_binning) {
  binning = default_binning;
  app->add_option("--device", device, device_help);
  app->add_option("--rays", rays,
                  std::string("rays (footprint: aperture cells) per 3 mm lenslet, ") + rays_rounding +
                      "; other lens sizes get the same per mm^2; 0: the converged default, " +
                      std::to_string(defaults::rays_per_lenslet) + " footprint cells or " +
                      std::to_string(defaults::rays_per_lenslet_point) + " point rays (docs/model.md \"Convergence\")")
      ->capture_default_str()->check(CLI::Range(0u, 1u << 24));
  app->add_option("--binning", binning, "analyse on B x B binned sensor pixels")
      ->capture_default_str()->check(CLI::Range(1u, 1024u));
  app->add_option("--lens-model", lens_model, "override the scene's lens model")->check(CLI::IsMember({"thin", "real"}));
  app->add_option("--photons", photons, "photons emitted by the source (default: the scene's, 6280 for built-ins)")
      ->check(positive_number)
      ->check(at_most(defaults::max_photons_emitted, "photons"));
  app->add_option("--backend", backend, "vulkan (kernels on the device) or cpu (double-precision reference)")
      ->capture_default_str()->check(CLI::IsMember({"vulkan", "cpu"}));
  app->add_option("--fisher-estimator", estimator,
                  "split: pair two independent halves of the rays (no noise bias in grad b grad b^T); "
                  "naive: plug-in estimate (biased upward by point rays' sampling noise; exact for footprints); "
                  "auto: split for --splat point, naive for footprint")
      ->capture_default_str()->check(CLI::IsMember({"auto", "split", "naive"}));
  splat.add_to(app);
}

void SplatOptions::add_to(CLI::App* app, const std::string& stratification_use) {
  app->add_option("--splat", splat,
                  "footprint: each aperture cell's image gives box pixels their exact area (the sensor's pixels); "
                  "point: each ray splatted bilinearly to the 4 nearest pixel centres (the paper's way)")
      ->capture_default_str()->check(CLI::IsMember({"footprint", "point"}));
  app->add_option("--stratification", stratification,
                  "0: the default strata; another number: another stratification of the same apertures (other jitter "
                  "for point rays, cells turned for footprints)" +
                      (stratification_use.empty() ? "" : "; " + stratification_use))
      ->capture_default_str();
}

void SplatOptions::apply(TraceSettings& t) const {
  t.splat = kind();
  t.stratification = stratification;
}

TraceSettings ForwardOptions::settings(const Scene& scene) const {
  return trace_settings(scene, binning, rays, photons, splat.kind(), splat.stratification, estimator);
}

void ForwardOptions::apply(Scene& scene) const { override_lens_model(scene, lens_model, "--lens-model"); }

namespace {

std::vector<std::string> split(const std::string& s, char sep) {
  std::vector<std::string> parts;
  std::stringstream ss(s);
  std::string part;
  while (std::getline(ss, part, sep)) parts.push_back(part);
  if (!s.empty() && s.back() == sep) parts.emplace_back();  // "1,2," ends in an empty item
  return parts;
}

// One finite number, all of `s`; else an error naming the option and `form`.
double number_in(const std::string& s, const std::string& option, const std::string& form) {
  try {
    size_t used = 0;
    double v = std::stod(s, &used);
    if (used != s.size() || !std::isfinite(v)) throw std::invalid_argument(s);
    return v;
  } catch (const std::exception&) {
    throw std::runtime_error(option + ": '" + s + "' is not a number (" + form + ")");
  }
}

}  // namespace

std::vector<double> parse_list(const std::string& text, const std::string& option) {
  auto num = [&](const std::string& s) {
    return number_in(s, option, "use A,B,C, FIRST:LAST:STEP or both, e.g. 0:10:1,12.5,15:50:5");
  };
  std::vector<double> out;
  for (const std::string& item : split(text, ',')) {
    if (item.find(':') == std::string::npos) {
      out.push_back(num(item));
      continue;
    }
    auto p = split(item, ':');
    if (p.size() != 3) throw std::runtime_error(option + ": a range is FIRST:LAST:STEP, got '" + item + "'");
    double a = num(p[0]), b = num(p[1]), step = num(p[2]);
    if (!(step > 0) || b < a) throw std::runtime_error(option + ": need FIRST <= LAST and STEP > 0 in '" + item + "'");
    const double count = std::floor((b - a) / step + 1e-9) + 1;  // counted before anything is allocated
    if (!(double(out.size()) + count <= double(max_list_values)))
      throw std::runtime_error(option + ": '" + item + "' gives " +
                               (std::isfinite(count) ? format_number(count) : std::string("too many")) +
                               " values; at most " +
                               std::to_string(max_list_values) + " in one list: choose a larger STEP");
    for (size_t i = 0; i < size_t(count); ++i) out.push_back(a + double(i) * step);
  }
  if (out.size() > max_list_values)
    throw std::runtime_error(option + ": " + std::to_string(out.size()) + " values; at most " +
                             std::to_string(max_list_values) + " in one list");
  if (out.empty()) throw std::runtime_error(option + ": empty list");
  return out;
}

std::string format_list(std::span<const double> values) {
  std::string out;
  for (double v : values) {
    char b[32];
    std::snprintf(b, sizeof b, "%s%g", out.empty() ? "" : ",", v);
    out += b;
  }
  return out;
}

namespace {
// `text` as a finite number at least (or above) zero; "" when it is one.
std::string sign_check(const std::string& text, bool zero_allowed) {
  char* end = nullptr;
  const double v = std::strtod(text.c_str(), &end);
  if (end == text.c_str() || *end != '\0') return "'" + text + "' is not a number";
  if (!std::isfinite(v)) return "'" + text + "' is not a finite number";
  if (zero_allowed ? v < 0 : v <= 0) return text + (zero_allowed ? " must be >= 0" : " must be > 0");
  return "";
}
}  // namespace

// No names: the help's type column stays as CLI11 writes it.
const CLI::Validator positive_number([](std::string& text) { return sign_check(text, false); }, "");
const CLI::Validator non_negative_number([](std::string& text) { return sign_check(text, true); }, "");

CLI::Validator at_most(double limit, const std::string& unit) {
  return CLI::Validator(
      [limit, unit](std::string& text) -> std::string {
        const double v = std::strtod(text.c_str(), nullptr);
        return v <= limit ? "" : "'" + text + "' is more than " + format_number(limit) + " " + unit;
      },
      "");
}

void require_finite_numbers(CLI::App& app) {
  // No name: the help's type column stays as CLI11 writes it.
  static const CLI::Validator finite(
      [](std::string& text) -> std::string {
        char* end = nullptr;
        const double v = std::strtod(text.c_str(), &end);
        if (end != text.c_str() && !std::isfinite(v)) return "'" + text + "' is not a finite number";
        return "";  // anything else: CLI11's own conversion judges it
      },
      "");
  // CLI11 reads "-3" into an unsigned option as 2^64 - 3 (simulate --events
  // -3 set out to write that many events).
  static const CLI::Validator not_negative(
      [](std::string& text) -> std::string {
        const size_t first = text.find_first_not_of(" \t");
        if (first != std::string::npos && text[first] == '-') return "'" + text + "' is negative; give a whole number >= 0";
        return "";
      },
      "");
  for (CLI::Option* o : app.get_options()) {
    const std::string type = o->get_type_name();
    if (type.find("FLOAT") != std::string::npos) o->check(finite);
    if (type.find("UINT") != std::string::npos) o->check(not_negative);
  }
  for (CLI::App* sub : app.get_subcommands({})) require_finite_numbers(*sub);
}

std::optional<std::string> missing_command(const CLI::App& app, const CLI::ParseError& error) {
  const CLI::App* at = &app;
  std::string path = "prism";
  while (!at->get_subcommands().empty()) {  // the commands the parse got to
    at = at->get_subcommands().front();
    path += " " + at->get_name();
  }
  // A command's own options and words: CLI11's errors say it well.
  if (at->get_subcommands({}).empty() || !dynamic_cast<const CLI::RequiredError*>(&error)) return std::nullopt;
  std::vector<std::string> names;
  for (const CLI::App* s : at->get_subcommands({})) names.push_back(s->get_name());
  const std::string choose = join(names) + " (" + path + " --help says what each does)";
  const auto rest = at->remaining();
  if (rest.empty()) return path + " needs a command: " + choose;
  return "'" + rest.front() + "' is not a command of " + path + "; choose from " + choose;
}

void add_memory_limit(CLI::App& command) {
  // Checked as it is read, so that a bad size is a usage error naming the option.
  command
      .add_option_function<std::string>(
          "--max-memory", [](const std::string& text) { set_memory_limit_bytes(parse_memory_size(text, "--max-memory")); },
          "memory this command may plan to use, as bytes or with K, M, G, T (powers of 1024): 512M, 8G; work "
          "estimated beyond it is refused before it starts. Default " +
              format_bytes(double(memory_limit_bytes())) + ", " + memory_limit_origin())
      ->type_name("SIZE")
      ->envname("PRISM_MAX_MEMORY")
      ->check(CLI::Validator(
          [](std::string& text) -> std::string {
            try {
              parse_memory_size(text, "--max-memory");
            } catch (const std::invalid_argument& e) {
              return std::string(e.what()).substr(std::string("--max-memory: ").size());  // CLI11 names the option
            }
            return "";
          },
          ""));
}

std::vector<double> parse_numbers(const std::string& text, const std::string& option, const std::string& form,
                                  size_t min_count, size_t max_count) {
  const auto items = split(text, ',');
  if (items.size() < min_count || items.size() > max_count)
    throw std::runtime_error(option + ": expected " + form + ", got '" + text + "'");
  std::vector<double> out;
  for (const auto& item : items) out.push_back(number_in(item, option, "expected " + form + ", got '" + text + "'"));
  return out;
}

glm::dvec3 parse_point(const std::string& text, const std::string& option) {
  auto v = parse_numbers(text, option, "X,Y,DEPTH in mm", 3, 3);
  return {v[0], v[1], v[2]};
}

void add_always_scan_options(CLI::App* c, double& below_mm, int& below_clicks) {
  c->add_option("--always-scan-below-mm", below_mm,
                "the refinement's lattice scan (sites blurred) and continuation for every estimate shallower than this, "
                "whatever its fit (engine/defaults.h says why; 0: none by depth)")
      ->capture_default_str()
      ->check(non_negative_number);
  c->add_option("--always-scan-below-clicks", below_clicks,
                "the same for every event with fewer clicks: with few clicks the hard edges of the images hold a "
                "fit at any depth (at 20 photons 5 of 80 unifocal-f15 events; at 100 photons the scan at every "
                "depth cost 3x the renders and moved no estimate by a CRLB; 0: none by clicks)")
      ->capture_default_str()
      ->check(non_negative_number);
}

void add_refine_level_option(CLI::App* c, int& refine_level) {
  c->add_option("--refine-level", refine_level,
                "dictionary level whose pixels the refinement renders on; where coarser than the clicks', the clicks "
                "are binned to it for the refinement's starts, aliases and scans, and its answer is then fitted again "
                "on the clicks' own pixels (default: the finest level of at least 110 um pixels, or the clicks' own "
                "where coarser; at 6.9 um a render costs 50-100x one at 110 um)")
      ->check(CLI::NonNegativeNumber);
}

}  // namespace prism::cmd
