// Sharded engines (scandyn/sharded.hpp): shard ranges, device lists, the shard pool,
// and every sharded engine over serial engines (the CPU stand-in for one engine per
// device) bit-identical to one serial engine over the whole batch, in every layout,
// with failures renumbered as the caller's instances. With a CUDA device: the
// factories' sharded engines (a device named twice: two shards on one GPU; every
// visible device) bit-identical to one CUDA engine, and errors naming the device.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>
#include <stdexcept>
#include <string>

#include "scandyn/algorithm/loops.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sharded.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

// ---- ranges and names -------------------------------------------------------------

TEST(ShardRange, CoversTheBatchInOrderWithSizesWithinOne) {
  for (Index B : {0, 1, 2, 5, 7, 64, 1000003})
    for (int n : {1, 2, 3, 4, 7, 8}) {
      Index next = 0, lo = B, hi = 0;
      for (int k = 0; k < n; ++k) {
        const ShardRange r = shard_range(B, n, k);
        EXPECT_EQ(r.begin, next) << "B " << B << " n " << n << " k " << k;
        next += r.count;
        lo = std::min(lo, r.count);
        hi = std::max(hi, r.count);
        EXPECT_LE(r.count, shard_capacity(B, n));
      }
      EXPECT_EQ(next, B);
      EXPECT_LE(hi - lo, 1);
    }
}

TEST(ParseDevices, ListsCurrentAndErrors) {
  EXPECT_EQ(parse_devices("0,1"), (std::vector<int>{0, 1}));
  EXPECT_EQ(parse_devices("1,1"), (std::vector<int>{1, 1}));
  EXPECT_EQ(parse_devices("3"), (std::vector<int>{3}));
  EXPECT_TRUE(parse_devices("current").empty());
  EXPECT_TRUE(parse_devices("").empty());
  for (const char* bad : {"x", "-1", "0,,1", "0,", "1.5", "0;1", "all,0"}) {
    try {
      parse_devices(bad);
      ADD_FAILURE() << "no error for '" << bad << "'";
    } catch (const BackendError& e) {
      EXPECT_NE(std::string(e.what()).find(std::string("devices '") + bad + "'"), std::string::npos) << e.what();
    }
  }
  EXPECT_EQ(devices_string({}), "current");
  EXPECT_EQ(devices_string({0, 1}), "0,1");
  if (!cuda::device_count() || cuda::device_count().value == 0) {
    try {
      parse_devices("all");
      ADD_FAILURE() << "'all' without a device";
    } catch (const BackendError& e) {
      EXPECT_NE(std::string(e.what()).find("no usable CUDA device"), std::string::npos) << e.what();
    }
  }
}

TEST(ShardPool, RunsEveryShardAndNamesTheFailingOne) {
  ShardPool pool({7, 8, 9}, false);
  std::vector<int> ran(3, 0);
  for (int round = 0; round < 50; ++round) pool.run([&](int k) { ++ran[static_cast<std::size_t>(k)]; });
  EXPECT_EQ(ran, (std::vector<int>{50, 50, 50}));
  try {
    pool.run([](int k) {
      if (k >= 1) throw std::runtime_error("failed in " + std::to_string(k));
    });
    ADD_FAILURE() << "no error";
  } catch (const BackendError& e) {
    EXPECT_EQ(std::string(e.what()), "shard 1: failed in 1");  // the lowest failing shard
  }
  // the pool still works after a failed run
  pool.run([&](int k) { ++ran[static_cast<std::size_t>(k)]; });
  EXPECT_EQ(ran, (std::vector<int>{51, 51, 51}));
}

TEST(ShardedEngines, OtherBackendsRefuseDevices) {
  const Model m = load_model("rope:5");
  BackendOptions o;
  o.backend = BackendKind::Serial;
  o.devices = {0, 1};
  try {
    make_inverse_dynamics<double>(m, o);
    ADD_FAILURE() << "no error";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("only the cuda backend"), std::string::npos) << e.what();
  }
}

