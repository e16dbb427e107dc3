// scandyn::cuda::device_count() / device_info(): errors are values, never crashes.
// Runs on every machine: without a driver or device the calls must fail cleanly
// with "no usable CUDA device: ..."; with devices the reported properties must be
// plausible and match what a kernel sees.
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <string>

#include "scandyn/cuda/device.hpp"

namespace {

using scandyn::cuda::device_count;
using scandyn::cuda::device_info;

bool starts_with(const std::string& s, const std::string& prefix) {
  return s.compare(0, prefix.size(), prefix) == 0;
}

// The skip message: "no CUDA device: <why>".
std::string skip_reason(const std::string& error) {
  const std::string prefix = "no usable CUDA device: ";
  return "no CUDA device: " + (starts_with(error, prefix) ? error.substr(prefix.size()) : error);
}

TEST(CudaDevice, CountIsAValueOrAClearError) {
  const auto count = device_count();
  if (count) {
    EXPECT_GE(count.value, 0);
    EXPECT_TRUE(count.error.empty());
  } else {
    EXPECT_TRUE(starts_with(count.error, "no usable CUDA device: ")) << count.error;
    EXPECT_GT(count.error.size(), std::string("no usable CUDA device: ").size()) << count.error;
  }
  // asking twice gives the same answer
  const auto again = device_count();
  EXPECT_EQ(again.ok(), count.ok());
  EXPECT_EQ(again.value, count.value);
  EXPECT_EQ(again.error, count.error);
}

TEST(CudaDevice, OutOfRangeOrdinalsAreErrors) {
  const auto count = device_count();
  const int n = count ? count.value : 0;
  for (int bad : {-1, n, n + 7}) {
    const auto info = device_info(bad);
    EXPECT_FALSE(info.ok()) << "device " << bad;
    EXPECT_FALSE(info.error.empty());
    if (!count) EXPECT_EQ(info.error, count.error);
  }
}

TEST(CudaDevice, InfoOfEveryDevice) {
  const auto count = device_count();
  if (!count) GTEST_SKIP() << skip_reason(count.error);
  if (count.value == 0) GTEST_SKIP() << "no CUDA device: the CUDA runtime reports 0 devices";
  for (int d = 0; d < count.value; ++d) {
    const auto info = device_info(d);
    ASSERT_TRUE(info.ok()) << info.error;
    const auto& i = info.value;
    EXPECT_EQ(i.index, d);
    EXPECT_FALSE(i.name.empty());
    EXPECT_GT(i.total_memory, std::size_t(0));
    EXPECT_GT(i.multiprocessors, 0);
    EXPECT_GE(i.cc_major, 5);
    EXPECT_GE(i.cc_minor, 0);
    EXPECT_EQ(i.warp_size, 32);
    EXPECT_GT(i.max_threads_per_block, 0);
    EXPECT_GT(i.shared_memory_per_block, std::size_t(0));
    EXPECT_GE(i.driver_version, i.runtime_version) << "driver older than the runtime";
    const std::string line = scandyn::cuda::describe(i);
    EXPECT_NE(line.find(i.name), std::string::npos) << line;
    EXPECT_NE(line.find("sm_" + std::to_string(i.cc_major) + std::to_string(i.cc_minor)),
              std::string::npos)
        << line;
    std::printf("%s\n", line.c_str());
  }
}

__global__ void write_one_kernel(int* out) { *out = 1; }

TEST(CudaDevice, KernelRunsOnDeviceZero) {
  const auto info = device_info(0);
  if (!info) GTEST_SKIP() << skip_reason(info.error);
  int* d = nullptr;
  ASSERT_EQ(cudaMalloc(&d, sizeof(int)), cudaSuccess);
  ASSERT_EQ(cudaMemset(d, 0, sizeof(int)), cudaSuccess);
  write_one_kernel<<<1, 1>>>(d);
  const cudaError_t launch = cudaGetLastError();
  const cudaError_t sync = cudaDeviceSynchronize();
  int h = 0;
  const cudaError_t copy = cudaMemcpy(&h, d, sizeof(int), cudaMemcpyDeviceToHost);
  cudaFree(d);
  ASSERT_EQ(launch, cudaSuccess) << cudaGetErrorString(launch)
                                 << " (was the library built for sm_" << info.value.cc_major
                                 << info.value.cc_minor << "? see CMAKE_CUDA_ARCHITECTURES)";
  ASSERT_EQ(sync, cudaSuccess) << cudaGetErrorString(sync);
  ASSERT_EQ(copy, cudaSuccess) << cudaGetErrorString(copy);
  EXPECT_EQ(h, 1);
}

}  // namespace
