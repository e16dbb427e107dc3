// Forward dynamics on the GPU by the joint-space inertia, one thread per instance
// (CudaForwardDynamics).
//
// Rows (names as scripts/bench_results.py reads them: algo fd, strategy jsi_thread...):
//   fd_jsi_thread/<precision>/<model>/cuda           compute_async on device buffers,
//                                                    soa layout, B = 10^4 .. 10^7
//                                                    instances of iiwa, hyq, atlas
//                                                    (double to 10^7 when it fits in
//                                                    device memory);
//   fd_jsi_thread-host/<precision>/iiwa/cuda         compute() from host buffers
//                                                    (copies included), B = 10^6;
//   fd_jsi_thread-keepxup/<precision>/iiwa/cuda      the same through the public device
//                                                    function with the forward pass's
//                                                    transforms kept for the backward
//                                                    pass (more registers, no second
//                                                    sin/cos);
//   fd_jsi_thread-rolled/<precision>/iiwa/cuda       ... with the loops not unrolled
//                                                    (state in local memory);
//   fd_jsi_thread-cap128/<precision>/iiwa/cuda       ... the engine's code held to 128
//                                                    registers (__launch_bounds__ with
//                                                    4 blocks of 128 per SM: more warps,
//                                                    some spills);
//   fd_jsi_thread-unrolled/float/hyq/cuda            capacity 16 unrolled (the engine
//                                                    rolls it: > 255 registers);
//   the variants at B = 10^6 and 10^7, to show what the engine's choices cost;
//   fd_aba_thread/<precision>/<model>/cuda           the engine with FdMethod::Aba
//                                                    (articulated-body algorithm, one
//                                                    thread per instance, the kernel
//                                                    choose_aba_kernel picks), as the
//                                                    fd_jsi_thread rows; max_rel_err
//                                                    against the double serial aba;
//   fd_aba_thread+check/<precision>/<model>/cuda,
//   fd_jsi_thread+check/<precision>/<model>/cuda    the same engines with the run-time
//                                                    check on (BackendOptions::fd_check:
//                                                    one more launch, the double RNEA
//                                                    residual and M^-1 r per instance,
//                                                    scandyn/cuda/fd_check.hpp), B =
//                                                    10^4 .. 10^6: its cost beside the
//                                                    rows without it; `failed` counts
//                                                    the instances it flagged;
//   fd_aba_thread-<shape>-<loops>-<cap>[-keepxup][-libtrig]/<precision>/<model>/cuda
//                                                    the bench's own ABA kernels, at
//                                                    B = 10^6 and 10^7, to choose the
//                                                    engine's by: <shape> chain (no
//                                                    branch slots), slots1 (one in
//                                                    registers) or tree (in local
//                                                    memory); <loops> unrolled or
//                                                    rolled; <cap> the registers
//                                                    ptxas may use (cap255, cap168,
//                                                    cap128: 1, 3, 4 blocks of 128
//                                                    per SM in __launch_bounds__);
//                                                    keepxup: pass 1's transforms kept;
//                                                    libtrig: CUDA's sinf/cosf in float
//                                                    instead of the SFU (the engine's
//                                                    Trig::Hardware). Which ones run on
//                                                    which model: aba_rows() below.
// Device rows are timed with CUDA events around the launch alone (manual time), so
// host copies are excluded; q, qd, tau are uniform in [-1, 1] from a counter-based
// hash, generated on the device (M is well conditioned for the robots at any q).
// Counters: links, instances, max_rel_err (against the double serial fd_jsi on up
// to 64 instances, float-rounded inputs for float), failed (instances whose
// factorisation failed: 0 expected) and GBps (q, qd, tau read + qdd and the failed
// DoF written, per second).
//
// Before the rows the program prints the device, a device-to-device copy bandwidth
// (the memory roofline) and the registers, local memory and occupancy of the
// kernels (the engine's choices for capacity 8, and the variants).
//
// Flags (before Google Benchmark's): --models-dir=DIR (default $SCANDYN_MODELS_DIR or
// ../shared/models), --max-instances=N (default 10^7).
//
// SCANDYN_BENCH_VARIANTS=0 (CMake option SCANDYN_BENCH_VARIANTS=OFF, what
// scripts/test.sh uses on machines without a GPU, where this program is compiled but
// never run) compiles only the variant rows whose kernel is the engine's own choice
// (FdKernelChoice in kernels/forward_dynamics.cu: fd_jsi_thread-cap128 in float,
// fd_jsi_thread-rolled in double, the fd_aba_thread-<variant> rows marked `engine`),
// so that every kernel template here still compiles, without the alternatives
// (tuning experiments, ~2.5 s of nvcc each).
#include <benchmark/benchmark.h>
#include <cuda_runtime.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <memory>
#include <string>
#include <type_traits>
#include <vector>

