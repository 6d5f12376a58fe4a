#include "engine/vk/compute.h"

#include <algorithm>
#include <chrono>
#include <cstring>

#include "engine/vk/error.h"

namespace prism::vk {

// ---------------------------------------------------------------------------
// Buffer

namespace {

struct RawBuffer {
  VkBuffer buffer = VK_NULL_HANDLE;
  VkDeviceMemory memory = VK_NULL_HANDLE;
  void* mapped = nullptr;
  bool host_cached = false;  // the host reads the mapped memory through its cache
};

enum class Role { storage, staging };

// Memory for a buffer, most preferred first. Storage: device-local memory the
// host maps and reads through its cache (lavapipe, integrated GPUs: one
// memory); device-local memory the host maps but reads uncached (a discrete
// GPU's resizable BAR: uploads write into it directly, downloads go through a
// staging copy, since each uncached read crosses the bus: on an H200 the
// refinement's image downloads made a 6 ms render take about 190 ms);
// device-local memory (a discrete GPU without resizable BAR, or when its BAR
// is full); host memory. Staging: host memory, cached first. With
// ContextOptions::staged_buffers, storage is never mapped.
RawBuffer make_buffer(Context& ctx, uint64_t bytes, VkBufferUsageFlags usage, Role role) {
  RawBuffer rb;
  VkBufferCreateInfo bi{VK_STRUCTURE_TYPE_BUFFER_CREATE_INFO};
  bi.size = bytes;
  bi.usage = usage;
  bi.sharingMode = VK_SHARING_MODE_EXCLUSIVE;
  check(vkCreateBuffer(ctx.device(), &bi, nullptr, &rb.buffer), "vkCreateBuffer");
  VkMemoryRequirements req;
  vkGetBufferMemoryRequirements(ctx.device(), rb.buffer, &req);
  const VkMemoryPropertyFlags host = VK_MEMORY_PROPERTY_HOST_VISIBLE_BIT | VK_MEMORY_PROPERTY_HOST_COHERENT_BIT;
  const VkMemoryPropertyFlags cached = VK_MEMORY_PROPERTY_HOST_CACHED_BIT;
  const VkMemoryPropertyFlags local = VK_MEMORY_PROPERTY_DEVICE_LOCAL_BIT;
  const bool map = role == Role::staging || !ctx.staged_buffers();
  std::vector<VkMemoryPropertyFlags> wanted;
  if (role == Role::staging) wanted = {host | cached, host};
  else if (map) wanted = {local | host | cached, local | host, local, host | cached, host};
  else wanted = {local, host};
  VkResult r = VK_ERROR_OUT_OF_DEVICE_MEMORY;
  std::vector<uint32_t> tried;
  for (VkMemoryPropertyFlags want : wanted) {
    const uint32_t type = ctx.find_memory_type(req.memoryTypeBits, want);
    if (type == UINT32_MAX || std::find(tried.begin(), tried.end(), type) != tried.end()) continue;
    tried.push_back(type);
    VkMemoryAllocateInfo ai{VK_STRUCTURE_TYPE_MEMORY_ALLOCATE_INFO};
    ai.allocationSize = req.size;
    ai.memoryTypeIndex = type;
    r = vkAllocateMemory(ctx.device(), &ai, nullptr, &rb.memory);
    // A heap that is full (a BAR of 256 MiB) leaves the next kind of memory.
    if (r == VK_ERROR_OUT_OF_DEVICE_MEMORY || r == VK_ERROR_OUT_OF_HOST_MEMORY) continue;
    if (r != VK_SUCCESS) break;
    const VkMemoryPropertyFlags flags = ctx.memory_type_flags(type);
    check(vkBindBufferMemory(ctx.device(), rb.buffer, rb.memory, 0), "vkBindBufferMemory");
    if (map && (flags & host) == host) {
      check(vkMapMemory(ctx.device(), rb.memory, 0, VK_WHOLE_SIZE, 0, &rb.mapped), "vkMapMemory");
      rb.host_cached = (flags & cached) != 0;
    }
    return rb;
  }
  vkDestroyBuffer(ctx.device(), rb.buffer, nullptr);
  if (tried.empty()) throw Error("no memory type for a " + std::to_string(bytes) + "-byte buffer");
  check(r, ("vkAllocateMemory of " + std::to_string(bytes >> 20) + " MiB").c_str());
  throw Error("vkAllocateMemory failed");  // not reached: check throws
}

void destroy(Context& ctx, RawBuffer& rb) {
  if (rb.mapped) vkUnmapMemory(ctx.device(), rb.memory);
  vkDestroyBuffer(ctx.device(), rb.buffer, nullptr);
  vkFreeMemory(ctx.device(), rb.memory, nullptr);
}

const VkBufferUsageFlags kStorage = VK_BUFFER_USAGE_STORAGE_BUFFER_BIT | VK_BUFFER_USAGE_UNIFORM_TEXEL_BUFFER_BIT |
                                     VK_BUFFER_USAGE_TRANSFER_SRC_BIT | VK_BUFFER_USAGE_TRANSFER_DST_BIT;

// Bytes per texel of the formats Buffer::view offers.
uint64_t texel_bytes(VkFormat f) {
  switch (f) {
    case VK_FORMAT_R16_SFLOAT: return 2;
    case VK_FORMAT_R32_SFLOAT: return 4;
    case VK_FORMAT_R32G32B32A32_SFLOAT:
    case VK_FORMAT_R32G32B32A32_UINT: return 16;
    default: throw Error("Buffer::view: format " + std::to_string(int(f)) + " is not one of the texel formats used here");
  }
}
// Binding i of a kernel: a uniform texel buffer where texel_formats names a format for it.
VkDescriptorType descriptor_type(const std::vector<VkFormat>& texel_formats, uint32_t i) {
  return i < texel_formats.size() && texel_formats[i] != VK_FORMAT_UNDEFINED ? VK_DESCRIPTOR_TYPE_UNIFORM_TEXEL_BUFFER
                                                                             : VK_DESCRIPTOR_TYPE_STORAGE_BUFFER;
}

const VkBufferUsageFlags kStaging = VK_BUFFER_USAGE_TRANSFER_SRC_BIT | VK_BUFFER_USAGE_TRANSFER_DST_BIT;

}  // namespace

Buffer::Buffer(Context& ctx, uint64_t bytes) : ctx_(ctx), bytes_(bytes) {
  if (bytes == 0) throw Error("Buffer: zero-byte buffer requested");
  if (bytes > ctx.max_storage_buffer_bytes())
    throw Error("Buffer of " + std::to_string(bytes) + " bytes exceeds maxStorageBufferRange (" +
                std::to_string(ctx.max_storage_buffer_bytes()) + ") of " + ctx.describe() + "; chunk the data");
  RawBuffer rb = make_buffer(ctx, bytes, kStorage, Role::storage);
  buffer_ = rb.buffer;
  memory_ = rb.memory;
  mapped_ = rb.mapped;
  host_cached_ = rb.host_cached;
}

Buffer::~Buffer() {
  for (auto& [format, view] : views_) vkDestroyBufferView(ctx_.device(), view, nullptr);
  RawBuffer rb{buffer_, memory_, mapped_};
  destroy(ctx_, rb);
}

VkBufferView Buffer::view(VkFormat format) const {
  std::lock_guard<std::mutex> lock(views_mutex_);
  auto it = views_.find(format);
  if (it != views_.end()) return it->second;
  const uint64_t texels = bytes_ / texel_bytes(format);
  if (texels > ctx_.properties().limits.maxTexelBufferElements)
    throw Error("Buffer of " + std::to_string(bytes_) + " bytes holds " + std::to_string(texels) +
                " texels, more than maxTexelBufferElements (" +
                std::to_string(ctx_.properties().limits.maxTexelBufferElements) + ") of " + ctx_.describe() +
                "; chunk the data");
  VkBufferViewCreateInfo vi{VK_STRUCTURE_TYPE_BUFFER_VIEW_CREATE_INFO};
  vi.buffer = buffer_;
  vi.format = format;
  vi.offset = 0;
  vi.range = texels * texel_bytes(format);
  VkBufferView view;
  check(vkCreateBufferView(ctx_.device(), &vi, nullptr, &view), "vkCreateBufferView");
  return views_.emplace(format, view).first->second;
}

void Buffer::copy(VkBuffer src, VkBuffer dst, uint64_t src_off, uint64_t dst_off, uint64_t bytes) const {
  VkCommandBufferAllocateInfo ai{VK_STRUCTURE_TYPE_COMMAND_BUFFER_ALLOCATE_INFO};
  ai.commandPool = ctx_.command_pool();
  ai.level = VK_COMMAND_BUFFER_LEVEL_PRIMARY;
  ai.commandBufferCount = 1;
  VkCommandBuffer cmd;
  check(vkAllocateCommandBuffers(ctx_.device(), &ai, &cmd), "vkAllocateCommandBuffers");
  VkCommandBufferBeginInfo bi{VK_STRUCTURE_TYPE_COMMAND_BUFFER_BEGIN_INFO};
  bi.flags = VK_COMMAND_BUFFER_USAGE_ONE_TIME_SUBMIT_BIT;
  vkBeginCommandBuffer(cmd, &bi);
  // Earlier kernels' writes before the copy reads (or overwrites) them; the
  // copy's writes before later kernels and the host read them.
  VkMemoryBarrier before{VK_STRUCTURE_TYPE_MEMORY_BARRIER};
  before.srcAccessMask = VK_ACCESS_SHADER_WRITE_BIT | VK_ACCESS_TRANSFER_WRITE_BIT;
  before.dstAccessMask = VK_ACCESS_TRANSFER_READ_BIT | VK_ACCESS_TRANSFER_WRITE_BIT;
  vkCmdPipelineBarrier(cmd, VK_PIPELINE_STAGE_COMPUTE_SHADER_BIT | VK_PIPELINE_STAGE_TRANSFER_BIT,
                       VK_PIPELINE_STAGE_TRANSFER_BIT, 0, 1, &before, 0, nullptr, 0, nullptr);
  VkBufferCopy region{src_off, dst_off, bytes};
  vkCmdCopyBuffer(cmd, src, dst, 1, &region);
  VkMemoryBarrier after{VK_STRUCTURE_TYPE_MEMORY_BARRIER};
  after.srcAccessMask = VK_ACCESS_TRANSFER_WRITE_BIT;
  after.dstAccessMask = VK_ACCESS_SHADER_READ_BIT | VK_ACCESS_SHADER_WRITE_BIT | VK_ACCESS_HOST_READ_BIT;
  vkCmdPipelineBarrier(cmd, VK_PIPELINE_STAGE_TRANSFER_BIT, VK_PIPELINE_STAGE_COMPUTE_SHADER_BIT | VK_PIPELINE_STAGE_HOST_BIT,
                       0, 1, &after, 0, nullptr, 0, nullptr);
  vkEndCommandBuffer(cmd);
  VkSubmitInfo si{VK_STRUCTURE_TYPE_SUBMIT_INFO};
  si.commandBufferCount = 1;
  si.pCommandBuffers = &cmd;
  check(vkQueueSubmit(ctx_.queue(), 1, &si, VK_NULL_HANDLE), "vkQueueSubmit (copy)");
  check(vkQueueWaitIdle(ctx_.queue()), "vkQueueWaitIdle (copy)");
  vkFreeCommandBuffers(ctx_.device(), ctx_.command_pool(), 1, &cmd);
}

void Buffer::upload(const void* data, uint64_t bytes, uint64_t offset) {
  if (offset + bytes > bytes_) throw Error("Buffer::upload past the end of the buffer");
  if (mapped_) {  // host writes: combined on the way, fast whether cached or not
    std::memcpy(static_cast<char*>(mapped_) + offset, data, bytes);
    return;
  }
  RawBuffer staging = make_buffer(ctx_, bytes, kStaging, Role::staging);
  std::memcpy(staging.mapped, data, bytes);
  copy(staging.buffer, buffer_, 0, offset, bytes);
  destroy(ctx_, staging);
}

void Buffer::download(void* data, uint64_t bytes, uint64_t offset) const {
  if (offset + bytes > bytes_) throw Error("Buffer::download past the end of the buffer");
  // A few words (the footprint's list counts between its passes) cost less
  // read uncached across the bus (tens of microseconds) than a staging copy
  // (an allocation, a submit and a wait).
  constexpr uint64_t kUncachedReadBytes = 1024;
  if (mapped_ && (host_cached_ || bytes <= kUncachedReadBytes)) {
    std::memcpy(data, static_cast<const char*>(mapped_) + offset, bytes);
    return;
  }
  RawBuffer staging = make_buffer(ctx_, bytes, kStaging, Role::staging);
  copy(buffer_, staging.buffer, offset, 0, bytes);
  std::memcpy(data, staging.mapped, bytes);
  destroy(ctx_, staging);
}

// ---------------------------------------------------------------------------
// Kernel

PipelineCache::~PipelineCache() {
  for (auto& [key, p] : pipelines_) {
    vkDestroyPipeline(device_, p.pipeline, nullptr);
    vkDestroyPipelineLayout(device_, p.layout, nullptr);
    vkDestroyDescriptorSetLayout(device_, p.set_layout, nullptr);
  }
}

size_t PipelineCache::size() const {
  std::lock_guard lock(mutex_);
  return pipelines_.size();
}

const PipelineCache::Pipeline& PipelineCache::get(const std::string& name, std::span<const uint32_t> spirv,
                                                  uint32_t buffer_count, uint32_t push_bytes,
                                                  const std::vector<uint32_t>& specialisation,
                                                  const std::vector<VkFormat>& texel_formats) {
  std::lock_guard lock(mutex_);
  Key key{std::vector<uint32_t>(spirv.begin(), spirv.end()), buffer_count, push_bytes, specialisation, texel_formats};
  if (auto it = pipelines_.find(key); it != pipelines_.end()) return it->second;

  Pipeline p;
  // Whatever is created is destroyed again if a later step throws.
  struct Undo {
    VkDevice device;
    Pipeline& p;
    bool keep = false;
    ~Undo() {
      if (keep) return;
      vkDestroyPipelineLayout(device, p.layout, nullptr);
      vkDestroyDescriptorSetLayout(device, p.set_layout, nullptr);
    }
  } undo{device_, p};
  std::vector<VkDescriptorSetLayoutBinding> bindings(buffer_count);
  for (uint32_t i = 0; i < buffer_count; ++i)
    bindings[i] = {i, descriptor_type(texel_formats, i), 1, VK_SHADER_STAGE_COMPUTE_BIT, nullptr};
  VkDescriptorSetLayoutCreateInfo li{VK_STRUCTURE_TYPE_DESCRIPTOR_SET_LAYOUT_CREATE_INFO};
  li.bindingCount = buffer_count;
  li.pBindings = bindings.data();
  check(vkCreateDescriptorSetLayout(device_, &li, nullptr, &p.set_layout), "vkCreateDescriptorSetLayout");

  VkPushConstantRange range{VK_SHADER_STAGE_COMPUTE_BIT, 0, push_bytes};
  VkPipelineLayoutCreateInfo pli{VK_STRUCTURE_TYPE_PIPELINE_LAYOUT_CREATE_INFO};
  pli.setLayoutCount = 1;
  pli.pSetLayouts = &p.set_layout;
  pli.pushConstantRangeCount = push_bytes ? 1 : 0;
  pli.pPushConstantRanges = &range;
  check(vkCreatePipelineLayout(device_, &pli, nullptr, &p.layout), "vkCreatePipelineLayout");

  VkShaderModuleCreateInfo mi{VK_STRUCTURE_TYPE_SHADER_MODULE_CREATE_INFO};
  mi.codeSize = spirv.size_bytes();
  mi.pCode = spirv.data();
  VkShaderModule module;
  check(vkCreateShaderModule(device_, &mi, nullptr, &module), ("vkCreateShaderModule " + name).c_str());

  std::vector<VkSpecializationMapEntry> entries(specialisation.size());
  for (uint32_t i = 0; i < specialisation.size(); ++i) entries[i] = {i, uint32_t(i * sizeof(uint32_t)), sizeof(uint32_t)};
  VkSpecializationInfo si{uint32_t(entries.size()), entries.data(), specialisation.size() * sizeof(uint32_t),
                          specialisation.data()};
  VkComputePipelineCreateInfo ci{VK_STRUCTURE_TYPE_COMPUTE_PIPELINE_CREATE_INFO};
  ci.stage = {VK_STRUCTURE_TYPE_PIPELINE_SHADER_STAGE_CREATE_INFO};
  ci.stage.stage = VK_SHADER_STAGE_COMPUTE_BIT;
  ci.stage.module = module;
  ci.stage.pName = "main";
  ci.stage.pSpecializationInfo = specialisation.empty() ? nullptr : &si;
  ci.layout = p.layout;
  VkResult r = vkCreateComputePipelines(device_, VK_NULL_HANDLE, 1, &ci, nullptr, &p.pipeline);
  vkDestroyShaderModule(device_, module, nullptr);
  check(r, ("vkCreateComputePipelines " + name).c_str());
  undo.keep = true;
  return pipelines_.emplace(std::move(key), p).first->second;
}

Kernel::Kernel(Context& ctx, std::string name, std::span<const uint32_t> spirv, uint32_t buffer_count,
               uint32_t push_bytes, std::vector<uint32_t> specialisation, std::vector<VkFormat> texel_formats)
    : ctx_(ctx),
      name_(std::move(name)),
      spirv_(spirv.begin(), spirv.end()),
      buffer_count_(buffer_count),
      push_bytes_(push_bytes),
      specialisation_(std::move(specialisation)),
      texel_formats_(std::move(texel_formats)) {}

const PipelineCache::Pipeline& Kernel::pipeline() {
  if (!pipeline_) pipeline_ = &ctx_.pipelines().get(name_, spirv_, buffer_count_, push_bytes_, specialisation_, texel_formats_);
  return *pipeline_;
}

// ---------------------------------------------------------------------------
// Stream

Stream::Stream(Context& ctx, uint32_t max_dispatches) : ctx_(ctx), max_dispatches_(max_dispatches) {
  VkCommandBufferAllocateInfo ai{VK_STRUCTURE_TYPE_COMMAND_BUFFER_ALLOCATE_INFO};
  ai.commandPool = ctx.command_pool();
  ai.level = VK_COMMAND_BUFFER_LEVEL_PRIMARY;
  ai.commandBufferCount = 1;
  check(vkAllocateCommandBuffers(ctx.device(), &ai, &cmd_), "vkAllocateCommandBuffers");
  const VkDescriptorPoolSize sizes[2] = {{VK_DESCRIPTOR_TYPE_STORAGE_BUFFER, max_dispatches * 8},
                                         {VK_DESCRIPTOR_TYPE_UNIFORM_TEXEL_BUFFER, max_dispatches * 4}};
  VkDescriptorPoolCreateInfo pi{VK_STRUCTURE_TYPE_DESCRIPTOR_POOL_CREATE_INFO};
  pi.maxSets = max_dispatches;
  pi.poolSizeCount = 2;
  pi.pPoolSizes = sizes;
  check(vkCreateDescriptorPool(ctx.device(), &pi, nullptr, &pool_), "vkCreateDescriptorPool");
  if (ctx.timestamp_period_ns() > 0) {
    VkQueryPoolCreateInfo qi{VK_STRUCTURE_TYPE_QUERY_POOL_CREATE_INFO};
    qi.queryType = VK_QUERY_TYPE_TIMESTAMP;
    qi.queryCount = 2 * max_dispatches;
    check(vkCreateQueryPool(ctx.device(), &qi, nullptr, &queries_), "vkCreateQueryPool");
  }
  VkFenceCreateInfo fi{VK_STRUCTURE_TYPE_FENCE_CREATE_INFO};
  check(vkCreateFence(ctx.device(), &fi, nullptr, &fence_), "vkCreateFence");
}

Stream::~Stream() {
  vkDestroyFence(ctx_.device(), fence_, nullptr);
  if (queries_) vkDestroyQueryPool(ctx_.device(), queries_, nullptr);
  vkDestroyDescriptorPool(ctx_.device(), pool_, nullptr);
  vkFreeCommandBuffers(ctx_.device(), ctx_.command_pool(), 1, &cmd_);
}

void Stream::begin_if_needed() {
  if (recording_) return;
  VkCommandBufferBeginInfo bi{VK_STRUCTURE_TYPE_COMMAND_BUFFER_BEGIN_INFO};
  bi.flags = VK_COMMAND_BUFFER_USAGE_ONE_TIME_SUBMIT_BIT;
  check(vkBeginCommandBuffer(cmd_, &bi), "vkBeginCommandBuffer");
  if (queries_) vkCmdResetQueryPool(cmd_, queries_, 0, 2 * max_dispatches_);
  recording_ = true;
  dispatches_ = 0;
  names_.clear();
}

void Stream::fill_zero(Buffer& buffer) {
  begin_if_needed();
  vkCmdFillBuffer(cmd_, buffer.handle(), 0, VK_WHOLE_SIZE, 0);
}

void Stream::fill_zero(Buffer& buffer, uint64_t offset, uint64_t bytes) {
  begin_if_needed();
  vkCmdFillBuffer(cmd_, buffer.handle(), offset, bytes, 0);
}

void Stream::barrier() {
  begin_if_needed();
  VkMemoryBarrier mb{VK_STRUCTURE_TYPE_MEMORY_BARRIER};
  mb.srcAccessMask = VK_ACCESS_SHADER_WRITE_BIT | VK_ACCESS_TRANSFER_WRITE_BIT;
  mb.dstAccessMask = VK_ACCESS_SHADER_READ_BIT | VK_ACCESS_SHADER_WRITE_BIT;
  vkCmdPipelineBarrier(cmd_, VK_PIPELINE_STAGE_COMPUTE_SHADER_BIT | VK_PIPELINE_STAGE_TRANSFER_BIT,
                       VK_PIPELINE_STAGE_COMPUTE_SHADER_BIT, 0, 1, &mb, 0, nullptr, 0, nullptr);
}

void Stream::dispatch(Kernel& k, std::initializer_list<const Buffer*> buffers, const void* push, uint32_t gx,
                      uint32_t gy, uint32_t gz) {
  begin_if_needed();
  if (buffers.size() != k.buffer_count_)
    throw Error("dispatch " + k.name_ + ": expects " + std::to_string(k.buffer_count_) + " buffers, got " +
                std::to_string(buffers.size()));
  if (dispatches_ >= max_dispatches_) throw Error("Stream: more than " + std::to_string(max_dispatches_) + " dispatches before submit()");
  const PipelineCache::Pipeline& p = k.pipeline();
  VkDescriptorSetAllocateInfo ai{VK_STRUCTURE_TYPE_DESCRIPTOR_SET_ALLOCATE_INFO};
  ai.descriptorPool = pool_;
  ai.descriptorSetCount = 1;
  ai.pSetLayouts = &p.set_layout;
  VkDescriptorSet set;
  check(vkAllocateDescriptorSets(ctx_.device(), &ai, &set), "vkAllocateDescriptorSets");
  std::vector<VkDescriptorBufferInfo> infos;
  std::vector<VkBufferView> views;
  for (const Buffer* b : buffers) {
    const uint32_t i = uint32_t(infos.size());
    infos.push_back({b->handle(), 0, VK_WHOLE_SIZE});
    const bool texel = descriptor_type(k.texel_formats_, i) == VK_DESCRIPTOR_TYPE_UNIFORM_TEXEL_BUFFER;
    views.push_back(texel ? b->view(k.texel_formats_[i]) : VK_NULL_HANDLE);
  }
  std::vector<VkWriteDescriptorSet> writes(infos.size());
  for (uint32_t i = 0; i < infos.size(); ++i) {
    writes[i] = {VK_STRUCTURE_TYPE_WRITE_DESCRIPTOR_SET};
    writes[i].dstSet = set;
    writes[i].dstBinding = i;
    writes[i].descriptorCount = 1;
    writes[i].descriptorType = descriptor_type(k.texel_formats_, i);
    if (views[i] != VK_NULL_HANDLE)
      writes[i].pTexelBufferView = &views[i];
    else
      writes[i].pBufferInfo = &infos[i];
  }
  vkUpdateDescriptorSets(ctx_.device(), uint32_t(writes.size()), writes.data(), 0, nullptr);

  vkCmdBindPipeline(cmd_, VK_PIPELINE_BIND_POINT_COMPUTE, p.pipeline);
  vkCmdBindDescriptorSets(cmd_, VK_PIPELINE_BIND_POINT_COMPUTE, p.layout, 0, 1, &set, 0, nullptr);
  if (k.push_bytes_) vkCmdPushConstants(cmd_, p.layout, VK_SHADER_STAGE_COMPUTE_BIT, 0, k.push_bytes_, push);
  if (queries_) vkCmdWriteTimestamp(cmd_, VK_PIPELINE_STAGE_TOP_OF_PIPE_BIT, queries_, 2 * dispatches_);
  vkCmdDispatch(cmd_, gx, gy, gz);
  if (queries_) vkCmdWriteTimestamp(cmd_, VK_PIPELINE_STAGE_BOTTOM_OF_PIPE_BIT, queries_, 2 * dispatches_ + 1);
  names_.push_back(k.name_);
  ++dispatches_;
}

double Stream::submit() {
  if (!recording_) return 0.0;
  check(vkEndCommandBuffer(cmd_), "vkEndCommandBuffer");
  recording_ = false;
  VkSubmitInfo si{VK_STRUCTURE_TYPE_SUBMIT_INFO};
  si.commandBufferCount = 1;
  si.pCommandBuffers = &cmd_;
  auto t0 = std::chrono::steady_clock::now();
  check(vkResetFences(ctx_.device(), 1, &fence_), "vkResetFences");
  check(vkQueueSubmit(ctx_.queue(), 1, &si, fence_), "vkQueueSubmit");
  check(vkWaitForFences(ctx_.device(), 1, &fence_, VK_TRUE, UINT64_MAX), "vkWaitForFences");
  double wall_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  double ms = wall_ms;
  times_.clear();
  if (queries_ && dispatches_ > 0) {
    std::vector<uint64_t> stamps(2 * dispatches_);
    check(vkGetQueryPoolResults(ctx_.device(), queries_, 0, 2 * dispatches_, stamps.size() * sizeof(uint64_t),
                                stamps.data(), sizeof(uint64_t), VK_QUERY_RESULT_64_BIT | VK_QUERY_RESULT_WAIT_BIT),
          "vkGetQueryPoolResults");
    ms = 0;
    for (uint32_t i = 0; i < dispatches_; ++i) {
      const double t = double(stamps[2 * i + 1] - stamps[2 * i]) * ctx_.timestamp_period_ns() * 1e-6;
      ms += t;
      times_.push_back({names_[i], t});
    }
  }
  names_.clear();
  check(vkResetDescriptorPool(ctx_.device(), pool_, 0), "vkResetDescriptorPool");
  check(vkResetCommandBuffer(cmd_, 0), "vkResetCommandBuffer");
  dispatches_ = 0;
  return ms;
}

}  // namespace prism::vk
