// scandyn/instance/kinematics_instance.hpp: frame poses and frame Jacobians of one
// instance in one thread: the one routine behind every backend's Kinematics engine
// (the serial and OpenMP engines in cpu_fallback/kinematics.cpp, the CUDA kernel in
// kernels/kinematics.cu).
//
// Plain SCANDYN_HD code over a body array in DoF order (parent[i] < i): on the host
// the model's bodies, on the device the kernel parameter's (ThreadModelParams::body).
// Unlike the dynamics' instance functions it has no backward pass, and a frame reads
// the placement of every ancestor of its body, so it walks the bodies in DoF order
// and keeps each body's world placement (nv transforms of scratch, the caller's).
#pragma once

#include <cstddef>

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/instance/interleaved.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/spatial/quaternion.hpp"

namespace scandyn {

// One instance's entries of a strided output: entry e at data[e * stride].
template <class T>
struct Strided {
  T* data;
  std::ptrdiff_t stride;
  SCANDYN_HD T& operator[](Index e) const { return data[e * stride]; }
  // the entries from e on
  SCANDYN_HD Strided from(Index e) const { return {data + e * stride, stride}; }
};

// X0[i] = i_X_0, the placement of every body: world (base) coordinates -> body i's,
// at joint positions q (q[i], i < nv). Featherstone's X0 = Xup X0_parent.
template <Trig kTrig = Trig::Exact, class S, class Q>
SCANDYN_HD void body_placements(const Body<S>* body, Index nv, const Q& q, Transform<S>* X0) {
  for (Index i = 0; i < nv; ++i) {
    const Transform<S> Xup = joint_transform<kTrig>(body[i], S(q[i]));
    const Index p = body[i].parent;
    X0[i] = p < 0 ? Xup : Xup * X0[p];
  }
}

// f_X_0: the frame's placement, world coordinates -> frame coordinates. X0: a plain
// pointer or an array of interleaved.hpp (the general kernels' scratch).
template <class S, class XA>
SCANDYN_HD Transform<S> frame_placement(const FramePlacement<S>& f, const XA& X0) {
  return f.body < 0 ? f.X : f.X * Transform<S>(X0[f.body]);
}

// The pose of a frame with placement fX0 = (E, r): R = E^T, p = r, written in
// format (PoseFormat) to out[0 .. pose_width).
template <class S, class Out>
SCANDYN_HD void write_pose(const Transform<S>& fX0, PoseFormat format, const Out& out) {
  const Mat3<S> R = transpose(fX0.E);
  if (format == PoseFormat::Matrix) {
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) out[4 * r + c] = R(r, c);
      out[4 * r + 3] = fX0.r[r];
    }
    out[12] = S(0), out[13] = S(0), out[14] = S(0), out[15] = S(1);
    return;
  }
  const Quat<S> qr = quaternion_of(R);
  out[0] = fX0.r.x, out[1] = fX0.r.y, out[2] = fX0.r.z;
  out[3] = qr.x, out[4] = qr.y, out[5] = qr.z, out[6] = qr.w;
}

// The Jacobian column of body j's joint for a frame with placement fX0: the frame's
// motion [w; v] (v: of the frame's origin) per unit rate of joint j, in world axes
// or the frame's. S_j in world coordinates is X0_j^{-1} S_j (the motion of the
// body-fixed point at the world origin); moved to the frame's origin r that is
// [w; v + w x r], world axes; fX0 applied to it gives the frame's own axes.
template <class S>
SCANDYN_HD Motion<S> frame_jacobian_column(const Body<S>& bj, const Transform<S>& X0j, const Transform<S>& fX0,
                                           FrameReference reference) {
  const Motion<S> s0 = X0j.apply_inverse(joint_motion(bj, S(1)));
  if (reference == FrameReference::Local) return fX0.apply(s0);
  return {s0.w, s0.v + cross(s0.w, fX0.r)};
}

// The frame's 6 x nv Jacobian, row-major into out[r * nv + j]: the column of each
// joint on the path from the frame's body to the base, zeros in the others (each
// entry written once, columns from the last).
template <class S, class Out>
SCANDYN_HD void write_frame_jacobian(const Body<S>* body, Index nv, const FramePlacement<S>& f,
                                     const Transform<S>* X0, const Transform<S>& fX0, FrameReference reference,
                                     const Out& out) {
  Index next = f.body;  // the next ancestor (or the body itself) below j, -1 past the base
  for (Index j = nv - 1; j >= 0; --j) {
    Motion<S> c = Motion<S>::zero();
    if (j == next) {
      c = frame_jacobian_column(body[j], X0[j], fX0, reference);
      next = body[j].parent;
    }
    for (int r = 0; r < 6; ++r) out[r * nv + j] = c[r];
  }
}

