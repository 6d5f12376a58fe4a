// Errors the engine raises: every Vulkan failure becomes an exception with the
// VkResult spelled out and the call that failed.
#pragma once
#include <stdexcept>
#include <string>
#include <vulkan/vulkan.h>

namespace prism::vk {

struct Error : std::runtime_error {
  using std::runtime_error::runtime_error;
};

const char* result_name(VkResult r);

inline void check(VkResult r, const char* what) {
  if (r != VK_SUCCESS) throw Error(std::string(what) + " failed: " + result_name(r));
}

}  // namespace prism::vk
