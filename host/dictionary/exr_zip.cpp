#include "host/dictionary/exr_zip.h"

#include <libdeflate.h>

#include <memory>
#include <stdexcept>
#include <vector>

namespace prism::exr_zip {

namespace {

// One decompressor per thread: it holds ~32 KiB of tables and is not shared.
libdeflate_decompressor& decompressor() {
  struct Free {
    void operator()(libdeflate_decompressor* d) const { libdeflate_free_decompressor(d); }
  };
  thread_local std::unique_ptr<libdeflate_decompressor, Free> d(libdeflate_alloc_decompressor());
  if (!d) throw std::bad_alloc();
  return *d;
}

}  // namespace

void unfilter(std::span<uint8_t> t, std::span<uint8_t> out) {
  if (out.size() != t.size()) throw std::invalid_argument("exr_zip::unfilter: buffers of different sizes");
  const size_t n = t.size();
  for (size_t i = 1; i < n; ++i) t[i] = uint8_t(t[i - 1] + t[i] - 128);
  const uint8_t* even = t.data();
  const uint8_t* odd = t.data() + (n + 1) / 2;
  for (size_t i = 0; i < n / 2; ++i) out[2 * i] = even[i], out[2 * i + 1] = odd[i];
  if (n % 2) out[n - 1] = even[n / 2];
}

void decode(std::span<const uint8_t> packed, std::span<uint8_t> out, const std::string& what) {
  if (packed.size() == out.size()) {  // stored as it is
    std::copy(packed.begin(), packed.end(), out.begin());
    return;
  }
  thread_local std::vector<uint8_t> inflated;
  inflated.resize(out.size());
  size_t got = 0;
  const libdeflate_result r =
      libdeflate_zlib_decompress(&decompressor(), packed.data(), packed.size(), inflated.data(), inflated.size(), &got);
  if (r != LIBDEFLATE_SUCCESS || got != out.size())
    throw std::runtime_error(what + ": a ZIP chunk of " + std::to_string(packed.size()) + " bytes does not inflate to " +
                             std::to_string(out.size()));
  unfilter(inflated, out);
}

}  // namespace prism::exr_zip
