// scandyn/algorithm/rnea_scan.hpp: inverse dynamics as two associative scans
// over the links of one model instance, on the threads of the calling process.
//
// Two formulations (see scandyn/scan/elements.hpp):
//   ScanForm::Local  affine scans in body frames: (Xup, S qd) for velocities,
//                    (Xup, S qdd + v x S qd) for accelerations, (Xup, Xup^T f)
//                    for the wrenches; what the recursion computes, reassociated.
//   ScanForm::World  a scan of poses P_i = Xup_i P_parent, then world-frame joint
//                    twists, accelerations and body wrenches are plain prefix and
//                    subtree sums; tau_i = (P_i^{-1} S_i) . F_i^world.
// Both give RNEA's tau exactly in exact arithmetic; they differ in rounding (see
// docs/accuracy-id-scan.md) and in work (the world form has cheaper scan operators).
//
// Multi-DoF joints (ModelTpl::multi_dof()): one element per body, with the joint's
// entries of q, qd, qdd and tau at Body::idx_q / idx_v. A floating base (body 0's
// free joint) is the root element of every prefix scan: its pose (q_0..q_6) in Xup
// (the world form's first pose), its twist (qd_0..qd_5) as the velocity scan's
// first offset, its qdd and -g in the acceleration scan's; the backward scan ends
// at the base, whose wrench S^T F_0 = F_0 is tau_0..tau_5. Spherical joints are
// elements (Xup, [w; 0]) and project to the moment.
#pragma once

#include <vector>

#include "scandyn/algorithm/steps.hpp"
#include "scandyn/scan/elements.hpp"
#include "scandyn/scan/tree_plan.hpp"

namespace scandyn {

enum class ScanForm { Local, World };

// Scratch of the scan inverse dynamics for one model and thread count.
template <class S>
struct ScanWorkspace {
  ScanWorkspace(const ModelTpl<S>& model, int threads);

  int threads;                         // threads used by rnea_scan (1: serial scans)
  TreeScanPlan plan;                   // segments / pieces of the model's tree
  std::vector<Transform<S>> Xup;       // (nbodies) parent -> body
  std::vector<Motion<S>> v;            // (nbodies) body velocities (local form)
  std::vector<MotionAffine<S>> fwd;    // (nbodies) forward scan elements / prefixes
  std::vector<ForceAffine<S>> bwd;     // (nbodies) backward scan elements / suffixes
  std::vector<Transform<S>> P;         // (nbodies) world -> body poses (world form)
  std::vector<Motion<S>> sw;           // (nbodies) joint twists in world coordinates: unit
                                       // (1-DoF joints), S qd (multi-DoF models)
  std::vector<Motion<S>> Vw, Aw;       // (nbodies) world-frame velocities, accelerations
  std::vector<Force<S>> Fw;            // (nbodies) world-frame wrenches / subtree sums
  // carries between pieces, one per piece
  std::vector<MotionAffine<S>> carry_fwd;
  std::vector<ForceAffine<S>> carry_bwd;
  std::vector<Transform<S>> carry_pose;
  std::vector<Motion<S>> carry_motion;
  std::vector<Force<S>> carry_force;
};

// tau = RNEA(q, qd, qdd) (gravity and optional body-frame fext as in reference.hpp)
// computed by scans; parallel over links when ws.threads > 1. q has nq entries, qd,
// qdd and tau nv, fext nbodies.
template <class S>
void rnea_scan(const ModelTpl<S>& model, ScanWorkspace<S>& ws, ScanForm form, const S* q, const S* qd,
               const S* qdd, S* tau, const Force<S>* fext = nullptr);

}  // namespace scandyn
