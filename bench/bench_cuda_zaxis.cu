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
  std::vector<double> q(nv), qd(nv), u(nv), ref(rows), ours(rows);
  std::vector<S> col(rows);
  double worst = 0;
  const Index step = B > 64 ? B / 64 : 1;
  for (Index b = 0; b < B; b += step) {
    for (Index i = 0; i < nv; ++i) {
      const std::size_t k = static_cast<std::size_t>(i) * B + b;
      q[i] = double(S(uniform(0, k)));
      qd[i] = double(S(uniform(1, k)));
      u[i] = double(S(uniform(2, k)));
    }
    if (algo == Algo::Id) rnea(md, d, q.data(), qd.data(), u.data(), ref.data());
    else if (algo == Algo::Mass) crba(md, d, q.data(), ref.data());
    else if (!aba(md, d, q.data(), qd.data(), u.data(), ref.data()).ok()) continue;
    if (cudaMemcpy2D(col.data(), sizeof(S), out + b, B * sizeof(S), sizeof(S), rows, cudaMemcpyDeviceToHost) !=
        cudaSuccess)
      return std::nan("");
    for (Index i = 0; i < rows; ++i) ours[i] = double(col[i]);
    const double e = rel_err(ours.data(), ref.data(), ref.size());
    if (std::isnan(e)) return e;
    worst = std::fmax(worst, e);
  }
  return worst;
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
  const char* env = std::getenv("SCANDYN_MODELS_DIR");
  std::string models_dir = env && *env ? env : "../shared/models";
  long instances = 1000000;
  std::vector<char*> rest;
  for (int i = 0; i < argc; ++i) {
    if (std::strncmp(argv[i], "--models-dir=", 13) == 0) models_dir = argv[i] + 13;
    else if (std::strncmp(argv[i], "--instances=", 12) == 0) instances = std::atol(argv[i] + 12);
    else rest.push_back(argv[i]);
  }
  if (!have_device("bench_cuda_zaxis")) return 0;
  print_device_and_roofline("bench_cuda_zaxis");
  for (const std::string label : {"iiwa", "hyq", "atlas"}) {
    std::unique_ptr<Model> loaded = load_bench_robot("bench_cuda_zaxis", models_dir, label + ".urdf");
    if (!loaded) continue;
    g_models.push_back(std::move(loaded));
    const Model* m = g_models.back().get();
    const Index B = static_cast<Index>(instances);
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
  int rargc = static_cast<int>(rest.size());
  benchmark::Initialize(&rargc, rest.data());
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
