// The chain forward dynamics (scans over links, scandyn/algorithm/chain_fd.hpp)
// against the serial double ABA, and its building blocks against their definitions.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <random>

#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;
using test::Tol;

namespace {

Eigen::Matrix<double, 6, 6> eig(const Mat6<double>& M) {
  Eigen::Matrix<double, 6, 6> o;
  for (int r = 0; r < 6; ++r)
    for (int c = 0; c < 6; ++c) o(r, c) = M(r, c);
  return o;
}

// The serial double ABA of every instance, SoA (n x B).
std::vector<double> reference_fd(const Model& model, const std::vector<double>& q, const std::vector<double>& qd,
                                 const std::vector<double>& tau, Index B, const std::vector<Force<double>>* fext) {
  const Index n = model.nv();
  Data data(model, false);
  std::vector<double> out(q.size()), qi(n), qdi(n), ti(n), qddi(n);
  for (Index b = 0; b < B; ++b) {
    for (Index i = 0; i < n; ++i) qi[i] = q[i * B + b], qdi[i] = qd[i * B + b], ti[i] = tau[i * B + b];
    const Status st = aba(model, data, qi.data(), qdi.data(), ti.data(), qddi.data(), fext ? fext->data() + b * n : nullptr);
    EXPECT_TRUE(st.ok());
    for (Index i = 0; i < n; ++i) out[i * B + b] = qddi[i];
  }
  return out;
}

template <class S>
double chain_fd_error(const Model& model, Index B, unsigned seed, int threads, Index chunk, bool with_fext,
                      double qd_scale = 1.0) {
  std::mt19937_64 rng(seed);
  const Index n = model.nv();
  const auto q = test::random_vector(rng, n * B, -3, 3);
  const auto qd = test::random_vector(rng, n * B, -qd_scale, qd_scale);
  const auto tau = test::random_vector(rng, n * B, -2, 2);
  std::vector<Force<double>> fext;
  if (with_fext) fext = test::random_wrenches<double>(rng, n * B, 1.0);
  const auto ref = reference_fd(model, q, qd, tau, B, with_fext ? &fext : nullptr);

  const ModelTpl<S> m = model.cast<S>();
  ChainForwardDynamics<S> fd(m, B, threads, chunk);
  const auto qs = test::cast_vector<S>(q), qds = test::cast_vector<S>(qd), taus = test::cast_vector<S>(tau);
  std::vector<Force<S>> fs;
  for (const auto& f : fext) fs.push_back(f.cast<S>());
  std::vector<S> qdd(q.size(), S(NAN));
  FdBatchIn<S> in{BatchView<const S>::soa(qs.data(), n, B), BatchView<const S>::soa(qds.data(), n, B),
                  BatchView<const S>::soa(taus.data(), n, B), with_fext ? fs.data() : nullptr};
  std::vector<int> failed(static_cast<std::size_t>(B), 7);
  EXPECT_EQ(fd.compute(in, BatchView<S>::soa(qdd.data(), n, B), failed.data()), 0);
  for (int f : failed) EXPECT_EQ(f, -1);
  return test::max_rel_err(qdd, ref);
}

}  // namespace

TEST(ChainFdBlocks, InverseInertiaIsTheInverse) {
  const Model m = test::random_model(6, 11);
  for (const auto& b : m.bodies) {
    const auto Phi = InverseInertia<double>::from(b.I);
    const auto I = eig(to_mat6(ABInertia<double>::from(b.I)));
    Eigen::Matrix<double, 6, 6> P;
    for (int c = 0; c < 6; ++c) {
      Vec6<double> e = Vec6<double>::zero();
      e.m[c] = 1;
      const Vec6<double> col = to_vec6(Phi * to_force(e));
      for (int r = 0; r < 6; ++r) P(r, c) = col.m[r];
    }
    EXPECT_LT((P * I - Eigen::Matrix<double, 6, 6>::Identity()).norm(), 1e-12);
  }
}

