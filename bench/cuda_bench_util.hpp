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
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>
#include <utility>
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

// How sampled_rel_err treats an instance whose reference failed or whose error is NaN:
// the result is NaN, or (skip) the instance is left out.
struct SampleFailures {
  bool skip_failed_reference = false;
  bool skip_nan = false;
};

// max rel_err over up to `samples` instances (every (B / samples)-th): out (soa, rows x
// B, host or device) against the double reference on the same (S-rounded) inputs, the
// hash's arrays 0, 1, 2 (q, qd, and qdd or tau): reference(q, qd, u, ref) fills ref
// (rows) and returns false when it failed.
template <class S, class Reference>
double sampled_rel_err(const Model& md, Index B, const S* out, bool on_device, Index rows, Index samples,
                       Reference&& reference, SampleFailures failures = {}) {
  const Index nv = md.nv();
  std::vector<double> q(nv), qd(nv), u(nv), ref(rows), ours(rows);
  std::vector<S> col(rows);
  double worst = 0;
  const Index step = B > samples ? B / samples : 1;
  for (Index b = 0; b < B; b += step) {
    for (Index i = 0; i < nv; ++i) {
      const std::size_t k = static_cast<std::size_t>(i) * B + b;
      q[i] = double(S(uniform(0, k)));
      qd[i] = double(S(uniform(1, k)));
      u[i] = double(S(uniform(2, k)));
    }
    if (!reference(q.data(), qd.data(), u.data(), ref.data())) {
      if (failures.skip_failed_reference) continue;
      return std::nan("");
    }
    if (on_device) {
      if (cudaMemcpy2D(col.data(), sizeof(S), out + b, B * sizeof(S), sizeof(S), rows, cudaMemcpyDeviceToHost) !=
          cudaSuccess)
        return std::nan("");
    } else {
      for (Index i = 0; i < rows; ++i) col[i] = out[static_cast<std::size_t>(i) * B + b];
    }
    for (Index i = 0; i < rows; ++i) ours[i] = double(col[i]);
    const double e = rel_err(ours.data(), ref.data(), ref.size());
    if (std::isnan(e) && !failures.skip_nan) return e;
    worst = std::fmax(worst, e);
  }
  return worst;
}

// max rel_err over up to `samples` instances: tau (soa, nv x B, host or device)
// against the double reference (rnea) on the same (S-rounded) inputs.
template <class S>
double max_rel_err(const Model& md, Index B, const S* tau, bool on_device, Index samples = 64) {
  Data d(md, false);
  return sampled_rel_err<S>(md, B, tau, on_device, md.nv(), samples,
                            [&](const double* q, const double* qd, const double* qdd, double* ref) {
                              rnea(md, d, q, qd, qdd, ref);
                              return true;
                            });
}

// max rel_err over up to `samples` instances: qdd (soa, nv x B, host or device) against
// the double serial fd_jsi (with_aba: aba) on the same (S-rounded) inputs.
template <class S>
double fd_max_rel_err(const Model& md, Index B, const S* qdd, bool on_device, bool with_aba = false,
                      Index samples = 64, SampleFailures failures = {}) {
  Data d(md);
  return sampled_rel_err<S>(md, B, qdd, on_device, md.nv(), samples,
                            [&](const double* q, const double* qd, const double* tau, double* ref) {
                              return (with_aba ? aba(md, d, q, qd, tau, ref) : fd_jsi(md, d, q, qd, tau, ref)).ok();
                            },
                            failures);
}

// The hash's arrays 0, 1, 2 (q, qd, and qdd or tau) of n entries each, on the host, in
// precision S.
template <class S>
struct HostInputs {
  std::vector<S> q, qd, u;
  explicit HostInputs(std::size_t n) : q(n), qd(n), u(n) {
    for (std::size_t k = 0; k < n; ++k) q[k] = S(uniform(0, k)), qd[k] = S(uniform(1, k)), u[k] = S(uniform(2, k));
  }
};

