// Pure parts of hw/: GenCP, leader and trailer parsers (bounded seeded fuzz),
// pixel unpacking, stream layout, exposure spacing, GenICam over memory.
#define DOCTEST_CONFIG_IMPLEMENT_WITH_MAIN
#include <doctest/doctest.h>

#include <map>
#include <random>

#include "hw/capture.h"
#include "hw/gencp.h"
#include "hw/genicam.h"
#include "hw/pixels.h"
#include "hw/stream.h"
#include "hw/u3v_regs.h"

using namespace prism::hw;

namespace {

Bytes valid_ack() {
  Bytes a;
  put_le(a, u3v::kCommandPrefix, 4);
  put_le(a, 0, 2);
  put_le(a, u3v::kReadMemAck, 2);
  put_le(a, 4, 2);
  put_le(a, 7, 2);
  put_le(a, 0xDEADBEEF, 4);
  return a;
}
Bytes valid_leader() {
  Bytes b(u3v::kImageLeaderSize, 0);
  set_le(b, 0, u3v::kLeaderMagic, 4);
  set_le(b, 6, b.size(), 2);
  set_le(b, 8, 42, 8);
  set_le(b, 18, u3v::kPayloadImage, 2);
  set_le(b, 28, kMono16, 4);
  set_le(b, 32, 4, 4);
  set_le(b, 36, 3, 4);
  return b;
}
Bytes valid_trailer() {
  Bytes b(u3v::kImageTrailerSize, 0);
  set_le(b, 0, u3v::kTrailerMagic, 4);
  set_le(b, 6, b.size(), 2);
  set_le(b, 8, 42, 8);
  set_le(b, 20, 24, 8);
  set_le(b, 28, 3, 4);
  return b;
}

// Mutates a valid packet `rounds` times (flip, truncate, extend); every
// outcome must be a parse or a rejection with a reason, never a crash.
template <class Parse>
void fuzz(const Bytes& seed_packet, Parse parse, unsigned seed) {
  std::mt19937 rng(seed);
  unsigned accepted = 0, rejected = 0;
  for (int round = 0; round < 20000; ++round) {
    Bytes p = seed_packet;
    int edits = 1 + int(rng() % 4);
    for (int e = 0; e < edits; ++e) {
      switch (rng() % 3) {
        case 0: if (!p.empty()) p[rng() % p.size()] ^= uint8_t(1u << (rng() % 8)); break;
        case 1: p.resize(rng() % (p.size() + 1)); break;
        default: p.push_back(uint8_t(rng()));
      }
    }
    std::string why;
    if (parse(p, why)) ++accepted;
    else {
      ++rejected;
      REQUIRE(!why.empty());
    }
  }
  CHECK(accepted > 0);
  CHECK(rejected > 0);
}

struct MemoryPort : RegisterPort {
  std::map<uint64_t, uint8_t> mem;
  Bytes read(uint64_t a, size_t n) override {
    Bytes b;
    for (size_t i = 0; i < n; ++i) b.push_back(mem[a + i]);
    return b;
  }
  void write(uint64_t a, std::span<const uint8_t> d) override {
    for (size_t i = 0; i < d.size(); ++i) mem[a + i] = d[i];
  }
};

}  // namespace

TEST_CASE("GenCP encode and parse") {
  Bytes r = encode_readmem(9, 0x1234, 16);
  CHECK(r.size() == 24);
  CHECK(get32(r, 0) == u3v::kCommandPrefix);
  CHECK(get16(r, 6) == u3v::kReadMemCmd);
  CHECK(get16(r, 10) == 9);
  CHECK(get64(r, 12) == 0x1234);
  CHECK(get16(r, 22) == 16);
  std::string why;
  auto a = parse_ack(valid_ack(), why);
  REQUIRE(a);
  CHECK(a->request_id == 7);
  CHECK(get32(a->scd, 0) == 0xDEADBEEF);
  Bytes bad = valid_ack();
  bad[0] = 'X';
  CHECK(!parse_ack(bad, why));
  CHECK(why.find("prefix") != std::string::npos);
  CHECK(status_text(0x8003).find("address") != std::string::npos);
}

TEST_CASE("fuzz: GenCP acknowledge parser") {
  fuzz(valid_ack(), [](const Bytes& p, std::string& w) { return parse_ack(p, w).has_value(); }, 1);
}
TEST_CASE("fuzz: leader parser") {
  fuzz(valid_leader(), [](const Bytes& p, std::string& w) { return parse_leader(p, w).has_value(); }, 2);
}
TEST_CASE("fuzz: trailer parser") {
  fuzz(valid_trailer(), [](const Bytes& p, std::string& w) { return parse_trailer(p, w).has_value(); }, 3);
}

TEST_CASE("pixel unpacking") {
  CHECK(unpack(kMono8, Bytes{1, 255}, 2, 1) == std::vector<uint16_t>{1, 255});
  CHECK(unpack(kMono16, Bytes{0x34, 0x12}, 1, 1) == std::vector<uint16_t>{0x1234});
  CHECK(unpack(kMono12, Bytes{0x34, 0xF2}, 1, 1) == std::vector<uint16_t>{0x234});
  // Mono12p: 0xABC and 0x123 packed LSB first -> BC 3A 12
  CHECK(unpack(kMono12p, Bytes{0xBC, 0x3A, 0x12}, 2, 1) == std::vector<uint16_t>{0xABC, 0x123});
  CHECK(image_bytes(kMono12p, 3, 1) == 5);
  CHECK_THROWS_WITH(unpack(kMono16, Bytes{1}, 1, 1), doctest::Contains("needs 2 bytes"));
}

TEST_CASE("stream layout covers the payload with aligned transfers") {
  StreamLayout l = plan_layout(4464, 64, 52, 32, 1024);
  CHECK(l.transfer_size == 1024);
  CHECK(l.transfer_count == 4);
  CHECK(l.final1 == 320);
  CHECK(l.final2 == 64);
  CHECK(l.max_leader == 64);
  CHECK(uint64_t(l.transfer_count) * l.transfer_size + l.final1 + l.final2 >= l.payload_size);
}

TEST_CASE("exposures are log-uniform") {
  auto t = log_exposures(10, 1e6, 7);
  REQUIRE(t.size() == 7);
  CHECK(t.front() == doctest::Approx(10));
  CHECK(t.back() == doctest::Approx(1e6));
  for (size_t i = 1; i < t.size(); ++i) CHECK(t[i] / t[i - 1] == doctest::Approx(std::pow(1e5, 1.0 / 6)));
  CHECK_THROWS(log_exposures(0, 10, 3));
}

TEST_CASE("GenICam: big-endian masked register and read-only access") {
  MemoryPort port;
  NodeMap n(R"(<RegisterDescription>
    <MaskedIntReg Name="Flags"><Address>0x10</Address><Length>2</Length><AccessMode>RW</AccessMode>
      <LSB>15</LSB><MSB>12</MSB><Endianess>BigEndian</Endianess></MaskedIntReg>
    <IntReg Name="Id"><Address>0x20</Address><Length>4</Length><AccessMode>RO</AccessMode></IntReg>
  </RegisterDescription>)", port);
  n.set_int("Flags", 0x5);  // big-endian bits 12..15 = the low nibble
  CHECK(port.mem[0x11] == 0x05);
  CHECK(n.get_int("Flags") == 5);
  CHECK_THROWS_WITH(n.set_int("Id", 1), doctest::Contains("read-only"));
  CHECK_THROWS_WITH(NodeMap("<oops", port), doctest::Contains("does not parse"));
}
