// The first-order derivatives of inverse and forward dynamics on models with
// multi-DoF joints (a floating base, spherical joints; rnea_derivatives_general_instance
// in scandyn/instance/dynamics_derivatives.hpp) against independent truths: central
// differences of the reference rnea / aba along each DoF's local increment (q (+) h e_j
// by joint_integrate, the integrators' retraction: its first derivative is the
// tangent direction the analytical q columns are taken along), M against crba, the
// identities dqdd/dtau M = 1 and dqdd/dq = -M^-1 dtau/dq; the engines (serial equal
// to the reference, OpenMP equal to serial, float against double) and the cuda
// backend taking them (its results: tests/cuda/test_cuda_derivatives_multi_dof.cu).
// Pinocchio's computeRNEADerivatives / computeABADerivatives on the same
// models: scripts/check_pinocchio.py (ctest pinocchio_crosscheck).
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "floating_models.hpp"
#include "scandyn/algorithm/configuration.hpp"
#include "scandyn/algorithm/derivatives.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using test::random_vector;

using Case = test::NamedModel;

std::vector<Case> cases() { return test::multi_dof_models({"tree:12:3"}, 4, 6, 5, {1, 3, 8, 13, 30}, 40); }

struct State {
  std::vector<double> q, qd, qdd, tau;
  std::vector<Force<double>> fext;
};

State random_state(const Model& m, unsigned seed, bool with_fext) {
  std::mt19937_64 rng(seed);
  State s;
  s.q = test::random_q(m, rng, -2, 2);
  s.qd = random_vector(rng, m.nv(), -2, 2);
  s.qdd = random_vector(rng, m.nv(), -2, 2);
  s.tau = random_vector(rng, m.nv(), -5, 5);
  if (with_fext) s.fext = test::random_wrenches<double>(rng, m.nbodies(), 2.0);
  return s;
}

const Force<double>* wrenches(const State& s) { return s.fext.empty() ? nullptr : s.fext.data(); }

MatrixRef<double> ref(std::vector<double>& m, Index n) { return {m.data(), n, 1}; }

// q (+) h e_dof: the joint of DoF `dof` moved by h along its local direction
// (joint_integrate with the unit rate of that DoF).
std::vector<double> retract(const Model& m, std::vector<double> q, Index dof, double h) {
  for (const Body<double>& b : m.bodies) {
    const int nj = joint_nv(b.type);
    if (dof < b.idx_v || dof >= b.idx_v + nj) continue;
    double v[kMaxJointDofs] = {};
    v[dof - b.idx_v] = 1;
    joint_integrate(b, q.data() + b.idx_q, v, h);
    return q;
  }
  ADD_FAILURE() << "no joint has DoF " << dof;
  return q;
}

// d f / d x_j (nv x nv, row-major) by central differences D(h) = (f(x (+) h e_j) -
// f(x (+) -h e_j)) / 2h with one Richardson step (4 D(h / 2) - D(h)) / 3; move(x, j, h)
// gives x (+) h e_j (a retraction for q, x + h e_j for qd).
template <class Move, class F>
std::vector<double> central_jacobian(Index nv, Move&& move, F&& f, double h) {
  std::vector<double> J(static_cast<std::size_t>(nv) * nv), fp(nv), fm(nv), d1(nv), d2(nv);
  auto diff = [&](Index j, double step, std::vector<double>& d) {
    f(move(j, step), fp.data());
    f(move(j, -step), fm.data());
    for (Index i = 0; i < nv; ++i) d[i] = (fp[i] - fm[i]) / (2 * step);
  };
  for (Index j = 0; j < nv; ++j) {
    diff(j, h, d1);
    diff(j, h / 2, d2);
    for (Index i = 0; i < nv; ++i) J[i * nv + j] = (4 * d2[i] - d1[i]) / 3;
  }
  return J;
}