#include "cuda_bench_util.hpp"
#include "scandyn/accuracy.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/model/load.hpp"

using namespace scandyn;
using bench::cuda_ok;
using bench::fill_kernel;
using bench::time_launches;
using bench::uniform;

#if !defined(SCANDYN_BENCH_VARIANTS)
#define SCANDYN_BENCH_VARIANTS 1
#endif

namespace {

// The engine's kernel (kernels/forward_dynamics.cu) with other choices of
// fd_jsi_instance's kKeepXup, kUnrolled, and of the blocks per SM that ptxas plans
// registers for (kMinBlocks = 1: up to 255 registers; the engine's: FdKernelChoice).
template <class S, int C, bool kKeepXup, bool kUnrolled, int kMinBlocks>
__global__ void __launch_bounds__(cuda::kFdInstancesBlock, kMinBlocks)
    variant_kernel(const __grid_constant__ cuda::ThreadModelParams<S, C> model, const FdBatchIn<S> batch_in,
                   const BatchView<S> qdd_out, int* const failed_dof_out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= batch_in.q.batch) return;
  using cuda::instance_column;
  failed_dof_out[b] = cuda::fd_jsi_instance<S, C, kKeepXup, kUnrolled>(
      model, instance_column(batch_in.q, b), instance_column(batch_in.qd, b), instance_column(batch_in.tau, b), nullptr,
      instance_column(qdd_out, b));
}

// An ABA kernel: aba_instance with kSlots branch slots, loops unrolled or not, at
// most the registers for kMinBlocks blocks per SM, transforms kept or not, kTrig's
// sin/cos. The engine's kernels (kernels/forward_dynamics.cu) are some of these.
template <class S, int C, int kSlots, bool kUnrolled, int kMinBlocks, bool kKeepXup, Trig kTrig>
__global__ void __launch_bounds__(cuda::kFdInstancesBlock, kMinBlocks)
    aba_variant_kernel(const __grid_constant__ cuda::ThreadModelParams<S, C> model, const FdBatchIn<S> batch_in,
                       const BatchView<S> qdd_out, int* const failed_dof_out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= batch_in.q.batch) return;
  using cuda::instance_column;
  const Force<S>* fext = batch_in.fext ? batch_in.fext + b * model.nv : nullptr;
  failed_dof_out[b] = cuda::aba_instance<S, C, kKeepXup, kUnrolled, kTrig, kSlots>(
      model, instance_column(batch_in.q, b), instance_column(batch_in.qd, b), instance_column(batch_in.tau, b), fext,
      instance_column(qdd_out, b));
}

// Device buffers q, qd, tau, qdd (nv x B each, soa) and B failed DoFs, freed on scope exit.
template <class S>
struct DeviceBatch {
  S* p = nullptr;
  int* failed = nullptr;
  std::size_t n = 0;
  cudaError_t alloc(Index nv, Index B) {
    n = static_cast<std::size_t>(nv) * B;
    cudaError_t err = cudaMalloc(reinterpret_cast<void**>(&p), 4 * n * sizeof(S));
    if (err == cudaSuccess) err = cudaMalloc(reinterpret_cast<void**>(&failed), std::max<std::size_t>(B, 1) * sizeof(int));
    if (err != cudaSuccess) return err;
    for (int a = 0; a < 3; ++a) fill_kernel<S><<<1024, 256>>>(p + a * n, a, n);
    cudaMemset(p + 3 * n, 0xff, n * sizeof(S));  // NaN
    cudaMemset(failed, 0xff, B * sizeof(int));    // -1
    return cudaDeviceSynchronize();
  }
  ~DeviceBatch() {
    if (p) cudaFree(p);
    if (failed) cudaFree(failed);
  }
  FdBatchIn<S> in(Index nv, Index B) const {
    using V = BatchView<const S>;
    return {V::soa(p, nv, B), V::soa(p + n, nv, B), V::soa(p + 2 * n, nv, B)};
  }
  BatchView<S> qdd(Index nv, Index B) const { return BatchView<S>::soa(p + 3 * n, nv, B); }
};

