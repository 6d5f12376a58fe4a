#include "hw/usb.h"

#include "hw/u3v_regs.h"

namespace prism::hw {
namespace {

std::string advice(int code) {
  switch (code) {
    case LIBUSB_ERROR_NO_DEVICE: return "the camera was unplugged; reconnect it and start again";
    case LIBUSB_ERROR_ACCESS: return "no permission on /dev/bus/usb; add a udev rule giving your user access to the camera";
    case LIBUSB_ERROR_BUSY: return "another program holds the camera; close it";
    case LIBUSB_ERROR_TIMEOUT: return "the camera did not answer in time; check the cable and the camera's power";
    case LIBUSB_ERROR_PIPE: return "the endpoint stalled";
    case LIBUSB_ERROR_NO_MEM:
      return "the kernel's usbfs memory limit is too low for the stream buffers; raise it with "
             "`echo 1000 > /sys/module/usbcore/parameters/usbfs_memory_mb` (as root)";
    default: return "";
  }
}

std::string speed_name(int speed) {
  switch (speed) {
    case LIBUSB_SPEED_LOW: return "low (1.5 Mb/s)";
    case LIBUSB_SPEED_FULL: return "full (12 Mb/s)";
    case LIBUSB_SPEED_HIGH: return "high (480 Mb/s)";
    case LIBUSB_SPEED_SUPER: return "super (5 Gb/s)";
    case LIBUSB_SPEED_SUPER_PLUS: return "super+ (10 Gb/s)";
    default: return "unknown";
  }
}

// Finds the U3V interface with `protocol`; returns its number or -1.
int find_interface(const libusb_config_descriptor* cfg, uint8_t protocol,
                   const libusb_interface_descriptor** out) {
  for (int i = 0; i < cfg->bNumInterfaces; ++i)
    for (int a = 0; a < cfg->interface[i].num_altsetting; ++a) {
      const auto& d = cfg->interface[i].altsetting[a];
      if (d.bInterfaceClass == u3v::kInterfaceClass && d.bInterfaceSubClass == u3v::kInterfaceSubclass &&
          d.bInterfaceProtocol == protocol) {
        if (out) *out = &d;
        return d.bInterfaceNumber;
      }
    }
  return -1;
}

bool is_u3v(libusb_device* dev) {
  libusb_config_descriptor* cfg = nullptr;
  if (libusb_get_active_config_descriptor(dev, &cfg) != 0 &&
      libusb_get_config_descriptor(dev, 0, &cfg) != 0)
    return false;
  bool found = find_interface(cfg, u3v::kProtocolControl, nullptr) >= 0;
  libusb_free_config_descriptor(cfg);
  return found;
}

std::string string_descriptor(libusb_device_handle* h, uint8_t index) {
  if (index == 0) return "";
  unsigned char buf[256] = {};
  int n = libusb_get_string_descriptor_ascii(h, index, buf, sizeof buf);
  return n > 0 ? std::string(reinterpret_cast<char*>(buf), size_t(n)) : "?";
}

// Fills `info` from the device descriptor and, when the device opens, its strings.
CameraInfo describe(libusb_device* dev, libusb_device_handle* h) {
  CameraInfo info;
  libusb_device_descriptor d{};
  libusb_get_device_descriptor(dev, &d);
  info.bus = libusb_get_bus_number(dev);
  info.address = libusb_get_device_address(dev);
  info.vendor_id = d.idVendor;
  info.product_id = d.idProduct;
  info.speed = speed_name(libusb_get_device_speed(dev));
  if (h) {
    info.vendor = string_descriptor(h, d.iManufacturer);
    info.model = string_descriptor(h, d.iProduct);
    info.serial = string_descriptor(h, d.iSerialNumber);
  } else {
    info.vendor = info.model = info.serial = "? (cannot open: check permissions)";
  }
  return info;
}

struct DeviceList {
  libusb_device** list = nullptr;
  ssize_t n = 0;
  explicit DeviceList(libusb_context* ctx) {
    n = libusb_get_device_list(ctx, &list);
    if (n < 0) throw UsbError("listing USB devices", int(n));
  }
  ~DeviceList() { libusb_free_device_list(list, 1); }
};

}  // namespace

std::string usb_error_text(const std::string& what, int code) {
  std::string a = advice(code);
  return what + ": " + libusb_error_name(code) + (a.empty() ? "" : " (" + a + ")");
}

UsbError::UsbError(const std::string& what, int c) : std::runtime_error(usb_error_text(what, c)), code(c) {}

UsbContext::UsbContext() {
  if (int r = libusb_init(&ctx_); r != 0) throw UsbError("initialising libusb", r);
}
UsbContext::~UsbContext() { libusb_exit(ctx_); }

std::vector<CameraInfo> list_cameras(UsbContext& ctx) {
  std::vector<CameraInfo> out;
  DeviceList devs(ctx.get());
  for (ssize_t i = 0; i < devs.n; ++i) {
    if (!is_u3v(devs.list[i])) continue;
    libusb_device_handle* h = nullptr;
    if (libusb_open(devs.list[i], &h) != 0) h = nullptr;
    out.push_back(describe(devs.list[i], h));
    if (h) libusb_close(h);
  }
  return out;
}

UsbDevice::UsbDevice(UsbContext& ctx, const std::string& serial) : ctx_(ctx.get()) {
  DeviceList devs(ctx_);
  libusb_device* dev = nullptr;
  for (ssize_t i = 0; i < devs.n && !handle_; ++i) {
    if (!is_u3v(devs.list[i])) continue;
    libusb_device_handle* h = nullptr;
    if (int r = libusb_open(devs.list[i], &h); r != 0) {
      if (serial.empty()) throw UsbError("opening the USB3 Vision camera", r);
      continue;
    }
    CameraInfo info = describe(devs.list[i], h);
    if (!serial.empty() && info.serial != serial) {
      libusb_close(h);
      continue;
    }
    handle_ = h;
    dev = devs.list[i];
    info_ = info;
  }
  if (!handle_)
    throw std::runtime_error(serial.empty() ? "no USB3 Vision camera found; check the cable and `prism camera list`"
                                            : "no USB3 Vision camera with serial '" + serial +
                                                  "'; see `prism camera list`");
  libusb_config_descriptor* cfg = nullptr;
  if (int r = libusb_get_active_config_descriptor(dev, &cfg); r != 0) {
    libusb_close(handle_);
    throw UsbError("reading the camera's configuration descriptor", r);
  }
  const libusb_interface_descriptor *ctrl = nullptr, *stream = nullptr;
  int ctrl_if = find_interface(cfg, u3v::kProtocolControl, &ctrl);
  int stream_if = find_interface(cfg, u3v::kProtocolStream, &stream);
  for (int e = 0; ctrl && e < ctrl->bNumEndpoints; ++e) {
    uint8_t a = ctrl->endpoint[e].bEndpointAddress;
    (a & LIBUSB_ENDPOINT_IN ? control_in : control_out) = a;
  }
  for (int e = 0; stream && e < stream->bNumEndpoints; ++e)
    if (stream->endpoint[e].bEndpointAddress & LIBUSB_ENDPOINT_IN) stream_in = stream->endpoint[e].bEndpointAddress;
  libusb_free_config_descriptor(cfg);
  for (int itf : {ctrl_if, stream_if}) {
    if (itf < 0) continue;
    libusb_set_auto_detach_kernel_driver(handle_, 1);
    if (int r = libusb_claim_interface(handle_, itf); r != 0) {
      release();
      throw UsbError("claiming USB3 Vision interface " + std::to_string(itf), r);
    }
    claimed_.push_back(itf);
  }
  if (!control_in || !control_out) {
    release();
    throw std::runtime_error("the camera's U3V control interface lacks a bulk IN/OUT endpoint pair");
  }
}

UsbDevice::~UsbDevice() { release(); }

void UsbDevice::release() {
  if (!handle_) return;
  for (int c : claimed_) libusb_release_interface(handle_, c);
  libusb_close(handle_);
  handle_ = nullptr;
}

int UsbDevice::bulk_out(uint8_t ep, std::span<const uint8_t> data, int& done, unsigned timeout_ms) {
  done = 0;
  return libusb_bulk_transfer(handle_, ep, const_cast<uint8_t*>(data.data()), int(data.size()), &done, timeout_ms);
}

int UsbDevice::bulk_in(uint8_t ep, std::span<uint8_t> data, int& done, unsigned timeout_ms) {
  done = 0;
  return libusb_bulk_transfer(handle_, ep, data.data(), int(data.size()), &done, timeout_ms);
}

void UsbDevice::clear_halt(uint8_t ep) {
  if (int r = libusb_clear_halt(handle_, ep); r != 0) throw UsbError("clearing the halt on endpoint " + std::to_string(ep), r);
}

}  // namespace prism::hw