// Central differences, tolerance 1e-6 relative to the block's largest entry (at least
// 1). q: step 1e-3 with one Richardson step (truncation O(h^4)). qd: tau and qdd are
// quadratic in qd, so the central difference has no truncation error at any step, and
// a large step 0.1 keeps the rounding small (ballrope's tiny link inertias make the
// ABA's rounding, amplified by 1 / h, reach 3e-5 at h = 1e-3 and 3e-7 at 0.1).
constexpr double kStep = 1e-3;
constexpr double kStepQd = 0.1;
constexpr double kFdTol = 1e-6;

// The q and qd blocks (dq, dqd: nv x nv, row-major) of the derivatives of `what` at s
// against its central differences along q's tangent directions (retract; kStep) and
// along qd (kStepQd); f_q(q, out) and f_qd(qd, out) evaluate it with the other input at s.
template <class Fq, class Fqd>
void expect_central_differences(const Model& m, const State& s, const std::vector<double>& dq,
                                const std::vector<double>& dqd, Fq&& f_q, Fqd&& f_qd, const std::string& what) {
  const Index nv = m.nv();
  const auto move_q = [&](Index j, double h) { return retract(m, s.q, j, h); };
  const auto move_qd = [&](Index j, double h) {
    std::vector<double> x = s.qd;
    x[j] += h;
    return x;
  };
  EXPECT_LT(test::max_rel_err(dq, central_jacobian(nv, move_q, f_q, kStep)), kFdTol) << "d" << what << "/dq";
  EXPECT_LT(test::max_rel_err(dqd, central_jacobian(nv, move_qd, f_qd, kStepQd)), kFdTol) << "d" << what << "/dqd";
}

TEST(MultiDofDerivatives, InverseDynamicsMatchCentralDifferences) {
  for (const Case& c : cases()) {
    for (bool with_fext : {false, true}) {
      SCOPED_TRACE(c.name + (with_fext ? " with fext" : ""));
      const Model& m = c.m;
      ASSERT_TRUE(m.multi_dof());
      const Index nv = m.nv();
      const State s = random_state(m, 11 + static_cast<unsigned>(nv), with_fext);
      DerivativeDataTpl<double> dd(m);
      std::vector<double> dq(nv * nv), dqd(nv * nv), M(nv * nv), tau(nv);
      rnea_derivatives(m, dd, s.q.data(), s.qd.data(), s.qdd.data(), wrenches(s), ref(dq, nv), ref(dqd, nv),
                       ref(M, nv), tau.data());
      Data data(m);
      std::vector<double> tau_ref(nv);
      rnea(m, data, s.q.data(), s.qd.data(), s.qdd.data(), tau_ref.data(), wrenches(s));
      EXPECT_LT(test::max_rel_err(tau, tau_ref), 1e-12);

      const auto id_q = [&](const std::vector<double>& q, double* out) {
        rnea(m, data, q.data(), s.qd.data(), s.qdd.data(), out, wrenches(s));
      };
      const auto id_qd = [&](const std::vector<double>& qd, double* out) {
        rnea(m, data, s.q.data(), qd.data(), s.qdd.data(), out, wrenches(s));
      };
      expect_central_differences(m, s, dq, dqd, id_q, id_qd, "tau");
      std::vector<double> Mref(nv * nv);
      crba(m, data, s.q.data(), Mref.data());
      EXPECT_LT(test::max_rel_err(M, Mref), 1e-12) << "M against crba";
    }
  }
}

