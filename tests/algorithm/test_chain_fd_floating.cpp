// The parallel chain forward dynamics of a free rope (a floating base, then 1-DoF
// links: ChainForwardDynamics with the base's 6x6 articulated inertia at the end of
// pass 1) against the serial ABA's general path (aba_at through aba) in double,
// instance by instance; its refusals; the CPU engine's parallel method.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "floating_models.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

using test::random_soa_states;
using test::SoaStates;

template <class S>
double free_chain_error(const Model& model, Index B, unsigned seed, int threads, Index chunk, bool with_fext) {
  const SoaStates x = random_soa_states(model, B, seed, with_fext);
  const auto ref = test::soa_reference(model, x, true);
  const ModelTpl<S> m = model.cast<S>();
  ChainForwardDynamics<S> fd(m, B, threads, chunk);
  const auto qs = test::cast_vector<S>(x.q), qds = test::cast_vector<S>(x.qd), taus = test::cast_vector<S>(x.u);
  std::vector<Force<S>> fs;
  for (const auto& f : x.fext) fs.push_back(f.cast<S>());
  std::vector<S> qdd(x.qd.size(), S(NAN));
  FdBatchIn<S> in{BatchView<const S>::soa(qs.data(), x.nq, B), BatchView<const S>::soa(qds.data(), x.nv, B),
                  BatchView<const S>::soa(taus.data(), x.nv, B), with_fext ? fs.data() : nullptr};
  std::vector<int> failed(static_cast<std::size_t>(B), 7);
  EXPECT_EQ(fd.compute(in, BatchView<S>::soa(qdd.data(), x.nv, B), failed.data()), 0);
  for (int f : failed) EXPECT_EQ(f, -1);
  return test::max_rel_err(qdd, ref);
}

}  // namespace

// Tolerances: double 1e-9 (the fixed chains' bound, test_chain_fd.cpp); float
// against the double reference: 1e-3 on short random chains, 1e-2 on ropes up to
// 2 * 10^4 links (the fixed ropes' bound).

TEST(ChainFdFloating, RandomFreeChainsMatchSerialAba) {
  for (unsigned seed : {1u, 2u, 3u}) {
    const Model m = test::random_free_chain(41, seed);
    ASSERT_TRUE(m.floating_base());
    for (Index chunk : {1, 3, 8, 64}) {  // chunks cross instance boundaries, the base inside a chunk
      EXPECT_LT(free_chain_error<double>(m, 3, seed, 2, chunk, false), 1e-9) << "seed " << seed << " chunk " << chunk;
      EXPECT_LT(free_chain_error<double>(m, 2, seed, 1, chunk, true), 1e-9) << "fext, seed " << seed << " chunk " << chunk;
    }
    EXPECT_LT(free_chain_error<float>(m, 3, seed, 2, 0, true), 1e-3) << "float, seed " << seed;
  }
}

TEST(ChainFdFloating, FreeBodyAndTinyFreeChains) {
  for (int n : {1, 2, 3}) {
    const Model m = test::random_free_chain(n, 50 + n);
    for (Index chunk : {1, 2, 8}) {
      EXPECT_LT(free_chain_error<double>(m, 5, 7, 2, chunk, true), 1e-10) << n << " chunk " << chunk;
      EXPECT_LT(free_chain_error<double>(m, 4, 8, 1, chunk, false), 1e-10) << n << " chunk " << chunk;
    }
  }
  // one free body in zero gravity: its qdd from the Newton-Euler equations
  const Model body = test::free_body_model(2.0, {0.1, -0.2, 0.05}, {0.3, 0.5, 0.7});
  EXPECT_LT(free_chain_error<double>(body, 4, 3, 2, 1, true), 1e-12);
}

TEST(ChainFdFloating, FreeRopesMatchSerialAba) {
  for (int n : {10, 1000, 20000}) {
    const Model m = test::load_floating("rope:" + std::to_string(n));
    const double ed = free_chain_error<double>(m, 1, 5, 2, 0, false);
    const double ef = free_chain_error<float>(m, 1, 5, 2, 0, false);
    EXPECT_LT(ed, 1e-9) << "free rope:" << n;
    EXPECT_LT(ef, 1e-2) << "free rope:" << n;
    RecordProperty("free_rope_" + std::to_string(n) + "_err_double", std::to_string(ed));
    RecordProperty("free_rope_" + std::to_string(n) + "_err_float", std::to_string(ef));
  }
  const Model m = test::load_floating("rope:500");
  EXPECT_LT(free_chain_error<double>(m, 7, 6, 2, 16, true), 1e-9) << "batch of 7 free rope:500";
}

