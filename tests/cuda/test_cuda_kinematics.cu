// Frame poses and frame Jacobians on the GPU (kinematics_instance in
// kinematics_instances_kernel, launch_kinematics_instances, CudaKinematics) against
// the serial engine, which runs the same routine on the host; models with
// multi-DoF joints through the general path (kinematics_general_kernel), which runs
// the serial engine's kinematics_instance_at.
//
// Tolerances, per entry, |x - ref| <= tol * max(1, |ref|):
//   host     the kernel's instantiation (double, the library's sin/cos) run on the host
//            with the kernel's accessors: bit-identical to the serial engine (measured
//            0), checked on every machine, CI included;
//   double   device against serial double: 1e-11 (FMA contraction, the device's sin/cos);
//   float    device against serial float on the same float q: 1e-4 (the SFU's sin/cos,
//            absolute error <= 2^-21.4 per joint, over up to 64 joints).
// Quaternions are compared up to sign (q and -q are one rotation; with w within
// rounding of 0 the canonical w >= 0 may pick either). Outputs start as NaN, so an
// entry never written fails. Tests that need a device
// skip with "no CUDA device: ...".
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <string>
#include <vector>

#include "cuda_test_util.hpp"
#include "floating_models.hpp"
#include "kinematics_cases.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/cuda/kinematics.hpp"
#include "scandyn/instance/dof_column.hpp"
#include "scandyn/instance/kinematics_instance.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

std::vector<std::pair<std::string, Model>> models() {
  std::vector<std::pair<std::string, Model>> r;
  for (const char* f : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) r.emplace_back(f, test::load_robot(f));
  for (unsigned seed : {1u, 2u, 3u}) r.emplace_back("random_frame_tree:" + std::to_string(seed), build_model(test::random_frame_tree(20, seed)));
  r.emplace_back("rope:64", make_generated("rope:64"));  // the kernels' largest capacity, full
  return r;
}

std::vector<double> random_q(Index nv, Index B, unsigned seed) {
  std::mt19937_64 g(seed);
  return test::random_vector(g, static_cast<int>(nv * B), -2.5, 2.5);
}

template <class S>
void expect_near(const std::vector<S>& got, const std::vector<S>& ref, double tol, const std::string& what) {
  ASSERT_EQ(got.size(), ref.size()) << what;
  for (std::size_t e = 0; e < ref.size(); ++e)
    ASSERT_LE(std::fabs(double(got[e]) - double(ref[e])), tol * std::max(1.0, std::fabs(double(ref[e]))))
        << what << " entry " << e << ": " << got[e] << " against " << ref[e];
}

// What the kernel uses in double: the library's sin/cos.
constexpr Trig kKernelTrig = Trig::Library;
static_assert(cuda::kThreadTrig<double> == kKernelTrig, "the kernel's sin/cos in double");

// The kernel's per-instance call, on the host: ThreadModelParams' bodies, DofColumn
// input, the library's sin/cos (kThreadTrig<double>): the serial engine's result (to FMA contraction).
TEST(CudaKinematicsHost, TheKernelsRoutineIsTheSerialEngine) {
  for (const auto& [label, m] : models()) {
    const KinematicsOptions k = test::all_frames(m, PoseFormat::Matrix, FrameReference::Local);
    const Index nv = m.nv(), F = static_cast<Index>(k.frames.size()), B = 4;
    const std::vector<double> q = random_q(nv, B, 3);
    const auto ser = test::run_kinematics(m, BackendKind::Serial, k, q, B);
    const cuda::ThreadModel<double> tm(m);
    std::vector<FramePlacement<double>> frames(m.frames.begin(), m.frames.end());
    std::vector<double> poses(ser.poses.size(), std::nan("")), J(ser.J.size(), std::nan(""));
    std::visit(
        [&](const auto& params) {
          std::vector<Transform<double>> X0(static_cast<std::size_t>(params.capacity));
          for (Index b = 0; b < B; ++b)
            kinematics_instance<kKernelTrig>(
                params.body, params.nv, frames.data(), F, k.pose, k.reference,
                cuda::DofColumn<const double>{q.data() + b * nv, 1}, X0.data(),
                Strided<double>{poses.data() + b * F * 16, 1}, Strided<double>{J.data() + b * F * 6 * nv, 1});
        },
        tm.params());
    // the same routine and arithmetic; the CUDA file's host code may contract a*b+c to an FMA
    // where the serial engine's file does not (-march=native): equal to a few ulps
    EXPECT_LT(test::max_rel_err(poses, ser.poses), 1e-14) << label;
    EXPECT_LT(test::max_rel_err(J, ser.J), 1e-14) << label;
  }
}

