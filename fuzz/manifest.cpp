// Dictionary manifests (host/dictionary/store.h): JSON a user may edit.
#include "fuzz/fuzz.h"
#include "host/dictionary/store.h"

namespace prism::fuzz {

void manifest(const uint8_t* data, size_t size) {
  auto j = prism::fuzz::json_of(data, size);
  if (!j) return;
  try {
    const prism::DictionaryManifest m = prism::DictionaryManifest::from_json(*j, "manifest.json");
    // What a reader then computes from it must be safe too.
    for (int l = 0; l < m.levels; ++l) (void)m.level_grid(l);
    if (m.grid.size() > 0) (void)m.file_of(m.grid.size() - 1);
  } catch (const std::runtime_error&) {
  }
}

}  // namespace prism::fuzz

PRISM_FUZZ_MAIN(manifest)