TEST(ChainFdFloating, RefusesSphericalJointsAndFloatingTrees) {
  const Model ball = test::load_floating("ballrope:20");
  try {
    ChainForwardDynamics<double> fd(ball, 1);
    ADD_FAILURE() << "a ball rope was accepted";
  } catch (const BackendError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("body 1 (joint '" + ball.joint_names[1] + "') is a spherical joint"), std::string::npos) << what;
  }
  const Model tree = test::random_floating_model(12, 4, 0.0);
  ASSERT_GE(first_branching_body(tree), 0);
  EXPECT_THROW(ChainForwardDynamics<double>(tree, 1), BackendError);
  const Model fixed_ball = load_model("ballrope:20");
  EXPECT_THROW(ChainForwardDynamics<double>(fixed_ball, 1), BackendError);
}

// A NaN position past the base fails that instance's pivot: the failed DoF counts
// the base's six, the other instance is exact, the failed one's qdd unwritten.
TEST(ChainFdFloating, FailedPivotIsReportedAsADof) {
  const Model m = test::load_floating("rope:30");
  const Index nq = m.nq(), nv = m.nv(), B = 2;
  SoaStates x = random_soa_states(m, B, 9, false);
  x.q[static_cast<std::size_t>((7 + 11) * B + 1)] = NAN;  // instance 1, link 12's joint (DoF 17)
  ChainForwardDynamics<double> fd(m, B, 2, 4);
  std::vector<double> qdd(x.qd.size(), 7.0);
  std::vector<int> failed(2, 9);
  FdBatchIn<double> in{BatchView<const double>::soa(x.q.data(), nq, B), BatchView<const double>::soa(x.qd.data(), nv, B),
                       BatchView<const double>::soa(x.u.data(), nv, B), nullptr};
  EXPECT_EQ(fd.compute(in, BatchView<double>::soa(qdd.data(), nv, B), failed.data()), 1);
  EXPECT_EQ(failed[0], -1);
  EXPECT_GE(failed[1], 0);
  EXPECT_LE(failed[1], 17);
  for (Index i = 0; i < nv; ++i) {
    EXPECT_TRUE(std::isfinite(qdd[i * B])) << i;
    EXPECT_EQ(qdd[i * B + 1], 7.0) << i;
  }
}

// The CPU engines: Auto picks parallel for a long free rope on OpenMP, and the
// parallel method equals the engine's aba.
TEST(ChainFdFloating, EngineParallelMethodOnAFreeRope) {
  const Model m = test::load_floating("rope:5000");
  const int kT = kChainFdThreadsPerInstance;
  EXPECT_EQ(choose_fd_method(BackendKind::OpenMP, m, 1, kT), FdMethod::Parallel);
  EXPECT_EQ(choose_fd_method(BackendKind::OpenMP, m, 1, kT - 1), FdMethod::Aba);
  EXPECT_EQ(choose_fd_method(BackendKind::Serial, m, 1, kT), FdMethod::Aba);
  EXPECT_EQ(choose_fd_method(BackendKind::OpenMP, test::load_floating("ballrope:5000"), 1, kT), FdMethod::Aba);
  const Index B = 2;
  const SoaStates x = random_soa_states(m, B, 4, false);
  const auto ref = test::soa_reference(m, x, true);
  BackendOptions o;
  o.backend = backend_unusable(BackendKind::OpenMP).empty() ? BackendKind::OpenMP : BackendKind::Serial;
  o.fd_method = FdMethod::Parallel;
  o.max_batch = B;
  o.threads = 2;
  const auto engine = make_forward_dynamics(m, o);
  EXPECT_EQ(engine->method(), FdMethod::Parallel);
  std::vector<double> qdd(x.qd.size(), NAN);
  FdBatchIn<double> in{BatchView<const double>::soa(x.q.data(), x.nq, B),
                       BatchView<const double>::soa(x.qd.data(), x.nv, B),
                       BatchView<const double>::soa(x.u.data(), x.nv, B), nullptr};
  EXPECT_TRUE(engine->compute(in, BatchView<double>::soa(qdd.data(), x.nv, B)).ok());
  EXPECT_LT(test::max_rel_err(qdd, ref), 1e-9);
  o.fd_method = FdMethod::Hybrid;
  EXPECT_THROW(make_forward_dynamics(m, o), BackendError);
}

// Equal links share one table entry whatever their rows in q and qd (Body::idx_q /
// idx_v differ per link): a rope's links are three body classes (the first, at the
// origin; then axes y and x in turn), a free rope's three (the base; y, x).
TEST(ChainFdFloating, EqualLinksShareOneBodyClass) {
  EXPECT_EQ(ChainBodies<double>::from(load_model("rope:1000"), 1).body.size(), 3u);
  EXPECT_EQ(ChainBodies<float>::from(load_model("rope:1000").cast<float>(), 1).body.size(), 3u);
  EXPECT_EQ(ChainBodies<double>::from(test::load_floating("rope:1000"), 1).body.size(), 3u);
}
