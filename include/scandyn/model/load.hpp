// scandyn/model/load.hpp: building models from URDF files, generator specs, or a
// raw link/joint description. All three go through one builder and one validator.
#pragma once

#include <stdexcept>
#include <string>
#include <vector>

#include "scandyn/model/model.hpp"

namespace scandyn {

// Thrown for any invalid model input. what() is one line that names the source
// (file path or generator spec) and the offending link or joint.
class ModelError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// A link as written in a URDF file.
struct RawLink {
  std::string name;
  bool has_inertial = false;  // false: massless frame (no <inertial> element)
  double mass = 0;            // kg
  Vec3<double> com_xyz{0, 0, 0};  // <inertial><origin xyz>: inertial frame in link frame (m)
  Vec3<double> com_rpy{0, 0, 0};  // <inertial><origin rpy> (rad)
  Sym3<double> inertia{0, 0, 0, 0, 0, 0};  // about the centre of mass, inertial-frame axes (kg m^2)
};

enum class RawJointType { Revolute, Continuous, Prismatic, Fixed, Floating, Planar, Unknown };

// A joint as written in a URDF file.
struct RawJoint {
  std::string name;
  RawJointType type = RawJointType::Unknown;
  std::string type_name;          // the type as written, for error messages
  std::string parent;             // parent link name
  std::string child;              // child link name
  Vec3<double> xyz{0, 0, 0};      // <origin xyz>: child frame in parent frame (m)
  Vec3<double> rpy{0, 0, 0};      // <origin rpy> (rad)
  Vec3<double> axis{1, 0, 0};     // <axis xyz>, joint frame (URDF default 1 0 0)
};

struct RawTree {
  std::string name;    // robot name
  std::string source;  // file path or generator spec, used in error messages
  std::vector<RawLink> links;
  std::vector<RawJoint> joints;
};

// Builds and validates a model: DoF order, fixed-joint merging, every check
// listed in the README (unknown joint type, cycles, missing links, multiple
// parents or roots, non-positive mass, inertia not positive definite or violating
// the triangle inequality, NaN/Inf, zero axis). Throws ModelError.
Model build_model(const RawTree& tree);

// Parses URDF text (source names the file in error messages). Throws ModelError.
RawTree parse_urdf(const std::string& xml, const std::string& source);

// Reads and builds a URDF file. Throws ModelError (missing file included).
Model load_urdf(const std::string& path);

// Builds a generator spec: chain:N, rope:N, tree:N:SEED, curtain:K:N.
// Throws ModelError for a malformed spec.
Model make_generated(const std::string& spec);

// True when spec names a generator (chain:, rope:, tree:, curtain:).
bool is_generator_spec(const std::string& spec);

// A URDF path or a generator spec.
Model load_model(const std::string& path_or_spec);

}  // namespace scandyn
