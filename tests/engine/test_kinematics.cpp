// Kinematics engines (frame poses and frame Jacobians) and the model's frame table:
// against finite differences of the poses, against the same tree with its fixed
// joints made revolute (merged links must be where their own bodies would be), the
// quaternion against the matrix, every CPU backend and layout against serial, float
// against double. Pinocchio's framesForwardKinematics / computeFrameJacobian check
// them through `scandyn eval --algo fk,jac` (scripts/check_pinocchio.py).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <map>
#include <random>
#include <set>

#include "kinematics_cases.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/model/frames.hpp"
#include "test_util.hpp"

namespace scandyn::test {
namespace {

// Models with frames: the shipped robots and random trees with prismatic and fixed joints.
std::vector<std::pair<std::string, Model>> frame_models() {
  std::vector<std::pair<std::string, Model>> r;
  for (const char* f : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) r.emplace_back(f, load_robot(f));
  for (unsigned seed : {1u, 2u, 3u, 4u}) {
    const int n = static_cast<int>(3 + 7 * seed);
    r.emplace_back("random_frame_tree:" + std::to_string(n), build_model(random_frame_tree(n, seed)));
  }
  return r;
}

std::vector<double> random_q(Index nv, Index B, unsigned seed) {
  std::mt19937_64 g(seed);
  return random_vector(g, static_cast<int>(nv * B), -2.5, 2.5);
}

// The pose of frame k of instance b in a Matrix result: R(r, c) and p(r).
struct Pose {
  double R[3][3];
  double p[3];
};
Pose pose_at(const std::vector<double>& poses, Index F, Index b, Index k) {
  const double* m = poses.data() + (b * F + k) * 16;
  Pose P;
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) P.R[r][c] = m[4 * r + c];
    P.p[r] = m[4 * r + 3];
  }
  return P;
}

TEST(Frames, EveryLinkIsAFrameOnTheBodyThatCarriesIt) {
  for (unsigned seed = 1; seed <= 6; ++seed) {
    const RawTree t = random_frame_tree(12, seed);
    const Model m = build_model(t);
    ASSERT_EQ(m.frames.size(), t.links.size());
    ASSERT_EQ(m.frame_names.size(), t.links.size());
    std::set<std::string> names(m.frame_names.begin(), m.frame_names.end()), links;
    for (const RawLink& l : t.links) links.insert(l.name);
    EXPECT_EQ(names, links);
    EXPECT_EQ(m.frame_names[0], "base");
    EXPECT_EQ(m.frames[0].body, -1);
    const std::vector<Index> own = body_frames(m);
    for (Index b = 0; b < m.nv(); ++b) {
      const FramePlacement<double>& f = m.frames[static_cast<std::size_t>(own[static_cast<std::size_t>(b)])];
      EXPECT_EQ(f.body, b);
      EXPECT_EQ(m.frame_names[static_cast<std::size_t>(own[static_cast<std::size_t>(b)])], m.link_names[static_cast<std::size_t>(b)]);
      for (int k = 0; k < 9; ++k) EXPECT_EQ(f.X.E.m[k], k % 4 == 0 ? 1.0 : 0.0);
      EXPECT_EQ(f.X.r.x, 0.0);
    }
    for (const FramePlacement<double>& f : m.frames) EXPECT_LT(f.body, m.nv());
  }
  // casting keeps the table
  const ModelTpl<float> mf = load_robot("iiwa.urdf").cast<float>();
  EXPECT_EQ(mf.frames.size(), mf.frame_names.size());
  EXPECT_GT(mf.frames.size(), static_cast<std::size_t>(mf.nv()));  // iiwa's base and end-effector links are fixed
}

TEST(Frames, UnknownNamesAreNamedWithWhatExists) {
  const Model m = load_robot("iiwa.urdf");
  EXPECT_EQ(frame_index(m, m.frame_names.back()), static_cast<Index>(m.frame_names.size()) - 1);
  try {
    frame_index(m, "no_such_link");
    FAIL() << "no error";
  } catch (const ModelError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("no frame 'no_such_link'"), std::string::npos) << what;
    EXPECT_NE(what.find(m.frame_names[1]), std::string::npos) << what;
  }
  EXPECT_THROW(parse_frame_list(m, m.frame_names[1] + ",,"), ModelError);
  const std::vector<Index> two = parse_frame_list(m, m.frame_names[2] + "," + m.frame_names[0]);
  EXPECT_EQ(two, (std::vector<Index>{2, 0}));
  KinematicsOptions bad;
  bad.frames = {static_cast<Index>(m.frames.size())};
  EXPECT_THROW(make_kinematics(m, BackendOptions{}, bad), BackendError);
}

