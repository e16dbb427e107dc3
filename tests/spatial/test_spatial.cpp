// Spatial algebra against dense 6x6 forms built independently with Eigen from
// Featherstone's definitions (RBDA ch. 2).
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <random>

#include "scandyn/spatial.hpp"
#include "test_util.hpp"

using namespace scandyn;
using Mat6 = Eigen::Matrix<double, 6, 6>;
using Vec6 = Eigen::Matrix<double, 6, 1>;
using M3 = Eigen::Matrix3d;
using V3 = Eigen::Vector3d;

namespace {

struct Rng {
  std::mt19937_64 g{12345};
  double uni(double lo = -1, double hi = 1) { return std::uniform_real_distribution<double>(lo, hi)(g); }
  Vec3<double> vec() { return {uni(), uni(), uni()}; }
  Mat3<double> rot() {
    const Vec3<double> rpy = vec();
    return rpy_matrix(3 * rpy.x, 3 * rpy.y, 3 * rpy.z);
  }
};

V3 e(const Vec3<double>& v) { return {v.x, v.y, v.z}; }
M3 e(const Mat3<double>& A) {
  M3 o;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) o(r, c) = A(r, c);
  return o;
}
M3 e(const Sym3<double>& A) { return e(A.full()); }
M3 sk(const V3& v) {
  M3 o;
  o << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return o;
}
Vec6 e(const Motion<double>& m) { return (Vec6() << e(m.w), e(m.v)).finished(); }
Vec6 e(const Force<double>& f) { return (Vec6() << e(f.n), e(f.f)).finished(); }

// X = [E 0; -E rx E]
Mat6 dense(const Transform<double>& X) {
  Mat6 o = Mat6::Zero();
  const M3 E = e(X.E);
  o.topLeftCorner<3, 3>() = E;
  o.bottomRightCorner<3, 3>() = E;
  o.bottomLeftCorner<3, 3>() = -E * sk(e(X.r));
  return o;
}
// I = [Ibar hx; hx^T m1]
Mat6 dense(const Inertia<double>& I) {
  Mat6 o;
  o << e(I.I), sk(e(I.h)), sk(e(I.h)).transpose(), I.m * M3::Identity();
  return o;
}
Mat6 dense(const ABInertia<double>& I) {
  Mat6 o;
  o << e(I.Iww), e(I.Iwv), e(I.Iwv).transpose(), e(I.Ivv);
  return o;
}
// crm(m) = [wx 0; vx wx]
Mat6 crm(const Motion<double>& m) {
  Mat6 o = Mat6::Zero();
  o.topLeftCorner<3, 3>() = sk(e(m.w));
  o.bottomRightCorner<3, 3>() = sk(e(m.w));
  o.bottomLeftCorner<3, 3>() = sk(e(m.v));
  return o;
}

Inertia<double> random_inertia(Rng& rng) {
  // principal moments satisfying the triangle inequality, rotated
  const double a = rng.uni(0.1, 1), b = rng.uni(0.1, 1), c = rng.uni(std::fabs(a - b) + 0.01, a + b);
  const M3 R = e(rng.rot());
  const M3 Ic = R * V3(a, b, c).asDiagonal() * R.transpose();
  const Sym3<double> S{Ic(0, 0), Ic(1, 1), Ic(2, 2), Ic(0, 1), Ic(0, 2), Ic(1, 2)};
  return Inertia<double>::from_com(rng.uni(0.5, 3), rng.vec(), S);
}

constexpr double kTol = 1e-12;

}  // namespace

TEST(Spatial, TransformMatchesDense) {
  Rng rng;
  for (int t = 0; t < 50; ++t) {
    const Transform<double> X{rng.rot(), rng.vec()};
    const Motion<double> m{rng.vec(), rng.vec()};
    const Force<double> f{rng.vec(), rng.vec()};
    const Mat6 Xd = dense(X);
    const Mat6 Xstar = Xd.inverse().transpose();
    EXPECT_LT((e(X.apply(m)) - Xd * e(m)).norm(), kTol);
    EXPECT_LT((e(X.apply_inverse(m)) - Xd.inverse() * e(m)).norm(), kTol);
    EXPECT_LT((e(X.apply(f)) - Xstar * e(f)).norm(), kTol);
    EXPECT_LT((e(X.apply_transpose(f)) - Xd.transpose() * e(f)).norm(), kTol);
    EXPECT_LT((dense(X.inverse()) - Xd.inverse()).norm(), kTol);
    const Transform<double> Y{rng.rot(), rng.vec()};
    EXPECT_LT((dense(Y * X) - dense(Y) * Xd).norm(), kTol);
    // power is invariant: (X m) . (X* f) = m . f
    EXPECT_NEAR(dot(X.apply(m), X.apply(f)), dot(m, f), kTol);
  }
}

TEST(Spatial, FromPoseIsUrdfConvention) {
  // A frame B rotated 90 degrees about z and shifted by p: a point fixed in B at
  // the origin moving with linear velocity along B's x is moving along A's y.
  const Mat3<double> R = rpy_matrix(0.0, 0.0, M_PI / 2);
  const Transform<double> X = Transform<double>::from_pose(R, {1, 2, 3});
  const Motion<double> mB{{0, 0, 0}, {1, 0, 0}};
  const Motion<double> mA = X.apply_inverse(mB);
  EXPECT_NEAR(mA.v.x, 0, kTol);
  EXPECT_NEAR(mA.v.y, 1, kTol);
  // A pure rotation about A's z through A's origin seen at B's origin (1, 2, 3)
  // has linear velocity w x (-p) ... v_B = E (v_A - r x w).
  const Motion<double> spin{{0, 0, 1}, {0, 0, 0}};
  const Motion<double> sB = X.apply(spin);
  const V3 expect = e(R).transpose() * (-V3(1, 2, 3).cross(V3(0, 0, 1)));
  EXPECT_LT((e(sB.v) - expect).norm(), kTol);
}

