#include "fake_usb.h"

#include <linux/usbdevice_fs.h>
#include <sys/ioctl.h>
#include <umockdev.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <list>
#include <mutex>
#include <stdexcept>
#include <utility>

namespace prism::hw::test {
namespace {

constexpr const char* kDevNode = "/dev/bus/usb/002/003";

// umockdev_ioctl_data_resolve returns a reference the caller owns (GIR:
// transfer full): dropped here. Holding them forever leaked every URB's
// buffer copy, 18 kB per frame.
struct Resolved {
  UMockdevIoctlData* p = nullptr;
  Resolved(UMockdevIoctlData* parent, size_t offset, size_t len) {
    GError* err = nullptr;
    p = umockdev_ioctl_data_resolve(parent, offset, len, &err);
    if (err) g_error_free(err);
  }
  Resolved(Resolved&& o) noexcept : p(std::exchange(o.p, nullptr)) {}
  Resolved(const Resolved&) = delete;
  ~Resolved() {
    if (p) g_object_unref(p);
  }
  UMockdevIoctlData* operator->() const { return p; }
  explicit operator bool() const { return p != nullptr; }
};

struct Urb {
  Resolved data;    // the client's struct usbdevfs_urb
  Resolved buffer;  // its data buffer
  bool discarded = false;
  usbdevfs_urb* get() const { return reinterpret_cast<usbdevfs_urb*>(data->data); }
};

}  // namespace

struct FakeUsb::Impl {
  DeviceModel& model;
  UMockdevTestbed* testbed = nullptr;
  UMockdevIoctlBase* handler = nullptr;
  std::list<Urb> urbs;  // submitted, not yet reaped, in submission order
  size_t bytes_in_flight = 0;
  std::mutex mu;

  explicit Impl(DeviceModel& m) : model(m) {}

  static gboolean on_ioctl(UMockdevIoctlBase*, UMockdevIoctlClient* client, gpointer self) {
    static_cast<Impl*>(self)->handle(client);
    return TRUE;
  }

  void handle(UMockdevIoctlClient* client) {
    std::lock_guard lock(mu);
    const gulong req = umockdev_ioctl_client_get_request(client);
    UMockdevIoctlData* arg = umockdev_ioctl_client_get_arg(client);
    auto done = [&](long ret, int e) { umockdev_ioctl_client_complete(client, ret, e); };
    switch (req) {
      case USBDEVFS_GET_CAPABILITIES: {
        Resolved d(arg, 0, 4);
        *reinterpret_cast<uint32_t*>(d->data) = USBDEVFS_CAP_BULK_CONTINUATION | USBDEVFS_CAP_NO_PACKET_SIZE_LIM |
                                                USBDEVFS_CAP_REAP_AFTER_DISCONNECT | USBDEVFS_CAP_ZERO_PACKET;
        return done(0, 0);
      }
      case USBDEVFS_DISCONNECT_CLAIM:  // libusb auto-detach: no kernel driver here, just claim
      case USBDEVFS_CLAIMINTERFACE:
      case USBDEVFS_RELEASEINTERFACE:
      case USBDEVFS_SETINTERFACE:
      case USBDEVFS_RESET:
        return model.unplugged() ? done(-1, ENODEV) : done(0, 0);
      case USBDEVFS_CLEAR_HALT: {
        Resolved d(arg, 0, 4);
        if (model.unplugged()) return done(-1, ENODEV);
        model.clear_halt(uint8_t(*reinterpret_cast<unsigned*>(d->data)));
        return done(0, 0);
      }
      case USBDEVFS_GETDRIVER: return done(-1, ENODATA);  // no kernel driver bound
      case USBDEVFS_SUBMITURB: return submit(arg, done);
      case USBDEVFS_DISCARDURB: {
        unsigned long addr = *reinterpret_cast<unsigned long*>(arg->data);
        for (auto& u : urbs)
          if (u.data->client_addr == addr && !u.discarded) {
            u.discarded = true;
            return done(0, 0);
          }
        return done(-1, EINVAL);
      }
      case USBDEVFS_REAPURB:
      case USBDEVFS_REAPURBNDELAY: return reap(arg, done);
      default:
        if (getenv("PRISM_FAKE_USB_DEBUG")) fprintf(stderr, "fake usb: unhandled ioctl 0x%lx\n", req);
        return done(-1, ENOTTY);
    }
  }

