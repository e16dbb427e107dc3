// scandyn/sim/prescribed.hpp: prescribed joint motion in the simulator (a scene's
// "prescribed" key, docs/scenes.md): driven DoFs follow a given q(t) exactly, the
// others respond through the hybrid dynamics (scandyn::hybrid_dynamics).
#pragma once

#include <string>
#include <vector>

#include "scandyn/model/model.hpp"

namespace scandyn {
namespace sim {

// One driven DoF's trajectory: position, velocity and acceleration at any time.
struct JointTrajectory {
  enum class Kind { Sine, Table };
  Kind kind = Kind::Sine;
  // Sine: q(t) = offset + amplitude sin(2 pi frequency t + phase) (rad or m, Hz, rad)
  double amplitude = 0, frequency = 0, phase = 0, offset = 0;
  // Table: the clamped cubic spline through the knots (t[k], q[k]) (t strictly
  // increasing, at least 2 knots) with zero velocity at the first and the last; m
  // holds its second derivatives at the knots. Before t[0] and after the last knot
  // the joint holds the end position (velocity and acceleration zero): q, qd are
  // continuous everywhere.
  std::vector<double> t, q, m;

  // q, qd, qdd at time `time`.
  void eval(double time, double& q_out, double& qd_out, double& qdd_out) const;
};

// A sine trajectory.
JointTrajectory sine_trajectory(double amplitude, double frequency, double phase, double offset);
// A table trajectory through the knots (builds the spline). Throws
// std::invalid_argument for fewer than 2 knots, sizes that differ, times that do
// not increase strictly, or values that are not finite.
JointTrajectory table_trajectory(std::vector<double> t, std::vector<double> q);

// The driven DoFs of a scene and their trajectories.
struct PrescribedMotion {
  std::vector<Index> dofs;                  // driven DoFs, in the order the scene lists them
  std::vector<JointTrajectory> trajectory;  // (dofs.size()) the trajectory of each

  bool empty() const { return dofs.empty(); }
  // (nv) 1 at driven DoFs: hybrid_dynamics's prescribed mask
  std::vector<unsigned char> mask(Index nv) const;
};

}  // namespace sim
}  // namespace scandyn