TEST(ChainFdBlocks, DualFormGivesTheProjectedArticulatedInertia) {
  // Ia = IA - U U^T / D equals T (T^T IA^{-1} T)^{-1} T^T for any SPD IA
  const Model m = test::random_model(8, 5);
  std::mt19937_64 rng(3);
  for (const auto& b : m.bodies) {
    Eigen::Matrix<double, 6, 6> A = Eigen::Matrix<double, 6, 6>::Random();
    A = A * A.transpose() + 0.1 * Eigen::Matrix<double, 6, 6>::Identity();
    ABInertia<double> IA;
    Mat6<double> Am;
    for (int r = 0; r < 6; ++r)
      for (int c = 0; c < 6; ++c) Am(r, c) = A(r, c);
    IA = to_abinertia(Am);
    Force<double> U;
    double D, u;
    aba_joint_terms(b, IA, Force<double>::zero(), 0.0, U, D, u);
    const auto Ia = eig(to_mat6(IA.minus_outer(U, 1.0 / D)));
    // Y = T^T IA^{-1} T
    Eigen::Matrix<double, 6, 5> T;
    for (int k = 0; k < 5; ++k) {
      const auto t = to_vec6(constraint_force(b, k));
      for (int r = 0; r < 6; ++r) T(r, k) = t.m[r];
    }
    EXPECT_LT((T.transpose() * T - Eigen::Matrix<double, 5, 5>::Identity()).norm(), 1e-14);  // orthonormal
    const Eigen::Matrix<double, 6, 1> S = eig(to_mat6(Transform<double>::identity())) *
                                          Eigen::Map<const Eigen::Matrix<double, 6, 1>>(to_vec6(joint_motion(b, 1.0)).m);
    EXPECT_LT((T.transpose() * S).norm(), 1e-14);  // S^T T = 0
    const Eigen::Matrix<double, 5, 5> Yd = T.transpose() * A.inverse() * T;
    Mat5<double> Y;
    for (int r = 0; r < 5; ++r)
      for (int c = 0; c < 5; ++c) Y(r, c) = Yd(r, c);
    const auto Ia2 = eig(to_mat6(articulated_from_dual(b, Y)));
    EXPECT_LT((Ia - Ia2).norm(), 1e-10 * Ia.norm());
  }
}

TEST(ChainFdBlocks, DualCompositionIsAssociativeAndMatchesApplication) {
  // ((a o b) o c)(Y) = a(b(c(Y))) for random elements of a chain
  const Model m = test::random_chain(4, 9);
  std::mt19937_64 rng(1);
  const auto q = test::random_vector(rng, 4, -3, 3);
  DualRiccati<double> e[3];
  for (int i = 0; i < 3; ++i)
    e[i] = dual_element(m.bodies[i], InverseInertia<double>::from(m.bodies[i].I), true, m.bodies[i + 1],
                        joint_transform(m.bodies[i + 1], q[i + 1]));
  Mat5<double> Y = Mat5<double>::identity();
  for (int k = 0; k < 5; ++k) Y(k, k) = 0.5 + k;
  const auto seq = e[0].apply(e[1].apply(e[2].apply(Y)));
  const auto left = DualRiccati<double>::compose(DualRiccati<double>::compose(e[0], e[1]), e[2]).apply(Y);
  const auto right = DualRiccati<double>::compose(e[0], DualRiccati<double>::compose(e[1], e[2])).apply(Y);
  for (int k = 0; k < 25; ++k) {
    EXPECT_NEAR(left.m[k], seq.m[k], 1e-10 * (1 + std::fabs(seq.m[k])));
    EXPECT_NEAR(right.m[k], seq.m[k], 1e-10 * (1 + std::fabs(seq.m[k])));
  }
}

TEST(ChainFd, RandomChainsMatchSerialAbaDouble) {
  for (unsigned seed : {1u, 2u, 3u}) {
    const Model m = test::random_chain(57, seed);
    for (Index chunk : {1, 3, 8, 64}) {
      EXPECT_LT(chain_fd_error<double>(m, 3, seed, 2, chunk, false), 1e-9) << "seed " << seed << " chunk " << chunk;
      EXPECT_LT(chain_fd_error<double>(m, 2, seed, 1, chunk, true), 1e-9) << "fext, seed " << seed << " chunk " << chunk;
    }
  }
}

