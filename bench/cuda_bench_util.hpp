// bench/cuda_bench_util.hpp: what the CUDA benchmark programs share: inputs from
// a counter-based hash (the same numbers on host and device), device batches,
// accuracy against the double serial reference, CUDA-event timing of one launch per
// iteration, kernel resource reports and the memory roofline.
#pragma once

#include <benchmark/benchmark.h>
#include <cuda_runtime.h>

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "scandyn/accuracy.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/model/load.hpp"

namespace scandyn::bench {

// ---- inputs: a counter-based hash, the same on host and device --------------------

__host__ __device__ inline double uniform(std::uint64_t array, std::uint64_t k) {
  std::uint64_t z = (array << 56) + k + 0x9e3779b97f4a7c15ull;  // splitmix64
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  z ^= z >> 31;
  return double(z >> 11) * (2.0 / 9007199254740992.0) - 1.0;  // [-1, 1)
}

template <class S>
__global__ void fill_kernel(S* out, std::uint64_t array, std::size_t n) {
  for (std::size_t k = blockIdx.x * std::size_t(blockDim.x) + threadIdx.x; k < n; k += std::size_t(gridDim.x) * blockDim.x)
    out[k] = S(uniform(array, k));
}


inline bool cuda_ok(benchmark::State& st, cudaError_t err, const char* what) {
  if (err == cudaSuccess) return true;
  st.SkipWithError((std::string(what) + ": " + cudaGetErrorString(err)).c_str());
  (void)cudaGetLastError();
  return false;
}

// Device buffers q, qd, qdd, tau (nv x B each, soa), freed on scope exit.
template <class S>
struct DeviceBatch {
  S* p = nullptr;
  std::size_t n = 0;
  cudaError_t alloc(Index nv, Index B) {
    n = static_cast<std::size_t>(nv) * B;
    const cudaError_t err = cudaMalloc(reinterpret_cast<void**>(&p), 4 * n * sizeof(S));
    if (err != cudaSuccess) return err;
    for (int a = 0; a < 3; ++a) fill_kernel<S><<<1024, 256>>>(p + a * n, a, n);
    cudaMemset(p + 3 * n, 0xff, n * sizeof(S));  // NaN
    return cudaDeviceSynchronize();
  }
  ~DeviceBatch() {
    if (p) cudaFree(p);
  }
  IdBatchIn<S> in(Index nv, Index B) const {
    using V = BatchView<const S>;
    return {V::soa(p, nv, B), V::soa(p + n, nv, B), V::soa(p + 2 * n, nv, B)};
  }
  BatchView<S> tau(Index nv, Index B) const { return BatchView<S>::soa(p + 3 * n, nv, B); }
};

// max rel_err over up to `samples` instances: tau (soa, nv x B, host or device)
// against the double reference on the same (S-rounded) inputs.
template <class S>
double max_rel_err(const Model& md, Index B, const S* tau, bool on_device, Index samples = 64) {
  const Index nv = md.nv();
  Data d(md, false);
  std::vector<double> q(nv), qd(nv), qdd(nv), ref(nv), ours(nv);
  std::vector<S> col(nv);
  double worst = 0;
  const Index step = B > samples ? B / samples : 1;
  for (Index b = 0; b < B; b += step) {
    for (Index i = 0; i < nv; ++i) {
      const std::size_t k = static_cast<std::size_t>(i) * B + b;
      q[i] = double(S(uniform(0, k)));
      qd[i] = double(S(uniform(1, k)));
      qdd[i] = double(S(uniform(2, k)));
    }
    rnea(md, d, q.data(), qd.data(), qdd.data(), ref.data());
    if (on_device) {
      if (cudaMemcpy2D(col.data(), sizeof(S), tau + b, B * sizeof(S), sizeof(S), nv, cudaMemcpyDeviceToHost) !=
          cudaSuccess)
        return std::nan("");
    } else {
      for (Index i = 0; i < nv; ++i) col[i] = tau[static_cast<std::size_t>(i) * B + b];
    }
    for (Index i = 0; i < nv; ++i) ours[i] = double(col[i]);
    const double e = rel_err(ours.data(), ref.data(), ref.size());
    if (std::isnan(e)) return e;
    worst = std::fmax(worst, e);
  }
  return worst;
}

inline void set_counters(benchmark::State& st, Index nv, Index B, double err, double seconds, std::size_t scalar) {
  st.counters["links"] = nv;
  st.counters["instances"] = B;
  st.counters["max_rel_err"] = err;
  const double bytes = 4.0 * nv * double(B) * double(scalar);
  st.counters["GBps"] = seconds > 0 ? bytes * double(st.iterations()) / seconds * 1e-9 : 0;
}

// Times `launch` (one call on `stream`) with events; returns the total seconds.
template <class F>
double time_launches(benchmark::State& st, F&& launch) {
  cudaEvent_t start, stop;
  cudaEventCreate(&start);
  cudaEventCreate(&stop);
  double total = 0;
  if (!cuda_ok(st, launch(), "warm-up launch") || !cuda_ok(st, cudaDeviceSynchronize(), "warm-up run")) {
    for (auto _ : st) {
    }
  } else {
    for (auto _ : st) {
      cudaEventRecord(start);
      const cudaError_t err = launch();
      cudaEventRecord(stop);
      cudaEventSynchronize(stop);
      if (err != cudaSuccess) {
        cuda_ok(st, err, "launch");
        break;
      }
      float ms = 0;
      cudaEventElapsedTime(&ms, start, stop);
      st.SetIterationTime(ms * 1e-3);
      total += ms * 1e-3;
    }
    cuda_ok(st, cudaDeviceSynchronize(), "kernel");
  }
  cudaEventDestroy(start);
  cudaEventDestroy(stop);
  return total;
}


// One line: registers, local memory per thread, resident warps per SM at `block`.
template <class K>
void print_kernel(const char* name, K kernel, int block) {
  cudaFuncAttributes a{};
  int blocks = 0;
  if (cudaFuncGetAttributes(&a, kernel) != cudaSuccess ||
      cudaOccupancyMaxActiveBlocksPerMultiprocessor(&blocks, kernel, block, 0) != cudaSuccess) {
    (void)cudaGetLastError();
    std::printf("  %-34s attributes unavailable\n", name);
    return;
  }
  std::printf("  %-34s %3d registers, %6zu B local/thread, %2d warps/SM resident\n", name, a.numRegs,
              a.localSizeBytes, blocks * block / 32);
}

// The device, and a device-to-device copy bandwidth (the memory roofline: bytes read
// + written per second), prefixed with the program's name.
inline void print_device_and_roofline(const char* program) {
  const auto info = cuda::device_info(0);
  std::printf("%s: device %s\n", program, info ? cuda::describe(info.value).c_str() : info.error.c_str());
  const std::size_t bytes = std::size_t(1) << 30;
  void *a = nullptr, *b = nullptr;
  if (cudaMalloc(&a, bytes) == cudaSuccess && cudaMalloc(&b, bytes) == cudaSuccess) {
    cudaMemset(a, 1, bytes);
    cudaMemcpy(b, a, bytes, cudaMemcpyDeviceToDevice);
    cudaEvent_t s, e;
    cudaEventCreate(&s);
    cudaEventCreate(&e);
    float best = 1e30f;
    for (int r = 0; r < 10; ++r) {
      cudaEventRecord(s);
      cudaMemcpy(b, a, bytes, cudaMemcpyDeviceToDevice);
      cudaEventRecord(e);
      cudaEventSynchronize(e);
      float ms = 0;
      cudaEventElapsedTime(&ms, s, e);
      best = std::fmin(best, ms);
    }
    std::printf("%s: device-to-device copy of 1 GiB: %.0f GB/s (read + write, best of 10)\n", program,
                2.0 * bytes / (best * 1e-3) * 1e-9);
    cudaEventDestroy(s);
    cudaEventDestroy(e);
  }
  if (a) cudaFree(a);
  if (b) cudaFree(b);
  (void)cudaGetLastError();
}

// Is there a CUDA device? Without one, a line on stderr (the program has nothing to run).
inline bool have_device(const char* program) {
  const auto count = cuda::device_count();
  if (count && count.value > 0) return true;
  std::fprintf(stderr, "%s: %s; nothing to run\n", program,
               count ? "no CUDA device: the CUDA runtime reports 0 devices" : count.error.c_str());
  return false;
}

// A robot file from dir, nonphysical inertias allowed (GRiD's atlas.urdf); null, and a
// line on stderr, when it cannot be loaded.
inline std::unique_ptr<Model> load_bench_robot(const char* program, const std::string& dir, const std::string& file) {
  BuildOptions bo;
  bo.require_physical_inertia = false;
  try {
    return std::make_unique<Model>(load_urdf(dir + "/" + file, bo));
  } catch (const ModelError& e) {
    std::fprintf(stderr, "%s: skipping %s: %s\n", program, file.c_str(), e.what());
    return nullptr;
  }
}

}  // namespace scandyn::bench
