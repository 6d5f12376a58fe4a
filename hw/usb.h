// libusb plumbing: find USB3 Vision interfaces, open a camera, bulk transfers.
// Everything that touches libusb directly (except the stream's asynchronous
// transfers, see stream.cpp) lives here, so errors are worded in one place.
#pragma once
#include <libusb.h>

#include <cstdint>
#include <memory>
#include <span>
#include <stdexcept>
#include <string>
#include <vector>

namespace prism::hw {

// A libusb failure; `code` is the libusb_error value.
class UsbError : public std::runtime_error {
 public:
  UsbError(const std::string& what, int code);
  int code;
};

// Turns a libusb error code into "<what>: <libusb name> (<advice>)".
std::string usb_error_text(const std::string& what, int code);

struct CameraInfo {
  uint8_t bus = 0, address = 0;
  uint16_t vendor_id = 0, product_id = 0;
  std::string vendor, model, serial;  // from the USB string descriptors
  std::string speed;                  // "super (5 Gb/s)", "high (480 Mb/s)", ...
};

// Owns a libusb context.
class UsbContext {
 public:
  UsbContext();
  ~UsbContext();
  UsbContext(const UsbContext&) = delete;
  UsbContext& operator=(const UsbContext&) = delete;
  libusb_context* get() const { return ctx_; }

 private:
  libusb_context* ctx_ = nullptr;
};

// Every device with a U3V control interface (class 0xEF, subclass 0x05, protocol 0).
std::vector<CameraInfo> list_cameras(UsbContext& ctx);

// One opened camera: control and stream interfaces claimed, endpoints known.
class UsbDevice {
 public:
  // Opens the camera whose serial matches (any U3V camera when `serial` is empty).
  UsbDevice(UsbContext& ctx, const std::string& serial);
  ~UsbDevice();
  UsbDevice(const UsbDevice&) = delete;
  UsbDevice& operator=(const UsbDevice&) = delete;

  // Synchronous bulk transfers; return the libusb code and set `done` bytes.
  int bulk_out(uint8_t ep, std::span<const uint8_t> data, int& done, unsigned timeout_ms);
  int bulk_in(uint8_t ep, std::span<uint8_t> data, int& done, unsigned timeout_ms);
  // Clears a halted (stalled) endpoint; throws on failure.
  void clear_halt(uint8_t ep);

  libusb_device_handle* handle() const { return handle_; }
  libusb_context* context() const { return ctx_; }
  const CameraInfo& info() const { return info_; }
  uint8_t control_out = 0, control_in = 0, stream_in = 0;  // endpoint addresses

 private:
  void release();
  libusb_context* ctx_;
  libusb_device_handle* handle_ = nullptr;
  std::vector<int> claimed_;
  CameraInfo info_;
};

}  // namespace prism::hw
