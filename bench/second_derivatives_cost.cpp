// bench/second_derivatives_cost.cpp: the CPU cost of the second-order derivatives of
// inverse dynamics (rnea_second_derivatives: the analytical second-order recursion;
// rnea_second_derivatives_dual: 2 nv passes of the first-order recursion in dual
// numbers, the reference it replaced) next to one call of the first-order
// derivatives (rnea_derivatives), one instance, double, serial, the three tensors
// without dM/dq. Microseconds per call; ratio = second_order_us / first_order_us.
// Usage: second_derivatives_cost [min_seconds]   (CSV on stdout)
//
//        second_derivatives_cost weighted [min_seconds]   (CSV on stdout)
// The weighted contraction out(j, k) = sum_i w_i d2tau_i/dq_j dq_k as the variational
// integrator's Newton forms it (scandyn/sim/variational_instance.hpp: the model
// without gravity at (q, 0, v), w = v, no wrenches), three ways: rnea_weighted_dq2
// (the analytical recursion's weighted variant), rnea_second_derivatives (the full
// analytical tensors, three nv^3, no dM/dq) then the contraction with w, and
// rnea_weighted_dq2_dual (nv dual passes, what the Newton ran before); with one
// rnea_derivatives call for scale. Models up to the exact Newton's 64 DoFs.
#include <cstdio>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

#include "plain_bench_util.hpp"
#include "scandyn/algorithm/second_derivatives.hpp"
#include "scandyn/model/load.hpp"

using namespace scandyn;

static const Force<double>* const kNoWrenches = nullptr;

namespace {

int weighted(double min_time) {
  std::printf("model,nv,first_order_us,weighted_analytic_us,tensor_contracted_us,weighted_dual_us,dual_over_analytic\n");
  for (const std::string spec : {"iiwa", "hyq", "atlas", "tree:30:4", "chain:64"}) {
    BuildOptions options;  // GRiD's atlas.urdf has four non-physical link inertias (as the tests load it)
    options.require_physical_inertia = false;
    const bool generated = spec.find(':') != std::string::npos;
    Model model = generated ? load_model(spec) : load_urdf(bench::models_dir() + "/" + spec + ".urdf", options);
    model.gravity = Vec3<double>{0, 0, 0};  // the model at rest: ID(q, 0, v) = M(q) v
    const Index n = model.nv();
    const std::size_t nn = static_cast<std::size_t>(n) * n;
    std::mt19937_64 rng(2);
    std::uniform_real_distribution<double> u(-1, 1);
    std::vector<double> q(n), zero(n, 0.0), v(n), a(nn), b(nn), c(nn), out(nn);
    for (Index i = 0; i < n; ++i) q[i] = u(rng), v[i] = u(rng);
    std::vector<double> T(nn * n), U(T.size()), W(T.size());
    DerivativeDataTpl<double> dd(model);
    SecondDerivativeData<double> sd(model);
    const double first = bench::best_seconds_per_call(min_time, [&] {
      rnea_derivatives(model, dd, q.data(), zero.data(), v.data(), kNoWrenches, MatrixRef<double>{a.data(), n, 1},
                       MatrixRef<double>{b.data(), n, 1}, MatrixRef<double>{c.data(), n, 1});
      return std::size_t(1);
    });
    const double analytic = bench::best_seconds_per_call(min_time, [&] {
      rnea_weighted_dq2(model, sd, q.data(), zero.data(), v.data(), kNoWrenches, v.data(), out.data());
      return std::size_t(1);
    });
    const double tensor = bench::best_seconds_per_call(min_time, [&] {
      rnea_second_derivatives(model, sd, q.data(), zero.data(), v.data(), kNoWrenches, T.data(), U.data(), W.data());
      for (std::size_t e = 0; e < nn; ++e) out[e] = 0;
      for (Index i = 0; i < n; ++i)
        for (std::size_t e = 0; e < nn; ++e) out[e] += v[i] * T[i * nn + e];
      return std::size_t(1);
    });
    const double dual = bench::best_seconds_per_call(min_time, [&] {
      rnea_weighted_dq2_dual(model, sd, q.data(), zero.data(), v.data(), kNoWrenches, v.data(), out.data());
      return std::size_t(1);
    });
    std::printf("%s,%d,%.2f,%.2f,%.2f,%.2f,%.1f\n", spec.c_str(), int(n), first * 1e6, analytic * 1e6, tensor * 1e6,
                dual * 1e6, dual / analytic);
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc > 1 && std::string(argv[1]) == "weighted") return weighted(argc > 2 ? std::atof(argv[2]) : 0.3);
  const double min_time = argc > 1 ? std::atof(argv[1]) : 0.3;
  std::printf("model,nv,first_order_us,second_order_us,ratio,dual_passes_us\n");
  for (const std::string spec : {"iiwa", "hyq", "tree:30:4"}) {
    const Model model = load_model(spec == "tree:30:4" ? spec : bench::models_dir() + "/" + spec + ".urdf");
    const Index n = model.nv();
    std::mt19937_64 rng(2);
    std::uniform_real_distribution<double> u(-1, 1);
    std::vector<double> q(n), qd(n), qdd(n), a(n * n), b(n * n), c(n * n);
    for (Index i = 0; i < n; ++i) q[i] = u(rng), qd[i] = u(rng), qdd[i] = u(rng);
    std::vector<double> H1(static_cast<std::size_t>(n) * n * n), H2(H1.size()), H3(H1.size());
    DerivativeDataTpl<double> dd(model);
    SecondDerivativeData<double> sd(model);
    const double first = bench::best_seconds_per_call(min_time, [&] {
      rnea_derivatives(model, dd, q.data(), qd.data(), qdd.data(), kNoWrenches, MatrixRef<double>{a.data(), n, 1},
                       MatrixRef<double>{b.data(), n, 1}, MatrixRef<double>{c.data(), n, 1});
      return std::size_t(1);
    });
    const double second = bench::best_seconds_per_call(min_time, [&] {
      rnea_second_derivatives(model, sd, q.data(), qd.data(), qdd.data(), kNoWrenches, H1.data(), H2.data(), H3.data());
      return std::size_t(1);
    });
    const double dual = bench::best_seconds_per_call(min_time, [&] {
      rnea_second_derivatives_dual(model, sd, q.data(), qd.data(), qdd.data(), kNoWrenches, H1.data(), H2.data(),
                                   H3.data());
      return std::size_t(1);
    });
    std::printf("%s,%d,%.2f,%.2f,%.1f,%.2f\n", spec.c_str(), int(n), first * 1e6, second * 1e6, second / first,
                dual * 1e6);
  }
  return 0;
}