// Everything of one instance: the body placements into X0 (nv scratch transforms),
// then for each of the F frames its pose (into poses, pose_width(format) entries per
// frame, unless poses.data is null) and its Jacobian (into J, 6 nv entries per
// frame, unless J.data is null).
template <Trig kTrig = Trig::Exact, class S, class Q>
SCANDYN_HD void kinematics_instance(const Body<S>* body, Index nv, const FramePlacement<S>* frames, Index F,
                                    PoseFormat format, FrameReference reference, const Q& q, Transform<S>* X0,
                                    Strided<S> poses, Strided<S> J) {
  body_placements<kTrig>(body, nv, q, X0);
  const Index pw = pose_width(format);
  for (Index k = 0; k < F; ++k) {
    const Transform<S> fX0 = frame_placement(frames[k], X0);
    if (poses.data) write_pose(fX0, format, poses.from(k * pw));
    if (J.data) write_frame_jacobian(body, nv, frames[k], X0, fX0, reference, J.from(k * 6 * nv));
  }
}

// ---- joints of any type (a floating base, spherical joints) ----------------------
// The same quantities for a model with multi-DoF joints (ModelTpl::multi_dof()): nb
// bodies, body i's joint at q[idx_q..] (a quaternion for spherical and free joints)
// and at columns idx_v.. of the Jacobian (joint_nv of them; a free joint's six are
// the base twist [w; v] in the base frame, so its columns are the base frame's axes).
// The serial and OpenMP engines, and the CUDA engine's general strategy
// (kernels/general_dynamics.cu: q and X0 there arrays of interleaved.hpp).

// X0[i] = i_X_0 for every body at positions q (nq entries).
template <class S, class Q, class XA>
SCANDYN_HD void body_placements_at(const Body<S>* body, Index nb, const Q& q, const XA& X0) {
  for (Index i = 0; i < nb; ++i) {
    S qj[7];  // a free joint's 7 entries at most (unused for a plain pointer)
    load_run(q, body[i].idx_q, joint_nq(body[i].type), qj);
    const Transform<S> Xup = joint_transform_at(body[i], joint_run(q, body[i].idx_q, qj));
    const Index p = body[i].parent;
    X0[i] = p < 0 ? Xup : Xup * Transform<S>(X0[p]);
  }
}

// The frame's 6 x nv Jacobian into out[r * nv + j]: the columns of every joint on the
// path from the frame's body to the base, zeros elsewhere (each entry written once).
template <class S, class XA, class Out>
SCANDYN_HD void write_frame_jacobian_at(const Body<S>* body, Index nb, Index nv, const FramePlacement<S>& f,
                                        const XA& X0, const Transform<S>& fX0, FrameReference reference,
                                        const Out& out) {
  Index next = f.body;  // the next ancestor (or the body itself) below i, -1 past the base
  for (Index i = nb - 1; i >= 0; --i) {
    const Body<S>& b = body[i];
    const int nj = joint_nv(b.type);
    const bool on_path = i == next;
    if (on_path) next = b.parent;
    for (int k = 0; k < nj; ++k) {
      Motion<S> c = Motion<S>::zero();
      if (on_path) {
        const Motion<S> s0 = Transform<S>(X0[i]).apply_inverse(joint_column(b, k));
        c = reference == FrameReference::Local ? fX0.apply(s0) : Motion<S>{s0.w, s0.v + cross(s0.w, fX0.r)};
      }
      for (int r = 0; r < 6; ++r) out[r * nv + b.idx_v + k] = c[r];
    }
  }
}

// kinematics_instance for a model with multi-DoF joints: nb scratch transforms X0.
template <class S, class Q, class XA>
SCANDYN_HD void kinematics_instance_at(const Body<S>* body, Index nb, Index nv, const FramePlacement<S>* frames,
                                       Index F, PoseFormat format, FrameReference reference, const Q& q,
                                       const XA& X0, Strided<S> poses, Strided<S> J) {
  body_placements_at(body, nb, q, X0);
  const Index pw = pose_width(format);
  for (Index k = 0; k < F; ++k) {
    const Transform<S> fX0 = frame_placement(frames[k], X0);
    if (poses.data) write_pose(fX0, format, poses.from(k * pw));
    if (J.data) write_frame_jacobian_at(body, nb, nv, frames[k], X0, fX0, reference, J.from(k * 6 * nv));
  }
}

}  // namespace scandyn
