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
  std::vector<Transform<S>> Xup;       // (nv) parent -> body
  std::vector<Motion<S>> v;            // (nv) body velocities (local form)
  std::vector<MotionAffine<S>> fwd;    // (nv) forward scan elements / prefixes
  std::vector<ForceAffine<S>> bwd;     // (nv) backward scan elements / suffixes
  std::vector<Transform<S>> P;         // (nv) world -> body poses (world form)
  std::vector<Motion<S>> sw;           // (nv) unit joint twists in world coordinates
  std::vector<Motion<S>> Vw, Aw;       // (nv) world-frame velocities, accelerations
  std::vector<Force<S>> Fw;            // (nv) world-frame wrenches / subtree sums
  // carries between pieces, one per piece
  std::vector<MotionAffine<S>> carry_fwd;
  std::vector<ForceAffine<S>> carry_bwd;
  std::vector<Transform<S>> carry_pose;
  std::vector<Motion<S>> carry_motion;
  std::vector<Force<S>> carry_force;
};

// tau = RNEA(q, qd, qdd) (gravity and optional body-frame fext as in reference.hpp)
// computed by scans; parallel over links when ws.threads > 1.
template <class S>
void rnea_scan(const ModelTpl<S>& model, ScanWorkspace<S>& ws, ScanForm form, const S* q, const S* qd,
               const S* qdd, S* tau, const Force<S>* fext = nullptr);

}  // namespace scandyn
