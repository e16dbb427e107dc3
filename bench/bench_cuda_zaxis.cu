// The thread-per-instance kernels on the user's joint frames against the z-axis
// frames the engines now run on (ZThreadModel, scandyn/model/joint_frames.hpp): the
// same public launch functions with a ThreadModel (user frames, any axis: the kernels
// before the z-axis model) or a ZThreadModel (every axis +z: no axis test per body).
//
// Rows (names as scripts/bench_results.py reads them):
//   <algo>_thread-<frames>/<precision>/<model>/cuda   algo: id (launch_id_instances),
//        mass (launch_crba_instances), aba (launch_aba_instances), jsi
//        (launch_fd_jsi_instances); frames: userframes or zaxis; model: iiwa, hyq,
//        atlas; B = --instances (default 10^6), soa device buffers, inputs uniform in
//        [-1, 1] from the counter hash. Counters: links, instances, evals_per_second
//        (instances / s), max_rel_err (against the double serial reference on 64
//        sampled instances, on the S-rounded inputs).
// Timed with CUDA events around one launch (manual time).
//
// Flags (before Google Benchmark's): --models-dir=DIR (default $SCANDYN_MODELS_DIR or
// ../shared/models), --instances=N.
#include <benchmark/benchmark.h>
#include <cuda_runtime.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "scandyn/accuracy.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/cuda/mass_matrix.hpp"
#include "scandyn/model/load.hpp"
#include "cuda_bench_util.hpp"

using namespace scandyn;
using namespace scandyn::bench;

namespace {

enum class Algo { Id, Mass, Aba, Jsi };

const char* name_of(Algo a) {
  return a == Algo::Id ? "id" : a == Algo::Mass ? "mass" : a == Algo::Aba ? "aba" : "jsi";
}

// max rel_err over up to 64 sampled instances of the output (soa on the device:
// nv x B for id / fd, nv^2 x B for mass) against the double reference on the hash's
// S-rounded inputs (arrays 0, 1, 2: q, qd, and qdd or tau).
template <class S>
double output_error(const Model& md, Algo algo, Index B, const S* out) {
  const Index nv = md.nv(), rows = algo == Algo::Mass ? nv * nv : nv;
  Data d(md, false);
  return sampled_rel_err<S>(
      md, B, out, true, rows, 64,
      [&](const double* q, const double* qd, const double* u, double* ref) {
        if (algo == Algo::Id) rnea(md, d, q, qd, u, ref);
        else if (algo == Algo::Mass) crba(md, d, q, ref);
        else return aba(md, d, q, qd, u, ref).ok();
        return true;
      },
      SampleFailures{true, false});  // an instance whose aba failed is left out
}

template <class S, class Bd>
void bench_kernel(benchmark::State& st, const Model* md, Algo algo, Index B) {
  const ModelTpl<S> m = md->cast<S>();
  const Index nv = m.nv(), rows = algo == Algo::Mass ? nv * nv : nv;
  const cuda::ThreadModel<S, Bd> tm(m);
  DeviceBatch<S> buf;  // q, qd, qdd / tau
  if (!cuda_ok(st, buf.alloc(nv, B), "allocating and filling the batch")) return;
  S* out = nullptr;
  int* failed = nullptr;
  if (!cuda_ok(st, cudaMalloc(&out, static_cast<std::size_t>(rows) * B * sizeof(S)), "allocating the output") ||
      !cuda_ok(st, cudaMalloc(&failed, static_cast<std::size_t>(B) * sizeof(int)), "allocating the flags"))
    return;
  const IdBatchIn<S> in = buf.in(nv, B);
  const FdBatchIn<S> fin{in.q, in.qd, in.qdd};
  const BatchView<S> ov = BatchView<S>::soa(out, rows, B);
  const double seconds = time_launches(st, [&] {
    switch (algo) {
      case Algo::Id: return cuda::launch_id_instances(tm, in, ov, nullptr);
      case Algo::Mass: return cuda::launch_crba_instances(tm, in.q, ov, nullptr);
      case Algo::Aba: return cuda::launch_aba_instances(tm, fin, ov, failed, nullptr);
      default: return cuda::launch_fd_jsi_instances(tm, fin, ov, failed, nullptr);
    }
  });
  st.counters["links"] = nv;
  st.counters["instances"] = B;
  st.counters["evals_per_second"] = seconds > 0 ? double(B) * double(st.iterations()) / seconds : 0;
  st.counters["max_rel_err"] = output_error<S>(*md, algo, B, out);
  cudaFree(out);
  cudaFree(failed);
}

std::vector<std::unique_ptr<Model>> g_models;  // outlive the registered benchmarks

}  // namespace

int main(int argc, char** argv) {
  BenchArgs args = parse_bench_args(argc, argv, "--instances=", 1000000);
  if (!have_device("bench_cuda_zaxis")) return 0;
  print_device_and_roofline("bench_cuda_zaxis");
  for (const auto& robot : load_bench_robots("bench_cuda_zaxis", args.models_dir, g_models)) {
    const std::string& label = robot.first;
    const Model* m = robot.second;  // (a variable: lambdas capture it)
    const Index B = static_cast<Index>(args.count);
    for (Algo algo : {Algo::Id, Algo::Mass, Algo::Aba, Algo::Jsi}) {
      for (int prec = 0; prec < 2; ++prec) {
        for (int z = 0; z < 2; ++z) {
          const std::string name = std::string(name_of(algo)) + "_thread-" + (z ? "zaxis/" : "userframes/") +
                                   (prec ? "float/" : "double/") + label + "/cuda";
          auto add = [&](auto run) {
            benchmark::RegisterBenchmark(name.c_str(), run)->UseManualTime()->Unit(benchmark::kMicrosecond)->MinTime(0.2);
          };
          if (prec && z) add([=](benchmark::State& st) { bench_kernel<float, ZJointBody<float>>(st, m, algo, B); });
          else if (prec) add([=](benchmark::State& st) { bench_kernel<float, Body<float>>(st, m, algo, B); });
          else if (z) add([=](benchmark::State& st) { bench_kernel<double, ZJointBody<double>>(st, m, algo, B); });
          else add([=](benchmark::State& st) { bench_kernel<double, Body<double>>(st, m, algo, B); });
        }
      }
    }
  }
  return run_benchmarks(args.rest);
}