  template <class Done>
  void submit(UMockdevIoctlData* arg, Done& done) {
    Resolved d(arg, 0, sizeof(usbdevfs_urb));
    if (!d) return done(-1, EFAULT);
    auto* u = reinterpret_cast<usbdevfs_urb*>(d->data);
    if (model.unplugged()) return done(-1, ENODEV);
    size_t limit = model.faults.usbfs_limit;
    if (limit && bytes_in_flight + size_t(u->buffer_length) > limit) return done(-1, ENOMEM);  // usbfs_memory_mb
    Resolved buf(d.p, offsetof(usbdevfs_urb, buffer), size_t(u->buffer_length));
    if (!buf) return done(-1, EFAULT);
    bytes_in_flight += size_t(u->buffer_length);
    if (u->type == USBDEVFS_URB_TYPE_BULK && !(u->endpoint & 0x80))  // OUT: the device consumes it now
      model.out(u->endpoint, Bytes(buf->data, buf->data + u->buffer_length));
    urbs.push_back({std::move(d), std::move(buf)});
    done(0, 0);
  }

  // Completes the oldest URB the device can answer, keeping per-endpoint order.
  template <class Done>
  void reap(UMockdevIoctlData* arg, Done& done) {
    Resolved ptr(arg, 0, sizeof(void*));
    std::vector<unsigned> blocked;  // IN endpoints with an older URB still waiting
    for (auto it = urbs.begin(); it != urbs.end(); ++it) {
      usbdevfs_urb* u = it->get();
      bool ready = false;
      if (it->discarded) {
        u->status = -ENOENT;
        u->actual_length = 0;
        ready = true;
      } else if (u->type == USBDEVFS_URB_TYPE_CONTROL) {
        Bytes r = model.control_in(it->buffer->data);
        size_t n = std::min(r.size(), size_t(u->buffer_length) - 8);
        std::memcpy(it->buffer->data + 8, r.data(), n);
        u->status = r.empty() ? -EPIPE : 0;
        u->actual_length = int(n);
        ready = true;
      } else if (!(u->endpoint & 0x80)) {
        u->status = model.unplugged() ? -ENODEV : 0;
        u->actual_length = u->status ? 0 : u->buffer_length;
        ready = true;
      } else if (std::find(blocked.begin(), blocked.end(), u->endpoint) == blocked.end()) {
        if (auto in = model.in(u->endpoint, size_t(u->buffer_length))) {
          if (!in->data.empty()) std::memcpy(it->buffer->data, in->data.data(), in->data.size());
          u->status = in->status;
          u->actual_length = int(in->data.size());
          ready = true;
        } else {
          blocked.push_back(u->endpoint);
        }
      }
      if (!ready) continue;
      umockdev_ioctl_data_set_ptr(ptr.p, 0, it->data.p);
      bytes_in_flight -= size_t(u->buffer_length);
      done(0, 0);
      urbs.erase(it);
      return;
    }
    done(-1, EAGAIN);
  }
};

bool umockdev_active() {
  static int active = -1;
  if (active < 0) {
    UMockdevTestbed* tb = umockdev_testbed_new();
    active = umockdev_in_mock_environment() ? 1 : 0;
    g_object_unref(tb);
  }
  return active == 1;
}

FakeUsb::FakeUsb(Faults faults) : model_(std::make_unique<DeviceModel>(faults)), impl_(std::make_unique<Impl>(*model_)) {
  GError* err = nullptr;
  impl_->testbed = umockdev_testbed_new();
  if (!umockdev_testbed_add_from_string(impl_->testbed, model_->umockdev_description().c_str(), &err))
    throw std::runtime_error(std::string("umockdev: cannot add the device: ") + err->message);
  impl_->handler = umockdev_ioctl_base_new();
  g_signal_connect(impl_->handler, "handle-ioctl", G_CALLBACK(Impl::on_ioctl), impl_.get());
  if (!umockdev_testbed_attach_ioctl(impl_->testbed, kDevNode, impl_->handler, &err))
    throw std::runtime_error(std::string("umockdev: cannot attach the ioctl handler: ") + err->message);
}

FakeUsb::~FakeUsb() {
  umockdev_testbed_detach_ioctl(impl_->testbed, kDevNode, nullptr);
  {
    std::lock_guard lock(impl_->mu);
    impl_->urbs.clear();  // drops their references
  }
  g_object_unref(impl_->handler);
  g_object_unref(impl_->testbed);
}

}  // namespace prism::hw::test
