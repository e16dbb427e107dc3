// What the CUDA benchmark programs (bench/bench_cuda_*.cu) share: inputs from a
// counter-based hash (the same on host and device), CUDA-event timing of one launch
// per iteration, kernel resource reports and the memory roofline.
#pragma once

#include <benchmark/benchmark.h>
#include <cuda_runtime.h>

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <string>

#include "scandyn/cuda/device.hpp"

namespace scandyn::bench {

// Uniform in [-1, 1): element k of input array `array` (splitmix64 of both).
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

// false (and the benchmark marked as failed) unless err is cudaSuccess.
inline bool cuda_ok(benchmark::State& st, cudaError_t err, const char* what) {
  if (err == cudaSuccess) return true;
  st.SkipWithError((std::string(what) + ": " + cudaGetErrorString(err)).c_str());
  (void)cudaGetLastError();
  return false;
}

// Times `launch` (one call on the default stream) with events, one iteration each,
// after a warm-up; returns the total seconds.
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

}  // namespace scandyn::bench
