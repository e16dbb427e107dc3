// scandyn/sim/simulator.hpp: batched simulation of B instances of one scene, for
// RL rollouts and long-chain simulation.
//
//   scandyn::sim::Scene scene = scandyn::sim::load_scene("scenes/iiwa_rl.json");
//   scandyn::sim::Simulator<float> sim(scene);           // backend, B, dt, ... from the scene
//   for (int t = 0; t < T; ++t) {
//     write torques into tau (nv x B, the backend's memory: sim.on_device())
//     sim.step(tau);                                      // every instance, one dt
//     read / write sim.q(), sim.qd() in place (no copies)
//     sim.reset({3, 17});                                 // instances 3 and 17 restart
//   }
//
// State. q and qd live in the backend's memory, structure of arrays with the
// instance innermost: entry (DoF i, instance b) at q[i * B + b] (BatchView::soa).
// q has nq rows, qd nv (nq = nv for models of 1-DoF joints; a floating base's
// q = [p, quaternion x y z w, joints...], ball joints' quaternions, as the model's
// convention: scandyn/model/model.hpp). Such models step on the configuration
// manifold (integrators.hpp, step_instance_at) on the serial and openmp backends.
// Host memory for the serial and OpenMP backends; device memory for cuda, where the
// state stays resident across steps (no host round trip per step). q()/qd() return
// views of that memory; writes through them change the simulation. On cuda, work
// is queued on the simulator's stream (stream()); a caller touching the state on
// another stream synchronises first (synchronize()).
//
// Step. The scene's integrator (scandyn/sim/integrators.hpp) over the forward
// dynamics with the scene's effects, instantiated for the scene's effect set
// (scandyn/sim/effects.hpp; chosen here, at construction). Two shapes of work:
//   - per instance (many instances): step_instance, the whole step of one instance
//     (effects, forward dynamics, integration) at a time;
//   - per forward dynamics (a few long chains): the effects of every DoF of every
//     instance into tau, the forward-dynamics engine on the whole batch, the
//     integration of every DoF (rk4: four times the first two), with the same
//     per-DoF formulas (euler and rk4; the engines take no armature, so implicit
//     runs per instance where it can).
// Per backend (strategy()):
//   serial  "serial-aba": the instances one after another, step_instance over the
//           reference ABA (scandyn::aba);
//   openmp  "openmp-aba": the same, instances split over the threads by the CPU
//           engines' instance loop (cpu_fallback/instance_loop.hpp); bit-identical
//           to serial. "openmp-engine-parallel": per forward dynamics over the
//           parallel chain forward dynamics (make_forward_dynamics with
//           FdMethod::Parallel, scans across links on all threads), for what
//           choose_fd_method(OpenMP, model, batch, threads) runs by the parallel
//           method (unbranched chains from the base of >= 4096 links with at least
//           kChainFdThreadsPerInstance = 16 threads per instance: with fewer, threads
//           stepping whole instances by the ABA are faster; measured in
//           scandyn/engine.hpp and docs/scenes.md) and
//           euler or rk4 (cpu_fallback/simulator_step.hpp);
//   cuda    models of up to 64 DoF: one fused kernel per step, one thread per
//           instance: step_instance over the articulated-body algorithm
//           (aba_instance), state in registers / per-thread memory (strategy
//           "fused-aba"); beyond 64 DoF: per forward dynamics, over
//           CudaForwardDynamics::compute_async (Auto: the parallel chain forward
//           dynamics for chains, jsi_dense for trees; strategy "engine-parallel" /
//           "engine-jsi_dense"; euler and rk4 only: implicit is a BackendError).
//
// Devices. On the cuda backend the scene's "devices" (Scene::devices; docs/scenes.md)
// shards the batch across devices as the sharded engines do (scandyn/sharded.hpp):
// with more than one device, or one that is not the current one, shard k holds the
// instances shard_range(B, n, k) on devices[k] (its own CUDA backend, state, stream
// and memory; a device named twice holds two shards), and the shards step at once,
// one host thread each (strategy "<shard's>-x<n>"). The state then has no single
// resident view: q(), qd() (and wrenches(), contact_forces() where the scene has
// them) throw BackendError; read_state(), read_contact_forces(), reset(), status()
// (instances numbered as the whole batch's) work as before, and q(k), qd(k), ...
// view shard k's memory on its device. step() takes the torques in host memory then
// (torques_on_device() is false): each shard copies its instances' to its device.
// Errors of a shard begin "device D: ". The serial and openmp backends refuse a
// non-empty device list.
//
// Failures. A forward dynamics whose pivot is not positive and finite leaves that
// instance's state unchanged for the step and is recorded as the engines record a
// failed instance; status() is a BatchStatus of the steps since the last
// clear_status() (on cuda it synchronises): `failed` counts failed instance-steps
// (saturating at the largest Index), first_instance / first_dof / failure name the
// lowest failing instance, failed_dof is null. sim::failure_message words it.
// A step that leaves an instance's state (q or qd) not finite (a diverging
// explicit step, an effect coefficient too large for the precision) is recorded
// the same way, with Failure::NonFinite and the first such DoF; that state is kept
// as computed (the caller decides: the rollout stops there). With closed loops, a
// step whose projection onto the loops leaves the state more than kLoopStateTolerance
// off them (max |phi|, |J qd|) is recorded with Failure::LoopNotClosed (first_dof: the
// worst loop; estimate: the violation) and the instance keeps its state for the step.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include <functional>

