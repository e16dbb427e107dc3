// scandyn/model/load.hpp: building models from URDF files, generator specs, or a
// raw link/joint description. All three go through one builder and one validator.
#pragma once

#include <cmath>
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

// An orientation as a unit quaternion (x, y, z, w). parse_urdf fills these from
// urdfdom, which stores only quaternions: turning them back into roll-pitch-yaw
// (urdf::Rotation::getRPY) loses up to ~5e-3 rad near pitch = +-pi/2.
struct RawQuat {
  double x = 0, y = 0, z = 0, w = 1;
};

// A link as written in a URDF file.
struct RawLink {
  std::string name;
  bool has_inertial = false;  // false: massless frame (no <inertial> element)
  double mass = 0;            // kg
  Vec3<double> com_xyz{0, 0, 0};  // <inertial><origin xyz>: inertial frame in link frame (m)
  Vec3<double> com_rpy{0, 0, 0};  // <inertial><origin rpy> (rad), ignored when com_has_quat
  bool com_has_quat = false;      // true: the inertial frame's orientation is com_quat
  RawQuat com_quat;
  Sym3<double> inertia{0, 0, 0, 0, 0, 0};  // about the centre of mass, inertial-frame axes (kg m^2)
};

// Spherical: a ball joint (3 DoF); no URDF type maps to it, generators make it.
enum class RawJointType { Revolute, Continuous, Prismatic, Fixed, Floating, Planar, Unknown, Spherical };

// A joint as written in a URDF file.
struct RawJoint {
  std::string name;
  RawJointType type = RawJointType::Unknown;
  std::string type_name;          // the type as written, for error messages
  std::string parent;             // parent link name
  std::string child;              // child link name
  Vec3<double> xyz{0, 0, 0};      // <origin xyz>: child frame in parent frame (m)
  Vec3<double> rpy{0, 0, 0};      // <origin rpy> (rad), ignored when has_quat
  bool has_quat = false;          // true: the origin's orientation is quat
  RawQuat quat;
  Vec3<double> axis{1, 0, 0};     // <axis xyz>, joint frame (URDF default 1 0 0); unused if fixed
  double lower = -HUGE_VAL;       // <limit lower> (rad or m) of a revolute or prismatic joint;
  double upper = HUGE_VAL;        // <limit upper>; -inf / +inf when there is none (continuous)
};

struct RawTree {
  std::string name;    // robot name
  std::string source;  // file path or generator spec, used in error messages
  std::vector<RawLink> links;
  std::vector<RawJoint> joints;
};

// Options for building a model (defaults: every check on).
struct BuildOptions {
  // Require each link's rotational inertia about its centre of mass to be one a rigid
  // body can have: positive definite, principal moments satisfying the triangle
  // inequality. Some published models break this (GRiD's atlas.urdf: links l_lglut,
  // utorso, l_foot, r_foot); set false to load them anyway. Mass > 0, finite numbers
  // and everything structural are checked regardless.
  bool require_physical_inertia = true;
  // When non-null, each inertia check waived by require_physical_inertia = false
  // appends its message (the line ModelError would have had) here.
  std::vector<std::string>* warnings = nullptr;
  // Give the root link a free joint (6 DoF, body 0, joint name "root_joint"): the
  // floating base, as Pinocchio's buildModel(urdf, JointModelFreeFlyer()). The root
  // link and the links fixed to it are body 0. A root link named "world" (the model
  // is bolted to the world through it) or a massless base are a ModelError.
  bool floating_base = false;
};

// Builds and validates a model: DoF order, fixed-joint merging, every check
// listed in docs/models.md (unsupported joint type, cycles, missing links, multiple
// parents or roots, duplicate names, non-positive mass, inertia not positive definite
// or violating the triangle inequality, NaN/Inf, zero axis). A tree whose joints are
// all fixed gives an empty model (nv = 0). Throws ModelError.
Model build_model(const RawTree& tree, const BuildOptions& options = {});

// Parses URDF text (source names the file in error messages). Throws ModelError.
RawTree parse_urdf(const std::string& xml, const std::string& source);

// Reads and builds a URDF file. Throws ModelError (missing file included).
Model load_urdf(const std::string& path, const BuildOptions& options = {});

// The raw tree of a generator spec: chain:N, rope:N, tree:N:SEED, curtain:K:N,
// ballrope:N (the rope:N geometry on spherical joints) (geometry in docs/models.md). N, K >= 1, at most kMaxGeneratedBodies moving bodies.
// Throws ModelError naming the spec when it is malformed.
RawTree generate_tree(const std::string& spec);
// With floating_base, the tree a free model is built from: chain, rope and ballrope
// lose the massless base frame and their first joint (the first link is the floating
// base: N bodies, nv = 6 + (N - 1) joint DoFs); tree:N:SEED's base frame gets a
// random link's mass. build_model(..., floating_base) frees the root.
RawTree generate_tree(const std::string& spec, bool floating_base);
inline constexpr long long kMaxGeneratedBodies = 10000000;

// build_model(generate_tree(spec)). Throws ModelError for a malformed spec.
Model make_generated(const std::string& spec, const BuildOptions& options = {});

// True when spec names a generator (starts with chain:, rope:, tree:, curtain: or ballrope:);
// such a string is never taken as a file path (write ./rope:1.urdf for a file).
bool is_generator_spec(const std::string& spec);

// The directories a model name is looked up in, in order: $SCANDYN_MODELS_DIR when
// set, then the models shipped with scandyn (models/ in the source tree, or
// share/scandyn/models where it is installed): iiwa, hyq and atlas.
std::vector<std::string> model_search_dirs();

// The file a model path denotes. An absolute path is itself. A relative one is
// looked up in first_dirs when given (a scene's directory), else as given from the
// working directory; then in model_search_dirs(), also with ".urdf" appended
// ("iiwa" finds iiwa.urdf). Returns the first regular file found, or (none found)
// the path as first tried, whose loading then reports it missing.
std::string find_model_file(const std::string& path, const std::vector<std::string>& first_dirs = {});

// A generator spec, or a URDF file found by find_model_file.
Model load_model(const std::string& path_or_spec, const BuildOptions& options = {});

}  // namespace scandyn
