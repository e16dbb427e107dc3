// kernels/device.cu: the host API of scandyn/cuda/device.hpp over the CUDA runtime.
#include <cuda_runtime.h>

#include <string>

#include "scandyn/cuda/device.hpp"

namespace scandyn {
namespace cuda {
namespace {

// The runtime's message for err. Also resets the runtime's last-error state, so
// a failed query does not resurface in the caller's next cudaGetLastError()
// (initialisation failures, e.g. no driver, stay: every later call reports them).
std::string runtime_error_string(cudaError_t err) {
  (void)cudaGetLastError();
  const char* msg = cudaGetErrorString(err);
  return msg ? msg : "unknown CUDA error " + std::to_string(static_cast<int>(err));
}

}  // namespace

Result<int> device_count() {
  int n = 0;
  const cudaError_t err = cudaGetDeviceCount(&n);
  if (err != cudaSuccess) return {0, "no usable CUDA device: " + runtime_error_string(err)};
  return {n, {}};
}

Result<DeviceInfo> device_info(int device) {
  const Result<int> count = device_count();
  if (!count) return {DeviceInfo{}, count.error};
  if (device < 0 || device >= count.value) {
    return {DeviceInfo{}, "no CUDA device " + std::to_string(device) + ": " +
                              std::to_string(count.value) + " device(s) visible"};
  }
  cudaDeviceProp p{};
  cudaError_t err = cudaGetDeviceProperties(&p, device);
  if (err != cudaSuccess) {
    return {DeviceInfo{}, "cudaGetDeviceProperties(" + std::to_string(device) +
                              "): " + runtime_error_string(err)};
  }
  DeviceInfo d;
  d.index = device;
  d.name = p.name;
  d.total_memory = p.totalGlobalMem;
  d.multiprocessors = p.multiProcessorCount;
  d.cc_major = p.major;
  d.cc_minor = p.minor;
  d.warp_size = p.warpSize;
  d.max_threads_per_block = p.maxThreadsPerBlock;
  d.shared_memory_per_block = p.sharedMemPerBlockOptin > p.sharedMemPerBlock
                                  ? p.sharedMemPerBlockOptin
                                  : p.sharedMemPerBlock;
  d.l2_cache = p.l2CacheSize > 0 ? static_cast<std::size_t>(p.l2CacheSize) : 0;
  if ((err = cudaDriverGetVersion(&d.driver_version)) != cudaSuccess) {
    return {DeviceInfo{}, "cudaDriverGetVersion: " + runtime_error_string(err)};
  }
  if ((err = cudaRuntimeGetVersion(&d.runtime_version)) != cudaSuccess) {
    return {DeviceInfo{}, "cudaRuntimeGetVersion: " + runtime_error_string(err)};
  }
  return {d, {}};
}

Result<int> current_device() {
  int d = 0;
  const cudaError_t err = cudaGetDevice(&d);
  if (err != cudaSuccess) return {0, "no usable CUDA device: " + runtime_error_string(err)};
  return {d, {}};
}

Result<int> set_current_device(int device) {
  const Result<int> count = device_count();
  if (!count) return {0, count.error};
  if (device < 0 || device >= count.value) {
    return {0, "no CUDA device " + std::to_string(device) + ": " + std::to_string(count.value) +
                   " device(s) visible"};
  }
  const cudaError_t err = cudaSetDevice(device);
  if (err != cudaSuccess) {
    return {0, "cudaSetDevice(" + std::to_string(device) + "): " + runtime_error_string(err)};
  }
  return {device, {}};
}

}  // namespace cuda
}  // namespace scandyn