#include "scandyn/engine.hpp"
#include "scandyn/sharded.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/sparse_loops.hpp"

namespace scandyn {
namespace sim {

// "" when st is ok; else one line for a simulator's status (the steps' failures),
// e.g. "forward dynamics failed in 12 instance-steps, first in instance 3:
// articulated inertia pivot at DoF 6 is not positive; those instances kept their
// state for those steps", or "the state became non-finite in 1 instance-step, first
// in instance 0: the state at DoF 0 is not finite after the step".
std::string failure_message(const BatchStatus& st);

// Adds one step's failures (a batch's BatchStatus) to a simulator's status: the
// count saturates at the largest Index, the lowest failing instance is kept.
void add_step_failures(BatchStatus& status, const BatchStatus& step);

// A reset with closed loops projects each start onto them by Levenberg-Marquardt around
// Gauss-Newton (scandyn/algorithm/loop_projection.hpp) with at most this many
// linearisations (factorisations of J, dense or sparse), and refuses (SceneError
// naming the instance and its worst loop) a start left more than kLoopStateTolerance
// off its loops; every step projects with at most 10 (tolerance 1e-12), and a step
// left more than kLoopStateTolerance off is a failure of that instance
// (Failure::LoopNotClosed: it keeps its state).
inline constexpr int kResetLinearisations = 100;

// What the simulator's steps read, prepared once from the scene in precision S.
template <class S>
struct SimSetup {
  ModelTpl<S> model;                        // the scene's model; gravity zero without kGravity
  unsigned effects = 0;                     // declared Effect bits
  Integrator integrator = Integrator::Euler;  // effective_integrator(scene's, effects)
  S dt = S(0);
  Index batch = 0;                          // B
  std::vector<JointCoefficients<S>> coef;   // (nv) joint coefficients
  std::vector<S> armature;                  // (nv) dt d + dt^2 k for implicit, else empty
  std::vector<Force<S>> wrenches;           // (nbodies) the constant external wrenches (kExternal), else empty
  bool wrenches_per_step = false;           // (B x nbodies) buffer the caller rewrites
  int threads = 0;                          // OpenMP threads (0: all)
  // contacts (kContacts), else empty
  std::vector<ContactPoint<S>> contact_points;    // (P) points on the bodies
  std::vector<ContactPlane<S>> contact_planes;    // world planes
  std::vector<ContactSphere<S>> contact_spheres;  // world spheres
  ContactLaw<S> contact_law{};

