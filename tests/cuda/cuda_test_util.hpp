// Shared plumbing of the CUDA test programs (tests/test_cuda_*.cu): skipping with
// a visible reason when no device is usable, checked CUDA calls, device buffers,
// and strided batch layouts for the engines' views.
#pragma once

#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cstddef>
#include <random>
#include <string>
#include <vector>

#include "scandyn/config.hpp"
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

// ---- layouts --------------------------------------------------------------------

// Where the nv x B entries of one array live in a buffer: entry (i, b) at
// buffer[base + i * ds + b * bs]; the other buffer elements are gaps.
struct Layout {
  std::string name;
  std::ptrdiff_t ds = 0, bs = 0;
  std::ptrdiff_t base = 0;  // offset of entry (0, 0)
  std::size_t size = 0;     // buffer elements
  std::ptrdiff_t at(Index i, Index b) const { return base + i * ds + b * bs; }
};

inline Layout make_layout(const std::string& name, Index nv, Index B, std::ptrdiff_t ds, std::ptrdiff_t bs) {
  Layout l{name, ds, bs};
  std::ptrdiff_t lo = 0, hi = 0;
  for (std::ptrdiff_t e : {ds * (nv - 1), bs * (B - 1)}) (e < 0 ? lo : hi) += e;
  l.base = -lo;
  l.size = static_cast<std::size_t>(hi - lo + 1);
  return l;
}

inline Layout soa(Index nv, Index B) { return make_layout("soa", nv, B, B, 1); }
inline Layout aos(Index nv, Index B) { return make_layout("aos", nv, B, 1, nv); }

// A random layout: soa or aos, padded or not, either direction, or with both
// strides > 1 (entries interleaved with another array's).
inline Layout random_layout(std::mt19937_64& g, Index nv, Index B, bool output) {
  auto pick = [&](int n) { return static_cast<int>(std::uniform_int_distribution<int>(0, n - 1)(g)); };
  const int pad = pick(5);
  const std::ptrdiff_t s1 = pick(2) ? 1 : -1, s2 = pick(2) ? 1 : -1;
  switch (pick(output ? 5 : 6)) {
    case 0: return make_layout("soa+" + std::to_string(pad), nv, B, s2 * (B + pad), s1);
    case 1: return make_layout("aos+" + std::to_string(pad), nv, B, s1, s2 * (nv + pad));
    case 2: return make_layout("soa-interleaved", nv, B, s2 * 2 * B, s1 * 2);  // (q0 x0 q1 x1 ...) rows
    case 3: return make_layout("aos-interleaved", nv, B, s1 * 2, s2 * 2 * (nv + pad));
    case 4: return make_layout(pad % 2 ? "soa" : "aos", nv, B, pad % 2 ? B : 1, pad % 2 ? 1 : nv);
    default: return make_layout("broadcast", nv, B, s1 * (1 + pad), 0);  // one state for all instances
  }
}

// Fills a buffer in layout l with the batch array v (nv x B soa), gaps = sentinel.
template <class S>
std::vector<S> pack(const std::vector<double>& v, Index nv, Index B, const Layout& l, double sentinel) {
  std::vector<S> buf(l.size, S(sentinel));
  for (Index i = 0; i < nv; ++i)
    for (Index b = 0; b < B; ++b) buf[l.at(i, b)] = S(v[static_cast<std::size_t>(i) * B + b]);
  return buf;
}

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
