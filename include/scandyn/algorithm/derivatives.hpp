// scandyn/algorithm/derivatives.hpp: the serial reference of the first-order
// derivatives of inverse and forward dynamics (Carpentier & Mansard, RSS 2018; the
// recursions and formulas are in scandyn/instance/dynamics_derivatives.hpp, which
// these functions run on the host).
//
// Matrices are nv x nv, given as MatrixRef (entry (i, j) at data[(i * nv + j) *
// stride]; stride 1: row-major); every entry is written. Row i is the DoF
// differentiated, column j the variable: dtau_dq(i, j) = d tau_i / d q_j. Inputs
// as for rnea / aba (scandyn/algorithm/reference.hpp): q nq entries, qd, qdd, tau nv,
// fext nbodies body wrenches in body frames or null, gravity the model's. Models
// with multi-DoF joints (a floating base, spherical joints) take the general
// recursion (rnea_derivatives_general_instance): the q columns are then derivatives
// along the local increments q (+) d = q exp(d) of each joint (nv columns, the
// tangent space; scandyn/instance/dynamics_derivatives.hpp).
#pragma once

#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/instance/dynamics_derivatives.hpp"

namespace scandyn {

// Scratch for one evaluation of the derivatives (no allocation in a call).
template <class S>
struct DerivativeDataTpl {
  explicit DerivativeDataTpl(const ModelTpl<S>& model)
      : aba(model, /*mass_matrix=*/false),
        work(static_cast<std::size_t>(model.nv())),
        dof_parent(static_cast<std::size_t>(model.nv())),
        dof_last(static_cast<std::size_t>(model.nv())),
        dof_run(static_cast<std::size_t>(model.nv())) {
    dof_parents(model.bodies.data(), model.nbodies(), dof_parent.data());
    dof_subtree_last(dof_parent.data(), model.nv(), dof_last.data());
    dof_runs(dof_parent.data(), model.nv(), dof_run.data());
  }
  DataTpl<S> aba;                        // the ABA's scratch (aba_derivatives' qdd)
  std::vector<DerivativeBody<S>> work;   // (nv) world-frame body quantities (multi-DoF
                                         // joints: rnea_derivatives_general_instance's layout)
  std::vector<Index> dof_parent;         // (nv) the tree of DoFs (dof_parents)
  std::vector<Index> dof_last;           // (nv) the last DoF of each DoF's subtree
  std::vector<Index> dof_run;            // (nv) the first DoF of each DoF's unbranched run (dof_runs)
};

// dtau/dq, dtau/dqd and dtau/dqdd = M at (q, qd, qdd, fext); tau (optional) =
// ID(q, qd, qdd, fext) as a by-product.
template <class S>
void rnea_derivatives(const ModelTpl<S>& model, DerivativeDataTpl<S>& data, const S* q, const S* qd,
                      const S* qdd, const Force<S>* fext, MatrixRef<S> dtau_dq, MatrixRef<S> dtau_dqd,
                      MatrixRef<S> M, S* tau = nullptr);

// qdd = FD(q, qd, tau, fext) by the ABA, then dqdd/dq, dqdd/dqd and dqdd/dtau = M^-1
// there. A pivot that is not positive and finite (the ABA's, or M's) is reported;
// the outputs are then not meaningful. armature (nv, or null): joint-space inertia
// on M's diagonal, as aba's (fd_derivatives_instance).
template <class S>
Status aba_derivatives(const ModelTpl<S>& model, DerivativeDataTpl<S>& data, const S* q, const S* qd,
                       const S* tau, const Force<S>* fext, S* qdd, MatrixRef<S> dqdd_dq, MatrixRef<S> dqdd_dqd,
                       MatrixRef<S> dqdd_dtau, const S* armature = nullptr);

}  // namespace scandyn