TEST(MultiDofDerivatives, ForwardDynamicsMatchCentralDifferencesAndIdentities) {
  for (const Case& c : cases()) {
    for (bool with_fext : {false, true}) {
      SCOPED_TRACE(c.name + (with_fext ? " with fext" : ""));
      const Model& m = c.m;
      const Index nv = m.nv();
      const State s = random_state(m, 23 + static_cast<unsigned>(nv), with_fext);
      DerivativeDataTpl<double> dd(m);
      std::vector<double> dq(nv * nv), dqd(nv * nv), Minv(nv * nv), qdd(nv);
      ASSERT_TRUE(aba_derivatives(m, dd, s.q.data(), s.qd.data(), s.tau.data(), wrenches(s), qdd.data(),
                                  ref(dq, nv), ref(dqd, nv), ref(Minv, nv))
                      .ok());
      Data data(m);
      std::vector<double> qdd_ref(nv);
      ASSERT_TRUE(aba(m, data, s.q.data(), s.qd.data(), s.tau.data(), qdd_ref.data(), wrenches(s)).ok());
      EXPECT_LT(test::max_rel_err(qdd, qdd_ref), 1e-12);

      const auto fd_q = [&](const std::vector<double>& q, double* out) {
        ASSERT_TRUE(aba(m, data, q.data(), s.qd.data(), s.tau.data(), out, wrenches(s)).ok());
      };
      const auto fd_qd = [&](const std::vector<double>& qd, double* out) {
        ASSERT_TRUE(aba(m, data, s.q.data(), qd.data(), s.tau.data(), out, wrenches(s)).ok());
      };
      expect_central_differences(m, s, dq, dqd, fd_q, fd_qd, "qdd");

      // identities: M M^-1 = 1 (M from crba), dqdd/dq = -M^-1 dtau/dq and dqdd/dqd =
      // -M^-1 dtau/dqd with the inverse-dynamics derivatives at qdd = FD
      std::vector<double> M(nv * nv), tq(nv * nv), tqd(nv * nv), Mid(nv * nv);
      crba(m, data, s.q.data(), M.data());
      rnea_derivatives(m, dd, s.q.data(), s.qd.data(), qdd.data(), wrenches(s), ref(tq, nv), ref(tqd, nv),
                       ref(Mid, nv));
      std::vector<double> eye(nv * nv, 0.0), MMinv(nv * nv, 0.0), pq(nv * nv, 0.0), pqd(nv * nv, 0.0);
      for (Index i = 0; i < nv; ++i) eye[i * nv + i] = 1;
      for (Index i = 0; i < nv; ++i)
        for (Index j = 0; j < nv; ++j)
          for (Index k = 0; k < nv; ++k) {
            MMinv[i * nv + j] += M[i * nv + k] * Minv[k * nv + j];
            pq[i * nv + j] -= Minv[i * nv + k] * tq[k * nv + j];
            pqd[i * nv + j] -= Minv[i * nv + k] * tqd[k * nv + j];
          }
      EXPECT_LT(test::max_rel_err(MMinv, eye), 1e-9) << "M M^-1";
      EXPECT_LT(test::max_rel_err(dq, pq), 1e-9) << "dqdd/dq = -M^-1 dtau/dq";
      EXPECT_LT(test::max_rel_err(dqd, pqd), 1e-9) << "dqdd/dqd = -M^-1 dtau/dqd";
      for (Index i = 0; i < nv; ++i)
        for (Index j = 0; j < nv; ++j) EXPECT_EQ(Minv[i * nv + j], Minv[j * nv + i]);
    }
  }
}

// The general recursion on a model of 1-DoF joints is the 1-DoF one (same steps).
TEST(MultiDofDerivatives, GeneralRecursionOnOneDofModelsIsTheOneDofRecursion) {
  for (Model m : {test::load_robot("hyq.urdf"), load_model("tree:20:2"), test::random_model(15, 3)}) {
    SCOPED_TRACE(m.name);
    set_joint_offsets(m);  // (the general path reads idx_q / idx_v)
    const Index nv = m.nv();
    const State s = random_state(m, 5, true);
    DerivativeDataTpl<double> dd(m);
    std::vector<double> a(3 * nv * nv), b(3 * nv * nv), ta(nv), tb(nv);
    const Index n2 = nv * nv;
    const Motion<double> a0 = base_acceleration(m.gravity);
    rnea_derivatives_instance(m.bodies.data(), nv, a0, s.q.data(), s.qd.data(), s.qdd.data(), wrenches(s),
                              dd.work.data(), MatrixRef<double>{a.data(), nv, 1},
                              MatrixRef<double>{a.data() + n2, nv, 1}, MatrixRef<double>{a.data() + 2 * n2, nv, 1},
                              ta.data());
    rnea_derivatives_general_instance(m.bodies.data(), m.nbodies(), nv, a0, s.q.data(), s.qd.data(), s.qdd.data(),
                                      wrenches(s), dd.work.data(), MatrixRef<double>{b.data(), nv, 1},
                                      MatrixRef<double>{b.data() + n2, nv, 1},
                                      MatrixRef<double>{b.data() + 2 * n2, nv, 1}, tb.data());
    EXPECT_EQ(a, b);
    EXPECT_EQ(ta, tb);
  }
}

