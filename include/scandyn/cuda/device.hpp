// scandyn/cuda/device.hpp: which CUDA devices this process can use.
//
// A small host API over the CUDA runtime. Failures come back as values, never
// as exceptions or aborts: on a machine without a driver or a device,
// device_count() returns an error such as
//   "no usable CUDA device: CUDA driver version is insufficient for CUDA runtime version".
// Usable from plain C++ translation units (no CUDA headers are included). In a
// build without CUDA (SCANDYN_HAS_CUDA == 0) every call returns an error saying so.
#pragma once

#include <cstddef>
#include <string>

#include "scandyn/build_config.hpp"

namespace scandyn {
namespace cuda {

// A value or one line saying why there is none.
template <class T>
struct Result {
  T value{};          // meaningful only when ok()
  std::string error;  // empty on success

  bool ok() const { return error.empty(); }
  explicit operator bool() const { return ok(); }
};

// Properties of one device, as the CUDA runtime reports them.
struct DeviceInfo {
  int index = -1;                      // device ordinal (cudaSetDevice numbering)
  std::string name;                    // e.g. "NVIDIA H100 80GB HBM3"
  std::size_t total_memory = 0;        // global memory (bytes)
  int multiprocessors = 0;             // streaming multiprocessors (SMs)
  int cc_major = 0;                    // compute capability, major (9 for sm_90)
  int cc_minor = 0;                    // compute capability, minor
  int warp_size = 0;                   // threads per warp
  int max_threads_per_block = 0;       // threads per block limit
  std::size_t shared_memory_per_block = 0;  // static + opt-in limit per block (bytes)
  std::size_t l2_cache = 0;            // L2 cache size (bytes)
  int driver_version = 0;              // CUDA driver API version, e.g. 13000
  int runtime_version = 0;             // CUDA runtime version this library uses
};

#if SCANDYN_HAS_CUDA
// Number of CUDA devices visible to this process (0 is a valid answer). When the
// runtime cannot query them (no driver, no device, driver too old), the error is
// "no usable CUDA device: <cudaGetErrorString of the runtime's error>".
Result<int> device_count();

// Properties of device `device`; errors for a failed device_count(), an ordinal
// out of range, or a failed property query.
Result<DeviceInfo> device_info(int device = 0);

// The calling host thread's current device (cudaGetDevice).
Result<int> current_device();

// Makes `device` the calling host thread's current device (cudaSetDevice); errors for
// an ordinal out of range ("no CUDA device 3: 2 device(s) visible") or a failed call.
Result<int> set_current_device(int device);
#else
inline Result<int> device_count() {
  return {0, "no usable CUDA device: scandyn was built without CUDA (SCANDYN_CUDA=OFF)"};
}
inline Result<DeviceInfo> device_info(int = 0) {
  return {DeviceInfo{}, "no usable CUDA device: scandyn was built without CUDA (SCANDYN_CUDA=OFF)"};
}
inline Result<int> current_device() {
  return {0, "no usable CUDA device: scandyn was built without CUDA (SCANDYN_CUDA=OFF)"};
}
inline Result<int> set_current_device(int) {
  return {0, "no usable CUDA device: scandyn was built without CUDA (SCANDYN_CUDA=OFF)"};
}
#endif

// Sets a device current for the lifetime of a scope and restores the one before
// (engines bind to the device current at their construction). `ok()` false, with
// `error` saying why, when the device could not be made current; nothing is
// restored then.
class DeviceScope {
 public:
  explicit DeviceScope(int device) {
    const Result<int> before = current_device();
    if (!before) {
      error_ = before.error;
      return;
    }
    const Result<int> set = set_current_device(device);
    if (!set) {
      error_ = set.error;
      return;
    }
    previous_ = before.value;
  }
  ~DeviceScope() {
    if (previous_ >= 0) (void)set_current_device(previous_);
  }
  DeviceScope(const DeviceScope&) = delete;
  DeviceScope& operator=(const DeviceScope&) = delete;
  bool ok() const { return error_.empty(); }
  const std::string& error() const { return error_; }

 private:
  int previous_ = -1;
  std::string error_;
};

// One line: "0: NVIDIA H100 (sm_90, 132 SMs, 79.1 GiB, driver 13.0, runtime 13.0)".
inline std::string describe(const DeviceInfo& d) {
  auto version = [](int v) { return std::to_string(v / 1000) + "." + std::to_string(v % 1000 / 10); };
  const double gib = static_cast<double>(d.total_memory) / (1024.0 * 1024.0 * 1024.0);
  std::string mem = std::to_string(static_cast<long long>(gib * 10.0 + 0.5));
  if (mem.size() < 2) mem.insert(0, "0");
  mem.insert(mem.size() - 1, ".");
  return std::to_string(d.index) + ": " + d.name + " (sm_" + std::to_string(d.cc_major) +
         std::to_string(d.cc_minor) + ", " + std::to_string(d.multiprocessors) + " SMs, " + mem +
         " GiB, driver " + version(d.driver_version) + ", runtime " + version(d.runtime_version) +
         ")";
}

}  // namespace cuda
}  // namespace scandyn
