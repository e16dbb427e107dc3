// Inverse dynamics on the GPU, one thread per instance (CudaInverseDynamics).
//
// Rows (names as scripts/bench_results.py reads them):
//   id_thread/<precision>/<model>/cuda          compute_async on device buffers, soa
//                                               layout, B = 10^4 .. 10^7 instances of
//                                               iiwa, hyq, atlas (double to 10^7 when
//                                               it fits in device memory);
//   id_thread-host/<precision>/iiwa/cuda        compute() from host buffers (copies
//                                               included), B = 10^6;
//   id_thread-keepxup/<precision>/iiwa/cuda     the same RNEA through the public device
//                                               function with the forward pass's
//                                               transforms kept for the backward pass
//                                               (more registers, less arithmetic);
//   id_thread-rolled/<precision>/iiwa/cuda      ... with the body loops not unrolled
//                                               (state in local memory, few registers);
//                                               both at B = 10^6, 10^7, to show what the
//                                               engine's choice costs;
//   id_thread-libtrig[-keepxup]/float/iiwa/cuda CUDA's sinf/cosf (Trig::Library)
//                                               instead of the engine's SFU sin/cos.
// Device rows are timed with CUDA events around the launch alone (manual time), so
// host copies are excluded; inputs are uniform in [-1, 1] from a counter-based hash,
// generated on the device. Counters: links, instances, max_rel_err (against the
// double serial reference on up to 64 instances, float-rounded inputs for float) and
// GBps (q, qd, qdd read + tau written, per second).
//
// Before the rows the program prints the device, a device-to-device copy bandwidth
// (the memory roofline: bytes read + written per second) and the registers, local
// memory and occupancy of the iiwa kernel variants.
//
// Flags (before Google Benchmark's): --models-dir=DIR (default $SCANDYN_MODELS_DIR or
// ../shared/models), --max-instances=N (default 10^7).
#include <benchmark/benchmark.h>
#include <cuda_runtime.h>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <memory>
#include <type_traits>
#include <string>
#include <vector>

#include "scandyn/accuracy.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/model/load.hpp"
#include "cuda_bench_util.hpp"

using namespace scandyn;
using namespace scandyn::bench;

namespace {

// The engine's kernel with other choices of rnea_instance's kKeepXup, kUnrolled, kTrig.
template <class S, int C, bool kKeepXup, bool kUnrolled, Trig kTrig = cuda::kThreadTrig<S>>
__global__ void __launch_bounds__(cuda::kIdInstancesBlock)
    variant_kernel(const __grid_constant__ cuda::ThreadModelParams<S, C> model, const IdBatchIn<S> batch_in,
                   const BatchView<S> tau_out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= batch_in.q.batch) return;
  using cuda::instance_column;
  cuda::rnea_instance<S, C, kKeepXup, kUnrolled, kTrig>(model, instance_column(batch_in.q, b), instance_column(batch_in.qd, b),
                                                        instance_column(batch_in.qdd, b), nullptr, instance_column(tau_out, b));
}

// id_thread: the engine's device path.
template <class S>
void bench_device(benchmark::State& st, const Model* md, Index B) {
  const ModelTpl<S> m = md->cast<S>();
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 0;  // no staging buffers: the device path does not use them
  cuda::CudaInverseDynamics<S> engine(m, o);
  time_device_id<S>(st, *md, B, 64, [&](const IdBatchIn<S>& in, const BatchView<S>& tau) {
    return engine.compute_async(in, tau, nullptr);
  });
}

// id_thread-keepxup, id_thread-rolled: the bench's own instances of the device function.
template <class S, bool kKeepXup, bool kUnrolled, Trig kTrig = cuda::kThreadTrig<S>>
void bench_variant(benchmark::State& st, const Model* md, Index B) {
  const ModelTpl<S> m = md->cast<S>();
  const cuda::ThreadModel<S> tm(m);
  if (tm.capacity() != 8) {
    st.SkipWithError("the variants are built for capacity 8 only");
    return;
  }
  const auto& params = std::get<cuda::ThreadModelParams<S, 8>>(tm.params());
  const unsigned blocks = static_cast<unsigned>((static_cast<long long>(B) + cuda::kIdInstancesBlock - 1) /
                                                cuda::kIdInstancesBlock);
  time_device_id<S>(st, *md, B, 64, [&](const IdBatchIn<S>& in, const BatchView<S>& tau) {
    variant_kernel<S, 8, kKeepXup, kUnrolled, kTrig><<<blocks, cuda::kIdInstancesBlock>>>(params, in, tau);
    return cudaGetLastError();
  });
}

// id_thread-host: compute() from host buffers, copies included (wall clock).
template <class S>
void bench_host(benchmark::State& st, const Model* md, Index B) {
  time_host_id<S>(st, *md, B, BackendKind::Cuda, std::numeric_limits<S>::quiet_NaN());
}

// ---- what bounds the speed: printed before the rows ----------------------------------