// The tree of DoFs: a joint's DoFs a chain below the parent joint's last DoF.
TEST(MultiDofDerivatives, DofParents) {
  const Model m = test::load_floating("ballrope:3");  // free link_0, two spherical joints
  ASSERT_EQ(m.nv(), 12);
  DerivativeDataTpl<double> dd(m);
  const std::vector<Index> expect{-1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10};
  EXPECT_EQ(dd.dof_parent, expect);
  const Model t = test::random_floating_model(8, 41, 0.4);
  DerivativeDataTpl<double> dt(t);
  for (const Body<double>& b : t.bodies) {
    const Index p = b.parent;
    EXPECT_EQ(dt.dof_parent[b.idx_v], p < 0 ? -1 : t.bodies[p].idx_v + joint_nv(t.bodies[p].type) - 1);
    for (int k = 1; k < joint_nv(b.type); ++k) EXPECT_EQ(dt.dof_parent[b.idx_v + k], b.idx_v + k - 1);
  }
  // dof_last[k]: the largest DoF of k's subtree (every descendant at or before it; a
  // preorder, as the loader's, makes the subtree exactly k..dof_last[k])
  const Index nv = t.nv();
  for (Index k = 0; k < nv; ++k) {
    Index largest = k;
    for (Index i = k; i < nv; ++i)
      for (Index a = i; a >= 0; a = dt.dof_parent[a])
        if (a == k) largest = i;
    EXPECT_EQ(dt.dof_last[k], largest) << "DoF " << k;
  }
  EXPECT_EQ(dd.dof_last[0], 11);
}

// ---- the engines ----------------------------------------------------------------

struct Batch {
  Index nq, nv, nb, B;
  std::vector<double> q, qd, x;  // instance-major: B x nq, B x nv, B x nv
  std::vector<Force<double>> fext;  // B x nb
};

Batch make_batch(const Model& m, Index B, unsigned seed) {
  std::mt19937_64 rng(seed);
  Batch b{m.nq(), m.nv(), m.nbodies(), B, {}, {}, {}, {}};
  for (Index k = 0; k < B; ++k) {
    const std::vector<double> q = test::random_q(m, rng, -2, 2);
    b.q.insert(b.q.end(), q.begin(), q.end());
  }
  b.qd = random_vector(rng, static_cast<int>(b.nv * B), -1.5, 1.5);
  b.x = random_vector(rng, static_cast<int>(b.nv * B), -3, 3);
  b.fext = test::random_wrenches<double>(rng, static_cast<int>(b.nb * B), 1.0);
  return b;
}

