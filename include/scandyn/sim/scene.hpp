// scandyn/sim/scene.hpp: a simulation scene, read from a JSON file.
//
// A scene names the model, the effects present (and their coefficients), the
// integrator, dt, precision, backend, the number of instances and the initial
// state. The format, every key and every check: docs/scenes.md. Every error is a
// SceneError whose what() is one line naming the file and the key, e.g.
//   scenes/x.json: effects.damping: expected a non-negative number or an array of 7 numbers, got -1
// Unknown keys are errors too.
#pragma once

#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

#include "scandyn/engine.hpp"
#include "scandyn/model/model.hpp"
#include "scandyn/sim/contacts.hpp"
#include "scandyn/sim/effects.hpp"
#include "scandyn/sim/integrators.hpp"
#include "scandyn/sim/prescribed.hpp"
#include "scandyn/algorithm/loops.hpp"

namespace scandyn {
namespace sim {

// A scene file that cannot be read or is not valid.
class SceneError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};


// One constant external wrench.
struct SceneWrench {
  Index body;             // the body (DoF index) it acts on
  Force<double> wrench;   // [moment; force] in the body's frame about its origin (N m, N)
};

// The contact effect as declared (effects.contacts; docs/scenes.md): the points
// (those listed, then one at every link origin for all_links, in DoF order), the
// obstacles and the law.
struct SceneContacts {
  std::vector<ContactPoint<double>> points;
  std::vector<ContactPlane<double>> planes;
  std::vector<ContactSphere<double>> spheres;
  ContactLaw<double> law{0, 0, 0, 1e-3};
};

// How instances start (and restart after reset()).
struct InitialState {
  std::vector<double> q;      // (nq) joint positions (unit quaternions where the model has them)
  std::vector<double> qd;     // (nv) joint velocities
  // randomised: each reset draws q_i + U(-q_spread_i, q_spread_i), qd_i + U(-qd_spread_i,
  // qd_spread_i) from one std::mt19937_64 seeded once with seed (docs/scenes.md gives the order);
  // with quaternion positions q = initial.q ⊕ delta, delta_i ~ U(-q_spread_i, q_spread_i) (nv)
  bool random = false;
  std::uint64_t seed = 0;
  std::vector<double> q_spread;   // (nv) half-widths, >= 0
  std::vector<double> qd_spread;  // (nv)
};

struct Scene {
  std::string path;        // the file it was read from ("" when parsed from text)
  std::string model_spec;  // "model" as written
  std::string model_path;  // the generator spec, or the URDF file it resolved to
  Model model;             // the loaded model; gravity as declared (zero without the gravity effect)

  unsigned effects = 0;    // Effect bits of the declared effects
  // per-DoF coefficients of the joint effects (nv entries; zero / +-inf for undeclared)
  std::vector<JointCoefficients<double>> joints;
  std::vector<SceneWrench> wrenches;  // external: constant wrenches (one per listed body)
  bool wrenches_per_step = false;     // external: the caller may rewrite them before each step
  SceneContacts contacts;             // contacts: points, obstacles, law (empty without the effect)

  Integrator integrator = Integrator::Euler;
  double dt = 1e-3;                   // time step (s)
  Precision precision = Precision::Double;
  BackendKind backend = BackendKind::Serial;  // "auto": resolved when the scene is read (auto_backend)
  bool backend_auto = false;          // the scene said "backend": "auto"
  std::string backend_note;           // auto: why not cuda (auto_backend's why), "" when cuda was chosen
  int threads = 0;                    // OpenMP threads, 0: all
  // cuda: the devices the batch is sharded across ("devices"; Simulator's "Devices"),
  // empty: the current device only. A scene whose backend "auto" chose another keeps none.
  std::vector<int> devices;
  Index instances = 1;                // B
  InitialState initial;
  PrescribedMotion prescribed;        // driven DoFs and their trajectories ("prescribed"), or empty
  LoopSet loops;                      // closed loops: the generator's and the scene's "loops"
  // the closed loops' solver ("loop_solver"): "dense" (constrained_forward_dynamics,
  // project_to_loops), "sparse" (the registered sparse solver, scandyn/sim/sparse_loops.hpp),
  // "iterative" (matrix-free conjugate gradients, scandyn/sim/iterative_loops.hpp),
  // "iterative-cuda" (the same on a CUDA device, scandyn/cuda/loop_iterative.hpp: the
  // step on the serial or openmp backend, its loop solves on the GPU; docs/scenes.md) or
  // "auto" (sparse from kSparseLoopDofs DoFs on, when registered; docs/loops.md)
  std::string loop_solver = "auto";
  // the iterative solver's preconditioner ("loop_preconditioner": "block-jacobi",
  // "symmetric-gauss-seidel", "ssor", "block-tridiagonal", "block-dilu" or "none";
  // sim::LoopPreconditioner); empty: IterativeLoopOptions' default
  std::string loop_preconditioner;

  Index nv() const { return model.nv(); }
  Index nq() const { return model.nq(); }  // rows of q (> nv with a floating base or ball joints)
};

// The backend "backend": "auto" stands for on this machine: cuda when it is built
// and a device is usable (backend_unusable(Cuda) is ""), else openmp (serial in a
// build without OpenMP). why, when not null, gets "" for cuda, else the reasons,
// e.g. "cuda: no usable CUDA device: ...".
BackendKind auto_backend(std::string* why = nullptr);

// The line a program prints for a scene whose backend was "auto", e.g.
// "scene backend auto: openmp (cuda: no usable CUDA device: ...)"; "" otherwise.
std::string backend_choice(const Scene& scene);

// Reads and validates a scene file. Relative model paths are looked up, in order, in
// the scene file's directory, then in model_search_dirs() ($SCANDYN_MODELS_DIR,
// then the shipped models; find_model_file, scandyn/model/load.hpp). Throws
// SceneError (also for model errors, with the model's message after "model: ").
Scene load_scene(const std::string& path);

// The same for JSON text; source names it in error messages; base_dir is where
// relative model paths start.
Scene parse_scene(const std::string& json_text, const std::string& source, const std::string& base_dir = ".");

}  // namespace sim
}  // namespace scandyn
