// bench/directional_derivatives_cost.cpp: the CPU cost of the directional
// derivatives of forward and inverse dynamics (scandyn/algorithm/
// directional_derivatives.hpp: aba_jvp, aba_vjp, rnea_jvp, rnea_vjp; serial, O(nv))
// on long ropes, next to one forward-dynamics call: the serial ABA and the openmp
// engine (FdMethod Auto: the parallel chain forward dynamics from 4096 links) on
// all threads. Microseconds per call, one instance, double.
// Usage: directional_derivatives_cost [min_seconds]   (CSV on stdout)
//
// directional_derivatives_cost chain [min_seconds]: the same derivatives by the
// chunked scans on the host (ChainFdDirectional, scandyn/algorithm/
// chain_directional.hpp, all OpenMP threads) next to the chain forward dynamics they
// extend (ChainForwardDynamics, the same threads and chunks): rope:10^4, 10^5, one
// instance, float and double. Columns: backend, model, precision, threads, fd_us,
// jvp_us, vjp_us, jvp_over_fd, vjp_over_fd.
//
// directional_derivatives_cost cuda [min_seconds] [max_links] (builds with CUDA): the
// device's ChainFdPlan::launch_jvp / launch_vjp (a plan made with directional = true)
// next to one ChainFdPlan::launch of a plain plan (the forward dynamics), every array
// device-resident: rope:10^4, 10^5, 10^6 (up to max_links), one instance, float and
// double. Each time: one warm-up call, then batches of back-to-back calls on one
// stream between two CUDA events until a batch takes >= min_seconds (default 0.3),
// microseconds per call. Columns as chain's, and qdd_diff: the largest |qdd| difference
// between the JVP's and VJP's forward dynamics and launch()'s (a sanity check: the
// same passes, 0 unless the directional plan's chunks differ).
//
// directional_derivatives_cost floating [min_seconds]: models with multi-DoF joints
// (floating hyq and atlas, ballrope:20 and ballrope:200 on a floating base): aba_jvp /
// aba_vjp (the general path, O(nv)) next to one serial ABA and the dense derivatives
// (aba_derivatives: the three nv x nv blocks), one instance, double, serial, random
// states (unit quaternions). Columns: model, nv, aba_us, aba_jvp_us, aba_vjp_us,
// dfd_us, jvp_over_aba, vjp_over_aba, dfd_over_vjp.
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "plain_bench_util.hpp"
#include "scandyn/algorithm/chain_directional.hpp"
#include "scandyn/algorithm/configuration.hpp"
#include "scandyn/algorithm/derivatives.hpp"
#include "scandyn/algorithm/directional_derivatives.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

#include "scandyn/cuda/chain_fd.hpp"
#endif

using namespace scandyn;

static const Force<double>* const kNoWrenches = nullptr;