// ---- sharded serial engines against one serial engine ----------------------------

constexpr Index kB = 11;  // instances: not a multiple of the shard counts

enum class Layout { Soa, Aos, Strided };
template <class T>
BatchView<T> view(T* p, Index n, Index B, Layout l) {
  if (l == Layout::Soa) return BatchView<T>::soa(p, n, B);
  if (l == Layout::Aos) return BatchView<T>::aos(p, n, B);
  return BatchView<T>{p, B, 2, 2 * n};
}
std::size_t storage(Index n, Index B, Layout l) { return static_cast<std::size_t>(n) * B * (l == Layout::Strided ? 2 : 1); }

// Random inputs of B instances in layout l: q (nq rows), qd, x (nv rows), wrenches.
struct Inputs {
  std::vector<double> q, qd, x;
  std::vector<Force<double>> fext;
  Inputs(const Model& m, Layout l, unsigned seed) {
    std::mt19937_64 g(seed);
    q.assign(storage(m.nq(), kB, l), 0.0);
    const BatchView<double> Q = view(q.data(), m.nq(), kB, l);
    for (Index b = 0; b < kB; ++b) {
      const std::vector<double> qb = test::random_q(m, g);
      for (Index i = 0; i < m.nq(); ++i) Q.at(i, b) = qb[static_cast<std::size_t>(i)];
    }
    qd = test::random_vector(g, static_cast<int>(storage(m.nv(), kB, l)), -1, 1);
    x = test::random_vector(g, static_cast<int>(storage(m.nv(), kB, l)), -1, 1);
    fext = test::random_wrenches<double>(g, static_cast<int>(m.nbodies() * kB), 0.5);
  }
};

BackendOptions serial_options(Index max_batch) {
  BackendOptions o;
  o.backend = BackendKind::Serial;
  o.max_batch = max_batch;
  return o;
}

// n serial engines made by make(options), each for its share of kB instances
template <class E, class Make>
std::vector<std::unique_ptr<E>> serial_shards(int n, Make make) {
  std::vector<std::unique_ptr<E>> v;
  for (int k = 0; k < n; ++k) v.push_back(make(serial_options(shard_capacity(kB, n))));
  return v;
}
std::vector<int> no_devices(int n) { return std::vector<int>(static_cast<std::size_t>(n), -1); }

std::vector<std::pair<std::string, Model>> models() {
  return {{"iiwa", test::load_robot("iiwa.urdf")},
          {"tree:20:3", load_model("tree:20:3")},
          {"floating hyq", test::load_floating("hyq")}};
}