  Index contact_count() const { return static_cast<Index>(contact_points.size()); }  // P
  // the contacts over these host vectors
  ContactSet<S> contact_set() const {
    ContactSet<S> cs;
    cs.points = contact_points.data(), cs.npoints = contact_count();
    cs.planes = contact_planes.data(), cs.nplanes = static_cast<Index>(contact_planes.size());
    cs.spheres = contact_spheres.data(), cs.nspheres = static_cast<Index>(contact_spheres.size());
    cs.law = contact_law;
    cs.obstacles = (contact_planes.empty() ? 0u : unsigned(kPlanes)) | (contact_spheres.empty() ? 0u : unsigned(kSpheres));
    cs.walk_paths = contact_walks_paths(model.bodies.data(), model.nbodies(), cs.points, cs.npoints);
    return cs;
  }
  // prescribed joint motion (scene key "prescribed"): the driven DoFs follow their
  // trajectories exactly, the others respond through the hybrid dynamics (serial
  // and openmp backends; cuda refuses it)
  PrescribedMotion prescribed;
  std::vector<unsigned char> prescribed_mask;  // (nv) 1 at driven DoFs, or empty
  double time = 0;                          // the time at the start of the step being taken
  // closed loops (the scene's): forward dynamics with the loops
  // (constrained_forward_dynamics, double), the state projected onto the loops after
  // every step (project_to_loops); serial and openmp, euler and rk4
  LoopSet loops;
  Model loop_model;                         // the model in double for the loop solves
  // the sparse loop solver's factory (scandyn/sim/sparse_loops.hpp) when the scene's
  // "loop_solver" chose it, else null (the dense solves above); each thread's
  // workspace makes one solver and keeps it, with its symbolic analysis, across steps
  LoopSolverFactory loop_solver = nullptr;
};

namespace detail {

// A simulator backend: the resident state and the step (serial/OpenMP in
// cpu_fallback/simulator_step.cpp, cuda in kernels/simulator_step.cu).
template <class S>
class SimBackend {
 public:
  virtual ~SimBackend() = default;
  virtual void step(const BatchView<const S>& tau) = 0;
  virtual BatchView<S> q() = 0;
  virtual BatchView<S> qd() = 0;
  virtual Force<S>* wrenches() = 0;                // (B x nbodies) per-step wrenches, or null
  virtual ContactReading<S>* contact_forces() = 0;  // (B x P) the last step's contacts, or null
  // copies contact_forces() (B x P) to host memory
  virtual void read_contact_forces(ContactReading<S>* host) = 0;
  // writes the rows (count x nq of q, count x nv of qd, host memory) of the listed instances
  virtual void write_instances(const Index* instances, Index count, const S* q_rows, const S* qd_rows) = 0;
  // copies all of q (nq x B) and qd (nv x B), SoA, to host memory
  virtual void read_state(S* q_host, S* qd_host) = 0;
  virtual BatchStatus status() = 0;  // failed instance-steps since clear_status()
  virtual void clear_status() = 0;
  virtual void synchronize() = 0;
  virtual bool on_device() const = 0;
  virtual std::string strategy() const = 0;
  virtual void* stream() const { return nullptr; }
  // step() with tau (nv x B, any strides, or empty) in host memory: a backend on the
  // device copies it there first (on its stream), the host backends step on it
  virtual void step_host(const BatchView<const S>& tau) { step(tau); }
  // where step() reads tau: the backend's memory, host memory for a sharded backend
  virtual bool tau_on_device() const { return on_device(); }
  // the shards (a backend over several devices); one, this backend, otherwise
  virtual int shard_count() const { return 1; }
  virtual int shard_device(int) const { return -1; }               // its device ordinal, -1 when not sharded
  virtual SimBackend<S>* shard(int) { return this; }                // null for a shard with no instances
};

// Throws BackendError when CUDA is not built or no device is usable.
template <class S>
std::unique_ptr<SimBackend<S>> make_cuda_sim_backend(const SimSetup<S>& setup);

// Makes one shard's backend from its setup (the simulator's, batch its count).
template <class S>
using MakeSimBackend = std::function<std::unique_ptr<SimBackend<S>>(const SimSetup<S>&)>;

// A backend over n = devices.size() shards (src/sim/sharded_sim.cpp): shard k, the
// instances shard_range(setup.batch, n, k), stepped by make(its setup) on ShardPool
// worker k (devices[k] current there when cuda; errors "device D: ..."); every call
// runs on the shards at once. setup outlives it (the shards' setups copy its time
// before each step). With cuda false the shards are host backends (how the CPU tests
// check the routing against one backend over the whole batch).
template <class S>
std::unique_ptr<SimBackend<S>> make_sharded_sim_backend(const SimSetup<S>& setup, std::vector<int> devices, bool cuda,
                                                        const MakeSimBackend<S>& make);

// The shard of n over B instances (shard_range) that holds instance b (0 <= b < B).
inline int shard_of(Index B, int n, Index b) {
  const Index base = B / n, extra = B % n;  // the first `extra` shards hold base + 1
  const Index split = extra * (base + 1);
  return static_cast<int>(b < split ? b / (base + 1) : extra + (b - split) / base);
}

// The statuses of the shards of n over B instances (statuses[k] shard k's, its
// instances numbered from 0) as one status over the whole batch (add_step_failures).
BatchStatus merge_shard_statuses(const std::vector<BatchStatus>& statuses, Index B);

}  // namespace detail

template <class S>
class Simulator {
 public:
  // Prepares the scene in precision S (whatever the scene's "precision" says: that
  // field tells the command line which S to use) on the scene's backend, or on
  // `backend` when given, and puts every instance in its initial state. Throws
  // BackendError (backend not built, no device, no memory, a combination the
  // backend does not run); std::invalid_argument for an initial state whose sizes
  // are not the model's (q: nq, the others nv; a Scene made in code).
  explicit Simulator(const Scene& scene);
  Simulator(const Scene& scene, BackendKind backend);
  ~Simulator();
  Simulator(const Simulator&) = delete;
  Simulator& operator=(const Simulator&) = delete;

