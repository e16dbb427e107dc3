// The SCANDYN_HD spatial algebra and per-joint step functions on the device
// against the same calls on the host, float and double.
//
// One __host__ __device__ function, evaluate(), applies every operation to one
// random sample; a kernel runs it for all samples (one thread each) and the host
// runs it in a loop. Outputs are NaN-filled before the kernel so an untouched
// entry fails. Skipped, with the reason, when there is no usable CUDA device.
//
// Tolerance: for each output field and sample, max_k |dev_k - host_k| divided by
// max(1, max_k |host_k|) must be <= 1e-13 (double) or 5e-5 (float). Host and
// device evaluate the same expressions; they differ by nvcc's fused multiply-adds
// and the device's sin/cos, so each side is off from the exact result by at most
// its own rounding error. Measured on the host for these inputs (2000 samples,
// same seed, against a long double evaluation of the same rounded inputs): worst
// per-scalar error 1.3e-14 (double) and 4.7e-6 (float), at the end of the longest
// chains (ABInertia::transform_transpose inside aba_backward_to_parent). The
// tolerances are about 8x and 10x those figures.
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <random>
#include <string>
#include <type_traits>
#include <vector>

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/cuda/device.hpp"
#include "cuda_test_util.hpp"

using namespace scandyn;

namespace {

// ---- the operations under test ------------------------------------------------

// Inputs of one sample.
template <class S>
struct Case {
  Transform<S> X, Y;  // two transforms (B_X_A, A_X_C)
  Motion<S> m;        // a motion vector (also the parent velocity)
  Motion<S> a;        // a motion vector (the parent acceleration)
  Force<S> f;         // a force vector (also the bias force pA)
  Inertia<S> I;       // a rigid-body inertia
  ABInertia<S> IA;    // an articulated-body inertia (symmetric positive definite)
  Force<S> U;         // a 6-vector for minus_outer
  S Dinv;             // a positive scalar for minus_outer
  Body<S> body;       // a joint: revolute or prismatic, random axis, Xtree and inertia
  S q, qd, qdd, tau;  // joint variables
};

// Every output of one sample; only S members, so a field is an array of S.
template <class S>
struct Outputs {
  Motion<S> X_m;         // X m
  Motion<S> Xinv_m;      // X^-1 m
  Force<S> X_f;          // X* f
  Force<S> XT_f;         // X^T f
  Transform<S> XY;       // X Y
  Transform<S> Xinv;     // X^-1
  Motion<S> crm;         // m x a
  Force<S> crf;          // m x* f
  Force<S> I_m;          // I m
  Inertia<S> I_XT;       // X^T I X
  Inertia<S> I_sum;      // I + I
  Inertia<S> I_com;      // Inertia::from_com(m, c, Ic) rebuilt from I's numbers
  ABInertia<S> IA_from;  // ABInertia::from(I)
  Force<S> IA_m;         // IA m
  ABInertia<S> IA_XT;    // X^T IA X
  ABInertia<S> IA_minus; // IA - U U^T Dinv
  ABInertia<S> IA_sum;   // IA + from(I)
  Transform<S> Xup;      // joint_transform(body, q)
  Motion<S> S_qd;        // joint_motion(body, qd)
  S ST_f;                // joint_project(body, f)
  RneaForward<S> rnea;   // rnea_forward_step(body, Xup, m, a, qd, qdd)
  AbaForward<S> aba;     // aba_forward_step(body, Xup, m, qd)
  Force<S> abaU;         // aba_joint_terms: U = IA S
  S abaD, abau;          // aba_joint_terms: D = S^T U, u = tau - S^T pA
  ABInertia<S> IA_parent;  // aba_backward_to_parent, accumulated onto IA
  Force<S> pA_parent;      // aba_backward_to_parent, accumulated onto f
  Motion<S> aba_a;         // aba_acceleration_step: body acceleration
  S aba_qdd;               // aba_acceleration_step: joint acceleration
};

template <class S>
SCANDYN_HD void evaluate(const Case<S>& c, Outputs<S>& o) {
  // transforms
  o.X_m = c.X.apply(c.m);
  o.Xinv_m = c.X.apply_inverse(c.m);
  o.X_f = c.X.apply(c.f);
  o.XT_f = c.X.apply_transpose(c.f);
  o.XY = c.X * c.Y;
  o.Xinv = c.X.inverse();
  o.crm = cross(c.m, c.a);
  o.crf = cross(c.m, c.f);
  // rigid inertias
  o.I_m = c.I * c.m;
  o.I_XT = c.I.transform_transpose(c.X);
  o.I_sum = c.I + c.I;
  const S mass = c.I.m;
  const Vec3<S> com = (S(1) / mass) * c.I.h;
  o.I_com = Inertia<S>::from_com(mass, com, c.I.I);
  // articulated inertias
  o.IA_from = ABInertia<S>::from(c.I);
  o.IA_m = c.IA * c.m;
  o.IA_XT = c.IA.transform_transpose(c.X);
  o.IA_minus = c.IA.minus_outer(c.U, c.Dinv);
  o.IA_sum = c.IA;
  o.IA_sum += o.IA_from;
  // joints and per-body steps
  o.Xup = joint_transform(c.body, c.q);
  o.S_qd = joint_motion(c.body, c.qd);
  o.ST_f = joint_project(c.body, c.f);
  o.rnea = rnea_forward_step(c.body, o.Xup, c.m, c.a, c.qd, c.qdd);
  o.aba = aba_forward_step(c.body, o.Xup, c.m, c.qd);
  aba_joint_terms(c.body, c.IA, c.f, c.tau, o.abaU, o.abaD, o.abau);
  o.IA_parent = c.IA;
  o.pA_parent = c.f;
  aba_backward_to_parent(o.Xup, c.IA, c.f, o.aba.c, o.abaU, o.abaD, o.abau, o.IA_parent,
                         o.pA_parent);
  o.aba_qdd = aba_acceleration_step(c.body, o.Xup, c.a, o.aba.c, o.abaU, o.abaD, o.abau, o.aba_a);
}

template <class S>
__global__ void evaluate_kernel(const Case<S>* cases_in, Outputs<S>* outputs_out, int n) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i < n) evaluate(cases_in[i], outputs_out[i]);
}

