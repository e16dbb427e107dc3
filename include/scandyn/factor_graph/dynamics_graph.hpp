// scandyn/factor_graph/dynamics_graph.hpp: the dynamics factor graph of a kinematic
// tree (and its loop closures) as one sparse linear system A x = b (Xie & Dellaert,
// "A unified method for solving inverse, forward, and hybrid manipulator dynamics
// using factor graphs"; docs/factor-graph.md).
//
// Variables, per body i (DoF order), given q and qd (so the velocities v_i are known
// and evaluated ahead, as the seed does):
//   a_i   (6)  spatial acceleration, body frame, gravity included (base: -g)
//   f_i   (6)  force the parent transmits across joint i, body frame
//   qdd_i (1)  joint acceleration
//   tau_i (1)  joint force
// and per loop closure k: lambda_k (3 for a point, 6 for a weld), in world axes.
// Factors (one block row each):
//   acceleration  a_i - Xup_i a_parent - S_i qdd_i                       = v_i x S_i qd_i
//   force balance f_i - sum_c Xup_c^T f_c - I_i a_i + sum_k +-G_ik lambda_k = v_i x* I_i v_i
//   joint force   S_i^T f_i + armature_i qdd_i - tau_i                   = 0
//                 (armature: Featherstone's rotor inertia, zero unless given)
//   prior         qdd_i = given (inverse dynamics, prescribed DoF) or tau_i = given
//   loop k        sum_sides +-G_sk^T a_s                                  = -(velocity products)
// so the system is square: 14 nv + sum_k dim_k unknowns and as many equations. Its
// solution is RNEA's (all qdd given), ABA's (all tau given) or the hybrid dynamics'
// (a mix), whatever the elimination ordering.
//
// Units. The system is stored non-dimensionalised in the model's units of mass M
// and length L (the time unit 1 s; ModelUnits): every unknown is measured in its
// unit (angular acceleration 1, linear acceleration L, moment M L^2, force M L,
// ...) and every equation is divided by its unit, A = W A_SI S, b = W b_SI, x_SI =
// S x. In SI a 10 g, 1 cm link's inertial entries are 1e-7 of the kinematic ones
// and the sparse solvers' proximal term swamps them; in the model's units they are
// O(1). M and L are powers of two, so the scaling is exact; extract() returns SI.
#pragma once

#include <string>
#include <vector>

#include "scandyn/algorithm/loops.hpp"
#include "scandyn/model/model.hpp"

namespace scandyn::factor_graph {

// A loop closure between a point of body_a and a point of body_b (body -1: the
// base). Point: the two points have the same acceleration (3 equations). Weld: the
// frames at the two points have the same spatial acceleration (6 equations). Points
// in each body's frame.
struct LoopClosure {
  enum class Type { Point, Weld };
  Type type = Type::Point;
  Index body_a = -1;
  Vec3<double> point_a{0, 0, 0};
  Index body_b = -1;
  Vec3<double> point_b{0, 0, 0};
  int dim() const { return type == Type::Point ? 3 : 6; }
};

// The graph's loop closures of a loop set (a loop file's, or generator_loops' for
// fivebar, fourbar, cloth:K:N): the same bodies, points and types, in file order.
std::vector<LoopClosure> graph_loops(const scandyn::LoopSet& loops);

// The model's units: M the geometric mean of the bodies' masses, L the geometric
// mean of their radii of gyration about the joint origin (sqrt(trace(Ibar) / 2m)),
// over the bodies with mass, each rounded to the nearest power of two; 1 for a
// model without mass.
struct ModelUnits {
  double mass = 1.0;    // kg
  double length = 1.0;  // m
};
ModelUnits model_units(const Model& model);

// A sparse matrix in compressed sparse column form (0-based).
struct SparseMatrix {
  Index rows = 0, cols = 0;
  std::vector<Index> col_ptr;  // (cols + 1)
  std::vector<Index> row_idx;  // (nnz) row of each entry, ascending within a column
  std::vector<double> val;     // (nnz)
};

class DynamicsGraph {
 public:
  // known_qdd (nv): nonzero where the DoF's acceleration is given (its tau is then an
  // unknown); empty means none (forward dynamics). armature (nv; kg m^2 or kg by the
  // joint's type): a joint-space inertia added to M's diagonal (the joint force
  // factor's qdd_i entry); empty: none, and no such entry in the pattern. units:
  // the units to store the system in (powers of two), null: model_units(model).
  // Throws std::invalid_argument on a loop naming a body outside [-1, nv) or joining
  // a body to itself, or on known_qdd / armature of the wrong size.
  // loop_compliance: the loop rows get an entry on their own multipliers,
  // J qdd + w lambda = rhs (w: set_loop_compliance, 0 until set; in the model's
  // units), in the pattern from construction on (the simulator's damped projection
  // steps, scandyn/factor_graph/sparse_constrained_dynamics.hpp).
  DynamicsGraph(const Model& model, std::vector<LoopClosure> loops, std::vector<char> known_qdd,
                std::vector<double> armature = {}, const ModelUnits* units = nullptr, bool loop_compliance = false);
  // w >= 0 for the next assemble() (a graph made with loop_compliance; ignored otherwise).
  void set_loop_compliance(double w) { compliance_ = w; }

