// bench/directional_derivatives_cost.cpp: the CPU cost of the directional
// derivatives of forward and inverse dynamics (scandyn/algorithm/
// directional_derivatives.hpp: aba_jvp, aba_vjp, rnea_jvp, rnea_vjp; serial, O(nv))
// on long ropes, next to one forward-dynamics call: the serial ABA and the openmp
// engine (FdMethod Auto: the parallel chain forward dynamics from 4096 links) on
// all threads. Microseconds per call, one instance, double.
// Usage: directional_derivatives_cost [min_seconds]   (CSV on stdout)
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include "plain_bench_util.hpp"
#include "scandyn/algorithm/directional_derivatives.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"

using namespace scandyn;

static const Force<double>* const kNoWrenches = nullptr;

int main(int argc, char** argv) {
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