static_assert(std::is_trivially_copyable<Case<float>>::value, "Case must be copyable to the device");
static_assert(std::is_trivially_copyable<Outputs<double>>::value, "Outputs must be copyable");
static_assert(sizeof(Outputs<float>) % sizeof(float) == 0, "Outputs holds only floats");
static_assert(sizeof(Outputs<double>) % sizeof(double) == 0, "Outputs holds only doubles");

// ---- random inputs (double, cast to the test precision) -------------------------

struct Random {
  std::mt19937_64 g{20240601};
  double uni(double lo, double hi) { return std::uniform_real_distribution<double>(lo, hi)(g); }
  Vec3<double> vec(double s) { return {uni(-s, s), uni(-s, s), uni(-s, s)}; }
  Vec3<double> unit() {
    for (;;) {
      const Vec3<double> v = vec(1);
      const double n = std::sqrt(dot(v, v));
      if (n > 0.1 && n <= 1) return (1 / n) * v;
    }
  }
  // Uniform rotation from a random unit quaternion.
  Mat3<double> rotation() {
    double w, x, y, z, n;
    do {
      w = uni(-1, 1), x = uni(-1, 1), y = uni(-1, 1), z = uni(-1, 1);
      n = std::sqrt(w * w + x * x + y * y + z * z);
    } while (n < 0.1 || n > 1);
    w /= n, x /= n, y /= n, z /= n;
    return {{1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
             2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
             2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)}};
  }
  Transform<double> transform() { return {rotation(), vec(1)}; }
  // Physically valid: positive mass, principal moments obeying the triangle inequality.
  Inertia<double> inertia() {
    const double a = uni(0.01, 0.5), b = uni(0.01, 0.5);
    const double c = uni(std::fabs(a - b) + 0.005, a + b);
    const Sym3<double> principal{a, b, c, 0, 0, 0};
    return Inertia<double>::from_com(uni(0.1, 3), vec(0.5), congruence_transpose(rotation(), principal));
  }
  Case<double> sample(int i) {
    Case<double> c;
    c.X = transform();
    c.Y = transform();
    c.m = {vec(2), vec(2)};
    c.a = {vec(2), vec(10)};
    c.f = {vec(5), vec(20)};
    c.I = inertia();
    c.IA = ABInertia<double>::from(inertia()).transform_transpose(transform()) +
           ABInertia<double>::from(inertia());
    c.U = {vec(1), vec(1)};
    c.Dinv = uni(0.5, 2);
    c.body.parent = -1;
    c.body.type = i % 2 == 0 ? JointType::Revolute : JointType::Prismatic;
    c.body.axis = unit();
    c.body.Xtree = transform();
    c.body.I = inertia();
    c.q = uni(-3.14159, 3.14159);
    c.qd = uni(-2, 2);
    c.qdd = uni(-2, 2);
    c.tau = uni(-5, 5);
    return c;
  }
};

template <class T>
Case<T> cast_case(const Case<double>& c) {
  Case<T> o;
  o.X = c.X.template cast<T>();
  o.Y = c.Y.template cast<T>();
  o.m = c.m.template cast<T>();
  o.a = c.a.template cast<T>();
  o.f = c.f.template cast<T>();
  o.I = c.I.template cast<T>();
  o.IA = {c.IA.Iww.template cast<T>(), c.IA.Iwv.template cast<T>(), c.IA.Ivv.template cast<T>()};
  o.U = c.U.template cast<T>();
  o.Dinv = T(c.Dinv);
  o.body = c.body.template cast<T>();
  o.q = T(c.q);
  o.qd = T(c.qd);
  o.qdd = T(c.qdd);
  o.tau = T(c.tau);
  return o;
}