  // Writes the values of A and b for one state. qdd_in and tau_in (nv) are read
  // only at the given entries (either may be null when it has none).
  void assemble(const double* q, const double* qd, const double* qdd_in, const double* tau_in);

  // The system, stored transposed: At is (unknowns x equations), one column per
  // equation (the sparse solvers factor At At^T = A^T A without a transpose).
  const SparseMatrix& At() const { return At_; }
  const std::vector<double>& b() const { return b_; }
  Index unknowns() const { return At_.rows; }

  // The units the system is stored in (see "Units" above): unknown_unit (unknowns):
  // the SI size of one unit of each unknown (S); equation_unit (equations): the SI
  // size of one unit of each equation (W^-1), so that (b - A x)_e equation_unit[e]
  // is equation e's residual in SI.
  const ModelUnits& units() const { return units_; }
  const std::vector<double>& unknown_unit() const { return unknown_unit_; }
  const std::vector<double>& equation_unit() const { return equation_unit_; }

  Index var_a(Index i) const { return 14 * i; }
  Index var_f(Index i) const { return 14 * i + 6; }
  Index var_qdd(Index i) const { return 14 * i + 12; }
  Index var_tau(Index i) const { return 14 * i + 13; }
  Index var_lambda(std::size_t k) const { return lambda_offset_[k]; }

  // Elimination orders (permutations of the unknowns: entry k is the k-th
  // eliminated). tree_order: the seed's orders, leaves to root: for inverse
  // dynamics (every qdd given) {qdd, tau, f root->leaves, a leaves->root} (RNEA);
  // otherwise body by body from the last: {tau_i, f_i, a_i, qdd_i} (ABA, and the
  // articulated-body hybrid dynamics); loop multipliers last.
  std::vector<Index> tree_order() const;
  // For a model that is one unbranched chain: the bodies' blocks in the order block
  // cyclic reduction removes them (odd positions of the chain first, then odd
  // positions of what is left, ...), each block as in tree_order; throws
  // std::invalid_argument otherwise.
  std::vector<Index> cyclic_reduction_order() const;

  // Splits a solution x (in the model's units) into qdd, tau (nv each) and lambda
  // (sum of loop dims), in SI; any pointer may be null.
  void extract(const double* x, double* qdd, double* tau, double* lambda) const;

  const Model& model() const { return model_; }
  const std::vector<LoopClosure>& loops() const { return loops_; }

 private:
  const Model& model_;
  std::vector<LoopClosure> loops_;
  std::vector<char> known_qdd_;
  std::vector<double> armature_;  // (nv) or empty
  bool has_compliance_ = false;   // the loop rows' entries on their multipliers are in the pattern
  double compliance_ = 0;         // their value, in the model's units
  std::vector<Index> lambda_offset_;
  ModelUnits units_;
  std::vector<double> unknown_unit_, equation_unit_;
  SparseMatrix At_;
  std::vector<double> b_;
  std::vector<Index> slot_;       // triplet k -> position in At_.val
  std::vector<double> trip_val_;  // triplet values in the fixed assembly order
  void push_body_block(Index i, std::vector<Index>& order) const;
  void write(bool pattern, const double* q, const double* qd, const double* qdd_in,
             const double* tau_in);
  std::vector<Index> trip_row_, trip_col_;  // (pattern pass) equation, unknown of triplet k
};

}  // namespace scandyn::factor_graph