// Instances whose factorisation failed (failed DoF >= 0), from B device entries.
double count_failed(const int* failed, Index B) {
  std::vector<int> h(static_cast<std::size_t>(B));
  if (cudaMemcpy(h.data(), failed, h.size() * sizeof(int), cudaMemcpyDeviceToHost) != cudaSuccess) return std::nan("");
  return double(std::count_if(h.begin(), h.end(), [](int k) { return k >= 0; }));
}

void set_counters(benchmark::State& st, Index nv, Index B, double err, double failed, double seconds,
                  std::size_t scalar) {
  st.counters["links"] = nv;
  st.counters["instances"] = B;
  st.counters["max_rel_err"] = err;
  st.counters["failed"] = failed;
  const double bytes = (4.0 * nv * double(scalar) + sizeof(int)) * double(B);
  st.counters["GBps"] = seconds > 0 ? bytes * double(st.iterations()) / seconds * 1e-9 : 0;
}

// fd_jsi_thread (fd_aba_thread with FdMethod::Aba): the engine's device path.
// check: with the run-time check on (its estimates hold max_batch = B instances).
template <class S>
void bench_device(benchmark::State& st, const Model* md, Index B, FdMethod alg = FdMethod::Jsi, bool check = false) {
  const ModelTpl<S> m = md->cast<S>();
  const Index nv = m.nv();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = check ? B : 0;  // else no staging buffers: the device path does not use them
  o.fd_check = check ? FdCheckMode::On : FdCheckMode::Off;
  cuda::CudaForwardDynamics<S> engine(m, o, alg);
  DeviceBatch<S> buf;
  if (!cuda_ok(st, buf.alloc(nv, B), "allocating and filling the batch")) return;
  const FdBatchIn<S> in = buf.in(nv, B);
  const BatchView<S> qdd = buf.qdd(nv, B);
  const double seconds = time_launches(st, [&] { return engine.compute_async(in, qdd, buf.failed, nullptr); });
  set_counters(st, nv, B, bench::fd_max_rel_err<S>(*md, B, qdd.data, true, alg == FdMethod::Aba),
               count_failed(buf.failed, B), seconds, sizeof(S));
}

// The variants: the bench's own kernels (launch(params, in, qdd, failed, blocks)
// for the model's ThreadModelParams of capacity C), max_rel_err against the double
// serial fd_jsi (with_aba: aba).
template <class S, int C, class Launch>
void bench_kernel(benchmark::State& st, const Model* md, Index B, bool with_aba, Launch&& launch) {
  const ModelTpl<S> m = md->cast<S>();
  const Index nv = m.nv();
  const cuda::ThreadModel<S> tm(m);
  if (tm.capacity() != C) {
    st.SkipWithError(("this variant is built for capacity " + std::to_string(C)).c_str());
    return;
  }
  const auto& params = std::get<cuda::ThreadModelParams<S, C>>(tm.params());
  DeviceBatch<S> buf;
  if (!cuda_ok(st, buf.alloc(nv, B), "allocating and filling the batch")) return;
  const FdBatchIn<S> in = buf.in(nv, B);
  const BatchView<S> qdd = buf.qdd(nv, B);
  const unsigned blocks = static_cast<unsigned>((static_cast<long long>(B) + cuda::kFdInstancesBlock - 1) /
                                                cuda::kFdInstancesBlock);
  const double seconds = time_launches(st, [&] {
    launch(params, in, qdd, buf.failed, blocks);
    return cudaGetLastError();
  });
  set_counters(st, nv, B, bench::fd_max_rel_err<S>(*md, B, qdd.data, true, with_aba), count_failed(buf.failed, B), seconds,
               sizeof(S));
}

// fd_jsi_thread-<variant>: fd_jsi_instance with other choices.
template <class S, int C, bool kKeepXup, bool kUnrolled, int kMinBlocks>
void bench_variant(benchmark::State& st, const Model* md, Index B) {
  bench_kernel<S, C>(st, md, B, false, [](const auto& params, const auto& in, const auto& qdd, int* failed,
                                          unsigned blocks) {
    variant_kernel<S, C, kKeepXup, kUnrolled, kMinBlocks><<<blocks, cuda::kFdInstancesBlock>>>(params, in, qdd, failed);
  });
}

// fd_aba_thread-<variant>: aba_variant_kernel. A model that needs more branch slots
// than kSlots (0 < kSlots < C) is skipped with a reason (the kernel would be wrong).
template <class S, int C, int kSlots, bool kUnrolled, int kMinBlocks, bool kKeepXup = false,
          Trig kTrig = cuda::kThreadTrig<S>>
