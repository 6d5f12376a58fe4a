// OpenEXR's ZIP compression of one chunk, decoded with libdeflate instead of
// OpenEXR's own zlib path: the search's tile reads spend most of their time
// inflating (docs/reconstruction.md "Tile reads with libdeflate"), and libdeflate inflates a
// 64 x 64 half tile about twice as fast. PsfFile::read_tile uses it; OpenEXR
// stays the reference (tests/host/dictionary/test_exr_zip.cpp compares the
// two on every tile).
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>

namespace prism::exr_zip {

// A chunk stored with ZIP (or ZIPS) compression: `packed` as in the file,
// `out` its pixel bytes as OpenEXR lays them out (per row, per channel in
// name order, little-endian). A chunk whose deflated form would not be
// smaller is stored as it is (packed.size() == out.size()), which OpenEXR
// tells apart by that size alone. Throws std::runtime_error naming `what`
// on data that does not inflate to exactly out.size() bytes.
void decode(std::span<const uint8_t> packed, std::span<uint8_t> out, const std::string& what);

// The filter that ZIP compression applied before deflating, undone: the
// bytes are deltas (+128) of their predecessors, and the first half of the
// buffer holds the even bytes, the second half the odd ones. `inflated`
// is overwritten with the running sums.
void unfilter(std::span<uint8_t> inflated, std::span<uint8_t> out);

}  // namespace prism::exr_zip
