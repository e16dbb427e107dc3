// scandyn/algorithm/loops.hpp: closed kinematic loops beside a tree model, and the
// dynamics of the constrained system (serial reference, double, host; Eigen).
//
// A loop closure joins a point of one body to a point of another (or of the base):
//   point  the two points coincide: 3 equations (base-frame components);
//   weld   the frames at the points (the bodies' orientations) coincide: 6 equations,
//          3 angular then 3 linear.
// Loop files (`--loops FILE`, the scene key "loops") are JSON:
//   {"loops": [{"type": "point" | "weld", "link_a": NAME, "point_a": [x, y, z],
//               "link_b": NAME, "point_b": [x, y, z]}, ...]}
// points in each link's frame (m); NAME a moving link of the model or its root link
// (the base). The generators fivebar, fourbar and cloth:K:N carry their loops
// (generator_loops); docs/loops.md.
//
// With the loops' Jacobian J (m x nv, stacked in file order) and gamma = Jdot qd:
//   forward dynamics    M qdd + h = tau + J^T lambda,  J qdd + gamma = 0
//   inverse dynamics    M qdd + h = S_A^T tau_A + J^T lambda for the actuated DoFs A
// Redundant constraints (a planar loop closed by a 3D point constraint has a zero
// row of J; a cloth grid has dependent rows) are normal: qdd is unique, lambda is the
// minimum-norm solution, by a rank-revealing solve (complete orthogonal
// decomposition of J M^-1 J^T, rank threshold kLoopRankTolerance relative to its
// largest pivot).
#pragma once

#include <stdexcept>
#include <string>
#include <vector>

#include "scandyn/algorithm/loop_projection.hpp"
#include "scandyn/algorithm/loop_solver.hpp"
#include "scandyn/algorithm/point_kinematics.hpp"
#include "scandyn/model/model.hpp"