TEST(MultiDofDerivatives, EnginesSerialIsTheReferenceOpenMPEqualsSerial) {
  for (const Case& c : cases()) {
    SCOPED_TRACE(c.name);
    const Model& m = c.m;
    const Index nv = m.nv(), nq = m.nq(), nb = m.nbodies(), B = 7;
    const Batch in = make_batch(m, B, 3 + static_cast<unsigned>(nv));
    using V = BatchView<const double>;
    const IdBatchIn<double> id_in{V::aos(in.q.data(), nq, B), V::aos(in.qd.data(), nv, B),
                                  V::aos(in.x.data(), nv, B), in.fext.data()};
    const FdBatchIn<double> fd_in{V::aos(in.q.data(), nq, B), V::aos(in.qd.data(), nv, B),
                                  V::aos(in.x.data(), nv, B), in.fext.data()};
    std::vector<test::DerivativeBlocks<double>> id_out, fd_out;
    std::vector<std::vector<double>> qdds;
    for (BackendKind kind : {BackendKind::Serial, BackendKind::OpenMP}) {
      if (!backend_unusable(kind).empty()) continue;
      BackendOptions o;
      o.backend = kind;
      o.max_batch = B;
      o.threads = 3;
      id_out.emplace_back(nv, B, kind == BackendKind::OpenMP);  // openmp: the soa layout
      make_id_derivatives(m, o)->compute(id_in, {id_out.back().v[0], id_out.back().v[1], id_out.back().v[2]});
      fd_out.emplace_back(nv, B, kind == BackendKind::OpenMP);
      qdds.emplace_back(nv * B, NAN);
      const BatchStatus st = make_fd_derivatives(m, o)->compute(
          fd_in, {fd_out.back().v[0], fd_out.back().v[1], fd_out.back().v[2],
                  BatchView<double>::aos(qdds.back().data(), nv, B)});
      ASSERT_TRUE(st.ok()) << st.message();
    }
    ASSERT_FALSE(id_out.empty());
    // the serial engine is the reference instance by instance
    DerivativeDataTpl<double> dd(m);
    const Index n2 = nv * nv;
    std::vector<double> r(3 * n2), f(3 * n2), qdd(nv);
    for (Index b = 0; b < B; ++b) {
      const double* q = in.q.data() + b * nq;
      const double* qd = in.qd.data() + b * nv;
      const double* x = in.x.data() + b * nv;
      const Force<double>* fe = in.fext.data() + b * nb;
      rnea_derivatives(m, dd, q, qd, x, fe, MatrixRef<double>{r.data(), nv, 1},
                       MatrixRef<double>{r.data() + n2, nv, 1}, MatrixRef<double>{r.data() + 2 * n2, nv, 1});
      ASSERT_TRUE(aba_derivatives(m, dd, q, qd, x, fe, qdd.data(), MatrixRef<double>{f.data(), nv, 1},
                                  MatrixRef<double>{f.data() + n2, nv, 1}, MatrixRef<double>{f.data() + 2 * n2, nv, 1})
                      .ok());
      for (std::size_t e = 0; e < id_out.size(); ++e)
        for (int k = 0; k < 3; ++k)
          for (Index i = 0; i < nv; ++i)
            for (Index j = 0; j < nv; ++j) {
              ASSERT_EQ(id_out[e].at(k, i, j, b, nv), r[k * n2 + i * nv + j]) << "id engine " << e << " block " << k;
              ASSERT_EQ(fd_out[e].at(k, i, j, b, nv), f[k * n2 + i * nv + j]) << "fd engine " << e << " block " << k;
            }
      for (std::size_t e = 0; e < qdds.size(); ++e)
        for (Index i = 0; i < nv; ++i) ASSERT_EQ(qdds[e][b * nv + i], qdd[i]);
    }
  }
}