TEST(ShardedEngines, SerialShardsEqualOneEngine) {
  for (const auto& [name, m] : models())
    for (Layout l : {Layout::Soa, Layout::Aos, Layout::Strided})
      for (int n : {1, 2, 3, 4})
        for (bool with_fext : {false, true}) {
          SCOPED_TRACE(name + " layout " + std::to_string(static_cast<int>(l)) + " shards " + std::to_string(n) +
                       (with_fext ? " fext" : ""));
          const Index nv = m.nv(), nq = m.nq();
          Inputs in(m, l, static_cast<unsigned>(nv * 7 + static_cast<int>(l)));
          const Force<double>* fext = with_fext ? in.fext.data() : nullptr;
          const auto Q = view<const double>(in.q.data(), nq, kB, l), QD = view<const double>(in.qd.data(), nv, kB, l),
                     X = view<const double>(in.x.data(), nv, kB, l);
          const std::size_t size = storage(nv, kB, l);
          std::vector<double> one(size, -7.0), many(size, -7.0);  // gaps must keep -7

          {
            auto single = make_inverse_dynamics<double>(m, serial_options(kB));
            ShardedInverseDynamics<double> sharded(
                serial_shards<InverseDynamics<double>>(n, [&](const BackendOptions& o) { return make_inverse_dynamics<double>(m, o); }),
                no_devices(n), false, m.nbodies());
            single->compute({Q, QD, X, fext}, view(one.data(), nv, kB, l));
            sharded.compute({Q, QD, X, fext}, view(many.data(), nv, kB, l));
            EXPECT_EQ(one, many) << "inverse dynamics";
            EXPECT_EQ(sharded.shard_count(), n);
            EXPECT_EQ(sharded.strategy(), single->strategy() + (n > 1 ? "-x" + std::to_string(n) : ""));
          }
          {
            auto single = make_bias_forces<double>(m, serial_options(kB));
            ShardedBiasForces<double> sharded(
                serial_shards<BiasForces<double>>(n, [&](const BackendOptions& o) { return make_bias_forces<double>(m, o); }),
                no_devices(n), false, m.nbodies());
            single->compute({Q, QD, fext}, view(one.data(), nv, kB, l));
            sharded.compute({Q, QD, fext}, view(many.data(), nv, kB, l));
            EXPECT_EQ(one, many) << "bias forces";
          }
          {
            auto single = make_forward_dynamics<double>(m, serial_options(kB));
            ShardedForwardDynamics<double> sharded(
                serial_shards<ForwardDynamics<double>>(n, [&](const BackendOptions& o) { return make_forward_dynamics<double>(m, o); }),
                no_devices(n), false, m.nbodies(), kB);
            const BatchStatus s1 = single->compute({Q, QD, X, fext}, view(one.data(), nv, kB, l));
            const BatchStatus sn = sharded.compute({Q, QD, X, fext}, view(many.data(), nv, kB, l));
            EXPECT_TRUE(s1.ok() && sn.ok()) << sn.message();
            EXPECT_EQ(one, many) << "forward dynamics";
            EXPECT_EQ(sharded.method(), single->method());
          }
          if (!with_fext) {
            const std::size_t msize = static_cast<std::size_t>(nv * nv) * kB;
            std::vector<double> M1(msize), Mn(msize);
            auto single = make_mass_matrix<double>(m, serial_options(kB));
            ShardedMassMatrix<double> sharded(
                serial_shards<MassMatrix<double>>(n, [&](const BackendOptions& o) { return make_mass_matrix<double>(m, o); }),
                no_devices(n), false, m.nbodies());
            single->compute(Q, BatchView<double>::aos(M1.data(), nv * nv, kB));
            sharded.compute(Q, BatchView<double>::aos(Mn.data(), nv * nv, kB));
            EXPECT_EQ(M1, Mn) << "mass matrix";

            KinematicsOptions ko;
            ko.frames = {0, static_cast<Index>(m.frames.size()) - 1};
            const Index pw = static_cast<Index>(ko.frames.size()) * pose_width(ko.pose);
            const Index jw = static_cast<Index>(ko.frames.size()) * 6 * nv;
            std::vector<double> P1(static_cast<std::size_t>(pw * kB)), Pn(P1.size()), J1(static_cast<std::size_t>(jw * kB)),
                Jn(J1.size());
            auto ksingle = make_kinematics<double>(m, serial_options(kB), ko);
            ShardedKinematics<double> ksharded(
                serial_shards<Kinematics<double>>(n, [&](const BackendOptions& o) { return make_kinematics<double>(m, o, ko); }),
                no_devices(n), false, m.nbodies());
            ksingle->compute(Q, BatchView<double>::soa(P1.data(), pw, kB), BatchView<double>::soa(J1.data(), jw, kB));
            ksharded.compute(Q, BatchView<double>::soa(Pn.data(), pw, kB), BatchView<double>::soa(Jn.data(), jw, kB));
            EXPECT_EQ(P1, Pn) << "frame poses";
            EXPECT_EQ(J1, Jn) << "frame Jacobians";
          }
        }
}