void print_limits() {
  print_device_and_roofline("bench_cuda_id");
  std::printf("bench_cuda_id: kernels for capacity 8 (iiwa), block %d:\n", cuda::kIdInstancesBlock);
  const int bl = cuda::kIdInstancesBlock;
  print_kernel("float (the engine's)", variant_kernel<float, 8, false, true>, bl);
  print_kernel("float, keepxup", variant_kernel<float, 8, true, true>, bl);
  print_kernel("float, rolled", variant_kernel<float, 8, false, false>, bl);
  print_kernel("float, libtrig", variant_kernel<float, 8, false, true, Trig::Library>, bl);
  print_kernel("float, libtrig keepxup", variant_kernel<float, 8, true, true, Trig::Library>, bl);
  print_kernel("double", variant_kernel<double, 8, false, true>, bl);
  print_kernel("double, keepxup (the engine's)", variant_kernel<double, 8, true, true>, bl);
  print_kernel("double, rolled", variant_kernel<double, 8, false, false>, bl);
  std::fflush(stdout);
}

std::vector<std::unique_ptr<Model>> g_models;  // outlive the registered benchmarks

}  // namespace

int main(int argc, char** argv) {
  BenchArgs args = parse_bench_args(argc, argv, "--max-instances=", 10000000);
  if (!have_device("bench_cuda_id")) return 0;
  print_limits();
  std::size_t free_bytes = 0, total_bytes = 0;
  cudaMemGetInfo(&free_bytes, &total_bytes);

  for (const auto& robot : load_bench_robots("bench_cuda_id", args.models_dir, g_models)) {
    const std::string& label = robot.first;
    const Model* m = robot.second;  // (a variable: lambdas capture it)
    for (long B = 10000; B <= args.count; B *= 10) {
      for (int prec = 0; prec < 2; ++prec) {
        const std::size_t need = 4 * static_cast<std::size_t>(m->nv()) * B * (prec ? 4 : 8);
        if (need > free_bytes * 0.9) {
          std::fprintf(stderr, "bench_cuda_id: skipping %s %s B=%ld: %zu bytes, %zu free\n", label.c_str(),
                       prec ? "float" : "double", B, need, free_bytes);
          continue;
        }
        const std::string name = std::string("id_thread/") + (prec ? "float/" : "double/") + label + "/cuda";
        const Index b = static_cast<Index>(B);
        auto* r = prec ? benchmark::RegisterBenchmark(name.c_str(), [=](benchmark::State& st) { bench_device<float>(st, m, b); })
                       : benchmark::RegisterBenchmark(name.c_str(), [=](benchmark::State& st) { bench_device<double>(st, m, b); });
        r->UseManualTime()->Unit(benchmark::kMicrosecond)->MinTime(0.1);
        if (label == "iiwa" && B >= 1000000) {
          const std::string pre = prec ? "float/" : "double/";
          const std::string kname = "id_thread-keepxup/" + pre + label + "/cuda";
          const std::string rname = "id_thread-rolled/" + pre + label + "/cuda";
          auto* k = prec ? benchmark::RegisterBenchmark(kname.c_str(), [=](benchmark::State& st) { bench_variant<float, true, true>(st, m, b); })
                         : benchmark::RegisterBenchmark(kname.c_str(), [=](benchmark::State& st) { bench_variant<double, true, true>(st, m, b); });
          k->UseManualTime()->Unit(benchmark::kMicrosecond)->MinTime(0.1);
          auto* rr = prec ? benchmark::RegisterBenchmark(rname.c_str(), [=](benchmark::State& st) { bench_variant<float, false, false>(st, m, b); })
                         : benchmark::RegisterBenchmark(rname.c_str(), [=](benchmark::State& st) { bench_variant<double, false, false>(st, m, b); });
          rr->UseManualTime()->Unit(benchmark::kMicrosecond)->MinTime(0.1);
          if (prec) {  // CUDA's sinf/cosf (Trig::Library) instead of the SFU's
            const std::string lib = "id_thread-libtrig/" + pre + label + "/cuda";
            const std::string libk = "id_thread-libtrig-keepxup/" + pre + label + "/cuda";
            benchmark::RegisterBenchmark(lib.c_str(), [=](benchmark::State& st) { bench_variant<float, false, true, Trig::Library>(st, m, b); })
                ->UseManualTime()->Unit(benchmark::kMicrosecond)->MinTime(0.1);
            benchmark::RegisterBenchmark(libk.c_str(), [=](benchmark::State& st) { bench_variant<float, true, true, Trig::Library>(st, m, b); })
                ->UseManualTime()->Unit(benchmark::kMicrosecond)->MinTime(0.1);
          }
        }
        if (label == "iiwa" && B == 1000000) {
          const std::string hname = std::string("id_thread-host/") + (prec ? "float/" : "double/") + label + "/cuda";
          auto* h = prec ? benchmark::RegisterBenchmark(hname.c_str(), [=](benchmark::State& st) { bench_host<float>(st, m, b); })
                         : benchmark::RegisterBenchmark(hname.c_str(), [=](benchmark::State& st) { bench_host<double>(st, m, b); });
          h->UseRealTime()->Unit(benchmark::kMillisecond)->MinTime(0.2);
        }
      }
    }
  }
  return run_benchmarks(args.rest);
}