// A merged link is where its own body would be: the tree with its fixed joints made
// revolute, at angle 0 on those joints, puts every frame at the same pose, and its
// Jacobian columns for the other joints are the same.
TEST(Kinematics, MergedLinksAreWhereTheirOwnBodiesWouldBe) {
  for (unsigned seed = 1; seed <= 8; ++seed) {
    const Model A = build_model(random_frame_tree(15, seed));
    const Model Bm = build_model(random_frame_tree(15, seed, /*fixed_as_revolute=*/true));
    ASSERT_GT(Bm.nv(), A.nv()) << "seed " << seed << " has no fixed joint";
    const std::vector<double> qA = random_q(A.nv(), 1, seed);
    std::map<std::string, double> by_joint;
    for (Index i = 0; i < A.nv(); ++i) by_joint[A.joint_names[static_cast<std::size_t>(i)]] = qA[static_cast<std::size_t>(i)];
    std::vector<double> qB(static_cast<std::size_t>(Bm.nv()), 0.0);
    std::vector<Index> col_of_A(static_cast<std::size_t>(A.nv()));  // B's DoF of each of A's joints
    for (Index i = 0; i < Bm.nv(); ++i) {
      const auto it = by_joint.find(Bm.joint_names[static_cast<std::size_t>(i)]);
      if (it == by_joint.end()) continue;
      qB[static_cast<std::size_t>(i)] = it->second;
      for (Index a = 0; a < A.nv(); ++a)
        if (A.joint_names[static_cast<std::size_t>(a)] == it->first) col_of_A[static_cast<std::size_t>(a)] = i;
    }
    for (FrameReference ref : {FrameReference::World, FrameReference::Local}) {
      const auto rA = run_kinematics(A, BackendKind::Serial, all_frames(A, PoseFormat::Matrix, ref), qA, 1);
      const auto rB = run_kinematics(Bm, BackendKind::Serial, all_frames(Bm, PoseFormat::Matrix, ref), qB, 1);
      const Index FA = static_cast<Index>(A.frames.size()), FB = static_cast<Index>(Bm.frames.size());
      for (Index k = 0; k < FA; ++k) {
        const Index kb = frame_index(Bm, A.frame_names[static_cast<std::size_t>(k)]);
        for (int e = 0; e < 16; ++e)
          EXPECT_NEAR(rA.poses[static_cast<std::size_t>(k * 16 + e)], rB.poses[static_cast<std::size_t>(kb * 16 + e)], 1e-12)
              << "seed " << seed << " frame " << A.frame_names[static_cast<std::size_t>(k)];
        for (int r = 0; r < 6; ++r)
          for (Index a = 0; a < A.nv(); ++a)
            EXPECT_NEAR(rA.J[static_cast<std::size_t>((k * 6 + r) * A.nv() + a)],
                        rB.J[static_cast<std::size_t>((kb * 6 + r) * Bm.nv() + col_of_A[static_cast<std::size_t>(a)])], 1e-12)
                << "seed " << seed << " frame " << A.frame_names[static_cast<std::size_t>(k)] << " row " << r;
      }
      (void)FB;
    }
  }
}

