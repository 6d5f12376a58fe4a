// Vulkan instance, device choice and queue. A real GPU is chosen when present,
// Mesa lavapipe (CPU) otherwise; `--device` or PRISM_DEVICE overrides.
#pragma once
#include <cstdint>
#include <memory>
#include <string>
#include <vector>
#include <vulkan/vulkan.h>

namespace prism::vk {

class PipelineCache;  // compute.h

// Processes that share a node (MPI ranks) each take their own device: with
// the slot set, a choice by kind or name ("auto", "gpu", part of a name)
// takes the (slot mod n)-th of the n equally preferred devices that match (a
// node's GPUs) instead of the first; an index is taken as given. The host sets it
// once, before any Context; 0, the first, for a single process.
void set_device_slot(unsigned slot);

struct ContextOptions {
  // "auto" (GPU if present, else CPU), "gpu", "cpu", a device index, or part of
  // a device name. Empty: take PRISM_DEVICE from the environment, else "auto".
  std::string device;
  // Enable the Khronos validation layer and count its messages. Also switched
  // on by PRISM_VALIDATION=1 (the test suite sets it).
  bool validation = false;
  // Never map a storage buffer: every upload and download goes through a
  // staging copy, as on a discrete GPU whose memory the host cannot map
  // (vk::Buffer). For testing that path on a device that maps everything.
  bool staged_buffers = false;
};

class Context {
 public:
  explicit Context(ContextOptions options = {});
  ~Context();
  Context(const Context&) = delete;
  Context& operator=(const Context&) = delete;

  VkDevice device() const { return device_; }
  VkPhysicalDevice physical() const { return physical_; }
  VkQueue queue() const { return queue_; }
  uint32_t queue_family() const { return queue_family_; }
  VkCommandPool command_pool() const { return pool_; }
  // Compute pipelines, each compiled once per context (vk::Kernel).
  PipelineCache& pipelines() { return *pipelines_; }
  const VkPhysicalDeviceProperties& properties() const { return props_; }

  // "llvmpipe (LLVM 15.0.6, 256 bits) [cpu, Vulkan 1.3.230]"
  std::string describe() const;
  bool is_cpu() const { return props_.deviceType == VK_PHYSICAL_DEVICE_TYPE_CPU; }
  uint64_t max_storage_buffer_bytes() const { return props_.limits.maxStorageBufferRange; }
  uint32_t max_group_count_x() const { return props_.limits.maxComputeWorkGroupCount[0]; }
  // Nanoseconds per timestamp tick; 0 when the queue cannot time kernels.
  double timestamp_period_ns() const { return timestamp_period_ns_; }
  uint32_t find_memory_type(uint32_t type_bits, VkMemoryPropertyFlags want) const;
  VkMemoryPropertyFlags memory_type_flags(uint32_t type) const { return mem_props_.memoryTypes[type].propertyFlags; }

  bool staged_buffers() const { return staged_buffers_; }
  bool validation_enabled() const { return messenger_ != VK_NULL_HANDLE; }
  // Messages from the validation layer so far (warnings and errors).
  const std::vector<std::string>& validation_messages() const { return messages_; }

  // Each available device as "index: name [type]", for --help and errors.
  static std::vector<std::string> list_devices();

 private:
  VkInstance instance_ = VK_NULL_HANDLE;
  VkDebugUtilsMessengerEXT messenger_ = VK_NULL_HANDLE;
  VkPhysicalDevice physical_ = VK_NULL_HANDLE;
  VkDevice device_ = VK_NULL_HANDLE;
  VkQueue queue_ = VK_NULL_HANDLE;
  VkCommandPool pool_ = VK_NULL_HANDLE;
  uint32_t queue_family_ = 0;
  VkPhysicalDeviceProperties props_{};
  VkPhysicalDeviceMemoryProperties mem_props_{};
  double timestamp_period_ns_ = 0;
  bool staged_buffers_ = false;
  std::vector<std::string> messages_;
  std::unique_ptr<PipelineCache> pipelines_;

  static VKAPI_ATTR VkBool32 VKAPI_CALL on_message(VkDebugUtilsMessageSeverityFlagBitsEXT,
                                                   VkDebugUtilsMessageTypeFlagsEXT,
                                                   const VkDebugUtilsMessengerCallbackDataEXT*, void*);
};

}  // namespace prism::vk
