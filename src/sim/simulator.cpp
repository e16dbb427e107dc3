// src/sim/simulator.cpp: the Simulator front end: the setup from a scene, the
// choice of backend, resets, energy, the status's wording. The steps are the
// backends': serial and OpenMP in cpu_fallback/simulator_step.cpp, cuda in
// kernels/simulator_step.cu.
#include "scandyn/sim/simulator.hpp"

#include <algorithm>
#include <limits>
#include <random>
#include <stdexcept>

#include "../../cpu_fallback/simulator_step.hpp"
#include "scandyn/algorithm/configuration.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/sharded.hpp"
#include "scandyn/cuda/loop_iterative.hpp"
#include "scandyn/sim/iterative_loops.hpp"
#include "scandyn/sim/variational_instance.hpp"

namespace scandyn {
namespace sim {


std::string failure_message(const BatchStatus& st) {
  if (st.ok()) return "";
  const std::string steps = std::to_string(st.failed) + " instance-step" + (st.failed > 1 ? "s" : "") +
                            ", first in instance " + std::to_string(st.first_instance) + ": " + st.reason();
  if (st.failure == Failure::NonFinite) return "the state became non-finite in " + steps;
  if (st.failure == Failure::LoopNotClosed)
    return "the step's projection onto the closed loops failed in " + steps +
           "; those instances kept their state for those steps";
  if (st.failure == Failure::NotConverged)
    return "the variational step failed in " + steps + "; those instances kept their state for those steps";
  return "forward dynamics failed in " + steps + "; those instances kept their state for those steps";
}

void add_step_failures(BatchStatus& status, const BatchStatus& step) {
  BatchStatus add = step;
  add.failed = std::min(step.failed, std::numeric_limits<Index>::max() - status.failed);
  add.fell_back = 0;
  status.merge(add);
  status.failed_dof = nullptr;
}

double mechanical_energy(const Model& model, unsigned effects, const JointCoefficients<double>* coef,
                         const double* q, const double* qd) {
  if (model.multi_dof()) {  // quaternion positions: the general kinematics, the world frame
    const Index nb = model.nbodies();
    std::vector<Transform<double>> X(static_cast<std::size_t>(nb));  // body <- world
    std::vector<Motion<double>> v(static_cast<std::size_t>(nb));     // body velocities, body frames
    contact_kinematics_at(model.bodies.data(), nb, q, qd, X.data(), v.data());
    double kinetic = 0, potential = 0;
    for (Index i = 0; i < nb; ++i) {
      const Body<double>& b = model.bodies[i];
      kinetic += 0.5 * dot(v[i], b.I * v[i]);
      if (effects & kGravity) {
        const Vec3<double> c = (1.0 / b.I.m) * b.I.h;
        potential -= b.I.m * dot(model.gravity, mul_transpose(X[i].E, c) + X[i].r);
      }
      // springs and limits act on 1-DoF joints only (the scene refuses them elsewhere)
      if (coef && joint_nv(b.type) == 1) potential += joint_effect_energy(effects, coef[b.idx_v], q[b.idx_q]);
    }
    return kinetic + potential;
  }
  const Index n = model.nv();
  std::vector<Transform<double>> X(static_cast<std::size_t>(n));  // body <- base
  std::vector<Motion<double>> v(static_cast<std::size_t>(n));     // body velocities, body frames
  double kinetic = 0, potential = 0;
  for (Index i = 0; i < n; ++i) {
    const Body<double>& b = model.bodies[i];
    const Transform<double> Xup = joint_transform(b, q[i]);
    X[i] = b.parent < 0 ? Xup : Xup * X[b.parent];
    v[i] = add_joint_motion(b, b.parent < 0 ? Xup.apply(Motion<double>::zero()) : Xup.apply(v[b.parent]), qd[i]);
    kinetic += 0.5 * dot(v[i], b.I * v[i]);
    if (effects & kGravity) {
      const Vec3<double> c = (1.0 / b.I.m) * b.I.h;            // centre of mass, body frame
      const Vec3<double> p = mul_transpose(X[i].E, c) + X[i].r;  // in the base frame
      potential -= b.I.m * dot(model.gravity, p);
    }
    if (coef) potential += joint_effect_energy(effects, coef[i], q[i]);
  }
  return kinetic + potential;
}

namespace detail {

#if !SCANDYN_HAS_CUDA
template <class S>
std::unique_ptr<SimBackend<S>> make_cuda_sim_backend(const SimSetup<S>&) {
  throw BackendError("backend 'cuda' is not available in this build");
}
#endif

}  // namespace detail

// ---- the front end ------------------------------------------------------------------

// The initial-state generator: std::mt19937_64 through the same mapping as the
// tree generator's (the standard distributions differ between libraries).
template <class S>
struct Simulator<S>::Random {
  explicit Random(std::uint64_t seed) : g(seed) {}
  std::mt19937_64 g;
  double uniform(double a, double b) { return a + (b - a) * (static_cast<double>(g() >> 11) * 0x1.0p-53); }
};

template <class S>
Simulator<S>::Simulator(const Scene& scene) : Simulator(scene, scene.backend) {}

template <class S>
Simulator<S>::Simulator(const Scene& scene, BackendKind backend) : initial_(scene.initial) {
  const Index nv = scene.nv();
  // a Scene made in code: the initial state's sizes (parse_scene checks them by key)
  auto check_size = [&](const std::vector<double>& v, Index n, const char* key, const char* what, bool optional) {
    if ((optional && v.empty()) || static_cast<Index>(v.size()) == n) return;
    throw std::invalid_argument(std::string("Simulator: the scene's ") + key + " has " + std::to_string(v.size()) +
                                " entries, the model takes " + std::to_string(n) + " (" + what + ")");
  };
  check_size(scene.initial.q, scene.nq(), "initial.q", "nq", false);
  check_size(scene.initial.qd, nv, "initial.qd", "nv", false);
  check_size(scene.initial.q_spread, nv, "initial.random.q", "nv", !scene.initial.random);
  check_size(scene.initial.qd_spread, nv, "initial.random.qd", "nv", !scene.initial.random);
  if (!scene.devices.empty() && backend != BackendKind::Cuda)
    throw BackendError("devices " + devices_string(scene.devices) + ": only the cuda backend runs on devices (backend '" +
                       to_string(backend) + "')");
  if (scene.model.multi_dof()) {
    // the scene refuses these first; a Scene made in code meets the same refusals
    const std::string joint = printable(first_multi_dof_joint(scene.model));
    if (!scene.loops.empty())
      throw BackendError("closed loops take models of 1-DoF joints only (joint '" + joint + "')");
    if (!scene.prescribed.empty())
      throw BackendError("prescribed joint motion takes models of 1-DoF joints only (joint '" + joint + "')");
  }
  if (scene.integrator == Integrator::Variational) {
    // scandyn/sim/variational.hpp: per instance, dense Newton (cuda: up to 64 DoFs), smooth forces
    const std::string vi = "the variational integrator";
    if (backend == BackendKind::Cuda && nv > kVariationalCudaMaxDofs)
      throw BackendError(variational_cuda_refusal(scene.model.name, nv));
    if (scene.model.multi_dof())
      throw BackendError(vi + " takes models of 1-DoF joints only (joint '" +
                         printable(first_multi_dof_joint(scene.model)) + "')");
    if (scene.effects & kContacts)
      throw BackendError(vi + " does not take the contacts effect (its force switches with the contact set)");
    if (!scene.loops.empty()) throw BackendError(vi + " does not take closed loops");
    if (!scene.prescribed.empty()) throw BackendError(vi + " does not take prescribed joint motion");
  }
  setup_.model = scene.model.template cast<S>();
  setup_.effects = scene.effects;
  setup_.integrator = effective_integrator(scene.integrator, scene.effects);
  setup_.dt = S(scene.dt);
  setup_.batch = scene.instances;
  setup_.coef.resize(static_cast<std::size_t>(nv));
  for (Index i = 0; i < nv; ++i) {
    const JointCoefficients<double>& c = scene.joints[i];
    setup_.coef[i] = {S(c.damping), S(c.stiffness), S(c.rest), S(c.lower), S(c.upper), S(c.limit_stiffness),
                      S(c.limit_damping)};
  }
  if (setup_.integrator == Integrator::Implicit) {
    setup_.armature.resize(static_cast<std::size_t>(nv));
    for (Index i = 0; i < nv; ++i)
      setup_.armature[i] = S(scene.effects & kDamping ? scene.dt * scene.joints[i].damping : 0.0) +
                           S(scene.effects & kSprings ? scene.dt * scene.dt * scene.joints[i].stiffness : 0.0);
  }
  if (scene.effects & kExternal) {
    setup_.wrenches.assign(static_cast<std::size_t>(scene.model.nbodies()), Force<S>::zero());
    for (const SceneWrench& w : scene.wrenches) setup_.wrenches[w.body] += w.wrench.template cast<S>();
    setup_.wrenches_per_step = scene.wrenches_per_step;
  }
  if (scene.effects & kContacts) {
    const SceneContacts& c = scene.contacts;
    for (const ContactPoint<double>& p : c.points)
      setup_.contact_points.push_back({p.body, p.position.template cast<S>(), S(p.radius)});
    for (const ContactPlane<double>& p : c.planes) setup_.contact_planes.push_back({p.normal.template cast<S>(), S(p.offset)});
    for (const ContactSphere<double>& p : c.spheres)
      setup_.contact_spheres.push_back({p.center.template cast<S>(), S(p.radius)});
    setup_.contact_law = {S(c.law.stiffness), S(c.law.damping), S(c.law.friction), S(c.law.creep_speed)};
  }
  setup_.threads = scene.threads;
  if (!scene.loops.empty()) {
    if (backend == BackendKind::Cuda)
      throw BackendError("backend 'cuda': closed loops (the scene's \"loops\") run on the serial and openmp backends only");
    if (setup_.integrator == Integrator::Implicit)
      throw BackendError("closed loops step with euler or rk4, not implicit");
    if (!scene.prescribed.empty()) throw BackendError("a scene cannot have both closed loops and prescribed joints");
    setup_.loops = scene.loops;
    setup_.loop_model = scene.model;
    // the loops' solver: dense, the registered sparse one (scandyn/sim/sparse_loops.hpp) or
    // the iterative one (scandyn/sim/iterative_loops.hpp)
    const bool wrenches = (setup_.effects & (kContacts | kExternal)) != 0;
    const LoopSolverFactory iterative = scene.loop_preconditioner.empty()
                                            ? &make_iterative_loop_solver
                                            : iterative_loop_solver_factory(parse_loop_preconditioner(scene.loop_preconditioner));
    if (scene.loop_solver == "sparse") {
      if (!sparse_loop_solver())
        throw BackendError("\"loop_solver\": \"sparse\": this program has no sparse loop solver (it is the "
                           "factor graph's, CHOLMOD: link scandyn_factor_graph and call "
                           "factor_graph::register_sparse_loop_solver())");
      if (wrenches)
        throw BackendError("\"loop_solver\": \"sparse\" takes no contacts or external wrenches (the dense "
                           "solver does)");
      setup_.loop_solver = sparse_loop_solver();
    } else if (scene.loop_solver == "iterative") {
      if (wrenches)
        throw BackendError("\"loop_solver\": \"iterative\" takes no contacts or external wrenches (the dense "
                           "solver does)");
      setup_.loop_solver = iterative;  // the core library's (scandyn/sim/iterative_loops.hpp)
    } else if (scene.loop_solver == "iterative-cuda") {
      // the iterative solver's forward dynamics and projection on a CUDA device
      // (scandyn/cuda/loop_iterative.hpp), the step itself on this (serial or openmp) backend
      if (wrenches)
        throw BackendError("\"loop_solver\": \"iterative-cuda\" takes no contacts or external wrenches (the dense "
                           "solver does)");
      const LoopPreconditioner p = scene.loop_preconditioner.empty() ? LoopPreconditioner::BlockJacobi
                                                                     : parse_loop_preconditioner(scene.loop_preconditioner);
      const std::string why = cuda::cuda_iterative_loop_refusal(scene.model, scene.loops, p);
      if (!why.empty()) throw BackendError(why);
#if SCANDYN_HAS_CUDA
      setup_.loop_solver = cuda::cuda_iterative_loop_solver_factory(p);
#endif
    } else if (scene.loop_solver == "auto" && nv >= kSparseLoopDofs && !wrenches) {
      // the registered sparse solver, else the iterative one (docs/loops.md, "Choosing it")
      setup_.loop_solver = sparse_loop_solver() ? sparse_loop_solver() : iterative;
    }
  }
  if (!scene.prescribed.empty()) {
    if (backend == BackendKind::Cuda)
      throw BackendError("backend 'cuda': prescribed joint motion (the scene's \"prescribed\") runs on the serial and "
                         "openmp backends only");
    setup_.prescribed = scene.prescribed;
    setup_.prescribed_mask = scene.prescribed.mask(nv);
  }
  if (backend != BackendKind::Cuda) backend_ = cpu::make_simulator_step(setup_, backend);
  else if (spans_devices(scene.devices))
    backend_ = detail::make_sharded_sim_backend<S>(setup_, scene.devices, true, &detail::make_cuda_sim_backend<S>);
  else backend_ = detail::make_cuda_sim_backend(setup_);
  random_ = std::make_unique<Random>(initial_.seed);
  reset_all();
}

template <class S>
Simulator<S>::~Simulator() = default;

template <class S>
int Simulator<S>::checked_shard(int k) const {
  if (k < 0 || k >= shards())
    throw std::out_of_range("Simulator: shard " + std::to_string(k) + " is outside [0, " + std::to_string(shards()) + ")");
  return k;
}

template <class S>
detail::SimBackend<S>* Simulator<S>::shard_backend(int k) const {
  return backend_->shard(checked_shard(k));
}

template <class S>
BatchView<S> Simulator<S>::q(int k) {
  detail::SimBackend<S>* b = shard_backend(k);
  return b ? b->q() : BatchView<S>{};
}
template <class S>
BatchView<S> Simulator<S>::qd(int k) {
  detail::SimBackend<S>* b = shard_backend(k);
  return b ? b->qd() : BatchView<S>{};
}
template <class S>
Force<S>* Simulator<S>::wrenches(int k) {
  detail::SimBackend<S>* b = shard_backend(k);
  return b ? b->wrenches() : nullptr;
}
template <class S>
ContactReading<S>* Simulator<S>::contact_forces(int k) {
  detail::SimBackend<S>* b = shard_backend(k);
  return b ? b->contact_forces() : nullptr;
}
template <class S>
void* Simulator<S>::stream(int k) const {
  detail::SimBackend<S>* b = shard_backend(k);
  return b ? b->stream() : nullptr;
}

template <class S>
void Simulator<S>::step(const BatchView<const S>& tau) {
  setup_.time = time_;
  backend_->step(tau);
  ++steps_;
  time_ = static_cast<double>(steps_) * static_cast<double>(setup_.dt);
}

template <class S>
void Simulator<S>::reset(const std::vector<Index>& instances) {
  const Index n = nv(), B = batch();
  for (Index b : instances)
    if (b < 0 || b >= B)
      throw std::out_of_range("Simulator::reset: instance " + std::to_string(b) + " is outside [0, " +
                              std::to_string(B) + ")");
  if (setup_.model.multi_dof()) return reset_manifold(instances);
  // with closed loops every instance's row is drawn and projected first, and written
  // only when all of them closed: a refused start leaves every instance's state (and
  // the generator) as it was
  const bool loops = !setup_.loops.empty();
  const Random saved = loops ? *random_ : Random(0);
  std::unique_ptr<LoopSolver> reset_loops;  // closed loops on the sparse path
  // in chunks, so a reset of 10^7 instances needs no 10^7-row buffer (with loops: one
  // chunk)
  const Index chunk = loops ? std::max<Index>(1, static_cast<Index>(instances.size()))
                            : std::max<Index>(1, std::min<Index>(B, (1 << 20) / std::max<Index>(1, n)));
  for (std::size_t start = 0; start < instances.size(); start += static_cast<std::size_t>(chunk)) {
    const Index count = static_cast<Index>(std::min<std::size_t>(chunk, instances.size() - start));
    q_rows_.resize(static_cast<std::size_t>(count) * n);
    qd_rows_.resize(static_cast<std::size_t>(count) * n);
    for (Index k = 0; k < count; ++k) {
      // per instance: all q draws, then all qd draws
      for (Index i = 0; i < n; ++i)
        q_rows_[k * n + i] = S(initial_.random ? initial_.q[i] + random_->uniform(-initial_.q_spread[i], initial_.q_spread[i])
                                              : initial_.q[i]);
      for (Index i = 0; i < n; ++i)
        qd_rows_[k * n + i] = S(initial_.random ? initial_.qd[i] + random_->uniform(-initial_.qd_spread[i], initial_.qd_spread[i])
                                               : initial_.qd[i]);
      // with closed loops, the state is projected onto them: Levenberg-Marquardt around
      // Gauss-Newton (scandyn/algorithm/loop_projection.hpp) to max |phi| <= 1e-13, at
      // most kResetLinearisations factorisations
      if (loops) {
        std::vector<double> lq(q_rows_.begin() + k * n, q_rows_.begin() + (k + 1) * n);
        std::vector<double> lqd(qd_rows_.begin() + k * n, qd_rows_.begin() + (k + 1) * n);
        LoopProjectionInfo info;
        try {
          if (setup_.loop_solver) {  // one sparse solver for the reset's instances
            if (!reset_loops) reset_loops = setup_.loop_solver(setup_.loop_model, setup_.loops);
            reset_loops->project(lq.data(), lqd.data(), 1e-13, kResetLinearisations, &info);
          } else {
            project_to_loops(setup_.loop_model, setup_.loops, lq.data(), lqd.data(), 1e-13, kResetLinearisations,
                             &info);
          }
        } catch (const LoopError& e) {
          *random_ = saved;
          throw SceneError("initial state of instance " + std::to_string(instances[start + k]) +
                           ": its projection onto the loops failed (" + e.what() + "); no instance was reset");
        }
        // a start the projection cannot close (an infeasible loop set, a local minimum
        // of |phi|^2, the iteration bound) is refused (kLoopStateTolerance, as eval
        // --loops refuses such a state) rather than stepped from
        const double off = info.violation();
        if (!(off <= kLoopStateTolerance)) {
          *random_ = saved;
          Index loop = 0;
          for (Index row = 0; loop + 1 < static_cast<Index>(setup_.loops.loops.size()); ++loop) {
            row += setup_.loops.loops[loop].rows();
            if (info.worst_row < row) break;
          }
          const LoopClosure& l = setup_.loops.loops[static_cast<std::size_t>(std::max<Index>(0, loop))];
          throw SceneError("initial state of instance " + std::to_string(instances[start + k]) + ": " +
                           std::to_string(off) + " m off its loops (worst: loop " + std::to_string(loop) + ", " +
                           l.link_a + " - " + l.link_b + ") after projecting it onto them (tolerance " +
                           std::to_string(kLoopStateTolerance) + "; " + std::to_string(info.linearisations) +
                           " linearisations of the Levenberg-Marquardt projection from the scene's initial q: an "
                           "infeasible loop set, or a start that only reaches a local minimum of |phi|: start "
                           "closer to a closed configuration); no instance was reset");
        }
        for (Index i = 0; i < n; ++i) q_rows_[k * n + i] = S(lq[i]), qd_rows_[k * n + i] = S(lqd[i]);
      }
      // driven DoFs start on their trajectories, at the current time
      for (std::size_t j = 0; j < setup_.prescribed.dofs.size(); ++j) {
        double pq, pqd, pqdd;
        setup_.prescribed.trajectory[j].eval(time_, pq, pqd, pqdd);
        q_rows_[k * n + setup_.prescribed.dofs[j]] = S(pq);
        qd_rows_[k * n + setup_.prescribed.dofs[j]] = S(pqd);
      }
    }
    backend_->write_instances(instances.data() + start, count, q_rows_.data(), qd_rows_.data());
  }
}

// reset for a model with quaternion positions (instances in [0, B)): q (nq) = initial.q ⊕ delta, delta
// (nv) drawn as the 1-DoF q draws (per DoF, U(-q_spread_i, q_spread_i)): the
// quaternions move by a rotation vector and stay unit
template <class S>
void Simulator<S>::reset_manifold(const std::vector<Index>& instances) {
  const Index n = nv(), nq = this->nq(), B = batch();  // the instances are checked by reset
  const Body<S>* bodies = setup_.model.bodies.data();
  const Index nb = setup_.model.nbodies();
  std::vector<S> delta(static_cast<std::size_t>(n));
  const Index chunk = std::max<Index>(1, std::min<Index>(B, (1 << 20) / std::max<Index>(1, nq)));
  for (std::size_t start = 0; start < instances.size(); start += static_cast<std::size_t>(chunk)) {
    const Index count = static_cast<Index>(std::min<std::size_t>(chunk, instances.size() - start));
    q_rows_.resize(static_cast<std::size_t>(count) * nq);
    qd_rows_.resize(static_cast<std::size_t>(count) * n);
    for (Index k = 0; k < count; ++k) {
      S* const qrow = q_rows_.data() + k * nq;
      for (Index i = 0; i < nq; ++i) qrow[i] = S(initial_.q[i]);
      if (initial_.random) {  // per instance: all q draws, then all qd draws, as for 1-DoF models
        for (Index i = 0; i < n; ++i) delta[i] = S(random_->uniform(-initial_.q_spread[i], initial_.q_spread[i]));
        integrate_bodies(bodies, nb, qrow, delta.data(), S(1));
      }
      normalize_bodies(bodies, nb, qrow);  // unit in precision S
      for (Index i = 0; i < n; ++i)
        qd_rows_[k * n + i] = S(initial_.random ? initial_.qd[i] + random_->uniform(-initial_.qd_spread[i], initial_.qd_spread[i])
                                               : initial_.qd[i]);
    }
    backend_->write_instances(instances.data() + start, count, q_rows_.data(), qd_rows_.data());
  }
}

template <class S>
void Simulator<S>::reset_all() {
  std::vector<Index> all(static_cast<std::size_t>(batch()));
  for (Index b = 0; b < batch(); ++b) all[b] = b;
  reset(all);
}

template <class S>
std::vector<double> Simulator<S>::energy() {
  const std::size_t n = static_cast<std::size_t>(nv()), B = static_cast<std::size_t>(batch());
  const std::size_t nq = static_cast<std::size_t>(this->nq()), nb = static_cast<std::size_t>(setup_.model.nbodies());
  std::vector<S> q(nq * B), qd(n * B);
  read_state(q.data(), qd.data());
  const Model model = setup_.model.template cast<double>();
  std::vector<JointCoefficients<double>> coef(n);
  for (std::size_t i = 0; i < n; ++i) {
    const JointCoefficients<S>& c = setup_.coef[i];
    coef[i] = {double(c.damping), double(c.stiffness), double(c.rest), double(c.lower), double(c.upper),
               double(c.limit_stiffness), double(c.limit_damping)};
  }
  // the contacts in double
  std::vector<ContactPoint<double>> points;
  std::vector<ContactPlane<double>> planes;
  std::vector<ContactSphere<double>> spheres;
  for (const auto& p : setup_.contact_points) points.push_back({p.body, p.position.template cast<double>(), double(p.radius)});
  for (const auto& p : setup_.contact_planes) planes.push_back({p.normal.template cast<double>(), double(p.offset)});
  for (const auto& p : setup_.contact_spheres) spheres.push_back({p.center.template cast<double>(), double(p.radius)});
  ContactSet<double> cs;
  cs.points = points.data(), cs.npoints = static_cast<Index>(points.size());
  cs.planes = planes.data(), cs.nplanes = static_cast<Index>(planes.size());
  cs.spheres = spheres.data(), cs.nspheres = static_cast<Index>(spheres.size());
  cs.law.stiffness = double(setup_.contact_law.stiffness);
  std::vector<Transform<double>> X(nb);
  std::vector<Motion<double>> v(nb);
  std::vector<double> e(B), qb(nq), qdb(n);
  for (std::size_t b = 0; b < B; ++b) {
    for (std::size_t i = 0; i < nq; ++i) qb[i] = double(q[i * B + b]);
    for (std::size_t i = 0; i < n; ++i) qdb[i] = double(qd[i * B + b]);
    e[b] = mechanical_energy(model, setup_.effects, coef.data(), qb.data(), qdb.data());
    if (setup_.effects & kContacts) {
      if (model.multi_dof()) contact_kinematics_at(model.bodies.data(), model.nbodies(), qb.data(), qdb.data(), X.data(), v.data());
      else contact_kinematics(model.bodies.data(), model.nv(), qb.data(), qdb.data(), 1, X.data(), v.data());
      for (const ContactPoint<double>& p : points)
        e[b] += contact_energy_at(cs, mul_transpose(X[p.body].E, p.position) + X[p.body].r, p.radius);
    }
  }
  return e;
}

template class Simulator<float>;
template class Simulator<double>;
namespace detail {
#if !SCANDYN_HAS_CUDA
template std::unique_ptr<SimBackend<float>> make_cuda_sim_backend(const SimSetup<float>&);
template std::unique_ptr<SimBackend<double>> make_cuda_sim_backend(const SimSetup<double>&);
#endif
}  // namespace detail

}  // namespace sim
}  // namespace scandyn