// float against double, relative to each block's largest entry: inverse dynamics
// 1e-5, forward dynamics 1e-2 (measured: 1.6e-6 and 2.3e-3, atlas's M^-1; ballrope is
// left out: its links' 1e-8 kg m^2 inertias fail float's pivots).
TEST(MultiDofDerivatives, FloatAgainstDouble) {
  double worst_id = 0, worst_fd = 0;
  for (const Case& c : cases()) {
    if (c.name.rfind("ballrope", 0) == 0) continue;  // links of 1e-8 kg m^2: float's pivots fail
    SCOPED_TRACE(c.name);
    const Model& m = c.m;
    const ModelTpl<float> mf = m.cast<float>();
    const Index nv = m.nv(), nq = m.nq(), B = 3;
    const Batch in = make_batch(m, B, 77 + static_cast<unsigned>(nv));
    const std::vector<float> qf(in.q.begin(), in.q.end()), qdf(in.qd.begin(), in.qd.end()),
        xf(in.x.begin(), in.x.end());
    std::vector<Force<float>> ff;
    for (const Force<double>& w : in.fext) ff.push_back(w.template cast<float>());
    BackendOptions o;
    o.backend = BackendKind::Serial;
    o.max_batch = B;
    test::DerivativeBlocks<double> idd(nv, B, false), fdd(nv, B, false);
    test::DerivativeBlocks<float> idf(nv, B, false), fdf(nv, B, false);
    using V = BatchView<const double>;
    using W = BatchView<const float>;
    make_id_derivatives(m, o)->compute({V::aos(in.q.data(), nq, B), V::aos(in.qd.data(), nv, B),
                                        V::aos(in.x.data(), nv, B), in.fext.data()},
                                       {idd.v[0], idd.v[1], idd.v[2]});
    make_id_derivatives(mf, o)->compute({W::aos(qf.data(), nq, B), W::aos(qdf.data(), nv, B),
                                         W::aos(xf.data(), nv, B), ff.data()},
                                        {idf.v[0], idf.v[1], idf.v[2]});
    ASSERT_TRUE(make_fd_derivatives(m, o)
                    ->compute({V::aos(in.q.data(), nq, B), V::aos(in.qd.data(), nv, B), V::aos(in.x.data(), nv, B),
                               in.fext.data()},
                              {fdd.v[0], fdd.v[1], fdd.v[2], {}})
                    .ok());
    ASSERT_TRUE(make_fd_derivatives(mf, o)
                    ->compute({W::aos(qf.data(), nq, B), W::aos(qdf.data(), nv, B), W::aos(xf.data(), nv, B),
                               ff.data()},
                              {fdf.v[0], fdf.v[1], fdf.v[2], {}})
                    .ok());
    for (Index b = 0; b < B; ++b)
      for (int k = 0; k < 3; ++k) {
        std::vector<double> d, fl, d2, f2;
        for (Index i = 0; i < nv; ++i)
          for (Index j = 0; j < nv; ++j) {
            d.push_back(idd.at(k, i, j, b, nv));
            fl.push_back(idf.at(k, i, j, b, nv));
            d2.push_back(fdd.at(k, i, j, b, nv));
            f2.push_back(fdf.at(k, i, j, b, nv));
          }
        const double eid = test::max_rel_err(fl, d), efd = test::max_rel_err(f2, d2);
        worst_id = std::max(worst_id, eid);
        worst_fd = std::max(worst_fd, efd);
        EXPECT_LT(eid, 1e-5) << "id block " << k << " instance " << b;
        EXPECT_LT(efd, 1e-2) << "fd block " << k << " instance " << b;
      }
  }
  RecordProperty("worst_float_id", std::to_string(worst_id));
  RecordProperty("worst_float_fd", std::to_string(worst_fd));
}

// The cuda backend takes multi-DoF joints (its general derivative kernels): without a
// device, or with a capacity this build does not compile, the error says so and
// nothing about the joints.
TEST(MultiDofDerivatives, CudaTakesMultiDofJoints) {
#if SCANDYN_HAS_CUDA
  const Model m = test::load_floating(test::model_path("hyq.urdf"));
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  for (int k = 0; k < 2; ++k) {
    try {
      if (k == 0) EXPECT_EQ(make_id_derivatives(m, o)->strategy(), "general");
      else EXPECT_EQ(make_fd_derivatives(m, o)->strategy(), "general");
    } catch (const BackendError& e) {
      const std::string what = e.what();
      EXPECT_EQ(what.find("root_joint"), std::string::npos) << what;
      EXPECT_EQ(what.find("revolute and prismatic"), std::string::npos) << what;
      EXPECT_TRUE(what.find("device") != std::string::npos ||
                  what.find("SCANDYN_CUDA_ALL_CAPACITIES") != std::string::npos)
          << what;
    }
  }
  // the second-order derivatives keep refusing multi-DoF joints, and so do the cuda
  // directional derivatives (tests/algorithm/test_directional_multi_dof.cpp)
  BackendOptions s;
  EXPECT_THROW(make_id_second_derivatives(m, s), BackendError);
  EXPECT_THROW(make_fd_directional_derivatives(m, o), BackendError);
#else
  GTEST_SKIP() << "built without CUDA";
#endif
}

}  // namespace
}  // namespace scandyn
