#include "engine/vk/context.h"

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <cstring>

#include "engine/vk/compute.h"
#include "engine/vk/error.h"

namespace prism::vk {

namespace {

const char* kValidationLayer = "VK_LAYER_KHRONOS_validation";
const char* kNoDriver =
    "no Vulkan device found: install a Vulkan driver (Debian: `apt-get install mesa-vulkan-drivers` "
    "for the CPU driver lavapipe, or your GPU vendor's driver)";

const char* type_name(VkPhysicalDeviceType t) {
  switch (t) {
    case VK_PHYSICAL_DEVICE_TYPE_DISCRETE_GPU: return "discrete gpu";
    case VK_PHYSICAL_DEVICE_TYPE_INTEGRATED_GPU: return "integrated gpu";
    case VK_PHYSICAL_DEVICE_TYPE_VIRTUAL_GPU: return "virtual gpu";
    case VK_PHYSICAL_DEVICE_TYPE_CPU: return "cpu";
    default: return "other";
  }
}

unsigned device_slot = 0;  // set_device_slot

// Higher is preferred by "auto": a real GPU first, lavapipe last.
int preference(VkPhysicalDeviceType t) {
  switch (t) {
    case VK_PHYSICAL_DEVICE_TYPE_DISCRETE_GPU: return 4;
    case VK_PHYSICAL_DEVICE_TYPE_INTEGRATED_GPU: return 3;
    case VK_PHYSICAL_DEVICE_TYPE_VIRTUAL_GPU: return 2;
    case VK_PHYSICAL_DEVICE_TYPE_CPU: return 1;
    default: return 0;
  }
}

VkInstance create_instance(bool validation) {
  VkApplicationInfo app{VK_STRUCTURE_TYPE_APPLICATION_INFO};
  app.pApplicationName = "prism";
  app.apiVersion = VK_API_VERSION_1_2;
  VkInstanceCreateInfo ci{VK_STRUCTURE_TYPE_INSTANCE_CREATE_INFO};
  ci.pApplicationInfo = &app;
  const char* ext = VK_EXT_DEBUG_UTILS_EXTENSION_NAME;
  if (validation) {
    uint32_t n = 0;
    vkEnumerateInstanceLayerProperties(&n, nullptr);
    std::vector<VkLayerProperties> layers(n);
    vkEnumerateInstanceLayerProperties(&n, layers.data());
    bool found = std::any_of(layers.begin(), layers.end(),
                             [](const VkLayerProperties& l) { return std::strcmp(l.layerName, kValidationLayer) == 0; });
    if (!found)
      throw Error("the Vulkan validation layer was requested but is not installed: `apt-get install vulkan-validationlayers`");
    ci.enabledLayerCount = 1;
    ci.ppEnabledLayerNames = &kValidationLayer;
    ci.enabledExtensionCount = 1;
    ci.ppEnabledExtensionNames = &ext;
  }
  VkInstance instance = VK_NULL_HANDLE;
  VkResult r = vkCreateInstance(&ci, nullptr, &instance);
  if (r == VK_ERROR_INCOMPATIBLE_DRIVER || r == VK_ERROR_INITIALIZATION_FAILED) throw Error(kNoDriver);
  check(r, "vkCreateInstance");
  return instance;
}

std::vector<VkPhysicalDevice> physical_devices(VkInstance instance) {
  uint32_t n = 0;
  check(vkEnumeratePhysicalDevices(instance, &n, nullptr), "vkEnumeratePhysicalDevices");
  std::vector<VkPhysicalDevice> devices(n);
  check(vkEnumeratePhysicalDevices(instance, &n, devices.data()), "vkEnumeratePhysicalDevices");
  if (devices.empty()) throw Error(kNoDriver);
  return devices;
}

VkPhysicalDevice choose(const std::vector<VkPhysicalDevice>& devices, const std::string& request) {
  std::vector<VkPhysicalDeviceProperties> props(devices.size());
  for (size_t i = 0; i < devices.size(); ++i) vkGetPhysicalDeviceProperties(devices[i], &props[i]);
  // The most preferred of the accepted devices; of several equal ones, the
  // slot's (set_device_slot).
  auto best_of = [&](auto accept) -> VkPhysicalDevice {
    std::vector<size_t> best;
    for (size_t i = 0; i < devices.size(); ++i) {
      if (!accept(props[i])) continue;
      if (!best.empty() && preference(props[i].deviceType) > preference(props[best[0]].deviceType)) best.clear();
      if (best.empty() || preference(props[i].deviceType) == preference(props[best[0]].deviceType)) best.push_back(i);
    }
    return best.empty() ? VK_NULL_HANDLE : devices[best[device_slot % best.size()]];
  };
  auto is_cpu = [](const VkPhysicalDeviceProperties& p) { return p.deviceType == VK_PHYSICAL_DEVICE_TYPE_CPU; };
  VkPhysicalDevice chosen = VK_NULL_HANDLE;
  if (request.empty() || request == "auto") {
    chosen = best_of([](const auto&) { return true; });
  } else if (request == "cpu") {
    chosen = best_of(is_cpu);
    if (!chosen) throw Error("--device cpu: no CPU Vulkan device; install mesa-vulkan-drivers for lavapipe");
  } else if (request == "gpu") {
    chosen = best_of([&](const auto& p) { return !is_cpu(p); });
    if (!chosen) throw Error("--device gpu: no GPU Vulkan device found (only lavapipe); use --device cpu or auto");
  } else if (std::all_of(request.begin(), request.end(), ::isdigit)) {
    size_t i = std::stoul(request);
    if (i >= devices.size())
      throw Error("--device " + request + ": only " + std::to_string(devices.size()) + " Vulkan device(s)");
    chosen = devices[i];
  } else {
    chosen = best_of([&](const auto& p) { return std::strstr(p.deviceName, request.c_str()) != nullptr; });
    if (!chosen) throw Error("--device " + request + ": no Vulkan device name contains it; try `auto`, `gpu`, `cpu` or an index");
  }
  return chosen;
}

}  // namespace

void set_device_slot(unsigned slot) { device_slot = slot; }

VKAPI_ATTR VkBool32 VKAPI_CALL Context::on_message(VkDebugUtilsMessageSeverityFlagBitsEXT severity,
                                                   VkDebugUtilsMessageTypeFlagsEXT,
                                                   const VkDebugUtilsMessengerCallbackDataEXT* data, void* user) {
  if (severity >= VK_DEBUG_UTILS_MESSAGE_SEVERITY_WARNING_BIT_EXT) {
    auto* self = static_cast<Context*>(user);
    self->messages_.emplace_back(data->pMessage ? data->pMessage : "(empty message)");
    std::fprintf(stderr, "vulkan validation: %s\n", self->messages_.back().c_str());
  }
  return VK_FALSE;
}

Context::Context(ContextOptions options) {
  const char* env_validation = std::getenv("PRISM_VALIDATION");
  bool validation = options.validation || (env_validation && std::strcmp(env_validation, "0") != 0);
  std::string request = options.device;
  if (request.empty())
    if (const char* env = std::getenv("PRISM_DEVICE")) request = env;

  staged_buffers_ = options.staged_buffers;
  instance_ = create_instance(validation);
  if (validation) {
    VkDebugUtilsMessengerCreateInfoEXT mi{VK_STRUCTURE_TYPE_DEBUG_UTILS_MESSENGER_CREATE_INFO_EXT};
    mi.messageSeverity = VK_DEBUG_UTILS_MESSAGE_SEVERITY_WARNING_BIT_EXT | VK_DEBUG_UTILS_MESSAGE_SEVERITY_ERROR_BIT_EXT;
    mi.messageType = VK_DEBUG_UTILS_MESSAGE_TYPE_GENERAL_BIT_EXT | VK_DEBUG_UTILS_MESSAGE_TYPE_VALIDATION_BIT_EXT |
                     VK_DEBUG_UTILS_MESSAGE_TYPE_PERFORMANCE_BIT_EXT;
    mi.pfnUserCallback = &Context::on_message;
    mi.pUserData = this;
    auto create = reinterpret_cast<PFN_vkCreateDebugUtilsMessengerEXT>(
        vkGetInstanceProcAddr(instance_, "vkCreateDebugUtilsMessengerEXT"));
    check(create(instance_, &mi, nullptr, &messenger_), "vkCreateDebugUtilsMessengerEXT");
  }

  physical_ = choose(physical_devices(instance_), request);
  vkGetPhysicalDeviceProperties(physical_, &props_);
  vkGetPhysicalDeviceMemoryProperties(physical_, &mem_props_);

  // A compute queue.
  uint32_t nq = 0;
  vkGetPhysicalDeviceQueueFamilyProperties(physical_, &nq, nullptr);
  std::vector<VkQueueFamilyProperties> families(nq);
  vkGetPhysicalDeviceQueueFamilyProperties(physical_, &nq, families.data());
  queue_family_ = UINT32_MAX;
  for (uint32_t i = 0; i < nq; ++i)
    if (families[i].queueFlags & VK_QUEUE_COMPUTE_BIT) {
      queue_family_ = i;
      break;
    }
  if (queue_family_ == UINT32_MAX) throw Error(std::string(props_.deviceName) + " has no compute queue");
  if (families[queue_family_].timestampValidBits > 0) timestamp_period_ns_ = props_.limits.timestampPeriod;

  // The splat kernel accumulates photons with float atomics.
  VkPhysicalDeviceShaderAtomicFloatFeaturesEXT atomics{VK_STRUCTURE_TYPE_PHYSICAL_DEVICE_SHADER_ATOMIC_FLOAT_FEATURES_EXT};
  VkPhysicalDeviceFeatures2 features{VK_STRUCTURE_TYPE_PHYSICAL_DEVICE_FEATURES_2};
  features.pNext = &atomics;
  vkGetPhysicalDeviceFeatures2(physical_, &features);
  if (!atomics.shaderBufferFloat32AtomicAdd)
    throw Error(std::string(props_.deviceName) +
                " lacks float atomic add on buffers (VK_EXT_shader_atomic_float); choose another --device");
  VkPhysicalDeviceShaderAtomicFloatFeaturesEXT enable_atomics{VK_STRUCTURE_TYPE_PHYSICAL_DEVICE_SHADER_ATOMIC_FLOAT_FEATURES_EXT};
  enable_atomics.shaderBufferFloat32AtomicAdd = VK_TRUE;

  float priority = 1.0f;
  VkDeviceQueueCreateInfo qi{VK_STRUCTURE_TYPE_DEVICE_QUEUE_CREATE_INFO};
  qi.queueFamilyIndex = queue_family_;
  qi.queueCount = 1;
  qi.pQueuePriorities = &priority;
  const char* dev_ext = VK_EXT_SHADER_ATOMIC_FLOAT_EXTENSION_NAME;
  VkDeviceCreateInfo di{VK_STRUCTURE_TYPE_DEVICE_CREATE_INFO};
  di.pNext = &enable_atomics;
  di.queueCreateInfoCount = 1;
  di.pQueueCreateInfos = &qi;
  di.enabledExtensionCount = 1;
  di.ppEnabledExtensionNames = &dev_ext;
  check(vkCreateDevice(physical_, &di, nullptr, &device_), "vkCreateDevice");
  vkGetDeviceQueue(device_, queue_family_, 0, &queue_);

  VkCommandPoolCreateInfo pi{VK_STRUCTURE_TYPE_COMMAND_POOL_CREATE_INFO};
  pi.flags = VK_COMMAND_POOL_CREATE_RESET_COMMAND_BUFFER_BIT;
  pi.queueFamilyIndex = queue_family_;
  check(vkCreateCommandPool(device_, &pi, nullptr, &pool_), "vkCreateCommandPool");
  pipelines_ = std::make_unique<PipelineCache>(device_);
}

Context::~Context() {
  if (device_) {
    vkDeviceWaitIdle(device_);
    pipelines_.reset();
    vkDestroyCommandPool(device_, pool_, nullptr);
    vkDestroyDevice(device_, nullptr);
  }
  if (messenger_) {
    auto destroy = reinterpret_cast<PFN_vkDestroyDebugUtilsMessengerEXT>(
        vkGetInstanceProcAddr(instance_, "vkDestroyDebugUtilsMessengerEXT"));
    destroy(instance_, messenger_, nullptr);
  }
  if (instance_) vkDestroyInstance(instance_, nullptr);
}

std::string Context::describe() const {
  uint32_t v = props_.apiVersion;
  return std::string(props_.deviceName) + " [" + type_name(props_.deviceType) + ", Vulkan " +
         std::to_string(VK_API_VERSION_MAJOR(v)) + "." + std::to_string(VK_API_VERSION_MINOR(v)) + "." +
         std::to_string(VK_API_VERSION_PATCH(v)) + "]";
}

uint32_t Context::find_memory_type(uint32_t type_bits, VkMemoryPropertyFlags want) const {
  for (uint32_t i = 0; i < mem_props_.memoryTypeCount; ++i)
    if ((type_bits & (1u << i)) && (mem_props_.memoryTypes[i].propertyFlags & want) == want) return i;
  return UINT32_MAX;
}

std::vector<std::string> Context::list_devices() {
  VkInstance instance = create_instance(false);
  std::vector<std::string> out;
  try {
    auto devices = physical_devices(instance);
    for (size_t i = 0; i < devices.size(); ++i) {
      VkPhysicalDeviceProperties p;
      vkGetPhysicalDeviceProperties(devices[i], &p);
      out.push_back(std::to_string(i) + ": " + p.deviceName + " [" + type_name(p.deviceType) + "]");
    }
  } catch (...) {
    vkDestroyInstance(instance, nullptr);
    throw;
  }
  vkDestroyInstance(instance, nullptr);
  return out;
}

const char* result_name(VkResult r) {
  switch (r) {
#define PRISM_VK_CASE(x) \
  case x: return #x;
    PRISM_VK_CASE(VK_SUCCESS)
    PRISM_VK_CASE(VK_NOT_READY)
    PRISM_VK_CASE(VK_TIMEOUT)
    PRISM_VK_CASE(VK_INCOMPLETE)
    PRISM_VK_CASE(VK_ERROR_OUT_OF_HOST_MEMORY)
    PRISM_VK_CASE(VK_ERROR_OUT_OF_DEVICE_MEMORY)
    PRISM_VK_CASE(VK_ERROR_INITIALIZATION_FAILED)
    PRISM_VK_CASE(VK_ERROR_DEVICE_LOST)
    PRISM_VK_CASE(VK_ERROR_MEMORY_MAP_FAILED)
    PRISM_VK_CASE(VK_ERROR_LAYER_NOT_PRESENT)
    PRISM_VK_CASE(VK_ERROR_EXTENSION_NOT_PRESENT)
    PRISM_VK_CASE(VK_ERROR_FEATURE_NOT_PRESENT)
    PRISM_VK_CASE(VK_ERROR_INCOMPATIBLE_DRIVER)
    PRISM_VK_CASE(VK_ERROR_TOO_MANY_OBJECTS)
    PRISM_VK_CASE(VK_ERROR_FORMAT_NOT_SUPPORTED)
    PRISM_VK_CASE(VK_ERROR_OUT_OF_POOL_MEMORY)
#undef PRISM_VK_CASE
    default: return "VkResult (unknown)";
  }
}

}  // namespace prism::vk
