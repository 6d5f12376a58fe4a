// Dictionary PSF files (OpenEXR, host/dictionary/store.h) as the store and
// the search's tile reads take them: a one-entry dictionary of a 64 x 48 px
// sensor whose only file is the input.
#include <optional>

#include "fuzz/fuzz.h"
#include "fuzz/tiny_dictionary.h"


namespace prism::fuzz {

void psf_exr(const uint8_t* data, size_t size) {
  static const prism::DictionaryManifest m = tiny_manifest();
  static const std::filesystem::path dir = [] {
    const auto d = prism::fuzz::scratch() / "dictionary";
    std::filesystem::create_directories(d / "psf");
    std::ofstream(d / "manifest.json") << m.to_json().dump();
    return d;
  }();
  prism::fuzz::write_file(dir / m.file_of(0), data, size);
  std::optional<prism::DictionaryReader> reader;
  try {
    reader.emplace(dir.string());
  } catch (const std::runtime_error&) {
    return;
  }
  const prism::DictionaryReader& r = *reader;
  // Every tile as the search reads them (OpenEXR's C core and exr_zip's
  // decode), then through OpenEXR's C++ reader: each its own try, so that
  // one's refusal does not hide the other from the input.
  try {
    prism::PsfFile f(r, 0);
    std::vector<uint16_t> tile(size_t(m.tile_px) * size_t(m.tile_px));
    for (int l = 0; l < m.levels; ++l)
      for (int ty = 0; ty * m.tile_px < m.level_height(l); ++ty)
        for (int tx = 0; tx * m.tile_px < m.level_width(l); ++tx) f.read_tile(l, tx, ty, tile);
  } catch (const std::runtime_error&) {
  }
  try {
    for (int l = 0; l < m.levels; ++l) (void)r.read_level(0, l);
    (void)r.read_window(0, 0, 8, 8, 16, 16);
    (void)r.photons_on_sensor(0);
  } catch (const std::runtime_error&) {
  }
}

}  // namespace prism::fuzz

PRISM_FUZZ_MAIN(psf_exr)