// Runs evaluate_kernel on `cases`, filling `out` (NaN before the kernel).
template <class S>
void run_on_device(const std::vector<Case<S>>& cases, std::vector<Outputs<S>>& out) {
  const int n = static_cast<int>(cases.size());
  test::DeviceArray<Case<S>> d_in;
  test::DeviceArray<Outputs<S>> d_out;
  ASSERT_CUDA(d_in.alloc(cases.size()));
  ASSERT_CUDA(d_out.alloc(cases.size()));
  ASSERT_CUDA(cudaMemcpy(d_in.ptr, cases.data(), n * sizeof(Case<S>), cudaMemcpyHostToDevice));
  ASSERT_CUDA(cudaMemset(d_out.ptr, 0xff, n * sizeof(Outputs<S>)));  // all-ones bytes: NaN
  const int block = 128;
  evaluate_kernel<S><<<(n + block - 1) / block, block>>>(d_in.ptr, d_out.ptr, n);
  ASSERT_CUDA(cudaGetLastError());
  ASSERT_CUDA(cudaDeviceSynchronize());
  out.resize(cases.size());
  ASSERT_CUDA(cudaMemcpy(out.data(), d_out.ptr, n * sizeof(Outputs<S>), cudaMemcpyDeviceToHost));
}

// ---- comparison ---------------------------------------------------------------

// Compares one field of Outputs over all samples: the worst
// max_k |dev_k - host_k| / max(1, max_k |host_k|) must be <= tol, no NaN.
template <class S, class T>
void expect_field_near(const char* name, T Outputs<S>::*field, const std::vector<Outputs<S>>& dev,
                       const std::vector<Outputs<S>>& host, double tol) {
  static_assert(sizeof(T) % sizeof(S) == 0, "field must hold only S");
  constexpr int k = static_cast<int>(sizeof(T) / sizeof(S));
  double worst = 0;
  int worst_sample = -1, non_finite = 0, first_non_finite = -1;
  for (std::size_t i = 0; i < host.size(); ++i) {
    S a[k], b[k];
    std::memcpy(a, &(dev[i].*field), sizeof(T));
    std::memcpy(b, &(host[i].*field), sizeof(T));
    double scale = 1, err = 0;
    bool finite = true;
    for (int j = 0; j < k; ++j) {
      finite = finite && std::isfinite(double(a[j])) && std::isfinite(double(b[j]));
      scale = std::fmax(scale, std::fabs(double(b[j])));
    }
    if (!finite) {
      if (non_finite++ == 0) first_non_finite = static_cast<int>(i);
      continue;
    }
    for (int j = 0; j < k; ++j) err = std::fmax(err, std::fabs(double(a[j]) - double(b[j])));
    if (err / scale > worst) worst = err / scale, worst_sample = static_cast<int>(i);
  }
  EXPECT_EQ(non_finite, 0) << name << ": non-finite output (first at sample " << first_non_finite
                           << ")";
  EXPECT_LE(worst, tol) << name << ": device and host differ (worst sample " << worst_sample << ")";
}

template <class S>
class CudaSpatial : public ::testing::Test {};
using Precisions = ::testing::Types<double, float>;
TYPED_TEST_SUITE(CudaSpatial, Precisions);

TYPED_TEST(CudaSpatial, DeviceMatchesHost) {
  using S = TypeParam;
  SKIP_WITHOUT_CUDA_DEVICE();
  const double tol = std::is_same<S, float>::value ? 5e-5 : 1e-13;

  // 1000 samples: several blocks of 128 threads, the last one partial.
  Random rnd;
  std::vector<Case<S>> cases;
  for (int i = 0; i < 1000; ++i) cases.push_back(cast_case<S>(rnd.sample(i)));

  std::vector<Outputs<S>> host(cases.size()), dev;
  for (std::size_t i = 0; i < cases.size(); ++i) evaluate(cases[i], host[i]);
  run_on_device(cases, dev);
  if (::testing::Test::HasFatalFailure()) return;

#define SCANDYN_FIELD(f) expect_field_near<S>(#f, &Outputs<S>::f, dev, host, tol)
  SCANDYN_FIELD(X_m);
  SCANDYN_FIELD(Xinv_m);
  SCANDYN_FIELD(X_f);
  SCANDYN_FIELD(XT_f);
  SCANDYN_FIELD(XY);
  SCANDYN_FIELD(Xinv);
  SCANDYN_FIELD(crm);
  SCANDYN_FIELD(crf);
  SCANDYN_FIELD(I_m);
  SCANDYN_FIELD(I_XT);
  SCANDYN_FIELD(I_sum);
  SCANDYN_FIELD(I_com);
  SCANDYN_FIELD(IA_from);
  SCANDYN_FIELD(IA_m);
  SCANDYN_FIELD(IA_XT);
  SCANDYN_FIELD(IA_minus);
  SCANDYN_FIELD(IA_sum);
  SCANDYN_FIELD(Xup);
  SCANDYN_FIELD(S_qd);
  SCANDYN_FIELD(ST_f);
  SCANDYN_FIELD(rnea);
  SCANDYN_FIELD(aba);
  SCANDYN_FIELD(abaU);
  SCANDYN_FIELD(abaD);
  SCANDYN_FIELD(abau);
  SCANDYN_FIELD(IA_parent);
  SCANDYN_FIELD(pA_parent);
  SCANDYN_FIELD(aba_a);
  SCANDYN_FIELD(aba_qdd);
#undef SCANDYN_FIELD
}