TEST(CudaKinematicsHost, ModelsBeyondTheThreadKernelsAreRefused) {
  if (const std::string why = test::no_device_reason(); !why.empty()) GTEST_SKIP() << "no CUDA device: " << why;
  const Model m = make_generated("rope:65");
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  EXPECT_THROW(make_kinematics(m, o, test::all_frames(m)), BackendError);
}

// The device's poses and Jacobians of every frame against the serial engine's, in
// both references and both pose formats, for B instances of q (nq entries each).
template <class S>
void expect_device_as_serial(const ModelTpl<S>& m, const std::vector<S>& q, Index B, double tol,
                             const std::string& label) {
  for (FrameReference ref : {FrameReference::World, FrameReference::Local})
    for (PoseFormat pf : {PoseFormat::Matrix, PoseFormat::PositionQuaternion}) {
      const KinematicsOptions k = test::all_frames(m, pf, ref);
      const auto ser = test::run_kinematics(m, BackendKind::Serial, k, q, B);
      auto dev = test::run_kinematics(m, BackendKind::Cuda, k, q, B);
      if (pf == PoseFormat::PositionQuaternion) test::align_quaternion_signs(dev.poses, ser.poses);
      expect_near(dev.poses, ser.poses, tol, label + " poses");
      expect_near(dev.J, ser.J, tol, label + " J");
    }
}

template <class S>
void device_matches_serial(double tol) {
  if (const std::string why = test::no_device_reason(); !why.empty()) GTEST_SKIP() << "no CUDA device: " << why;
  for (const auto& [label, md] : models()) {
    const ModelTpl<S> m = md.template cast<S>();
    const Index B = 1000;
    expect_device_as_serial(m, test::cast_vector<S>(random_q(m.nv(), B, 9)), B, tol, label);
  }
}

TEST(CudaKinematics, DoubleMatchesSerial) { device_matches_serial<double>(1e-11); }
TEST(CudaKinematics, FloatMatchesSerial) { device_matches_serial<float>(1e-4); }

// Models with multi-DoF joints (a floating base, spherical joints) run the general
// path (kinematics_instance_at per thread, GeneralPlan): hyq and atlas on a floating
// base, a hanging ball-joint rope, random floating trees with spherical joints and
// one of 70 bodies (beyond the 1-DoF kernels' 64). q with unit quaternions.
template <class S>
void multi_dof_matches_serial(double tol) {
  if (const std::string why = test::no_device_reason(); !why.empty()) GTEST_SKIP() << "no CUDA device: " << why;
  std::vector<std::pair<std::string, Model>> cases;
  cases.emplace_back("hyq floating", test::load_floating("hyq.urdf"));
  cases.emplace_back("atlas floating", test::load_floating("atlas.urdf"));
  cases.emplace_back("ballrope:6", make_generated("ballrope:6"));
  cases.emplace_back("random floating tree 12", test::random_floating_model(12, 3, 0.4));
  cases.emplace_back("random floating tree 70", test::random_floating_model(70, 9, 0.2));
  for (const auto& [label, md] : cases) {
    const ModelTpl<S> m = md.template cast<S>();
    const Index nq = m.nq(), B = 300;
    std::mt19937_64 g(21);
    std::vector<S> q;
    for (Index b = 0; b < B; ++b)
      for (double x : test::random_q(md, g, -2.5, 2.5)) q.push_back(S(x));
    ASSERT_EQ(q.size(), static_cast<std::size_t>(nq * B));
    BackendOptions o;
    o.backend = BackendKind::Cuda;
    EXPECT_EQ(make_kinematics(m, o, test::all_frames(m))->strategy(), "general") << label;
    expect_device_as_serial(m, q, B, tol, label);
  }
}