void bench_aba_variant(benchmark::State& st, const Model* md, Index B) {
  if (kSlots < C && cuda::ThreadModel<S>(md->cast<S>()).branch_slots() > kSlots) {
    st.SkipWithError(("the model needs more than " + std::to_string(kSlots) + " branch slots").c_str());
    return;
  }
  bench_kernel<S, C>(st, md, B, true, [](const auto& params, const auto& in, const auto& qdd, int* failed,
                                         unsigned blocks) {
    aba_variant_kernel<S, C, kSlots, kUnrolled, kMinBlocks, kKeepXup, kTrig>
        <<<blocks, cuda::kFdInstancesBlock>>>(params, in, qdd, failed);
  });
}

// fd_jsi_thread-host: compute() from host buffers, copies included (wall clock).
template <class S>
void bench_host(benchmark::State& st, const Model* md, Index B) {
  const ModelTpl<S> m = md->cast<S>();
  const Index nv = m.nv();
  const std::size_t n = static_cast<std::size_t>(nv) * B;
  const bench::HostInputs<S> x(n);  // q, qd, tau
  std::vector<S> qdd(n, std::numeric_limits<S>::quiet_NaN());
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  cuda::CudaForwardDynamics<S> engine(m, o);
  using V = BatchView<const S>;
  const FdBatchIn<S> in{V::soa(x.q.data(), nv, B), V::soa(x.qd.data(), nv, B), V::soa(x.u.data(), nv, B)};
  const BatchView<S> out = BatchView<S>::soa(qdd.data(), nv, B);
  BatchStatus status = engine.compute(in, out);  // warm-up
  for (auto _ : st) {
    status = engine.compute(in, out);
    benchmark::ClobberMemory();
  }
  st.counters["links"] = nv;
  st.counters["instances"] = B;
  st.counters["max_rel_err"] = bench::fd_max_rel_err<S>(*md, B, qdd.data(), false);
  st.counters["failed"] = status.failed;
}

// ---- the ABA kernels' variants ------------------------------------------------------

// One fd_aba_thread-<variant> row: the model and precision it runs on, its name, its
// benchmark and a printer of its kernel's resources.
struct AbaRow {
  const char* model;    // "iiwa", "hyq" or "atlas"
  bool single;          // float (else double)
  const char* variant;  // <shape>-<loops>-<cap>[-keepxup][-libtrig]
  bool engine;          // the kernel launch_aba_instances runs for this model and precision
  void (*run)(benchmark::State&, const Model*, Index);
  void (*print)(const char* label);
};

template <class S, int C, int kSlots, bool kUnrolled, int kMinBlocks, bool kKeepXup = false,
          Trig kTrig = cuda::kThreadTrig<S>>
AbaRow aba_row(const char* model, const char* variant, bool engine = false) {
  return {model, sizeof(S) == 4, variant, engine,
          bench_aba_variant<S, C, kSlots, kUnrolled, kMinBlocks, kKeepXup, kTrig>,
          [](const char* label) {
            bench::print_kernel(label, aba_variant_kernel<S, C, kSlots, kUnrolled, kMinBlocks, kKeepXup, kTrig>,
                                cuda::kFdInstancesBlock);
          }};
}

