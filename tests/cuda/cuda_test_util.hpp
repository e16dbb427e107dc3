// Shared plumbing of the CUDA test programs (tests/cuda/test_cuda_*.cu): skipping with
// a visible reason when no device is usable, checked CUDA calls, device buffers,
// the shipped robots loaded once, strided batch layouts for the engines' views, and
// the layout trials the engines' tests share.
#pragma once

#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cstddef>
#include <limits>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "scandyn/config.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/engine.hpp"
#include "test_util.hpp"

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

// A shipped robot (test::load_robot), loaded once per program.
inline const Model& robot(const std::string& file) {
  static std::map<std::string, Model> cache;
  auto it = cache.find(file);
  if (it == cache.end()) it = cache.emplace(file, load_robot(file)).first;
  return it->second;
}

// Options of an engine used through compute_async alone: the CUDA backend, max_batch 1
// (compute_async is not limited by max_batch, which sizes compute()'s host staging).
inline BackendOptions device_path_options() {
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 1;
  return o;
}

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

// An output buffer in layout l: NaN at the nv x B entries (an entry never written
// fails), `sentinel` in the gaps between them.
template <class S>
std::vector<S> sentinel_output(const Layout& l, Index nv, Index B, double sentinel) {
  std::vector<S> buf(l.size, S(sentinel));
  for (Index i = 0; i < nv; ++i)
    for (Index b = 0; b < B; ++b) buf[l.at(i, b)] = std::numeric_limits<S>::quiet_NaN();
  return buf;
}

// How many gaps of a buffer in layout l (the elements that are none of its nv x B
// entries) no longer hold `sentinel`: 0 when the engine wrote only its entries.
template <class S>
std::size_t gap_writes(const std::vector<S>& buf, const Layout& l, Index nv, Index B, double sentinel) {
  std::vector<char> entry(l.size, 0);
  for (Index i = 0; i < nv; ++i)
    for (Index b = 0; b < B; ++b) entry[l.at(i, b)] = 1;
  std::size_t bad = 0;
  for (std::size_t k = 0; k < buf.size(); ++k) bad += !entry[k] && buf[k] != S(sentinel);
  return bad;
}

// ---- the engines' layout trials -------------------------------------------------

// One trial of host views in strided layouts: B = 1 every third trial, else `batch`
// instances; the first input (q) in a random layout that may broadcast, the second (qd)
// random and the third an aos or soa one (both like q when q broadcasts: then all three
// do), the output in a random layout; external wrenches every other trial.
struct LayoutTrial {
  Index B;
  Layout lq, lout, lqd, l3;
  bool fx;
};

inline LayoutTrial random_layout_trial(std::mt19937_64& g, Index nv, int trial, Index batch) {
  LayoutTrial t;
  t.B = trial % 3 == 0 ? 1 : batch;
  t.lq = random_layout(g, nv, t.B, false);
  t.lout = random_layout(g, nv, t.B, true);
  t.lqd = t.lq.bs == 0 ? t.lq : random_layout(g, nv, t.B, true);
  t.l3 = t.lq.bs == 0 ? t.lq : (trial % 2 ? aos(nv, t.B) : soa(nv, t.B));
  t.fx = trial % 2 == 0;
  return t;
}

// Host views in strided layouts: on iiwa and atlas, 12 trials (random_layout_trial) of
// B = 1 or 257 instances; run(model, B, with_fext, l1, l2, l3, lout, trial) under a
// trace naming the layouts by the inputs' names q, qd, third and the output's, out.
template <class Run>
void strided_host_layout_trials(const std::string& third, const std::string& out, Run&& run) {
  std::mt19937_64 g(99);
  for (const char* file : {"iiwa.urdf", "atlas.urdf"}) {
    const Model& md = robot(file);
    for (int trial = 0; trial < 12; ++trial) {
      const LayoutTrial t = random_layout_trial(g, md.nv(), trial, 257);
      SCOPED_TRACE(std::string(file) + " B=" + std::to_string(t.B) + " q " + t.lq.name + " qd " + t.lqd.name + " " +
                   third + " " + t.l3.name + " " + out + " " + t.lout.name + (t.fx ? " fext" : ""));
      run(md, t.B, t.fx, t.lq, t.lqd, t.l3, t.lout, trial);
    }
  }
}

// Device pointers: on iiwa, hyq and atlas, B = 1, 33 (inputs aos) and 4097 (output in a
// random layout) instances, inputs and output soa otherwise; run(model, B, lin, lout)
// under a trace naming them.
template <class Run>
void device_layout_trials(Run&& run) {
  std::mt19937_64 g(5);
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) {
    const Model& md = robot(file);
    const Index nv = md.nv();
    for (Index B : {1, 33, 4097}) {
      const Layout lin = B == 33 ? aos(nv, B) : soa(nv, B);
      const Layout lout = B == 4097 ? random_layout(g, nv, B, true) : lin;
      SCOPED_TRACE(std::string(file) + " B=" + std::to_string(B) + " in " + lin.name + " out " + lout.name);
      run(md, B, lin, lout);
    }
  }
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
