// Serves a DeviceModel to unmodified libusb code through umockdev: a testbed
// with the model's sysfs/descriptors and a usbdevfs ioctl handler (SUBMITURB,
// REAPURB, DISCARDURB, CLEAR_HALT, ...) answering from the model. Needs the
// process to run under `umockdev-wrapper` (LD_PRELOAD of libumockdev-preload).
#pragma once
#include <memory>

#include "device_model.h"

namespace prism::hw::test {

// True when this process runs with umockdev's preload library active.
bool umockdev_active();

class FakeUsb {
 public:
  explicit FakeUsb(Faults faults = {});
  ~FakeUsb();
  DeviceModel& model() { return *model_; }

 private:
  struct Impl;
  std::unique_ptr<DeviceModel> model_;
  std::unique_ptr<Impl> impl_;
};

}  // namespace prism::hw::test
