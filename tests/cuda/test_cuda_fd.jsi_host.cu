// test_cuda_fd, part: fd_jsi_instance (the joint-space inertia's device function) run on
// the host in every variant, against the serial fd_jsi and aba, and its pivot failures.
// Tolerances: tests/cuda/test_cuda_fd.cu.
#include "cuda_fd_test_util.hpp"

using namespace scandyn;
using namespace scandyn::test::fd;

// ---- fd_jsi_instance on the host ------------------------------------------------------

TEST(CudaFdModel, DeviceFunctionOnTheHost) {
  std::vector<std::pair<std::string, Model>> models;
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) models.emplace_back(file, robot(file));
  for (auto& m : generated_models()) models.push_back(std::move(m));
  for (const auto& [name, md] : models) {
    SCOPED_TRACE(name);
    for (bool fx : {false, true}) {
      SCOPED_TRACE(fx ? "fext" : "no fext");
      // every variant: loops unrolled (ancestor masks) or not (parent walks),
      // transforms kept or recomputed
      for (const Errors& e : {host_instance_errors<double, false, true>(md, 20, fx),
                              host_instance_errors<double, false, false>(md, 20, fx),
                              host_instance_errors<double, true, true>(md, 20, fx),
                              host_instance_errors<double, true, false>(md, 20, fx)}) {
        // the reference's formulas and order on the same host: bit-identical without
        // FMA contraction (CI); under -march=native the two compiled copies contract
        // products into FMAs differently, which moves the result as the GPU's
        // contractions do, by up to what the model's conditioning allows (jsi_tol;
        // measured on the H100 host: 2.2e-11 on chain:33, 5.5e-11 on chain:64)
        EXPECT_LE(e.jsi, jsi_tol(md));
        EXPECT_LE(e.aba, kAbaTol);
      }
      const double ftol = float_tol(md, 20, fx, kHostSeed);
      for (const Errors& e : {host_instance_errors<float, false, true>(md, 20, fx),
                              host_instance_errors<float, false, false>(md, 20, fx),
                              host_instance_errors<float, true, false>(md, 20, fx)})
        EXPECT_LE(e.jsi, ftol);
    }
  }
}

// Pivot failures on the host: the DoF the serial fd_jsi reports, qdd left unwritten.
template <class S, bool kUnrolled>
void check_host_failure(const Model& md, const std::vector<S>& q, const std::vector<S>& qd,
                        const std::vector<S>& tau) {
  const ModelTpl<S> m = md.cast<S>();
  DataTpl<S> d(m);
  const Index nv = m.nv();
  std::vector<S> ref(nv, S(kSentinel)), qdd(nv, S(kSentinel));
  const Status want = fd_jsi(m, d, q.data(), qd.data(), tau.data(), ref.data());
  ASSERT_FALSE(want.ok());
  const Index got = std::visit(
      [&](const auto& p) {
        using P = std::decay_t<decltype(p)>;
        return cuda::fd_jsi_instance<S, P::capacity, false, kUnrolled>(p, {q.data(), 1}, {qd.data(), 1},
                                                                      {tau.data(), 1}, nullptr, {qdd.data(), 1});
      },
      cuda::ThreadModel<S>(m).params());
  EXPECT_EQ(got, want.failed_dof);
  for (Index i = 0; i < nv; ++i) EXPECT_EQ(qdd[i], S(kSentinel)) << "qdd[" << i << "] was written";
}

template <class S>
void host_failures() {
  // a singular mass matrix: the last DoF, for every state
  {
    const Model md = massless_leaf(5);
    const std::vector<S> x(5, S(0.3));
    check_host_failure<S, true>(md, x, x, x);
    check_host_failure<S, false>(md, x, x, x);
  }
  // a non-finite joint position makes M non-finite: NaN or inf at each DoF in turn
  for (const char* file : {"iiwa.urdf", "hyq.urdf"}) {
    const Model& md = robot(file);
    const Index nv = md.nv();
    for (Index j = 0; j < nv; ++j) {
      for (S bad : {std::numeric_limits<S>::quiet_NaN(), std::numeric_limits<S>::infinity()}) {
        SCOPED_TRACE(std::string(file) + " q[" + std::to_string(j) + "] = " + std::to_string(bad));
        std::vector<S> q(nv, S(0.2)), x(nv, S(0.1));
        q[j] = bad;
        const ModelTpl<S> m = md.cast<S>();
        DataTpl<S> d(m);
        std::vector<S> out(nv);
        // M does not depend on a root joint's position: NaN qdd there, as in fd_jsi
        if (md.parent(j) < 0) continue;
        ASSERT_FALSE(fd_jsi(m, d, q.data(), x.data(), x.data(), out.data()).ok());
        check_host_failure<S, true>(md, q, x, x);
        check_host_failure<S, false>(md, q, x, x);
      }
    }
  }
}

TEST(CudaFdModel, PivotFailuresOnTheHost) {
  host_failures<double>();
  host_failures<float>();
  // the message the command line prints
  BatchStatus s;
  EXPECT_TRUE(s.ok());
  EXPECT_EQ(s.message(), "");
  s.record(3, 6, pivot_failure(FdMethod::Jsi));
  EXPECT_EQ(s.message(), "instance 3: mass matrix pivot at DoF 6 is not positive");
  s.failed = 2;
  EXPECT_EQ(s.message(), "instance 3: mass matrix pivot at DoF 6 is not positive (and 1 more instance)");
  s.failed = 42;
  EXPECT_EQ(s.message(), "instance 3: mass matrix pivot at DoF 6 is not positive (and 41 more instances)");
}