// Derivatives and hybrid dynamics take 1-DoF joints: iiwa and a random tree.
TEST(ShardedEngines, SerialShardsEqualOneEngineDerivativesHybrid) {
  for (const char* name : {"iiwa", "tree:20:3"}) {
    const Model m = std::string(name) == "iiwa" ? test::load_robot("iiwa.urdf") : load_model(name);
    const Index nv = m.nv();
    const Inputs in(m, Layout::Soa, 5);
    const auto Q = view<const double>(in.q.data(), nv, kB, Layout::Soa),
               QD = view<const double>(in.qd.data(), nv, kB, Layout::Soa),
               X = view<const double>(in.x.data(), nv, kB, Layout::Soa);
    const std::size_t mat = static_cast<std::size_t>(nv * nv) * kB;
    for (int n : {2, 3}) {
      SCOPED_TRACE(std::string(name) + " shards " + std::to_string(n));
      std::vector<double> a1(3 * mat), an(3 * mat);
      const auto blocks = [&](std::vector<double>& v, int k) {
        return BatchView<double>::soa(v.data() + k * mat, nv * nv, kB);
      };
      {
        auto single = make_id_derivatives<double>(m, serial_options(kB));
        ShardedIdDerivatives<double> sharded(
            serial_shards<IdDerivatives<double>>(n, [&](const BackendOptions& o) { return make_id_derivatives<double>(m, o); }),
            no_devices(n), false, m.nbodies());
        single->compute({Q, QD, X, in.fext.data()}, {blocks(a1, 0), blocks(a1, 1), blocks(a1, 2)});
        sharded.compute({Q, QD, X, in.fext.data()}, {blocks(an, 0), blocks(an, 1), blocks(an, 2)});
        EXPECT_EQ(a1, an) << "id derivatives";
      }
      {
        std::vector<double> q1(static_cast<std::size_t>(nv) * kB), qn(q1.size());
        auto single = make_fd_derivatives<double>(m, serial_options(kB));
        ShardedFdDerivatives<double> sharded(
            serial_shards<FdDerivatives<double>>(n, [&](const BackendOptions& o) { return make_fd_derivatives<double>(m, o); }),
            no_devices(n), false, m.nbodies(), kB);
        EXPECT_TRUE(single->compute({Q, QD, X, nullptr}, {blocks(a1, 0), blocks(a1, 1), blocks(a1, 2),
                                                          BatchView<double>::soa(q1.data(), nv, kB)}).ok());
        EXPECT_TRUE(sharded.compute({Q, QD, X, nullptr}, {blocks(an, 0), blocks(an, 1), blocks(an, 2),
                                                          BatchView<double>::soa(qn.data(), nv, kB)}).ok());
        EXPECT_EQ(a1, an) << "fd derivatives";
        EXPECT_EQ(q1, qn) << "fd derivatives' qdd";
      }
      {
        std::vector<unsigned char> prescribed(static_cast<std::size_t>(nv), 0);
        for (Index i = 0; i < nv; i += 3) prescribed[static_cast<std::size_t>(i)] = 1;
        std::vector<double> qdd1(static_cast<std::size_t>(nv) * kB), tau1(qdd1.size()), qddn(qdd1.size()),
            taun(qdd1.size());
        auto single = make_hybrid_dynamics<double>(m, prescribed, serial_options(kB));
        ShardedHybridDynamics<double> sharded(
            serial_shards<HybridDynamics<double>>(
                n, [&](const BackendOptions& o) { return make_hybrid_dynamics<double>(m, prescribed, o); }),
            no_devices(n), false, m.nbodies(), kB);
        const HybridBatchIn<double> hin{Q, QD, X, QD, nullptr};
        EXPECT_TRUE(single->compute(hin, BatchView<double>::soa(qdd1.data(), nv, kB),
                                    BatchView<double>::soa(tau1.data(), nv, kB)).ok());
        EXPECT_TRUE(sharded.compute(hin, BatchView<double>::soa(qddn.data(), nv, kB),
                                    BatchView<double>::soa(taun.data(), nv, kB)).ok());
        EXPECT_EQ(qdd1, qddn);
        EXPECT_EQ(tau1, taun);
        EXPECT_EQ(sharded.prescribed(), prescribed);
      }
    }
  }
}

