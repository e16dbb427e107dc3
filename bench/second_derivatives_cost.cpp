// bench/second_derivatives_cost.cpp: the CPU cost of the second-order derivatives of
// inverse dynamics (rnea_second_derivatives: the analytical second-order recursion;
// rnea_second_derivatives_dual: 2 nv passes of the first-order recursion in dual
// numbers, the reference it replaced) next to one call of the first-order
// derivatives (rnea_derivatives), one instance, double, serial, the three tensors
// without dM/dq. Microseconds per call; ratio = second_order_us / first_order_us.
// Usage: second_derivatives_cost [min_seconds]   (CSV on stdout)
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

int main(int argc, char** argv) {
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
