// Shared by the kinematics tests (tests/engine/test_kinematics.cpp, tests/cuda/
// test_cuda_kinematics.cu): random URDF-like trees with revolute, prismatic and fixed
// joints (built by the model builder, so merged links keep their frames), and the
// engine called on instance-major host arrays.
#pragma once

#include <memory>
#include <random>
#include <string>
#include <vector>

#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn::test {

// n links below a root link "base": each hangs from a random earlier link through a
// revolute (50%), prismatic (25%) or fixed (25%) joint with a random origin and unit
// axis; links have random mass and inertia, fixed ones sometimes none. With
// fixed_as_revolute, every fixed joint is revolute instead (the same tree, its merged
// links now bodies of their own: at q = 0 on those joints the frames are where they were).
inline RawTree random_frame_tree(int n, unsigned seed, bool fixed_as_revolute = false) {
  std::mt19937_64 g(seed);
  auto uni = [&](double lo, double hi) { return std::uniform_real_distribution<double>(lo, hi)(g); };
  auto vec = [&](double s) { return Vec3<double>{uni(-s, s), uni(-s, s), uni(-s, s)}; };
  RawTree t;
  t.name = "frames";
  t.source = "random_frame_tree:" + std::to_string(n) + ":" + std::to_string(seed);
  RawLink base;
  base.name = "base";
  t.links.push_back(base);
  for (int i = 0; i < n; ++i) {
    const int parent = std::uniform_int_distribution<int>(0, i)(g);
    const double kind = uni(0, 1);
    RawJoint j;
    j.name = "j" + std::to_string(std::uniform_int_distribution<int>(100, 999)(g)) + "_" + std::to_string(i);
    j.type = kind < 0.5 ? RawJointType::Revolute : kind < 0.75 ? RawJointType::Prismatic : RawJointType::Fixed;
    if (fixed_as_revolute && j.type == RawJointType::Fixed) j.type = RawJointType::Revolute;
    j.type_name = "random";
    j.parent = t.links[static_cast<std::size_t>(parent)].name;
    j.child = "l" + std::to_string(i);
    j.xyz = vec(0.4);
    j.rpy = vec(3);
    j.axis = vec(1);
    RawLink l;
    l.name = j.child;
    l.has_inertial = uni(0, 1) < 0.8;
    if (l.has_inertial) {
      l.mass = uni(0.2, 3);
      l.com_xyz = vec(0.1);
      const double a = uni(0.01, 0.3), b = uni(0.01, 0.3);
      l.inertia = {a, b, uni(std::fabs(a - b) + 1e-3, a + b), 0, 0, 0};
    }
    t.links.push_back(l);
    t.joints.push_back(j);
  }
  return t;
}

// Every frame of the model, in model.frames order.
template <class S>
KinematicsOptions all_frames(const ModelTpl<S>& model, PoseFormat pose = PoseFormat::Matrix,
                             FrameReference reference = FrameReference::World) {
  KinematicsOptions k;
  for (std::size_t f = 0; f < model.frames.size(); ++f) k.frames.push_back(static_cast<Index>(f));
  k.pose = pose;
  k.reference = reference;
  return k;
}

// Poses and Jacobians of B instances (q instance-major, B x nv) on one backend, in
// instance-major arrays (B x F x pose_width, B x F x 6 x nv), NaN before the call.
template <class S>
struct KinematicsResult {
  std::vector<S> poses, J;
};
template <class S>
KinematicsResult<S> run_kinematics(const ModelTpl<S>& model, BackendKind backend, const KinematicsOptions& k,
                                   const std::vector<S>& q, Index B, int threads = 0) {
  BackendOptions o;
  o.backend = backend;
  o.max_batch = B;
  o.threads = threads;
  const std::unique_ptr<Kinematics<S>> e = make_kinematics(model, o, k);
  const Index nv = model.nv(), F = static_cast<Index>(k.frames.size()), pw = pose_width(k.pose);
  KinematicsResult<S> r;
  r.poses.assign(static_cast<std::size_t>(B * F * pw), std::numeric_limits<S>::quiet_NaN());
  r.J.assign(static_cast<std::size_t>(B * F * 6 * nv), std::numeric_limits<S>::quiet_NaN());
  // q: nq entries per instance
  e->compute(BatchView<const S>::aos(q.data(), model.nq(), B), BatchView<S>::aos(r.poses.data(), F * pw, B),
             BatchView<S>::aos(r.J.data(), F * 6 * nv, B));
  return r;
}

// q and -q are one rotation: where a quaternion's w is within rounding of 0, two
// computations may canonicalise (w >= 0) to opposite signs. Flips each quaternion of
// `got` (PositionQuaternion poses, 7 entries per frame) that points away from ref's.
template <class S, class R>
void align_quaternion_signs(std::vector<S>& got, const std::vector<R>& ref) {
  for (std::size_t k = 0; k + 7 <= got.size() && k + 7 <= ref.size(); k += 7) {
    double d = 0;
    for (int e = 3; e < 7; ++e) d += double(got[k + e]) * double(ref[k + e]);
    if (d < 0)
      for (int e = 3; e < 7; ++e) got[k + e] = -got[k + e];
  }
}

}  // namespace scandyn::test
