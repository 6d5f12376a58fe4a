// Buffers, compute kernels and a command stream that records dispatches and
// times each one with GPU timestamps.
#pragma once
#include <cstdint>
#include <map>
#include <mutex>
#include <span>
#include <string>
#include <tuple>
#include <vector>

#include "engine/vk/context.h"

namespace prism::vk {

// A storage buffer in device-local memory where there is room. The host
// writes and reads it directly where it can map it; it reads through a staging
// copy where the mapping is uncached (a discrete GPU's BAR), and does both
// through one where it cannot map it (make_buffer in compute.cpp says why).
// One buffer may not exceed maxStorageBufferRange: callers chunk.
class Buffer {
 public:
  Buffer(Context& ctx, uint64_t bytes);
  ~Buffer();
  Buffer(const Buffer&) = delete;
  Buffer& operator=(const Buffer&) = delete;

  VkBuffer handle() const { return buffer_; }
  uint64_t bytes() const { return bytes_; }
  void upload(const void* data, uint64_t bytes, uint64_t offset = 0);
  void download(void* data, uint64_t bytes, uint64_t offset = 0) const;
  template <class T> void upload(std::span<const T> v) { upload(v.data(), v.size_bytes()); }
  // The whole buffer as a uniform texel buffer of `format` (a samplerBuffer
  // or usamplerBuffer binding, Kernel's texel_formats): made at the first
  // request and kept with the buffer. Throws where the buffer holds more
  // texels than maxTexelBufferElements.
  VkBufferView view(VkFormat format) const;
  template <class T> std::vector<T> download(size_t count) const {
    std::vector<T> v(count);
    download(v.data(), count * sizeof(T));
    return v;
  }

 private:
  void copy(VkBuffer src, VkBuffer dst, uint64_t src_off, uint64_t dst_off, uint64_t bytes) const;
  Context& ctx_;
  VkBuffer buffer_ = VK_NULL_HANDLE;
  VkDeviceMemory memory_ = VK_NULL_HANDLE;
  void* mapped_ = nullptr;
  bool host_cached_ = false;
  uint64_t bytes_ = 0;
  mutable std::mutex views_mutex_;
  mutable std::map<VkFormat, VkBufferView> views_;
};

// The compute pipelines of a context, each created once for its SPIR-V,
// buffer count, push-constant size and specialisation. Forward models are
// built again and again with the same kernels (a sweep builds one per batch
// of designs, the tests one per case), and a large kernel takes 0.3-0.7 s to
// compile on lavapipe.
class PipelineCache {
 public:
  struct Pipeline {
    VkDescriptorSetLayout set_layout = VK_NULL_HANDLE;
    VkPipelineLayout layout = VK_NULL_HANDLE;
    VkPipeline pipeline = VK_NULL_HANDLE;
  };
  explicit PipelineCache(VkDevice device) : device_(device) {}
  ~PipelineCache();
  PipelineCache(const PipelineCache&) = delete;
  PipelineCache& operator=(const PipelineCache&) = delete;

  // The pipeline, created on the first request (thread-safe). `name` only
  // names it in errors.
  const Pipeline& get(const std::string& name, std::span<const uint32_t> spirv, uint32_t buffer_count,
                      uint32_t push_bytes, const std::vector<uint32_t>& specialisation,
                      const std::vector<VkFormat>& texel_formats = {});
  size_t size() const;

 private:
  using Key = std::tuple<std::vector<uint32_t>, uint32_t, uint32_t, std::vector<uint32_t>, std::vector<VkFormat>>;
  VkDevice device_;
  mutable std::mutex mutex_;
  std::map<Key, Pipeline> pipelines_;
};

// A compute kernel from embedded SPIR-V. Specialisation constants (ids 0..n-1,
// 32 bits each) are fixed here; push constants change per dispatch. Its
// pipeline comes from the context's PipelineCache at the first dispatch: a
// kernel never dispatched (the values-only variant of a model used for
// derivatives) is never compiled.
//
// Bindings are storage buffers, except where texel_formats[i] names a format:
// binding i is then a uniform texel buffer (samplerBuffer) reading its buffer
// as that format. On a CPU device (Mesa's llvmpipe 22.x) a storage buffer
// load runs one invocation at a time, a texel fetch as one vector gather: the
// hot look-ups of a kernel go faster through a texel buffer there.
class Kernel {
 public:
  Kernel(Context& ctx, std::string name, std::span<const uint32_t> spirv, uint32_t buffer_count,
         uint32_t push_bytes, std::vector<uint32_t> specialisation = {}, std::vector<VkFormat> texel_formats = {});
  Kernel(const Kernel&) = delete;
  Kernel& operator=(const Kernel&) = delete;

  const std::string& name() const { return name_; }

 private:
  friend class Stream;
  const PipelineCache::Pipeline& pipeline();
  Context& ctx_;
  std::string name_;
  std::vector<uint32_t> spirv_;
  uint32_t buffer_count_;
  uint32_t push_bytes_;
  std::vector<uint32_t> specialisation_;
  std::vector<VkFormat> texel_formats_;
  const PipelineCache::Pipeline* pipeline_ = nullptr;
};

// Records dispatches into one command buffer; submit() runs them and returns
// after the device is done. Each dispatch is timed when the queue allows it.
class Stream {
 public:
  explicit Stream(Context& ctx, uint32_t max_dispatches = 256);
  ~Stream();
  Stream(const Stream&) = delete;
  Stream& operator=(const Stream&) = delete;

  void fill_zero(Buffer& buffer);
  void fill_zero(Buffer& buffer, uint64_t offset, uint64_t bytes);  // a multiple of 4 bytes
  void dispatch(Kernel& kernel, std::initializer_list<const Buffer*> buffers, const void* push, uint32_t groups_x,
                uint32_t groups_y = 1, uint32_t groups_z = 1);
  // Make the writes of everything recorded so far visible to what follows.
  void barrier();
  // Run what was recorded and wait. Returns the summed kernel time in
  // milliseconds (GPU timestamps; host wall time where the queue has none).
  double submit();
  // Each dispatch of the last submit() and its time in milliseconds (empty
  // where the queue has no timestamps): where a pipeline's time goes.
  struct KernelTime {
    std::string kernel;
    double ms;
  };
  const std::vector<KernelTime>& last_times() const { return times_; }

 private:
  void begin_if_needed();
  Context& ctx_;
  uint32_t max_dispatches_;
  VkCommandBuffer cmd_ = VK_NULL_HANDLE;
  VkDescriptorPool pool_ = VK_NULL_HANDLE;
  VkQueryPool queries_ = VK_NULL_HANDLE;
  VkFence fence_ = VK_NULL_HANDLE;
  uint32_t dispatches_ = 0;
  bool recording_ = false;
  std::vector<std::string> names_;  // of the dispatches recorded
  std::vector<KernelTime> times_;
};

}  // namespace prism::vk