TEST(ShardedEngines, SerialShardsEqualOneEngineClosedLoops) {
  const Model m = load_model("fivebar");
  const LoopSet loops = generator_loops("fivebar", m);
  const Index nv = m.nv();
  const Inputs in(m, Layout::Soa, 9);
  const auto Q = view<const double>(in.q.data(), nv, kB, Layout::Soa),
             QD = view<const double>(in.qd.data(), nv, kB, Layout::Soa),
             X = view<const double>(in.x.data(), nv, kB, Layout::Soa);
  auto single = make_constrained_forward_dynamics<double>(m, loops, serial_options(kB));
  const Index rows = single->rows();
  ShardedConstrainedForwardDynamics<double> sharded(
      serial_shards<ConstrainedForwardDynamics<double>>(
          3, [&](const BackendOptions& o) { return make_constrained_forward_dynamics<double>(m, loops, o); }),
      no_devices(3), false, m.nbodies(), kB);
  EXPECT_EQ(sharded.rows(), rows);
  std::vector<double> qdd1(static_cast<std::size_t>(nv) * kB), qddn(qdd1.size()),
      l1(static_cast<std::size_t>(rows) * kB), ln(l1.size());
  const BatchStatus s1 = single->compute({Q, QD, X, nullptr}, BatchView<double>::soa(qdd1.data(), nv, kB),
                                         BatchView<double>::soa(l1.data(), rows, kB));
  const BatchStatus sn = sharded.compute({Q, QD, X, nullptr}, BatchView<double>::soa(qddn.data(), nv, kB),
                                         BatchView<double>::soa(ln.data(), rows, kB));
  EXPECT_EQ(s1.failed, sn.failed);
  EXPECT_EQ(qdd1, qddn);
  EXPECT_EQ(l1, ln);
  std::vector<double> p1(l1.size()), pn(l1.size()), v1(l1.size()), vn(l1.size());
  single->residual(Q, QD, BatchView<double>::soa(p1.data(), rows, kB), BatchView<double>::soa(v1.data(), rows, kB));
  sharded.residual(Q, QD, BatchView<double>::soa(pn.data(), rows, kB), BatchView<double>::soa(vn.data(), rows, kB));
  EXPECT_EQ(p1, pn);
  EXPECT_EQ(v1, vn);
}

// An instance whose pivot fails (q not finite): the same status, instance and DoF as
// one engine's, the caller's numbering, other instances computed.
TEST(ShardedEngines, FailuresAreRenumberedAsTheCallersInstances) {
  const Model m = test::load_robot("iiwa.urdf");
  const Index nv = m.nv();
  Inputs in(m, Layout::Aos, 3);
  for (Index bad : {Index(8), Index(2)}) in.q[static_cast<std::size_t>(bad * nv + 1)] = std::numeric_limits<double>::quiet_NaN();
  const auto Q = view<const double>(in.q.data(), nv, kB, Layout::Aos),
             QD = view<const double>(in.qd.data(), nv, kB, Layout::Aos),
             X = view<const double>(in.x.data(), nv, kB, Layout::Aos);
  std::vector<double> one(static_cast<std::size_t>(nv) * kB, 0.0), many(one.size(), 0.0);
  auto single = make_forward_dynamics<double>(m, serial_options(kB));
  const BatchStatus s1 = single->compute({Q, QD, X, nullptr}, BatchView<double>::aos(one.data(), nv, kB));
  const std::vector<int> f1(s1.failed_dof, s1.failed_dof + kB);
  ShardedForwardDynamics<double> sharded(
      serial_shards<ForwardDynamics<double>>(3, [&](const BackendOptions& o) { return make_forward_dynamics<double>(m, o); }),
      no_devices(3), false, m.nbodies(), kB);
  const BatchStatus sn = sharded.compute({Q, QD, X, nullptr}, BatchView<double>::aos(many.data(), nv, kB));
  ASSERT_EQ(s1.failed, 2);
  EXPECT_EQ(sn.failed, 2);
  EXPECT_EQ(sn.first_instance, 2);
  EXPECT_EQ(sn.first_dof, s1.first_dof);
  EXPECT_EQ(sn.failure, s1.failure);
  EXPECT_EQ(sn.message(), s1.message());
  ASSERT_NE(sn.failed_dof, nullptr);
  EXPECT_EQ(std::vector<int>(sn.failed_dof, sn.failed_dof + kB), f1);
  EXPECT_EQ(one, many);
  // above max_batch
  std::vector<double> big(static_cast<std::size_t>(nv) * (kB + 1));
  EXPECT_THROW(sharded.compute({{in.q.data(), kB + 1, 1, nv}, {in.qd.data(), kB + 1, 1, nv}, {in.x.data(), kB + 1, 1, nv}, nullptr},
                               BatchView<double>::aos(big.data(), nv, kB + 1)),
               BackendError);
}