// The rows: for each robot and precision the engine's kernel (kernels/forward_dynamics.cu,
// FdKernelChoice) and the alternatives to it. Capacities: iiwa 8, hyq 16, atlas 32;
// branch slots: iiwa and hyq none (chains from the base), atlas 1.
const std::vector<AbaRow>& aba_rows() {
#if SCANDYN_BENCH_VARIANTS
  constexpr Trig kLib = Trig::Library;
#endif
  static const std::vector<AbaRow> rows = {
#if SCANDYN_BENCH_VARIANTS
      aba_row<float, 8, 0, true, 3>("iiwa", "chain-unrolled-cap168"),
      aba_row<float, 8, 0, true, 1>("iiwa", "chain-unrolled-cap255"),
      aba_row<float, 8, 0, true, 4>("iiwa", "chain-unrolled-cap128"),
#endif
      aba_row<float, 8, 0, false, 4>("iiwa", "chain-rolled-cap128", true),
#if SCANDYN_BENCH_VARIANTS
      aba_row<float, 8, 0, true, 1, true>("iiwa", "chain-unrolled-cap255-keepxup"),
      aba_row<float, 8, 0, true, 3, false, kLib>("iiwa", "chain-unrolled-cap168-libtrig"),
      aba_row<float, 8, 8, false, 4>("iiwa", "tree-rolled-cap128"),
#endif
      aba_row<double, 8, 0, false, 1>("iiwa", "chain-rolled-cap255", true),
#if SCANDYN_BENCH_VARIANTS
      aba_row<double, 8, 0, true, 1>("iiwa", "chain-unrolled-cap255"),
      aba_row<double, 8, 0, false, 3>("iiwa", "chain-rolled-cap168"),
      aba_row<double, 8, 0, false, 1, true>("iiwa", "chain-rolled-cap255-keepxup"),
      aba_row<double, 8, 8, false, 1>("iiwa", "tree-rolled-cap255"),
#endif
      aba_row<float, 16, 0, false, 4>("hyq", "chain-rolled-cap128", true),
#if SCANDYN_BENCH_VARIANTS
      aba_row<float, 16, 0, true, 1>("hyq", "chain-unrolled-cap255"),
      aba_row<float, 16, 16, false, 4>("hyq", "tree-rolled-cap128"),
#endif
      aba_row<double, 16, 0, false, 1>("hyq", "chain-rolled-cap255", true),
#if SCANDYN_BENCH_VARIANTS
      aba_row<double, 16, 16, false, 1>("hyq", "tree-rolled-cap255"),
      aba_row<float, 32, 1, false, 3>("atlas", "slots1-rolled-cap168"),
#endif
      aba_row<float, 32, 1, false, 4>("atlas", "slots1-rolled-cap128", true),
#if SCANDYN_BENCH_VARIANTS
      aba_row<float, 32, 32, false, 4>("atlas", "tree-rolled-cap128"),
#endif
      aba_row<double, 32, 32, false, 1>("atlas", "tree-rolled-cap255", true),
#if SCANDYN_BENCH_VARIANTS
      aba_row<double, 32, 1, false, 1>("atlas", "slots1-rolled-cap255"),
#endif
  };
  return rows;
}

// ---- what bounds the speed: printed before the rows ----------------------------------

void print_limits() {
  bench::print_device_and_roofline("bench_cuda_fd");
  constexpr int blk = cuda::kFdInstancesBlock;
  std::printf("bench_cuda_fd: kernels, block %d:\n", blk);
  // the JSI at capacity 8; the engine's (FdKernelChoice): float unrolled in 128
  // registers (cap128), double rolled
#if SCANDYN_BENCH_VARIANTS
  bench::print_kernel("C=8 float, unrolled", variant_kernel<float, 8, false, true, 1>, blk);
  bench::print_kernel("C=8 float, keepxup", variant_kernel<float, 8, true, true, 1>, blk);
  bench::print_kernel("C=8 float, rolled", variant_kernel<float, 8, false, false, 1>, blk);
#endif
  bench::print_kernel("C=8 float, cap128 (the engine's)", variant_kernel<float, 8, false, true, 4>, blk);
#if SCANDYN_BENCH_VARIANTS
  bench::print_kernel("C=8 double, unrolled", variant_kernel<double, 8, false, true, 1>, blk);
  bench::print_kernel("C=8 double, keepxup", variant_kernel<double, 8, true, true, 1>, blk);
#endif
  bench::print_kernel("C=8 double, rolled (the engine's)", variant_kernel<double, 8, false, false, 1>, blk);
#if SCANDYN_BENCH_VARIANTS
  bench::print_kernel("C=8 double, cap128", variant_kernel<double, 8, false, true, 4>, blk);
  bench::print_kernel("C=16 float, rolled", variant_kernel<float, 16, false, false, 1>, blk);
  bench::print_kernel("C=16 float, unrolled", variant_kernel<float, 16, false, true, 1>, blk);
#endif
  for (const AbaRow& r : aba_rows()) {
    const std::string label = std::string("ABA ") + r.model + (r.single ? " float " : " double ") + r.variant +
                              (r.engine ? " (the engine's)" : "");
    r.print(label.c_str());
  }
  std::fflush(stdout);
}

std::vector<std::unique_ptr<Model>> g_models;  // outlive the registered benchmarks

template <class F>
void add(const std::string& name, F&& f, bool host = false) {
  auto* r = benchmark::RegisterBenchmark(name.c_str(), std::forward<F>(f));
  if (host) r->UseRealTime()->Unit(benchmark::kMillisecond)->MinTime(0.2);
  else r->UseManualTime()->Unit(benchmark::kMicrosecond)->MinTime(0.1);
}

}  // namespace

