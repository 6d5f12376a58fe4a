// USB3 Vision register maps, GenCP packet codes and stream magic numbers.
// Offsets follow the USB3 Vision 1.0 standard (and Aravis arvuvcpprivate.h /
// arvuvspprivate.h); all multi-byte fields are little-endian on the wire.
#pragma once
#include <cstdint>

namespace prism::hw::u3v {

// --- Interface identification (USB descriptors) ---
inline constexpr uint8_t kInterfaceClass = 0xEF;     // miscellaneous device class
inline constexpr uint8_t kInterfaceSubclass = 0x05;  // USB3 Vision
inline constexpr uint8_t kProtocolControl = 0;       // GenCP command/ack interface
inline constexpr uint8_t kProtocolEvent = 1;         // asynchronous event interface
inline constexpr uint8_t kProtocolStream = 2;        // image stream interface

// --- GenCP packet ---
inline constexpr uint32_t kCommandPrefix = 0x43563355;  // "U3VC" command/ack magic
inline constexpr uint16_t kFlagRequestAck = 0x4000;     // command flag: device must acknowledge
inline constexpr uint16_t kReadMemCmd = 0x0800;         // read memory command
inline constexpr uint16_t kReadMemAck = 0x0801;         // read memory acknowledge
inline constexpr uint16_t kWriteMemCmd = 0x0802;        // write memory command
inline constexpr uint16_t kWriteMemAck = 0x0803;        // write memory acknowledge
inline constexpr uint16_t kPendingAck = 0x0805;         // device needs more time; SCD has new timeout
inline constexpr size_t kHeaderSize = 12;               // prefix + flags/status + id + length + req id
inline constexpr size_t kReadMemScdSize = 12;           // address u64 + reserved u16 + count u16
inline constexpr size_t kWriteMemAddrSize = 8;          // address u64 ahead of the written data

// GenCP status codes carried in acknowledges.
enum class Status : uint16_t {
  Success = 0x0000,             // command executed
  NotImplemented = 0x8001,      // command not supported by the device
  InvalidParameter = 0x8002,    // a parameter of the command is out of range
  InvalidAddress = 0x8003,      // address not mapped on the device
  WriteProtect = 0x8004,        // register is read-only
  BadAlignment = 0x8005,        // address or length not aligned as the device needs
  AccessDenied = 0x8006,        // register locked (e.g. while streaming)
  Busy = 0x8007,                // device busy, try again later
  MsgTimeout = 0x800B,          // device timed out internally
  InvalidHeader = 0x800E,       // malformed command header
  WrongConfig = 0x800F,         // current configuration forbids the access
  GenericError = 0x8FFF,        // unspecified device error
  ResendNotSupported = 0xA001,  // U3V: resend not supported
  StreamEndpointHalted = 0xA002,// U3V: stream endpoint halted, clear it first
  PayloadNotAligned = 0xA003,   // U3V: payload size not a multiple of the alignment
  InvalidSiState = 0xA004,      // U3V: SIRM written while streaming is enabled
  EventEndpointHalted = 0xA005, // U3V: event endpoint halted
};

// --- ABRM: technology-agnostic bootstrap registers (address 0) ---
inline constexpr uint64_t kAbrmGenCpVersion = 0x0000;          // u32 GenCP version
inline constexpr uint64_t kAbrmManufacturerName = 0x0004;      // char[64]
inline constexpr uint64_t kAbrmModelName = 0x0044;             // char[64]
inline constexpr uint64_t kAbrmFamilyName = 0x0084;            // char[64]
inline constexpr uint64_t kAbrmDeviceVersion = 0x00C4;         // char[64]
inline constexpr uint64_t kAbrmManufacturerInfo = 0x0104;      // char[64]
inline constexpr uint64_t kAbrmSerialNumber = 0x0144;          // char[64]
inline constexpr uint64_t kAbrmUserDefinedName = 0x0184;       // char[64]
inline constexpr uint64_t kAbrmDeviceCapability = 0x01C4;      // u64 capability bits
inline constexpr uint64_t kAbrmMaxDeviceResponseTime = 0x01CC; // u32 ms the host must wait for an ack
inline constexpr uint64_t kAbrmManifestTableAddress = 0x01D0;  // u64 address of the XML manifest
inline constexpr uint64_t kAbrmSbrmAddress = 0x01D8;           // u64 address of SBRM
inline constexpr uint64_t kAbrmSize = 0x0250;                  // bytes read in one bootstrap pass
inline constexpr size_t kStringSize = 64;                      // ABRM string field length

// --- SBRM: USB3 Vision specific bootstrap registers (relative to SBRM address) ---
inline constexpr uint64_t kSbrmU3vVersion = 0x00;          // u32 U3V version
inline constexpr uint64_t kSbrmU3vcpCapability = 0x04;     // u64 capability bits
inline constexpr uint64_t kSbrmMaxCmdTransfer = 0x14;      // u32 largest command the device accepts
inline constexpr uint64_t kSbrmMaxAckTransfer = 0x18;      // u32 largest ack the device sends
inline constexpr uint64_t kSbrmNumStreamChannels = 0x1C;   // u32 number of stream interfaces
inline constexpr uint64_t kSbrmSirmAddress = 0x20;         // u64 address of SIRM
inline constexpr uint64_t kSbrmSirmLength = 0x28;          // u32 SIRM size
inline constexpr uint64_t kSbrmCurrentSpeed = 0x40;        // u32 bus speed the device sees
inline constexpr uint64_t kSbrmSize = 0x44;                // bytes read in one pass

// --- SIRM: streaming interface registers (relative to SIRM address) ---
inline constexpr uint64_t kSirmInfo = 0x00;              // u32; bits 24..31 = log2(payload alignment)
inline constexpr uint64_t kSirmControl = 0x04;           // u32; bit 0 enables the stream interface
inline constexpr uint64_t kSirmRequiredPayload = 0x08;   // u64 payload bytes per frame
inline constexpr uint64_t kSirmRequiredLeader = 0x10;    // u32 leader bytes the device needs
inline constexpr uint64_t kSirmRequiredTrailer = 0x14;   // u32 trailer bytes the device needs
inline constexpr uint64_t kSirmMaxLeader = 0x18;         // u32 host leader buffer size (host writes)
inline constexpr uint64_t kSirmPayloadTransferSize = 0x1C;   // u32 host payload transfer size
inline constexpr uint64_t kSirmPayloadTransferCount = 0x20;  // u32 number of full payload transfers
inline constexpr uint64_t kSirmFinalTransfer1 = 0x24;    // u32 first final transfer size (0 = none)
inline constexpr uint64_t kSirmFinalTransfer2 = 0x28;    // u32 second final transfer size (0 = none)
inline constexpr uint64_t kSirmMaxTrailer = 0x2C;        // u32 host trailer buffer size (host writes)
inline constexpr uint64_t kSirmSize = 0x30;              // bytes read in one pass
inline constexpr uint32_t kSirmEnable = 1;               // SIRM control: stream enable bit

// --- Manifest table: u64 entry count, then 64-byte entries ---
inline constexpr size_t kManifestEntrySize = 64;
inline constexpr size_t kManifestAddressOffset = 8;   // u64 file address inside an entry
inline constexpr size_t kManifestSizeOffset = 16;     // u64 file size inside an entry
inline constexpr size_t kManifestSchemaOffset = 4;    // u32; bits 10..15 = file type
inline constexpr uint32_t kManifestTypeXml = 0;       // plain XML file
inline constexpr uint32_t kManifestTypeZip = 1;       // zip archive holding the XML

// --- Stream protocol (leader / trailer) ---
inline constexpr uint32_t kLeaderMagic = 0x4C563355;   // "U3VL"
inline constexpr uint32_t kTrailerMagic = 0x54563355;  // "U3VT"
inline constexpr uint16_t kPayloadImage = 0x0001;      // leader payload type: uncompressed image
inline constexpr size_t kImageLeaderSize = 52;         // generic leader (20) + image info (32)
inline constexpr size_t kImageTrailerSize = 32;        // generic trailer (28) + actual size_y (4)

// Field offsets shared by leader and trailer.
inline constexpr size_t kStreamMagic = 0;       // u32 magic
inline constexpr size_t kStreamHeaderSize = 6;  // u16 size of this leader/trailer
inline constexpr size_t kStreamBlockId = 8;     // u64 frame counter
// Image leader fields.
inline constexpr size_t kLeaderPayloadType = 18;  // u16 payload type
inline constexpr size_t kLeaderTimestamp = 20;    // u64 device ticks
inline constexpr size_t kLeaderPixelFormat = 28;  // u32 PFNC code
inline constexpr size_t kLeaderSizeX = 32;        // u32 width
inline constexpr size_t kLeaderSizeY = 36;        // u32 height
// Image trailer fields.
inline constexpr size_t kTrailerStatus = 16;       // u16 GenCP status of the frame
inline constexpr size_t kTrailerValidPayload = 20; // u64 payload bytes actually sent
inline constexpr size_t kTrailerSizeY = 28;        // u32 lines actually sent

}  // namespace prism::hw::u3v