  // Advances every instance by dt under the joint torques tau (nv x B view in the
  // backend's memory, host memory when sharded across devices: torques_on_device();
  // any strides; an empty view, data == nullptr, means zero torques). Allocates
  // nothing (sharded: its staging, once); on cuda, queues the work and returns.
  void step(const BatchView<const S>& tau = {});
  bool torques_on_device() const { return backend_->tau_on_device(); }

  // Puts the listed instances back in the scene's initial state (randomised ones
  // draw again, continuing the scene's seeded generator). Throws std::out_of_range
  // for an index outside [0, B). With closed loops, each start is projected onto
  // them (kResetLinearisations); a start that cannot be closed is a SceneError naming
  // the instance, and then no instance is written and the generator is as before.
  void reset(const std::vector<Index>& instances);
  void reset_all();

  BatchView<S> q() { return backend_->q(); }    // (nq x B) joint positions, resident
  BatchView<S> qd() { return backend_->qd(); }  // (nv x B) joint velocities, resident

  // The shards of a simulator across devices ("Devices" above): shards() of them,
  // shard k holding the instances shard_range(k) on device shard_device(k); q(k)
  // (nq x its count), qd(k), wrenches(k), contact_forces(k) and stream(k) as the
  // accessors without k, in that device's memory (make it current before using
  // them). Not sharded: one shard, the whole batch, shard_device -1. Throws
  // std::out_of_range for k outside [0, shards()).
  int shards() const { return backend_->shard_count(); }
  ShardRange shard_range(int k) const { return scandyn::shard_range(batch(), shards(), checked_shard(k)); }
  int shard_device(int k) const { return backend_->shard_device(checked_shard(k)); }
  BatchView<S> q(int k);
  BatchView<S> qd(int k);
  Force<S>* wrenches(int k);
  ContactReading<S>* contact_forces(int k);
  void* stream(int k) const;
  // (B x nbodies) external wrenches, wrench[b * nbodies + i] on body i of instance b, in the
  // backend's memory, read by every step: with "external": {"per_step": true}
  // (initialised to the scene's constant wrenches); null otherwise.
  Force<S>* wrenches() { return backend_->wrenches(); }