TEST(Spatial, RpyAndAxisAngle) {
  Rng rng;
  for (int t = 0; t < 20; ++t) {
    const double r = rng.uni(-3, 3), p = rng.uni(-1.5, 1.5), y = rng.uni(-3, 3);
    const M3 expect = (Eigen::AngleAxisd(y, V3::UnitZ()) * Eigen::AngleAxisd(p, V3::UnitY()) *
                       Eigen::AngleAxisd(r, V3::UnitX()))
                          .toRotationMatrix();
    EXPECT_LT((e(rpy_matrix(r, p, y)) - expect).norm(), kTol);
    V3 a = e(rng.vec()).normalized();
    const double q = rng.uni(-4, 4);
    const Mat3<double> R = axis_angle(Vec3<double>{a.x(), a.y(), a.z()}, std::sin(q), std::cos(q));
    EXPECT_LT((e(R) - Eigen::AngleAxisd(q, a).toRotationMatrix()).norm(), kTol);
  }
}

TEST(Spatial, CrossProductsMatchDense) {
  Rng rng;
  for (int t = 0; t < 50; ++t) {
    const Motion<double> m{rng.vec(), rng.vec()}, u{rng.vec(), rng.vec()};
    const Force<double> f{rng.vec(), rng.vec()};
    EXPECT_LT((e(cross(m, u)) - crm(m) * e(u)).norm(), kTol);
    EXPECT_LT((e(cross(m, f)) - (-crm(m).transpose()) * e(f)).norm(), kTol);
  }
}

TEST(Spatial, InertiaMatchesDense) {
  Rng rng;
  for (int t = 0; t < 50; ++t) {
    const Inertia<double> I = random_inertia(rng);
    const Mat6 Id = dense(I);
    // the dense form from mass, com and Ic: [Ic + m cx cx^T, m cx; m cx^T, m 1]
    const Motion<double> v{rng.vec(), rng.vec()};
    EXPECT_LT((e(I * v) - Id * e(v)).norm(), kTol);
    EXPECT_LT((Id - Id.transpose()).norm(), kTol);
    EXPECT_GT(Eigen::SelfAdjointEigenSolver<Mat6>(Id).eigenvalues().minCoeff(), 0);
    const Transform<double> X{rng.rot(), rng.vec()};
    const Mat6 Xd = dense(X);
    EXPECT_LT((dense(I.transform_transpose(X)) - Xd.transpose() * Id * Xd).norm(), 1e-11);
    const Inertia<double> J = random_inertia(rng);
    EXPECT_LT((dense(I + J) - (Id + dense(J))).norm(), kTol);
  }
}

TEST(Spatial, FromComIsParallelAxis) {
  const Sym3<double> Ic{1, 2, 2.5, 0.1, 0, -0.2};
  const Vec3<double> c{0.3, -0.2, 0.5};
  const double m = 2;
  const Inertia<double> I = Inertia<double>::from_com(m, c, Ic);
  const M3 C = sk(e(c));
  const M3 expect = e(Ic) + m * C * C.transpose();
  EXPECT_LT((e(I.I) - expect).norm(), kTol);
  EXPECT_LT((e(I.h) - m * e(c)).norm(), kTol);
}

TEST(Spatial, ArticulatedInertiaMatchesDense) {
  Rng rng;
  for (int t = 0; t < 50; ++t) {
    const Inertia<double> I = random_inertia(rng);
    ABInertia<double> IA = ABInertia<double>::from(I);
    EXPECT_LT((dense(IA) - dense(I)).norm(), kTol);
    // a general symmetric IA: add a random rank-1 term
    const Force<double> U{rng.vec(), rng.vec()};
    const double D = rng.uni(1, 2);
    IA = IA.minus_outer(U, 1.0 / D);
    const Mat6 IAd = dense(I) - e(U) * e(U).transpose() / D;
    EXPECT_LT((dense(IA) - IAd).norm(), kTol);
    const Motion<double> v{rng.vec(), rng.vec()};
    EXPECT_LT((e(IA * v) - IAd * e(v)).norm(), kTol);
    const Transform<double> X{rng.rot(), rng.vec()};
    const Mat6 Xd = dense(X);
    EXPECT_LT((dense(IA.transform_transpose(X)) - Xd.transpose() * IAd * Xd).norm(), 1e-11);
    EXPECT_LT((dense(IA + ABInertia<double>::from(I)) - (IAd + dense(I))).norm(), kTol);
  }
}

TEST(Spatial, FloatFollowsDouble) {
  Rng rng;
  for (int t = 0; t < 20; ++t) {
    const Transform<double> X{rng.rot(), rng.vec()};
    const Inertia<double> I = random_inertia(rng);
    const Motion<double> m{rng.vec(), rng.vec()};
    const Transform<float> Xf = X.cast<float>();
    const Inertia<float> If = I.cast<float>();
    const Motion<float> mf = m.cast<float>();
    const Force<double> fd = I.transform_transpose(X) * X.apply_inverse(m);
    const Force<float> ff = If.transform_transpose(Xf) * Xf.apply_inverse(mf);
    // float: a few ulps of the magnitudes involved (|.| ~ 10)
    EXPECT_LT((e(ff.cast<double>()) - e(fd)).norm(), test::Tol<float>(0, 1e-4) * e(fd).norm());
  }
}