// J qd is the frame's velocity: [w; v] with v = dp/dt and [w]x = dR/dt R^T in world
// axes, R^T w and R^T v in the frame's; central differences of the poses along qd,
// step 1e-6: truncation ~1e-12, rounding ~1e-10.
TEST(Kinematics, JacobianTimesVelocityIsTheDerivativeOfThePose) {
  for (const auto& [label, m] : frame_models()) {
    const Index nv = m.nv(), F = static_cast<Index>(m.frames.size());
    const std::vector<double> q = random_q(nv, 1, 7);
    const std::vector<double> qd = random_q(nv, 1, 8);
    const double h = 1e-6;
    std::vector<double> qp(q), qm(q);
    for (Index i = 0; i < nv; ++i) qp[static_cast<std::size_t>(i)] += h * qd[static_cast<std::size_t>(i)], qm[static_cast<std::size_t>(i)] -= h * qd[static_cast<std::size_t>(i)];
    const auto plus = run_kinematics(m, BackendKind::Serial, all_frames(m), qp, 1);
    const auto minus = run_kinematics(m, BackendKind::Serial, all_frames(m), qm, 1);
    for (FrameReference ref : {FrameReference::World, FrameReference::Local}) {
      const auto at = run_kinematics(m, BackendKind::Serial, all_frames(m, PoseFormat::Matrix, ref), q, 1);
      for (Index k = 0; k < F; ++k) {
        const Pose P = pose_at(at.poses, F, 0, k), Pp = pose_at(plus.poses, F, 0, k), Pm = pose_at(minus.poses, F, 0, k);
        double dR[3][3], W[3][3], w[3], v[3];
        for (int r = 0; r < 3; ++r) {
          for (int c = 0; c < 3; ++c) dR[r][c] = (Pp.R[r][c] - Pm.R[r][c]) / (2 * h);
          v[r] = (Pp.p[r] - Pm.p[r]) / (2 * h);
        }
        for (int r = 0; r < 3; ++r)
          for (int c = 0; c < 3; ++c) W[r][c] = dR[r][0] * P.R[c][0] + dR[r][1] * P.R[c][1] + dR[r][2] * P.R[c][2];
        w[0] = 0.5 * (W[2][1] - W[1][2]), w[1] = 0.5 * (W[0][2] - W[2][0]), w[2] = 0.5 * (W[1][0] - W[0][1]);
        double want[6];
        for (int r = 0; r < 3; ++r) {
          if (ref == FrameReference::World) {
            want[r] = w[r], want[3 + r] = v[r];
          } else {  // R^T w, R^T v
            want[r] = P.R[0][r] * w[0] + P.R[1][r] * w[1] + P.R[2][r] * w[2];
            want[3 + r] = P.R[0][r] * v[0] + P.R[1][r] * v[1] + P.R[2][r] * v[2];
          }
        }
        for (int r = 0; r < 6; ++r) {
          double got = 0;
          for (Index j = 0; j < nv; ++j) got += at.J[static_cast<std::size_t>((k * 6 + r) * nv + j)] * qd[static_cast<std::size_t>(j)];
          EXPECT_NEAR(got, want[r], 1e-7 * std::max(1.0, std::fabs(want[r])))
              << label << " frame " << m.frame_names[static_cast<std::size_t>(k)] << " row " << r
              << (ref == FrameReference::World ? " world" : " local");
        }
      }
    }
  }
}

// Columns of joints that do not move a frame are exactly zero; the rotation is
// orthonormal; the quaternion output is the matrix's (unit, w >= 0, same position).
TEST(Kinematics, StructureAndTheQuaternionOfTheMatrix) {
  for (const auto& [label, m] : frame_models()) {
    const Index nv = m.nv(), F = static_cast<Index>(m.frames.size()), B = 3;
    const std::vector<double> q = random_q(nv, B, 11);
    const auto mat = run_kinematics(m, BackendKind::Serial, all_frames(m), q, B);
    const auto pq = run_kinematics(m, BackendKind::Serial, all_frames(m, PoseFormat::PositionQuaternion), q, B);
    for (Index b = 0; b < B; ++b) {
      for (Index k = 0; k < F; ++k) {
        const Pose P = pose_at(mat.poses, F, b, k);
        const double* e = pq.poses.data() + (b * F + k) * 7;
        for (int r = 0; r < 3; ++r) EXPECT_EQ(e[r], P.p[r]) << label;
        const double x = e[3], y = e[4], z = e[5], w = e[6];
        EXPECT_NEAR(x * x + y * y + z * z + w * w, 1.0, 1e-14) << label;
        EXPECT_GE(w, 0.0) << label;
        const double R[3][3] = {{1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)},
                                {2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)},
                                {2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)}};
        for (int r = 0; r < 3; ++r)
          for (int c = 0; c < 3; ++c) {
            EXPECT_NEAR(R[r][c], P.R[r][c], 1e-14) << label << " frame " << k;
            const double RRt = P.R[r][0] * P.R[c][0] + P.R[r][1] * P.R[c][1] + P.R[r][2] * P.R[c][2];
            EXPECT_NEAR(RRt, r == c ? 1.0 : 0.0, 1e-14);
          }
        const double* last = mat.poses.data() + (b * F + k) * 16 + 12;
        for (int e = 0; e < 4; ++e) EXPECT_EQ(last[e], e == 3 ? 1.0 : 0.0);
        // a column is non-zero only on the path from the frame's body to the base
        std::vector<bool> on_path(static_cast<std::size_t>(nv), false);
        for (Index j = m.frames[static_cast<std::size_t>(k)].body; j >= 0; j = m.parent(j)) on_path[static_cast<std::size_t>(j)] = true;
        for (int r = 0; r < 6; ++r)
          for (Index j = 0; j < nv; ++j)
            if (!on_path[static_cast<std::size_t>(j)]) {
              EXPECT_EQ(mat.J[static_cast<std::size_t>(((b * F + k) * 6 + r) * nv + j)], 0.0) << label;
            }
      }
    }
  }
}