namespace scandyn {

// A loop file or loop that cannot be used: what() names the file, the loop and the key.
class LoopError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

enum class LoopType { Point, Weld };

struct LoopClosure {
  LoopType type = LoopType::Point;
  Index body_a = -1, body_b = -1;  // bodies (DoF index), -1: the base
  Vec3<double> point_a{0, 0, 0};   // in body_a's frame (m)
  Vec3<double> point_b{0, 0, 0};   // in body_b's frame (m)
  std::string link_a, link_b;      // the link names as written
  Index rows() const { return type == LoopType::Point ? 3 : 6; }
};

struct LoopSet {
  std::vector<LoopClosure> loops;
  Index rows() const;  // m: the constraint equations, 3 per point and 6 per weld loop
  bool empty() const { return loops.empty(); }
};

// Relative rank threshold of the loop solves; and the default tolerance on a state's
// loop violation (m and rad of the position residual; m/s and rad/s of J qd).
inline constexpr double kLoopRankTolerance = 1e-10;
inline constexpr double kLoopStateTolerance = 1e-6;

// The loops as the per-instance routines read them (loop_solver.hpp), in scalar S.
template <class S>
std::vector<LoopRow<S>> loop_rows_of(const LoopSet& loops) {
  std::vector<LoopRow<S>> r;
  r.reserve(loops.loops.size());
  for (const LoopClosure& l : loops.loops)
    r.push_back({l.type == LoopType::Weld ? 1 : 0, l.body_a, l.body_b, l.point_a.template cast<S>(),
                 l.point_b.template cast<S>()});
  return r;
}

// Parses a loop file's JSON text for `model` (source names it in messages). Throws
// LoopError for JSON that is not the schema (unknown or missing keys, wrong types,
// points that are not 3 finite numbers), an unknown link, or a loop between a link
// and itself.
LoopSet parse_loops(const std::string& json_text, const std::string& source, const Model& model);
LoopSet load_loops(const std::string& path, const Model& model);
// The loops a generator spec carries: fivebar, fourbar, cloth:K:N; empty for others.
LoopSet generator_loops(const std::string& spec, const Model& model);
// The loop file text of a loop set (pretty JSON, the schema above).
std::string loops_json(const LoopSet& loops);

// Position residual phi(q) (m entries: point a - point b in base coordinates; weld:
// first the rotation vector of R_b R_a^T's small-angle form, 1/2 vee(R_b R_a^T -
// R_a R_b^T)), the Jacobian J (m x nv, row-major) and gamma = Jdot qd (m); any of
// phi, J, gamma may be null.
void loop_kinematics(const Model& model, const LoopSet& loops, const double* q, const double* qd, double* phi,
                     double* J, double* gamma);

// The largest violation of the loops by (q, qd): max over |phi| and |J qd|; loop,
// when not null, receives the index of the loop where it is (-1 without loops).
double loop_violation(const Model& model, const LoopSet& loops, const double* q, const double* qd,
                      Index* loop = nullptr);

// How far qdd is from closing the loops at (q, qd, tau): residual = ||J qdd + gamma||_2,
// with what the iterative solvers measure it against, gamma = ||gamma||_2 and jqdd0 =
// ||J qdd0||_2 (qdd0 = M^-1 (tau - h), the tree's forward dynamics without the loops,
// gravity included), and qdd0 = ||qdd0||_2. O(nv + m) by the tree passes of
// algorithm/loop_iterative.hpp: no J or M formed.
struct LoopAccelerationClosure {
  double residual = 0, gamma = 0, jqdd0 = 0, qdd0 = 0;
};
LoopAccelerationClosure loop_acceleration_closure(const Model& model, const LoopSet& loops, const double* q,
                                                  const double* qd, const double* tau, const double* qdd);

// True for the generator specs that carry loops (fivebar, fourbar, cloth:K:N).
bool generator_has_loops(const std::string& spec);

// Outcome of a constrained solve.
struct LoopSolveInfo {
  Index rank = 0;            // numerical rank of J M^-1 J^T (or of the actuation system)
  double residual = 0;       // max |J qdd + gamma| (forward) or max |M qdd + h - S^T tau - J^T lambda| (inverse)
};

// Forward dynamics with loops: qdd (nv) and lambda (m) with M qdd + h = tau + J^T
// lambda and J qdd + gamma = 0 (gravity included; fext: nv body wrenches or null),
// lambda of minimum norm. Throws LoopError when M is not positive definite.
LoopSolveInfo constrained_forward_dynamics(const Model& model, const LoopSet& loops, const double* q, const double* qd,
                                           const double* tau, double* qdd, double* lambda,
                                           const Force<double>* fext = nullptr);

// Inverse dynamics with loops: for qdd satisfying the loops' J qdd + gamma = 0 and
// the actuated DoFs (actuated[i] != 0), tau (nv; zero at unactuated DoFs) and lambda
// (m) with M qdd + h = tau + J^T lambda; among all solutions the one of minimum
// ||tau_A|| (redundant actuation), then of minimum ||lambda||. When no solution
// exists (too few actuators for this motion) the least-squares one is returned and
// info.residual says by how much the equations fail.
LoopSolveInfo constrained_inverse_dynamics(const Model& model, const LoopSet& loops, const double* q, const double* qd,
                                           const double* qdd, const unsigned char* actuated, double* tau,
                                           double* lambda, const Force<double>* fext = nullptr);

// Moves (q, qd) onto the loops: min |phi(q)|^2 by Levenberg-Marquardt around Gauss-Newton
// (minimum-norm steps; scandyn/algorithm/loop_projection.hpp: from close to the loops
// it is plain Gauss-Newton, from far off globally convergent) until max |phi| <= tol
// or `iterations` linearisations (or a stationary point of |phi|^2), then qd to its
// minimum-norm change with J qd = 0. Returns the final max |phi|; info (may be null):
// also max |J qd| after, the worst row, the linearisations and trials it took.
double project_to_loops(const Model& model, const LoopSet& loops, double* q, double* qd, double tol = 1e-13,
                        int iterations = 50, LoopProjectionInfo* info = nullptr);

}  // namespace scandyn