// The host side alone: every output is finite for these inputs, so a NaN on the
// device can only come from the device (or from an output the kernel never wrote).
TYPED_TEST(CudaSpatial, HostOutputsFinite) {
  using S = TypeParam;
  Random rnd;
  for (int i = 0; i < 200; ++i) {
    Outputs<S> o;
    evaluate(cast_case<S>(rnd.sample(i)), o);
    S v[sizeof(Outputs<S>) / sizeof(S)];
    std::memcpy(v, &o, sizeof(o));
    for (std::size_t k = 0; k < sizeof(v) / sizeof(S); ++k) {
      ASSERT_TRUE(std::isfinite(double(v[k]))) << "sample " << i << ", scalar " << k;
    }
  }
}

}  // namespace

// ---- joint rotations stay on the unit circle, without drift --------------------------
//
// A chain multiplies one joint rotation per link, so a bias of the rotation's norm
// s^2 + c^2 - 1 or of its angle grows linearly with the chain's length: CUDA's
// float sinf/cosf (2 ulp) have a norm bias of about 0.1 ulp, which made float ropes
// of 10^5 links drift by 10^-3. joint_sincos removes it. Over 2^20 angles in
// [-pi, pi], the mean of s^2 + c^2 - 1 and of atan2(s, c) - q must be below 1e-9,
// 1/120 of float's epsilon (glibc's correctly rounded sinf/cosf give 1.3e-10 and 0
// on these angles; the drift above came from a bias of about 7e-9).

namespace {

__host__ __device__ float test_angle(int k, int n) {
  return float(-3.14159265358979 + 6.28318530717958 * (k + 0.5) / n);
}

__global__ void rotation_bias_kernel(int n, double* sums_out) {
  double norm = 0, angle = 0;
  for (int k = blockIdx.x * blockDim.x + threadIdx.x; k < n; k += gridDim.x * blockDim.x) {
    const float q = test_angle(k, n);
    float s, c;
    scandyn::joint_sincos(q, s, c);
    norm += double(s) * s + double(c) * c - 1.0;
    angle += atan2(double(s), double(c)) - double(q);
  }
  atomicAdd(sums_out, norm);
  atomicAdd(sums_out + 1, angle);
}

}  // namespace

TEST(CudaJointRotation, FloatRotationIsUnbiased) {
  const int n = 1 << 20;
  double norm = 0, angle = 0;
  for (int k = 0; k < n; ++k) {
    const float q = test_angle(k, n);
    float s, c;
    scandyn::joint_sincos(q, s, c);
    norm += double(s) * s + double(c) * c - 1.0;
    angle += std::atan2(double(s), double(c)) - double(q);
  }
  EXPECT_LT(std::fabs(norm / n), 1e-9) << "host mean of s^2 + c^2 - 1";
  EXPECT_LT(std::fabs(angle / n), 1e-9) << "host mean of atan2(s, c) - q";
  SKIP_WITHOUT_CUDA_DEVICE();
  scandyn::test::DeviceArray<double> sums;
  ASSERT_CUDA(sums.alloc(2));
  ASSERT_CUDA(cudaMemset(sums.ptr, 0, 2 * sizeof(double)));
  rotation_bias_kernel<<<256, 256>>>(n, sums.ptr);
  ASSERT_CUDA(cudaGetLastError());
  double dev[2] = {0, 0};
  ASSERT_CUDA(cudaMemcpy(dev, sums.ptr, sizeof dev, cudaMemcpyDeviceToHost));
  EXPECT_LT(std::fabs(dev[0] / n), 1e-9) << "device mean of s^2 + c^2 - 1";
  EXPECT_LT(std::fabs(dev[1] / n), 1e-9) << "device mean of atan2(s, c) - q";
}