// A shard's error names its shard; the batch is not half-reported as done.
TEST(ShardedEngines, AShardsErrorNamesTheShard) {
  const Model m = load_model("rope:4");
  // shard engines for 2 instances each: a batch of 6 over 2 shards gives each 3
  std::vector<std::unique_ptr<InverseDynamics<double>>> v;
  for (int k = 0; k < 2; ++k) v.push_back(make_inverse_dynamics<double>(m, serial_options(k == 0 ? 3 : 2)));
  ShardedInverseDynamics<double> sharded(std::move(v), no_devices(2), false, m.nbodies());
  std::vector<double> q(4 * 6), tau(4 * 6);
  const BatchView<const double> Q{q.data(), 6, 6, 1};
  try {
    sharded.compute({Q, Q, Q, nullptr}, BatchView<double>::soa(tau.data(), 4, 6));
    ADD_FAILURE() << "no error";
  } catch (const BackendError& e) {
    EXPECT_EQ(std::string(e.what()).rfind("shard 1: ", 0), 0u) << e.what();
  }
}

// ---- the factories on cuda ------------------------------------------------------------

std::string no_cuda_reason() {
  if (!SCANDYN_HAS_CUDA) return "built without CUDA";
  return backend_unusable(BackendKind::Cuda);
}

// Sharded CUDA engines against one CUDA engine over the whole batch: bit-identical
// (tol 0) for the thread-per-instance kernels, whose arithmetic per instance does not
// depend on the batch; within tol for the scans across links (a rope beyond 64 DoF),
// whose device-wide sums are split into tiles by the batch's size, so that a shard's
// sums associate differently. The bound: each of the two is within the CUDA scan tests'
// own bounds of the serial double recursion (1e-10 for id, 1e-9 for the chain FD,
// relative to max(1, |x|)), so they are within twice the larger of each other.
template <class S>
void expect_sharded_cuda_equals_one(const Model& md, const std::vector<int>& devices, double tol = 0) {
  const auto expect_same = [tol](const std::vector<S>& one, const std::vector<S>& many, const char* what) {
    if (tol == 0)
      EXPECT_EQ(one, many) << what;
    else
      EXPECT_LE(test::max_rel_err(many, one), tol) << what;
  };
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv(), B = 1001;
  std::mt19937_64 g(11);
  const std::vector<S> q = test::cast_vector<S>(test::random_vector(g, static_cast<int>(nv * B), -2, 2));
  const std::vector<S> qd = test::cast_vector<S>(test::random_vector(g, static_cast<int>(nv * B), -1, 1));
  const std::vector<S> x = test::cast_vector<S>(test::random_vector(g, static_cast<int>(nv * B), -1, 1));
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  BackendOptions od = o;
  od.devices = devices;
  const auto Q = BatchView<const S>::aos(q.data(), nv, B), QD = BatchView<const S>::aos(qd.data(), nv, B),
             X = BatchView<const S>::aos(x.data(), nv, B);
  std::vector<S> one(static_cast<std::size_t>(nv) * B), many(one.size());
  auto id1 = make_inverse_dynamics<S>(m, o);
  auto idn = make_inverse_dynamics<S>(m, od);
  ASSERT_NE(dynamic_cast<ShardedEngine*>(idn.get()), nullptr);
  EXPECT_EQ(dynamic_cast<ShardedEngine*>(idn.get())->shard_count(), static_cast<int>(devices.size()));
  id1->compute({Q, QD, X, nullptr}, BatchView<S>::aos(one.data(), nv, B));
  idn->compute({Q, QD, X, nullptr}, BatchView<S>::aos(many.data(), nv, B));
  expect_same(one, many, "inverse dynamics");
  auto fd1 = make_forward_dynamics<S>(m, o);
  auto fdn = make_forward_dynamics<S>(m, od);
  EXPECT_TRUE(fd1->compute({Q, QD, X, nullptr}, BatchView<S>::aos(one.data(), nv, B)).ok());
  EXPECT_TRUE(fdn->compute({Q, QD, X, nullptr}, BatchView<S>::aos(many.data(), nv, B)).ok());
  expect_same(one, many, "forward dynamics");
  std::vector<S> M1(static_cast<std::size_t>(nv * nv) * B), Mn(M1.size());
  make_mass_matrix<S>(m, o)->compute(Q, BatchView<S>::aos(M1.data(), nv * nv, B));
  make_mass_matrix<S>(m, od)->compute(Q, BatchView<S>::aos(Mn.data(), nv * nv, B));
  expect_same(M1, Mn, "mass matrix");
  make_bias_forces<S>(m, o)->compute({Q, QD, nullptr}, BatchView<S>::aos(one.data(), nv, B));
  make_bias_forces<S>(m, od)->compute({Q, QD, nullptr}, BatchView<S>::aos(many.data(), nv, B));
  expect_same(one, many, "bias forces");
}

