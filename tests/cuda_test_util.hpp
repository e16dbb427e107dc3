// Shared plumbing of the CUDA test programs (tests/test_cuda_*.cu): skipping with
// a visible reason when no device is usable, checked CUDA calls, device buffers.
#pragma once

#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cstddef>
#include <string>

#include "scandyn/cuda/device.hpp"

namespace scandyn::test {

// Why CUDA tests cannot run here, or "" when a device is usable.
inline std::string no_device_reason() {
  const auto count = scandyn::cuda::device_count();
  const std::string prefix = "no usable CUDA device: ";
  if (!count) {
    return count.error.compare(0, prefix.size(), prefix) == 0 ? count.error.substr(prefix.size())
                                                              : count.error;
  }
  if (count.value == 0) return "the CUDA runtime reports 0 devices";
  return "";
}

// Device memory for n objects (at least one, so n = 0 is a valid pointer), freed
// on scope exit.
template <class T>
struct DeviceArray {
  T* ptr = nullptr;
  cudaError_t alloc(std::size_t n) {
    return cudaMalloc(reinterpret_cast<void**>(&ptr), std::max<std::size_t>(n, 1) * sizeof(T));
  }
  ~DeviceArray() {
    if (ptr) cudaFree(ptr);
  }
};

}  // namespace scandyn::test

#define SKIP_WITHOUT_CUDA_DEVICE()                                           \
  do {                                                                       \
    const std::string why = ::scandyn::test::no_device_reason();             \
    if (!why.empty()) GTEST_SKIP() << "no CUDA device: " << why;             \
  } while (0)

#define ASSERT_CUDA(call)                                                       \
  do {                                                                          \
    const cudaError_t err_ = (call);                                            \
    ASSERT_EQ(err_, cudaSuccess) << #call << ": " << cudaGetErrorString(err_); \
  } while (0)