// Inverse dynamics by the engine of backend `kind` (max_batch B) through compute() from
// host buffers (soa; inputs HostInputs, tau starting at tau0), wall clock after one
// warm-up call; counters links, instances and max_rel_err (over `samples` instances).
// Returns the engine's strategy.
template <class S>
std::string time_host_id(benchmark::State& st, const Model& md, Index B, BackendKind kind, S tau0,
                         Index samples = 64) {
  BackendOptions o;
  o.backend = kind;
  o.max_batch = B;
  auto engine = make_inverse_dynamics<S>(md.cast<S>(), o);
  const Index nv = md.nv();
  const std::size_t n = static_cast<std::size_t>(nv) * B;
  const HostInputs<S> x(n);
  std::vector<S> tau(n, tau0);
  using V = BatchView<const S>;
  const IdBatchIn<S> in{V::soa(x.q.data(), nv, B), V::soa(x.qd.data(), nv, B), V::soa(x.u.data(), nv, B)};
  const BatchView<S> out = BatchView<S>::soa(tau.data(), nv, B);
  engine->compute(in, out);  // warm-up
  for (auto _ : st) {
    engine->compute(in, out);
    benchmark::ClobberMemory();
  }
  st.counters["links"] = nv;
  st.counters["instances"] = B;
  st.counters["max_rel_err"] = max_rel_err<S>(md, B, tau.data(), false, samples);
  return engine->strategy();
}

// An engine (or plan) E made from args; null, with the benchmark skipped with the
// message, when its constructor throws a BackendError.
template <class E, class... Args>
std::unique_ptr<E> make_or_skip(benchmark::State& st, Args&&... args) {
  try {
    return std::make_unique<E>(std::forward<Args>(args)...);
  } catch (const BackendError& e) {
    st.SkipWithError(e.what());
    return nullptr;
  }
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

// Inverse dynamics on a DeviceBatch of B instances (the hash's inputs): launch(in, tau)
// (one launch; its cudaError_t) timed by time_launches; counters as set_counters,
// max_rel_err over `samples` instances.
template <class S, class Launch>
void time_device_id(benchmark::State& st, const Model& md, Index B, Index samples, Launch&& launch) {
  const Index nv = md.nv();
  DeviceBatch<S> buf;
  if (!cuda_ok(st, buf.alloc(nv, B), "allocating and filling the batch")) return;
  const IdBatchIn<S> in = buf.in(nv, B);
  const BatchView<S> tau = buf.tau(nv, B);
  const double seconds = time_launches(st, [&] { return launch(in, tau); });
  set_counters(st, nv, B, max_rel_err<S>(md, B, tau.data, true, samples), seconds, sizeof(S));
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

// The flags of the robot programs, before Google Benchmark's: --models-dir=DIR
// (default $SCANDYN_MODELS_DIR or ../shared/models) and the program's count flag
// (count_flag, e.g. "--max-instances=", default `count`); the rest (argv[0] first)
// are Google Benchmark's.
struct BenchArgs {
  std::string models_dir;
  long count;
  std::vector<char*> rest;
};

inline BenchArgs parse_bench_args(int argc, char** argv, const char* count_flag, long count) {
  const char* env = std::getenv("SCANDYN_MODELS_DIR");
  BenchArgs a{env && *env ? env : "../shared/models", count, {}};
  const std::size_t nc = std::strlen(count_flag);
  for (int i = 0; i < argc; ++i) {
    if (std::strncmp(argv[i], "--models-dir=", 13) == 0) a.models_dir = argv[i] + 13;
    else if (std::strncmp(argv[i], count_flag, nc) == 0) a.count = std::atol(argv[i] + nc);
    else a.rest.push_back(argv[i]);
  }
  return a;
}

// iiwa, hyq and atlas from dir (load_bench_robot: a line on stderr for each that cannot
// be loaded), kept in `models` (they must outlive the registered benchmarks), each with
// its label (the file name without .urdf).
inline std::vector<std::pair<std::string, const Model*>> load_bench_robots(const char* program, const std::string& dir,
                                                                           std::vector<std::unique_ptr<Model>>& models) {
  std::vector<std::pair<std::string, const Model*>> robots;
  for (const std::string label : {"iiwa", "hyq", "atlas"}) {
    std::unique_ptr<Model> loaded = load_bench_robot(program, dir, label + ".urdf");
    if (!loaded) continue;
    models.push_back(std::move(loaded));
    robots.emplace_back(label, models.back().get());
  }
  return robots;
}

// Google Benchmark on the flags left (argv[0] first): the rows registered so far.
inline int run_benchmarks(std::vector<char*>& rest) {
  int rargc = static_cast<int>(rest.size());
  benchmark::Initialize(&rargc, rest.data());
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}

}  // namespace scandyn::bench