// OpenMP is serial bit for bit, in every layout (q and outputs structure-of-arrays,
// or a view skipped); float is within 2e-5 of double (positions in m, |p| <= ~2).
TEST(Kinematics, EveryCpuBackendAndLayoutIsSerialAndFloatIsNearDouble) {
  for (const auto& [label, m] : frame_models()) {
    const Index nv = m.nv(), B = 37;
    for (FrameReference ref : {FrameReference::World, FrameReference::Local}) {
      for (PoseFormat pf : {PoseFormat::Matrix, PoseFormat::PositionQuaternion}) {
        const KinematicsOptions k = all_frames(m, pf, ref);
        const Index F = static_cast<Index>(k.frames.size()), pw = pose_width(pf);
        const std::vector<double> q = random_q(nv, B, 5);
        const auto ser = run_kinematics(m, BackendKind::Serial, k, q, B);
        if (SCANDYN_HAS_OPENMP) {
          const auto omp = run_kinematics(m, BackendKind::OpenMP, k, q, B, 3);
          EXPECT_EQ(omp.poses, ser.poses) << label;
          EXPECT_EQ(omp.J, ser.J) << label;
        }
        // structure-of-arrays: q[i * B + b], poses[e * B + b]; J not computed
        std::vector<double> qs(q.size()), ps(ser.poses.size(), std::nan(""));
        for (Index b = 0; b < B; ++b)
          for (Index i = 0; i < nv; ++i) qs[static_cast<std::size_t>(i * B + b)] = q[static_cast<std::size_t>(b * nv + i)];
        BackendOptions o;
        o.max_batch = B;
        make_kinematics(m, o, k)->compute(BatchView<const double>::soa(qs.data(), nv, B),
                                          BatchView<double>::soa(ps.data(), F * pw, B), BatchView<double>{});
        for (Index b = 0; b < B; ++b)
          for (Index e = 0; e < F * pw; ++e)
            ASSERT_EQ(ps[static_cast<std::size_t>(e * B + b)], ser.poses[static_cast<std::size_t>(b * F * pw + e)]) << label;
        // float
        const ModelTpl<float> mf = m.cast<float>();
        auto fl = run_kinematics(mf, BackendKind::Serial, k, cast_vector<float>(q), B);
        if (pf == PoseFormat::PositionQuaternion) align_quaternion_signs(fl.poses, ser.poses);
        for (std::size_t e = 0; e < ser.poses.size(); ++e)
          ASSERT_NEAR(fl.poses[e], ser.poses[e], 2e-5 * std::max(1.0, std::fabs(ser.poses[e]))) << label;
        for (std::size_t e = 0; e < ser.J.size(); ++e)
          ASSERT_NEAR(fl.J[e], ser.J[e], 2e-5 * std::max(1.0, std::fabs(ser.J[e]))) << label;
      }
    }
  }
}

}  // namespace
}  // namespace scandyn::test
