// Inverse dynamics by scans over links (rnea_scan, both forms, serial and on
// threads) on models with multi-DoF joints: a floating base (the root element of
// the prefix scans; its wrench the backward scan's tau_0..5) and spherical joints,
// against the serial reference's general path (rnea_at through rnea) in double on
// the same inputs; and the CPU engines' scan strategies against their recursion.
#include <gtest/gtest.h>

#include <limits>
#include <random>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/algorithm/rnea_scan.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "floating_models.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

// max relative error of rnea_scan<S> (form, threads) against the double reference;
// qdd_on false: the bias forces (qdd null)
template <class S>
double floating_scan_error(const Model& md, ScanForm form, int threads, unsigned seed, bool with_fext,
                           bool qdd_on = true) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv(), nb = m.nbodies();
  std::mt19937_64 g(seed);
  // inputs rounded to S, and the reference on the rounded values
  const auto q = test::cast_vector<S>(test::random_q(md, g));
  const auto qd = test::cast_vector<S>(test::random_vector(g, static_cast<int>(nv), -1, 1));
  const auto qdd = test::cast_vector<S>(test::random_vector(g, static_cast<int>(nv), -1, 1));
  const std::vector<Force<S>> fext = test::random_wrenches<S>(g, static_cast<int>(nb), 1);
  const std::vector<double> qr(q.begin(), q.end()), qdr(qd.begin(), qd.end()), qddr(qdd.begin(), qdd.end());
  std::vector<Force<double>> fext_r(fext.size());
  for (std::size_t i = 0; i < fext.size(); ++i) fext_r[i] = fext[i].template cast<double>();
  Data data(md, /*mass_matrix=*/false);
  std::vector<double> ref(static_cast<std::size_t>(nv));
  rnea(md, data, qr.data(), qdr.data(), qdd_on ? qddr.data() : nullptr, ref.data(),
       with_fext ? fext_r.data() : nullptr);
  ScanWorkspace<S> ws(m, threads);
  std::vector<S> tau(static_cast<std::size_t>(nv), std::numeric_limits<S>::quiet_NaN());
  rnea_scan(m, ws, form, q.data(), qd.data(), qdd_on ? qdd.data() : nullptr, tau.data(),
            with_fext ? fext.data() : nullptr);
  return test::max_rel_err(tau, ref);
}

const char* name(ScanForm f) { return f == ScanForm::Local ? "local" : "world"; }

}  // namespace

// Tolerances: double 1e-10 (the scans reassociate the recursion's products);
// float against the double reference on the same rounded inputs: 1e-4 on robots
// and short chains, 2e-3 on random trees (as for fixed bases, test_scan.cpp), 1e-2
// on ropes of 10^4 links (the error of a float recursion grows with the length).

TEST(RneaScanFloating, FreeRopesMatchTheGeneralRecursion) {
  for (int n : {1, 2, 10, 300, 10000}) {
    const Model m = test::load_floating("rope:" + std::to_string(n));
    ASSERT_TRUE(m.floating_base());
    for (ScanForm form : {ScanForm::Local, ScanForm::World})
      for (int t : {1, 4}) {
        EXPECT_LT(floating_scan_error<double>(m, form, t, 3, true), 1e-10) << name(form) << " rope:" << n << " t=" << t;
        EXPECT_LT(floating_scan_error<double>(m, form, t, 4, false, false), 1e-10)
            << "bias, " << name(form) << " rope:" << n;
        EXPECT_LT(floating_scan_error<float>(m, form, t, 3, true), n <= 300 ? 1e-4 : 1e-2)
            << "float, " << name(form) << " rope:" << n << " t=" << t;
      }
  }
}

TEST(RneaScanFloating, RandomFloatingTreesWithSphericalJoints) {
  for (int n : {1, 2, 7, 40, 400})
    for (unsigned seed : {1u, 2u, 3u}) {
      const Model m = test::random_floating_model(n, seed * 13 + n);
      for (ScanForm form : {ScanForm::Local, ScanForm::World})
        for (int t : {1, 3}) {
          EXPECT_LT(floating_scan_error<double>(m, form, t, seed, true), 1e-10) << name(form) << " n=" << n;
          EXPECT_LT(floating_scan_error<double>(m, form, t, seed, false, false), 1e-10) << "bias n=" << n;
          EXPECT_LT(floating_scan_error<float>(m, form, t, seed, true), 2e-3) << "float " << name(form) << " n=" << n;
        }
    }
}

TEST(RneaScanFloating, FloatingChainsBallRopesAndRobots) {
  std::vector<Model> models = {test::random_free_chain(50, 4), load_model("ballrope:200"),
                               test::load_floating("ballrope:200"), test::load_floating("hyq"),
                               test::load_floating("atlas"), test::load_floating("tree:300:5"),
                               test::load_floating("chain:60")};
  for (const Model& m : models)
    for (ScanForm form : {ScanForm::Local, ScanForm::World})
      for (int t : {1, 4}) {
        EXPECT_LT(floating_scan_error<double>(m, form, t, 8, true), 1e-10) << name(form) << " " << m.name;
        EXPECT_LT(floating_scan_error<float>(m, form, t, 8, false), 1e-3) << "float " << name(form) << " " << m.name;
      }
}

// The pieces of a long free rope are cut per thread: the multi-piece path with the
// base in the first piece of the first level.
TEST(RneaScanFloating, FreeRopeOfOneHundredThousandLinksOnThreads) {
  const Model m = test::load_floating("rope:100000");
  for (ScanForm form : {ScanForm::Local, ScanForm::World})
    EXPECT_LT(floating_scan_error<double>(m, form, 4, 11, true), 1e-10) << name(form);
}

// The CPU engines' scan strategies take multi-DoF models (strided batches, nq rows
// of q) and agree with their recursion.
TEST(RneaScanFloating, EnginesScanStrategiesMatchTheRecursion) {
  for (const Model& m : {test::load_floating("rope:3000"), test::random_floating_model(60, 9)}) {
    const Index nq = m.nq(), nv = m.nv(), B = 3;
    const test::SoaStates x = test::random_soa_states(m, B, 5, false);
    const IdBatchIn<double> in{BatchView<const double>::soa(x.q.data(), nq, B),
                               BatchView<const double>::soa(x.qd.data(), nv, B),
                               BatchView<const double>::soa(x.u.data(), nv, B)};
    BackendOptions o;
    o.backend = BackendKind::Serial;
    o.max_batch = B;
    std::vector<double> ref(x.qd.size());
    make_inverse_dynamics(m, o)->compute(in, BatchView<double>::soa(ref.data(), nv, B));
    for (BackendKind backend : {BackendKind::Serial, BackendKind::OpenMP}) {
      if (!backend_unusable(backend).empty()) continue;
      for (IdStrategy s : {IdStrategy::ScanLocal, IdStrategy::ScanWorld}) {
        o.backend = backend;
        o.strategy = s;
        o.threads = 2;
        const auto engine = make_inverse_dynamics(m, o);
        EXPECT_EQ(engine->strategy(), to_string(s));
        std::vector<double> tau(x.qd.size(), std::numeric_limits<double>::quiet_NaN());
        engine->compute(in, BatchView<double>::soa(tau.data(), nv, B));
        EXPECT_LT(test::max_rel_err(tau, ref), 1e-10) << m.name << " " << to_string(s);
      }
    }
  }
}