TEST(ShardedCuda, TwoShardsOnOneDeviceEqualOneEngine) {
  if (const std::string why = no_cuda_reason(); !why.empty()) GTEST_SKIP() << why;
  const Model iiwa = test::load_robot("iiwa.urdf");
  expect_sharded_cuda_equals_one<float>(iiwa, {0, 0});
  expect_sharded_cuda_equals_one<double>(iiwa, {0, 0, 0});
  expect_sharded_cuda_equals_one<double>(load_model("rope:60"), {0, 0});  // thread engines up to 64 DoF
  // the scans across links and the parallel chain FD (rope:100 > 64 DoF): H200, 2026-11-28,
  // not bit-identical with two shards on one device (rounding-level differences)
  expect_sharded_cuda_equals_one<double>(load_model("rope:100"), {0, 0}, 2e-9);
}

TEST(ShardedCuda, EveryVisibleDeviceEqualsOneEngine) {
  if (const std::string why = no_cuda_reason(); !why.empty()) GTEST_SKIP() << why;
  const std::vector<int> all = parse_devices("all");
  if (all.size() < 2) GTEST_SKIP() << "one CUDA device visible (this test needs two)";
  const Model iiwa = test::load_robot("iiwa.urdf");
  expect_sharded_cuda_equals_one<float>(iiwa, all);
  expect_sharded_cuda_equals_one<double>(iiwa, {1});  // one device other than the current one
}

TEST(ShardedCuda, AnAbsentDeviceIsNamed) {
  if (const std::string why = no_cuda_reason(); !why.empty()) GTEST_SKIP() << why;
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 10;
  o.devices = {0, 977};
  try {
    make_forward_dynamics<float>(load_model("rope:5").cast<float>(), o);
    ADD_FAILURE() << "no error";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("device 977: no CUDA device 977"), std::string::npos) << e.what();
  }
}

}  // namespace
