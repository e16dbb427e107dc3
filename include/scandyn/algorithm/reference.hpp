// scandyn/algorithm/reference.hpp: the serial reference algorithms.
//
// RNEA (inverse dynamics), bias forces, CRBA (joint-space inertia), ABA (forward
// dynamics) and forward dynamics by CRBA + Cholesky, for Scalar = float or double.
// Every call reads the model, writes only its outputs and the preallocated scratch
// in DataTpl, and allocates nothing.
//
// Arrays qd, qdd, tau, h have nv entries in DoF order, q has nq (= nv unless a
// spherical or free joint holds a unit quaternion; the floating base's block comes
// first: scandyn/model/model.hpp). fext, when given, has nbodies wrenches: fext[i]
// acts on body i, expressed in body i's frame about its origin, [moment; force].
// Gravity is the model's (entered as base acceleration -g). Models with multi-DoF
// joints take a general path per algorithm (the *_at steps); 1-DoF models run the
// 1-DoF steps alone.
#pragma once

#include <vector>

#include "scandyn/algorithm/steps.hpp"

namespace scandyn {

// Scratch for one evaluation of any reference algorithm.
template <class S>
struct DataTpl {
  // mass_matrix = false skips the nv x nv workspace that only fd_jsi needs (a
  // 10^5-link rope would need 80 GB); fd_jsi then throws std::logic_error.
  explicit DataTpl(const ModelTpl<S>& model, bool mass_matrix = true);

  std::vector<Transform<S>> Xup;  // (nbodies) parent -> body transform at the current q
  std::vector<Motion<S>> v;       // (nbodies) body velocities, body frames
  std::vector<Motion<S>> a;       // (nbodies) body accelerations (gravity included)
  std::vector<Motion<S>> c;       // (nbodies) ABA velocity-product accelerations
  std::vector<Force<S>> f;        // (nbodies) RNEA joint forces / ABA bias forces pA
  std::vector<Inertia<S>> Ic;     // (nbodies) CRBA composite inertias
  std::vector<ABInertia<S>> IA;   // (nbodies) ABA articulated inertias
  std::vector<Force<S>> U;        // (nv) ABA IA S per DoF (multi-DoF joints: Y = U L^-T)
  std::vector<S> D;               // (nv) ABA S^T IA S per DoF (multi-DoF joints: unused)
  std::vector<S> u;               // (nv) ABA tau - S^T pA per DoF (multi-DoF joints: w = L^-1 u)
  std::vector<S> L;               // (kMaxJointDofs nv) multi-DoF joints' Cholesky factors of
                                  // D = S^T IA S: row k of body i's at (idx_v + k) * kMaxJointDofs;
                                  // empty for a model of 1-DoF joints
  std::vector<S> M;               // (nv x nv) row-major mass matrix / its factor (fd_jsi), or empty
  std::vector<S> h;               // (nv) bias forces for JSI
  std::vector<Index> lambda;      // (nv) parent DoF of each DoF (Featherstone 6.5's lambda): the
                                  // previous DoF of the same joint, else the parent body's last
                                  // DoF, -1 at the base; = the body parents for 1-DoF joints
  std::vector<Index> run_start;   // (nv) first DoF of the chain run holding DoF i: DoFs
                                  // run_start[i]..i each have the previous one as lambda
};

using Data = DataTpl<double>;

// Outcome of a factorisation or a forward-dynamics call.
struct Status {
  Index failed_dof = -1;  // first DoF whose pivot was not positive and finite, -1 if none
  bool ok() const { return failed_dof < 0; }
};

// tau = M(q) qdd + C(q, qd) qd + g(q) - sum_i J_i^T fext_i.
template <class S>
void rnea(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* qdd,
          S* tau, const Force<S>* fext = nullptr);

// h = RNEA(q, qd, 0): Coriolis, centrifugal and gravity forces (and -J^T fext if given).
template <class S>
void bias_forces(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, S* h,
                 const Force<S>* fext = nullptr);

// M(q), the joint-space inertia matrix: nv x nv, row-major, both triangles written.
template <class S>
void crba(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, S* M);

// qdd = FD(q, qd, tau) by the articulated-body algorithm. Stops and reports the body
// (qdd untouched) when an articulated pivot D_i = S_i^T IA_i S_i (+ armature_i) is not
// positive and finite. armature, when given, has nv joint-space inertias added to
// M's diagonal: qdd = (M + diag(armature))^{-1} (tau - h) (aba_joint_terms); null
// computes exactly what it computes without the argument.
template <class S>
Status aba(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* tau,
           S* qdd, const Force<S>* fext = nullptr, const S* armature = nullptr);

// Hybrid dynamics (Featherstone 2008, 9.2, the articulated-body hybrid algorithm):
// every DoF has either its acceleration given (prescribed[i] != 0: qdd_in[i]) or its
// force (prescribed[i] == 0: tau_in[i]); computes the other of each pair, so that
// tau_out = M(q) qdd_out + h(q, qd) (- J^T fext) on every row, with qdd_out[i] =
// qdd_in[i] and tau_out[i] = tau_in[i] at the given entries (copied through).
// qdd_in is read at prescribed DoFs only, tau_in at the others only (the other
// entries may hold anything, NaN included). Outputs may alias the inputs. With no
// DoF prescribed, qdd_out is aba's exactly (the same arithmetic); with all of them,
// tau_out is the inverse dynamics (articulated-body forces S^T (IA a + pA), equal
// to rnea's to rounding). Stops and reports the DoF (outputs untouched) when an
// articulated pivot of a DoF whose force is given is not positive and finite.
// armature as for aba (enters the pivots of the DoFs whose force is given).
template <class S>
Status hybrid_dynamics(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd,
                       const unsigned char* prescribed, const S* qdd_in, const S* tau_in, S* qdd_out, S* tau_out,
                       const Force<S>* fext = nullptr, const S* armature = nullptr);

// qdd = M^{-1} (tau - h) with M from CRBA and the tree-sparse L^T L factorisation
// (Featherstone 6.5). Reports the first DoF whose pivot is not positive. armature as
// for aba: added to M's diagonal after the CRBA, before the factorisation.
template <class S>
Status fd_jsi(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* tau,
              S* qdd, const Force<S>* fext = nullptr, const S* armature = nullptr);

// The general path of rnea, crba and aba, for models with multi-DoF joints
// (ModelTpl::multi_dof(): a floating base, spherical joints), to which those
// dispatch: the same recursions over joints of 1, 3 and 6 DoFs (the *_at steps of
// steps.hpp). Callable on any model whose Body::idx_q / idx_v are set.
template <class S>
void rnea_at(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* qdd, S* tau,
             const Force<S>* fext);
template <class S>
void crba_at(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, S* M);
template <class S>
Status aba_at(const ModelTpl<S>& model, DataTpl<S>& data, const S* q, const S* qd, const S* tau, S* qdd,
              const Force<S>* fext, const S* armature);

// In place M = L^T L for a tree mass matrix (nv x nv row-major, lower triangle used,
// L written to the lower triangle). data.lambda gives the branch-induced sparsity; the
// ancestor walks run over data.run_start's contiguous chain runs.
template <class S>
Status ltl_factor(const ModelTpl<S>& model, const DataTpl<S>& data, S* M);

// Solves L^T L x = b in place (x = b on entry) with the factor from ltl_factor.
template <class S>
void ltl_solve(const ModelTpl<S>& model, const DataTpl<S>& data, const S* L, S* x);

}  // namespace scandyn
