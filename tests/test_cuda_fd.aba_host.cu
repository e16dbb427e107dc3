// test_cuda_fd, part: aba_instance (the articulated-body algorithm's device function)
// run on the host in every variant with the capacity's slots, against the serial aba
// and fd_jsi, and its pivot failures. Tolerances: tests/test_cuda_fd.cu.
#include "cuda_fd_test_util.hpp"

using namespace scandyn;
using namespace scandyn::test::fd;

// ---- aba_instance on the host ---------------------------------------------------------
//
// Against the serial aba (the same algorithm, formulas and order: bit-identical on
// the same host up to FMA contraction, asserted as <= 1e-12 in double), and against
// fd_jsi within jsi_tol (two exact algorithms on one mass matrix). Float: within
// max(1e-4, 10 x the serial float aba's own error on the same inputs).
TEST(CudaFdAbaModel, DeviceFunctionOnTheHost) {
  std::vector<std::pair<std::string, Model>> models;
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) models.emplace_back(file, robot(file));
  for (auto& m : generated_models()) models.push_back(std::move(m));
  for (const auto& [name, md] : models) {
    SCOPED_TRACE(name);
    const double jtol = jsi_tol(md);
    for (bool fx : {false, true}) {
      SCOPED_TRACE(fx ? "fext" : "no fext");
      for (const Errors& e : {host_instance_errors<double, false, true, true>(md, 20, fx),
                              host_instance_errors<double, false, false, true>(md, 20, fx),
                              host_instance_errors<double, true, true, true>(md, 20, fx),
                              host_instance_errors<double, true, false, true>(md, 20, fx)}) {
        EXPECT_LE(e.aba, 1e-12);
        EXPECT_LE(e.jsi, jtol);
      }
      const double ftol = aba_float_tol(md, 20, fx, kHostSeed);
      for (const Errors& e : {host_instance_errors<float, false, true, true>(md, 20, fx),
                              host_instance_errors<float, false, false, true>(md, 20, fx),
                              host_instance_errors<float, true, false, true>(md, 20, fx)})
        EXPECT_LE(e.aba, ftol);
    }
  }
}

// Articulated pivot failures on the host: the DoF the serial aba reports, qdd left
// unwritten (kSlots as in host_instance_errors).
template <class S, bool kUnrolled, int kSlots = -1>
void check_host_aba_failure(const Model& md, const std::vector<S>& q, const std::vector<S>& qd,
                            const std::vector<S>& tau) {
  const ModelTpl<S> m = md.cast<S>();
  DataTpl<S> d(m);
  const Index nv = m.nv();
  std::vector<S> ref(nv, S(kSentinel)), qdd(nv, S(kSentinel));
  const Status want = aba(m, d, q.data(), qd.data(), tau.data(), ref.data());
  ASSERT_FALSE(want.ok());
  const Index got = std::visit(
      [&](const auto& p) {
        using P = std::decay_t<decltype(p)>;
        constexpr int C = P::capacity;
        return cuda::aba_instance<S, C, false, kUnrolled, Trig::Library, (kSlots < 0 ? C : kSlots)>(
            p, {q.data(), 1}, {qd.data(), 1}, {tau.data(), 1}, nullptr, {qdd.data(), 1});
      },
      cuda::ThreadModel<S>(m).params());
  EXPECT_EQ(got, want.failed_dof);
  for (Index i = 0; i < nv; ++i) EXPECT_EQ(qdd[i], S(kSentinel)) << "qdd[" << i << "] was written";
}

template <class S>
void host_aba_failures() {
  // a massless leaf: D = 0 at the last DoF, for every state (a chain: the chain
  // kernels too)
  {
    const Model md = massless_leaf(5);
    const std::vector<S> x(5, S(0.3));
    check_host_aba_failure<S, true>(md, x, x, x);
    check_host_aba_failure<S, false>(md, x, x, x);
    check_host_aba_failure<S, true, 0>(md, x, x, x);
    check_host_aba_failure<S, false, 0>(md, x, x, x);
  }
  // a non-finite joint position reaches the parent's articulated inertia (wherever
  // the serial aba reports a failure; a root's position does not enter any IA)
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) {
    const Model& md = robot(file);
    const Index nv = md.nv();
    const ModelTpl<S> m = md.cast<S>();
    DataTpl<S> d(m);
    Index checked = 0;
    for (Index j = 0; j < nv; ++j) {
      for (S bad : {std::numeric_limits<S>::quiet_NaN(), std::numeric_limits<S>::infinity()}) {
        SCOPED_TRACE(std::string(file) + " q[" + std::to_string(j) + "] = " + std::to_string(bad));
        std::vector<S> q(nv, S(0.2)), x(nv, S(0.1)), out(nv);
        q[j] = bad;
        if (aba(m, d, q.data(), x.data(), x.data(), out.data()).ok()) continue;
        check_host_aba_failure<S, true>(md, q, x, x);
        check_host_aba_failure<S, false>(md, q, x, x);
        // the kernel for the model's shape (iiwa, hyq: chains; atlas: one branch slot)
        if (cuda::ThreadModel<S>(m).branch_slots() == 0) check_host_aba_failure<S, false, 0>(md, q, x, x);
        else check_host_aba_failure<S, false, 1>(md, q, x, x);
        ++checked;
      }
    }
    EXPECT_GT(checked, 0) << file;
  }
}

TEST(CudaFdAbaModel, PivotFailuresOnTheHost) {
  host_aba_failures<double>();
  host_aba_failures<float>();
  // the message names the ABA's pivot, D_i = S_i^T IA_i S_i
  BatchStatus s;
  EXPECT_EQ(s.message(), "");
  s.record(3, 6, pivot_failure(FdMethod::Aba));
  EXPECT_EQ(s.message(), "instance 3: articulated inertia pivot at DoF 6 is not positive");
  s.failed = 42;
  EXPECT_EQ(s.message(), "instance 3: articulated inertia pivot at DoF 6 is not positive (and 41 more instances)");
}