namespace {

// Inputs of one rope: q, qd, tau, dq, dqd, dtau, w (n each), as the CPU rows draw them.
template <class S>
std::vector<std::vector<S>> rope_inputs(Index n) {
  std::mt19937_64 rng(2);
  std::uniform_real_distribution<double> u(-0.01, 0.01);
  std::vector<std::vector<S>> x(7, std::vector<S>(static_cast<std::size_t>(n)));
  for (Index i = 0; i < n; ++i)
    for (int k = 0; k < 7; ++k) x[k][i] = static_cast<S>(k == 2 ? 1e-4 * u(rng) : u(rng));
  return x;
}

template <class S>
void chain_rows(const char* spec, double min_time) {
  const ModelTpl<S> model = load_model(spec).cast<S>();
  const Index n = model.nv();
  const auto x = rope_inputs<S>(n);
  std::vector<S> qdd(n), out(n), g1(n), g2(n), g3(n);
  using V = BatchView<const S>;
  using O = BatchView<S>;
  auto v = [&](int k) { return V::aos(x[k].data(), n, 1); };
  const FdBatchIn<S> in{v(0), v(1), v(2)};
  ChainForwardDynamics<S> fd(model, 1);
  ChainFdDirectional<S> dir(model, 1, fd.threads(), fd.chunk());
  const double fd_s = bench::best_seconds_per_call(min_time, [&] {
    fd.compute(in, O::aos(qdd.data(), n, 1));
    return std::size_t(1);
  });
  const double jvp_s = bench::best_seconds_per_call(min_time, [&] {
    dir.jvp(in, v(3), v(4), v(5), O::aos(qdd.data(), n, 1), O::aos(out.data(), n, 1));
    return std::size_t(1);
  });
  const double vjp_s = bench::best_seconds_per_call(min_time, [&] {
    dir.vjp(in, v(6), O::aos(qdd.data(), n, 1), O::aos(g1.data(), n, 1), O::aos(g2.data(), n, 1),
            O::aos(g3.data(), n, 1));
    return std::size_t(1);
  });
  std::printf("openmp,%s,%s,%d,%.1f,%.1f,%.1f,%.2f,%.2f,\n", spec, sizeof(S) == 4 ? "float" : "double", fd.threads(),
              fd_s * 1e6, jvp_s * 1e6, vjp_s * 1e6, jvp_s / fd_s, vjp_s / fd_s);
  std::fflush(stdout);
}

#if SCANDYN_HAS_CUDA
void cuda_check(cudaError_t e, const char* what) { bench::exit_on_cuda_error("directional_derivatives_cost", e, what); }

// Seconds per call of f (launches on `stream`): one warm-up call, then batches of
// 1, 2, 4, ... back-to-back calls between two events until a batch takes min_time.
template <class F>
double device_seconds(double min_time, cudaStream_t stream, F&& f) {
  cudaEvent_t t0, t1;
  cuda_check(cudaEventCreate(&t0), "cudaEventCreate");
  cuda_check(cudaEventCreate(&t1), "cudaEventCreate");
  cuda_check(f(), "the warm-up call");
  cuda_check(cudaStreamSynchronize(stream), "the warm-up call");
  double per_call = 0;
  for (long calls = 1;; calls *= 2) {
    cuda_check(cudaEventRecord(t0, stream), "cudaEventRecord");
    for (long k = 0; k < calls; ++k) cuda_check(f(), "a timed call");
    cuda_check(cudaEventRecord(t1, stream), "cudaEventRecord");
    cuda_check(cudaEventSynchronize(t1), "cudaEventSynchronize");
    float ms = 0;
    cuda_check(cudaEventElapsedTime(&ms, t0, t1), "cudaEventElapsedTime");
    per_call = 1e-3 * ms / double(calls);
    if (1e-3 * ms >= min_time) break;
  }
  cudaEventDestroy(t0);
  cudaEventDestroy(t1);
  return per_call;
}

template <class S>
void cuda_rows(const char* spec, double min_time) {
  const ModelTpl<S> model = load_model(spec).cast<S>();
  const Index n = model.nv();
  const auto x = rope_inputs<S>(n);
  S* d = nullptr;
  const std::size_t N = static_cast<std::size_t>(n);
  cuda_check(cudaMalloc(reinterpret_cast<void**>(&d), 13 * N * sizeof(S)), "allocating the arrays");
  int* failed = nullptr;
  cuda_check(cudaMalloc(reinterpret_cast<void**>(&failed), sizeof(int)), "allocating failed");
  for (int k = 0; k < 7; ++k)
    cuda_check(cudaMemcpy(d + k * N, x[k].data(), N * sizeof(S), cudaMemcpyHostToDevice), "copying the inputs");
  using V = BatchView<const S>;
  using O = BatchView<S>;
  auto v = [&](int k) { return V::aos(d + k * N, n, 1); };
  auto o = [&](int k) { return O::aos(d + k * N, n, 1); };  // 7 qdd, 8 qdd (jvp), 9 dqdd, 10 gq, 11 gqd, 12 gtau
  const FdBatchIn<S> in{v(0), v(1), v(2)};
  cudaStream_t stream;
  cuda_check(cudaStreamCreate(&stream), "cudaStreamCreate");
  cuda::ChainFdPlan<S> fd(model, 1);
  cuda::ChainFdPlan<S> dir(model, 1, 0, 0, /*directional=*/true);
  const double fd_s = device_seconds(min_time, stream, [&] { return fd.launch(in, o(7), failed, stream); });
  const double jvp_s = device_seconds(min_time, stream, [&] {
    return dir.launch_jvp(in, v(3), v(4), v(5), o(8), o(9), failed, stream);
  });
  std::vector<S> a(N), b(N);
  cuda_check(cudaStreamSynchronize(stream), "sync");
  cuda_check(cudaMemcpy(a.data(), d + 7 * N, N * sizeof(S), cudaMemcpyDeviceToHost), "copying qdd");
  cuda_check(cudaMemcpy(b.data(), d + 8 * N, N * sizeof(S), cudaMemcpyDeviceToHost), "copying qdd");
  double diff = 0;
  for (std::size_t i = 0; i < N; ++i) diff = std::fmax(diff, std::fabs(double(a[i]) - double(b[i])));
  const double vjp_s = device_seconds(min_time, stream, [&] {
    return dir.launch_vjp(in, v(6), o(8), o(10), o(11), o(12), failed, stream);
  });
  cuda_check(cudaStreamSynchronize(stream), "sync");
  cuda_check(cudaMemcpy(b.data(), d + 8 * N, N * sizeof(S), cudaMemcpyDeviceToHost), "copying qdd");
  for (std::size_t i = 0; i < N; ++i) diff = std::fmax(diff, std::fabs(double(a[i]) - double(b[i])));
  std::printf("cuda,%s,%s,1,%.1f,%.1f,%.1f,%.2f,%.2f,%.3g\n", spec, sizeof(S) == 4 ? "float" : "double", fd_s * 1e6,
              jvp_s * 1e6, vjp_s * 1e6, jvp_s / fd_s, vjp_s / fd_s, diff);
  std::fflush(stdout);
  cudaStreamDestroy(stream);
  cudaFree(failed);
  cudaFree(d);
}
#endif

void floating_rows(double min_time) {
  std::printf("model,nv,aba_us,aba_jvp_us,aba_vjp_us,dfd_us,jvp_over_aba,vjp_over_aba,dfd_over_vjp\n");
  BuildOptions bo;
  bo.floating_base = true;
  bo.require_physical_inertia = false;  // atlas.urdf (tests/test_util.hpp, load_robot)
  const std::string dir = SCANDYN_DEFAULT_MODELS_DIR;
  for (const std::string& spec : {dir + "/hyq.urdf", dir + "/atlas.urdf", std::string("ballrope:20"),
                                 std::string("ballrope:200")}) {
    const Model model = load_model(spec, bo);
    const Index n = model.nv();
    std::mt19937_64 rng(2);
    std::uniform_real_distribution<double> u(-1, 1);
    std::vector<double> q(model.nq()), qd(n), tau(n), dq(n), dqd(n), dtau(n), qdd(n), out(n), g1(n), g2(n), g3(n);
    neutral_bodies(model.bodies.data(), model.nbodies(), q.data());
    std::vector<double> d(n);
    for (Index i = 0; i < n; ++i) d[i] = u(rng), qd[i] = u(rng), tau[i] = u(rng), dq[i] = u(rng), dqd[i] = u(rng), dtau[i] = u(rng);
    integrate_bodies(model.bodies.data(), model.nbodies(), q.data(), d.data(), 1.0);  // a random configuration
    DataTpl<double> data(model, false);
    AbaJvpData<double> jd(model);
    DerivativeDataTpl<double> dd(model);
    std::vector<double> A(n * n), B(n * n), C(n * n);
    const double aba_s = bench::best_seconds_per_call(min_time, [&] {
      aba(model, data, q.data(), qd.data(), tau.data(), qdd.data());
      return std::size_t(1);
    });
    const double jvp_s = bench::best_seconds_per_call(min_time, [&] {
      aba_jvp(model, jd, q.data(), qd.data(), tau.data(), kNoWrenches, dq.data(), dqd.data(), dtau.data(), out.data(),
              qdd.data());
      return std::size_t(1);
    });
    const double vjp_s = bench::best_seconds_per_call(min_time, [&] {
      aba_vjp(model, jd, q.data(), qd.data(), tau.data(), kNoWrenches, dtau.data(), g1.data(), g2.data(), g3.data(),
              qdd.data());
      return std::size_t(1);
    });
    const double dfd_s = bench::best_seconds_per_call(min_time, [&] {
      aba_derivatives(model, dd, q.data(), qd.data(), tau.data(), kNoWrenches, qdd.data(), {A.data(), n, 1},
                      {B.data(), n, 1}, {C.data(), n, 1});
      return std::size_t(1);
    });
    const std::string name = spec.find('/') == std::string::npos ? spec : spec.substr(spec.rfind('/') + 1);
    std::printf("%s,%d,%.2f,%.2f,%.2f,%.2f,%.2f,%.2f,%.2f\n", name.c_str(), int(n), aba_s * 1e6, jvp_s * 1e6,
                vjp_s * 1e6, dfd_s * 1e6, jvp_s / aba_s, vjp_s / aba_s, dfd_s / vjp_s);
    std::fflush(stdout);
  }
}

}  // namespace

