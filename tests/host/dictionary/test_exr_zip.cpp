// host/dictionary/exr_zip.h against OpenEXR's own decoder: the tiles
// PsfFile::read_tile decodes with libdeflate must be OpenEXR's bit for bit.
#include <Imath/half.h>
#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfTiledInputFile.h>
#include <OpenEXR/ImfTiledOutputFile.h>
#include <OpenEXR/openexr.h>

#include <cstring>
#include <random>
#include <vector>

#include "host/dictionary/exr_zip.h"
#include "support.h"

#include <doctest/doctest.h>

namespace {

// A mip-mapped half image whose tiles span what ZIP meets: noise (which does
// not deflate smaller, so its tiles are stored as they are), zeros, a smooth
// ramp, and partial tiles on the right and bottom edges.
std::string write_test_image(int width, int height, int tile) {
  const std::string path = (prism::test::scratch_dir() / "zip.exr").string();
  Imf::Header header(width, height);
  header.channels().insert("Y", Imf::Channel(Imf::HALF));
  header.setTileDescription(Imf::TileDescription(tile, tile, Imf::MIPMAP_LEVELS, Imf::ROUND_UP));
  header.compression() = Imf::ZIP_COMPRESSION;
  Imf::TiledOutputFile out(path.c_str(), header);
  std::mt19937 rng(5);
  for (int l = 0; l < out.numLevels(); ++l) {
    const int w = out.levelWidth(l), h = out.levelHeight(l);
    std::vector<half> px(size_t(w) * h);
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        half v;
        if (x < w / 3)
          do v.setBits(uint16_t(rng())); while (!v.isFinite());
        else if (x < 2 * w / 3)
          v = 0.0f;
        else
          v = float(x + 3 * y) / float(w + 3 * h);
        px[size_t(y) * w + x] = v;
      }
    Imf::FrameBuffer fb;
    fb.insert("Y", Imf::Slice(Imf::HALF, (char*)px.data(), sizeof(half), sizeof(half) * size_t(w)));
    out.setFrameBuffer(fb);
    out.writeTiles(0, out.numXTiles(l) - 1, 0, out.numYTiles(l) - 1, l);
  }
  return path;
}

}  // namespace

TEST_CASE("libdeflate decodes OpenEXR's ZIP tiles bit for bit as OpenEXR does, tiles stored as they are included") {
  const int tile = 32;
  const std::string path = write_test_image(150, 101, tile);
  Imf::TiledInputFile ref(path.c_str());
  exr_context_t core = nullptr;
  exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
  REQUIRE(exr_start_read(&core, path.c_str(), &init) == EXR_ERR_SUCCESS);
  int stored = 0, deflated = 0, partial = 0;
  for (int l = 0; l < ref.numLevels(); ++l)
    for (int ty = 0; ty < ref.numYTiles(l); ++ty)
      for (int tx = 0; tx < ref.numXTiles(l); ++tx) {
        CAPTURE(l);
        CAPTURE(tx);
        CAPTURE(ty);
        std::vector<half> want(size_t(tile) * tile);
        Imf::FrameBuffer fb;
        fb.insert("Y", Imf::Slice(Imf::HALF, (char*)(want.data() - tx * tile - size_t(ty) * tile * tile), sizeof(half),
                                  sizeof(half) * tile));
        ref.setFrameBuffer(fb);
        ref.readTile(tx, ty, l, l);
        exr_chunk_info_t chunk;
        REQUIRE(exr_read_tile_chunk_info(core, 0, tx, ty, l, l, &chunk) == EXR_ERR_SUCCESS);
        REQUIRE(chunk.compression == EXR_COMPRESSION_ZIP);
        std::vector<uint8_t> packed(chunk.packed_size), got(chunk.unpacked_size);
        REQUIRE(exr_read_chunk(core, 0, &chunk, packed.data()) == EXR_ERR_SUCCESS);
        prism::exr_zip::decode(packed, got, path);
        (chunk.packed_size == chunk.unpacked_size ? stored : deflated)++;
        partial += chunk.width < tile || chunk.height < tile;
        bool same = true;
        for (int y = 0; y < chunk.height; ++y)
          same = same && std::memcmp(got.data() + size_t(y) * chunk.width * 2, want.data() + size_t(y) * tile,
                                     size_t(chunk.width) * 2) == 0;
        CHECK(same);
      }
  exr_finish(&core);
  INFO("tiles stored as they are: " << stored << ", deflated: " << deflated << ", partial: " << partial);
  CHECK(stored > 0);  // both of decode()'s paths ran
  CHECK(deflated > 0);
  CHECK(partial > 0);
}

TEST_CASE("exr_zip: the filter undone on odd and even sizes as its definition says; bad data named") {
  for (size_t n : {size_t(1), size_t(2), size_t(7), size_t(64)}) {
    CAPTURE(n);
    std::vector<uint8_t> in(n), out(n);
    for (size_t i = 0; i < n; ++i) in[i] = uint8_t(37 * i + 11);
    // The definition, step by step: running sums of (byte - 128), then the
    // two halves interleaved.
    std::vector<uint8_t> sums(n), want(n);
    int acc = 0;
    for (size_t i = 0; i < n; ++i) {
      acc = i == 0 ? in[0] : acc + int(in[i]) - 128;
      sums[i] = uint8_t(acc);
    }
    for (size_t i = 0; i < n; ++i) want[i] = i % 2 == 0 ? sums[i / 2] : sums[(n + 1) / 2 + i / 2];
    prism::exr_zip::unfilter(in, out);
    CHECK(out == want);
  }
  std::vector<uint8_t> junk{0x78, 0x9c, 1, 2, 3}, out(64);
  CHECK_THROWS_WITH_AS(prism::exr_zip::decode(junk, out, "psf/00007.exr"),
                       doctest::Contains("psf/00007.exr: a ZIP chunk of 5 bytes does not inflate to 64"),
                       std::runtime_error);
}