TEST(ChainFd, SingleLinkAndTinyChains) {
  for (int n : {1, 2, 3}) {
    const Model m = test::random_chain(n, 40 + n);
    EXPECT_LT(chain_fd_error<double>(m, 5, 7, 2, 1, true), 1e-11) << n;
    EXPECT_LT(chain_fd_error<double>(m, 5, 7, 2, 2, false), 1e-11) << n;
  }
}

TEST(ChainFd, RopesMatchSerialAba) {
  for (int n : {10, 1000, 20000}) {
    const Model m = make_generated("rope:" + std::to_string(n));
    const double ed = chain_fd_error<double>(m, 1, 5, 2, 0, false);
    const double ef = chain_fd_error<float>(m, 1, 5, 2, 0, false);
    EXPECT_LT(ed, 1e-9) << "rope:" << n;
    EXPECT_LT(ef, 1e-2) << "rope:" << n;
    std::printf("rope:%d chain fd max rel err: double %.2e float %.2e\n", n, ed, ef);
  }
}

// Chains hanging from the base (a curtain, fingers on a fixed palm) are independent
// chains inside one instance: their boundaries are absorbed as instance boundaries.
TEST(ChainFd, ChainsFromTheBaseMatchSerialAba) {
  for (unsigned seed : {4u, 5u}) {
    // chains of 1, 2, 7, 13 and 17 links; arbitrary axes, prismatic joints, rotated inertias
    const Model m = test::random_chains_from_base(40, seed, {1, 3, 10, 23});
    ASSERT_EQ(first_branching_body(m), -1);
    for (Index chunk : {1, 2, 5, 64}) {
      EXPECT_LT(chain_fd_error<double>(m, 3, seed, 2, chunk, false), 1e-9) << "seed " << seed << " chunk " << chunk;
      EXPECT_LT(chain_fd_error<double>(m, 2, seed, 1, chunk, true), 1e-9) << "fext, seed " << seed << " chunk " << chunk;
    }
  }
  const Model curtain = make_generated("curtain:6:50");
  ASSERT_EQ(first_branching_body(curtain), -1);
  EXPECT_LT(chain_fd_error<double>(curtain, 2, 9, 2, 0, false), 1e-9);
  EXPECT_LT(chain_fd_error<float>(curtain, 2, 9, 2, 0, false), 1e-3);
}

TEST(ChainFd, RefusesTrees) {
  for (const Model& m : {test::random_model(10, 3), make_generated("tree:20:3")}) {
    const Index i = first_branching_body(m);
    ASSERT_GE(i, 0) << m.name;  // a body whose parent is neither the previous body nor the base
    try {
      ChainForwardDynamics<double> fd(m, 1);
      ADD_FAILURE() << m.name << " was accepted";
    } catch (const BackendError& e) {
      EXPECT_NE(std::string(e.what()).find("body " + std::to_string(i) + " "), std::string::npos) << e.what();
    }
  }
}

TEST(ChainFd, FailedPivotIsReportedAndQddUnwritten) {
  const Model m = make_generated("rope:50");
  std::vector<double> q(100, 0.1), qd(100, 0.0), tau(100, 0.0), qdd(100, 7.0);
  q[20 * 2 + 1] = NAN;  // instance 1, link 20
  ChainForwardDynamics<double> fd(m, 2, 2, 4);
  std::vector<int> failed(2, 9);
  FdBatchIn<double> in{BatchView<const double>::soa(q.data(), 50, 2), BatchView<const double>::soa(qd.data(), 50, 2),
                       BatchView<const double>::soa(tau.data(), 50, 2), nullptr};
  EXPECT_EQ(fd.compute(in, BatchView<double>::soa(qdd.data(), 50, 2), failed.data()), 1);
  EXPECT_EQ(failed[0], -1);
  EXPECT_GE(failed[1], 0);
  EXPECT_LE(failed[1], 20);
  for (Index i = 0; i < 50; ++i) {
    EXPECT_TRUE(std::isfinite(qdd[i * 2])) << i;
    EXPECT_EQ(qdd[i * 2 + 1], 7.0) << i;
  }
}