int main(int argc, char** argv) {
  if (argc > 1 && std::strcmp(argv[1], "floating") == 0) {
    floating_rows(argc > 2 ? std::atof(argv[2]) : 0.3);
    return 0;
  }
  if (argc > 1 && (std::strcmp(argv[1], "chain") == 0 || std::strcmp(argv[1], "cuda") == 0)) {
    const bool on_cuda = std::strcmp(argv[1], "cuda") == 0;
    const double min_time = argc > 2 ? std::atof(argv[2]) : 0.3;
    const long max_links = argc > 3 ? std::atol(argv[3]) : 1000000;
    std::printf("backend,model,precision,threads,fd_us,jvp_us,vjp_us,jvp_over_fd,vjp_over_fd,qdd_diff\n");
    if (!on_cuda) {
      for (const char* spec : {"rope:10000", "rope:100000"}) {
        chain_rows<float>(spec, min_time);
        chain_rows<double>(spec, min_time);
      }
      return 0;
    }
#if SCANDYN_HAS_CUDA
    for (const char* spec : {"rope:10000", "rope:100000", "rope:1000000"}) {
      if (std::atol(spec + 5) > max_links) break;
      cuda_rows<float>(spec, min_time);
      cuda_rows<double>(spec, min_time);
    }
    return 0;
#else
    std::fprintf(stderr, "directional_derivatives_cost cuda: built without CUDA\n");
    return 1;
#endif
  }
  const double min_time = argc > 1 ? std::atof(argv[1]) : 0.3;
  std::printf("model,nv,aba_us,fd_openmp_us,openmp_threads,fd_openmp_method,aba_jvp_us,aba_vjp_us,rnea_jvp_us,"
              "rnea_vjp_us,aba_jvp_over_aba,aba_vjp_over_aba,aba_jvp_over_fd_openmp\n");
  for (const char* spec : {"rope:1000", "rope:10000", "rope:100000"}) {
    const Model model = load_model(spec);
    const Index n = model.nv();
    std::mt19937_64 rng(2);
    std::uniform_real_distribution<double> u(-0.01, 0.01);
    std::vector<double> q(n), qd(n), tau(n), dq(n), dqd(n), dtau(n), qdd(n), out(n), g1(n), g2(n), g3(n);
    for (Index i = 0; i < n; ++i) q[i] = u(rng), qd[i] = u(rng), tau[i] = 1e-4 * u(rng), dq[i] = u(rng), dqd[i] = u(rng), dtau[i] = u(rng);
    DataTpl<double> data(model, false);
    AbaJvpData<double> jd(model);
    const double aba_s = bench::best_seconds_per_call(min_time, [&] {
      aba(model, data, q.data(), qd.data(), tau.data(), qdd.data());
      return std::size_t(1);
    });
    BackendOptions o;
    o.backend = backend_unusable(BackendKind::OpenMP).empty() ? BackendKind::OpenMP : BackendKind::Serial;
    auto fd = make_forward_dynamics<double>(model, o);
    using V = BatchView<const double>;
    const FdBatchIn<double> in{V::aos(q.data(), n, 1), V::aos(qd.data(), n, 1), V::aos(tau.data(), n, 1)};
    const double fd_s = bench::best_seconds_per_call(min_time, [&] {
      fd->compute(in, BatchView<double>::aos(out.data(), n, 1));
      return std::size_t(1);
    });
    const double jvp_s = bench::best_seconds_per_call(min_time, [&] {
      aba_jvp(model, jd, q.data(), qd.data(), tau.data(), kNoWrenches, dq.data(), dqd.data(), dtau.data(), out.data(), qdd.data());
      return std::size_t(1);
    });
    const double vjp_s = bench::best_seconds_per_call(min_time, [&] {
      aba_vjp(model, jd, q.data(), qd.data(), tau.data(), kNoWrenches, dtau.data(), g1.data(), g2.data(), g3.data(), qdd.data());
      return std::size_t(1);
    });
    const double rjvp_s = bench::best_seconds_per_call(min_time, [&] {
      rnea_jvp(model, jd.id, q.data(), qd.data(), qdd.data(), kNoWrenches, dq.data(), dqd.data(), dtau.data(), out.data());
      return std::size_t(1);
    });
    const double rvjp_s = bench::best_seconds_per_call(min_time, [&] {
      rnea_vjp(model, jd.id, q.data(), qd.data(), qdd.data(), kNoWrenches, dtau.data(), g1.data(), g2.data(), g3.data());
      return std::size_t(1);
    });
    std::printf("%s,%d,%.1f,%.1f,%d,%s,%.1f,%.1f,%.1f,%.1f,%.2f,%.2f,%.2f\n", spec, int(n), aba_s * 1e6, fd_s * 1e6,
                backend_threads(o.backend, 0), fd->strategy().c_str(), jvp_s * 1e6, vjp_s * 1e6, rjvp_s * 1e6,
                rvjp_s * 1e6, jvp_s / aba_s, vjp_s / aba_s, jvp_s / fd_s);
    std::fflush(stdout);
  }
  return 0;
}