int main(int argc, char** argv) {
  bench::BenchArgs args = bench::parse_bench_args(argc, argv, "--max-instances=", 10000000);
  if (!bench::have_device("bench_cuda_fd")) return 0;
  print_limits();
  std::size_t free_bytes = 0, total_bytes = 0;
  cudaMemGetInfo(&free_bytes, &total_bytes);

  for (const auto& robot : bench::load_bench_robots("bench_cuda_fd", args.models_dir, g_models)) {
    const std::string& label = robot.first;
    const Model* m = robot.second;  // (a variable: lambdas capture it)
    for (long B = 10000; B <= args.count; B *= 10) {
      for (int prec = 0; prec < 2; ++prec) {
        const bool fl = prec == 1;
        const std::size_t need = (4 * static_cast<std::size_t>(m->nv()) * (fl ? 4 : 8) + sizeof(int)) * B;
        if (need > free_bytes * 0.9) {
          std::fprintf(stderr, "bench_cuda_fd: skipping %s %s B=%ld: %zu bytes, %zu free\n", label.c_str(),
                       fl ? "float" : "double", B, need, free_bytes);
          continue;
        }
        const std::string pre = fl ? "float/" : "double/";
        const std::string post = pre + label + "/cuda";
        const Index b = static_cast<Index>(B);
        if (fl) add("fd_jsi_thread/" + post, [=](benchmark::State& st) { bench_device<float>(st, m, b); });
        else add("fd_jsi_thread/" + post, [=](benchmark::State& st) { bench_device<double>(st, m, b); });
        constexpr auto kAba = FdMethod::Aba;
        if (fl) add("fd_aba_thread/" + post, [=](benchmark::State& st) { bench_device<float>(st, m, b, kAba); });
        else add("fd_aba_thread/" + post, [=](benchmark::State& st) { bench_device<double>(st, m, b, kAba); });
        if (B <= 1000000) {  // the check's rows (its engine stages max_batch = B instances)
          for (FdMethod alg : {FdMethod::Aba, FdMethod::Jsi}) {
            const std::string name = std::string(alg == kAba ? "fd_aba_thread" : "fd_jsi_thread") + "+check/" + post;
            if (fl) add(name, [=](benchmark::State& st) { bench_device<float>(st, m, b, alg, true); });
            else add(name, [=](benchmark::State& st) { bench_device<double>(st, m, b, alg, true); });
          }
        }
        if (label == "iiwa" && B >= 1000000) {
          if (fl) {
#if SCANDYN_BENCH_VARIANTS
            add("fd_jsi_thread-keepxup/" + post, [=](benchmark::State& st) { bench_variant<float, 8, true, true, 1>(st, m, b); });
            add("fd_jsi_thread-rolled/" + post, [=](benchmark::State& st) { bench_variant<float, 8, false, false, 1>(st, m, b); });
#endif
            add("fd_jsi_thread-cap128/" + post, [=](benchmark::State& st) { bench_variant<float, 8, false, true, 4>(st, m, b); });
          } else {
#if SCANDYN_BENCH_VARIANTS
            add("fd_jsi_thread-keepxup/" + post, [=](benchmark::State& st) { bench_variant<double, 8, true, true, 1>(st, m, b); });
#endif
            add("fd_jsi_thread-rolled/" + post, [=](benchmark::State& st) { bench_variant<double, 8, false, false, 1>(st, m, b); });
#if SCANDYN_BENCH_VARIANTS
            add("fd_jsi_thread-cap128/" + post, [=](benchmark::State& st) { bench_variant<double, 8, false, true, 4>(st, m, b); });
#endif
          }
        }
        if (B >= 1000000)
          for (const AbaRow& r : aba_rows())
            if (label == r.model && fl == r.single)
              add("fd_aba_thread-" + std::string(r.variant) + "/" + post,
                  [=, run = r.run](benchmark::State& st) { run(st, m, b); });
#if SCANDYN_BENCH_VARIANTS
        if (label == "hyq" && fl && B >= 1000000)
          add("fd_jsi_thread-unrolled/" + post, [=](benchmark::State& st) { bench_variant<float, 16, false, true, 1>(st, m, b); });
#endif
        if (label == "iiwa" && B == 1000000) {
          if (fl) add("fd_jsi_thread-host/" + post, [=](benchmark::State& st) { bench_host<float>(st, m, b); }, true);
          else add("fd_jsi_thread-host/" + post, [=](benchmark::State& st) { bench_host<double>(st, m, b); }, true);
        }
      }
    }
  }
  return bench::run_benchmarks(args.rest);
}