  // With contacts (effects.contacts): the contacts of the last step, (B x P) in
  // the backend's memory, entry [b * P + k] for point k (setup().contact_points) of
  // instance b: the total contact force on the point (world frame), its largest
  // penetration and whether an obstacle pushes on it, at the state the step
  // started from (rk4: its first stage); zeros before the first step. Null without
  // contacts. On cuda, synchronise() before reading it from another stream.
  ContactReading<S>* contact_forces() { return backend_->contact_forces(); }
  Index contact_count() const { return setup_.contact_count(); }  // P
  // Copies contact_forces() to host memory (B x P); synchronises on cuda.
  void read_contact_forces(ContactReading<S>* host) { backend_->read_contact_forces(host); }

  // Copies the state to host memory (q: nq x B, qd: nv x B, SoA); synchronises on cuda.
  void read_state(S* q_host, S* qd_host) { backend_->read_state(q_host, qd_host); }
  // Mechanical energy of every instance (B values, computed in double on the host
  // from a copy of the state): kinetic 1/2 sum v_i . I_i v_i, plus the potential of
  // gravity (-sum m_i g . c_i, c_i the centre of mass of body i in the base frame;
  // when gravity is declared), of the declared springs and violated limits
  // (joint_effect_energy) and of the contacts' springs (contact_energy_at: 1/2 k d^2
  // per touching pair). External wrenches and damping are not potentials.
  std::vector<double> energy();

  // the forward-dynamics failures since the last clear_status(): `failed` counts
  // instance-steps (see "Failures" above); failure_message(status()) words them
  BatchStatus status() { return backend_->status(); }
  void clear_status() { backend_->clear_status(); }
  void synchronize() { backend_->synchronize(); }

  bool on_device() const { return backend_->on_device(); }
  // "serial-aba", "openmp-aba", "openmp-engine-parallel" (openmp, a few long
  // chains), "fused-aba" (cuda, thread per instance) or "engine-parallel" /
  // "engine-jsi_dense" (cuda, beyond 64 DoF: chains / trees)
  std::string strategy() const { return backend_->strategy(); }
  void* stream() const { return backend_->stream(); }  // cudaStream_t on cuda, else null

  const SimSetup<S>& setup() const { return setup_; }
  Index batch() const { return setup_.batch; }
  Index nv() const { return setup_.model.nv(); }
  Index nq() const { return setup_.model.nq(); }  // rows of q (> nv with quaternions)
  double time() const { return time_; }        // steps taken since construction, times dt
  long long steps() const { return steps_; }

 private:
  SimSetup<S> setup_;
  InitialState initial_;  // the scene's (the scene itself is not kept: a rope's model is large)
  std::unique_ptr<detail::SimBackend<S>> backend_;
  int checked_shard(int k) const;                        // k, or std::out_of_range
  detail::SimBackend<S>* shard_backend(int k) const;      // shard k's, null when it holds no instances
  // the initial-state generator (std::mt19937_64 state, kept opaque here)
  struct Random;
  std::unique_ptr<Random> random_;
  void reset_manifold(const std::vector<Index>& instances);  // reset with quaternion positions
  std::vector<S> q_rows_, qd_rows_;  // reset scratch
  double time_ = 0;
  long long steps_ = 0;
};

// Mechanical energy of one state (see Simulator::energy): model in double, its
// gravity used when effects has kGravity; coef (nv) for springs and limits.
// q has nq entries (the world frame for a floating base; springs and limits of
// 1-DoF joints only).
double mechanical_energy(const Model& model, unsigned effects, const JointCoefficients<double>* coef,
                         const double* q, const double* qd);

}  // namespace sim
}  // namespace scandyn