TEST(CudaKinematics, MultiDofDoubleMatchesSerial) { multi_dof_matches_serial<double>(1e-11); }
TEST(CudaKinematics, MultiDofFloatMatchesSerial) { multi_dof_matches_serial<float>(1e-4); }

// compute_async on device memory, structure-of-arrays (q[i * B + b], poses[e * B + b],
// J[e * B + b]) on a stream of ours, equals compute() on host rows; poses alone too.
TEST(CudaKinematics, ComputeAsyncOnDeviceMemoryInAnyLayout) {
  if (const std::string why = test::no_device_reason(); !why.empty()) GTEST_SKIP() << "no CUDA device: " << why;
  const Model m = test::load_robot("hyq.urdf");
  const KinematicsOptions k = test::all_frames(m);
  const Index nv = m.nv(), F = static_cast<Index>(k.frames.size()), B = 777, P = F * 16, NJ = F * 6 * nv;
  const std::vector<double> q = random_q(nv, B, 4);
  const auto host = test::run_kinematics(m, BackendKind::Cuda, k, q, B);
  std::vector<double> qs(q.size());
  for (Index b = 0; b < B; ++b)
    for (Index i = 0; i < nv; ++i) qs[static_cast<std::size_t>(i * B + b)] = q[static_cast<std::size_t>(b * nv + i)];
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 1;  // compute_async is not limited by it
  auto e = make_kinematics(m, o, k);
  auto* ce = dynamic_cast<cuda::CudaKinematics<double>*>(e.get());
  ASSERT_NE(ce, nullptr);
  test::DeviceArray<double> dq, dp, dJ;
  ASSERT_EQ(dq.alloc(qs.size()), cudaSuccess);
  ASSERT_EQ(dp.alloc(static_cast<std::size_t>(P * B)), cudaSuccess);
  ASSERT_EQ(dJ.alloc(static_cast<std::size_t>(NJ * B)), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(dq.ptr, qs.data(), qs.size() * sizeof(double), cudaMemcpyHostToDevice), cudaSuccess);
  cudaStream_t stream;
  ASSERT_EQ(cudaStreamCreate(&stream), cudaSuccess);
  ASSERT_EQ(ce->compute_async(BatchView<const double>::soa(dq.ptr, nv, B), BatchView<double>::soa(dp.ptr, P, B),
                              BatchView<double>::soa(dJ.ptr, NJ, B), stream),
            cudaSuccess);
  ASSERT_EQ(cudaStreamSynchronize(stream), cudaSuccess);
  cudaStreamDestroy(stream);
  std::vector<double> ps(static_cast<std::size_t>(P * B)), Js(static_cast<std::size_t>(NJ * B));
  ASSERT_EQ(cudaMemcpy(ps.data(), dp.ptr, ps.size() * sizeof(double), cudaMemcpyDeviceToHost), cudaSuccess);
  ASSERT_EQ(cudaMemcpy(Js.data(), dJ.ptr, Js.size() * sizeof(double), cudaMemcpyDeviceToHost), cudaSuccess);
  for (Index b = 0; b < B; ++b) {
    for (Index x = 0; x < P; ++x)
      ASSERT_EQ(ps[static_cast<std::size_t>(x * B + b)], host.poses[static_cast<std::size_t>(b * P + x)]);
    for (Index x = 0; x < NJ; ++x)
      ASSERT_EQ(Js[static_cast<std::size_t>(x * B + b)], host.J[static_cast<std::size_t>(b * NJ + x)]);
  }
  // poses only: J's view empty
  o.max_batch = B;
  auto e2 = make_kinematics(m, o, k);
  std::vector<double> p2(static_cast<std::size_t>(P * B), std::nan(""));
  e2->compute(BatchView<const double>::aos(q.data(), nv, B), BatchView<double>::aos(p2.data(), P, B), BatchView<double>{});
  EXPECT_EQ(p2, host.poses);
}

}  // namespace
