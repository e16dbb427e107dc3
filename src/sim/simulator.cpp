// src/sim/simulator.cpp: the Simulator front end (setup from a scene, resets,
// energy) and the CPU backends (serial, OpenMP): per instance, the shared
// step_instance (scandyn/sim/integrators.hpp) over the reference ABA.
#include "scandyn/sim/simulator.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <random>
#include <stdexcept>
#include <utility>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/build_config.hpp"

#if defined(_OPENMP)
#include <omp.h>
#endif

namespace scandyn {
namespace sim {

std::string SimStatus::message() const {
  if (ok()) return "";
  return "forward dynamics failed " + std::to_string(failed) + " time" + (failed > 1 ? "s" : "") +
         " (first failing instance " + std::to_string(first_instance) +
         "): a pivot was not positive and finite; those instances kept their state for those steps";
}

double mechanical_energy(const Model& model, unsigned effects, const JointCoefficients<double>* coef,
                         const double* q, const double* qd) {
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
namespace {

// ---- the CPU backends ------------------------------------------------------------

template <class S>
class CpuSimBackend final : public SimBackend<S> {
 public:
  CpuSimBackend(const SimSetup<S>& setup, bool openmp) : setup_(setup), openmp_(openmp) {
    const std::size_t nv = static_cast<std::size_t>(setup.model.nv());
    const std::size_t B = static_cast<std::size_t>(setup.batch);
    q_.assign(nv * B, S(0));
    qd_.assign(nv * B, S(0));
    if (setup.wrenches_per_step) {
      wrenches_.resize(B * nv);
      for (std::size_t b = 0; b < B; ++b)
        std::copy(setup.wrenches.begin(), setup.wrenches.end(), wrenches_.begin() + b * nv);
    }
#if defined(_OPENMP)
    threads_ = openmp ? (setup.threads > 0 ? setup.threads : omp_get_max_threads()) : 1;
#endif
    threads_ = std::max(1, std::min<int>(threads_, std::max<Index>(1, setup.batch)));
    for (int t = 0; t < threads_; ++t) work_.emplace_back(setup_.model, nv);
    step_ = table()[static_cast<int>(setup.integrator) * kEffectSets + static_cast<int>(setup.effects)];
  }

  void step(const BatchView<const S>& tau) override {
    const Index B = setup_.batch, n = setup_.model.nv();
    if (tau.data && tau.batch != B)
      throw BackendError("Simulator::step: torques for " + std::to_string(tau.batch) + " instances, the simulator has " +
                         std::to_string(B));
    S* const q = q_.data();
    S* const qd = qd_.data();
    const Force<S>* const constant = setup_.wrenches.empty() ? nullptr : setup_.wrenches.data();
    std::atomic<long long> failed{0};
    std::atomic<Index> first{-1};
    // instance b with thread slot t's work arrays
    auto one = [&](Index b, std::size_t t) {
      Work& w = work_[t];
      for (Index i = 0; i < n; ++i) {
        w.q[i] = q[static_cast<std::size_t>(i) * B + b];
        w.qd[i] = qd[static_cast<std::size_t>(i) * B + b];
        w.tau[i] = tau.data ? tau.at(i, b) : S(0);
      }
      const Force<S>* fext = wrenches_.empty() ? constant : wrenches_.data() + static_cast<std::size_t>(b) * n;
      if (step_(setup_, w.data, w.scratch, w.q.data(), w.qd.data(), w.tau.data(), fext) >= 0) {
        failed.fetch_add(1);
        Index f = first.load();
        while ((f < 0 || b < f) && !first.compare_exchange_weak(f, b)) {
        }
        return;
      }
      for (Index i = 0; i < n; ++i) {
        q[static_cast<std::size_t>(i) * B + b] = w.q[i];
        qd[static_cast<std::size_t>(i) * B + b] = w.qd[i];
      }
    };
    if (openmp_ && threads_ > 1 && B > 1) {
#pragma omp parallel for num_threads(threads_) schedule(static)
      for (Index b = 0; b < B; ++b) {
#if defined(_OPENMP)
        one(b, static_cast<std::size_t>(omp_get_thread_num()));
#else
        one(b, 0);
#endif
      }
    } else {
      // no parallel region: entering even a serialized one costs ~0.4 us, a fifth of
      // a 7-DoF step
      for (Index b = 0; b < B; ++b) one(b, 0);
    }
    if (failed.load() > 0) {
      status_.failed += failed.load();
      if (status_.first_instance < 0 || first.load() < status_.first_instance) status_.first_instance = first.load();
    }
  }

  BatchView<S> q() override { return BatchView<S>::soa(q_.data(), setup_.model.nv(), setup_.batch); }
  BatchView<S> qd() override { return BatchView<S>::soa(qd_.data(), setup_.model.nv(), setup_.batch); }
  Force<S>* wrenches() override { return wrenches_.empty() ? nullptr : wrenches_.data(); }

  void write_instances(const Index* instances, Index count, const S* q_rows, const S* qd_rows) override {
    const std::size_t n = static_cast<std::size_t>(setup_.model.nv()), B = static_cast<std::size_t>(setup_.batch);
    for (Index k = 0; k < count; ++k)
      for (std::size_t i = 0; i < n; ++i) {
        q_[i * B + static_cast<std::size_t>(instances[k])] = q_rows[k * n + i];
        qd_[i * B + static_cast<std::size_t>(instances[k])] = qd_rows[k * n + i];
      }
  }
  void read_state(S* q_host, S* qd_host) override {
    std::copy(q_.begin(), q_.end(), q_host);
    std::copy(qd_.begin(), qd_.end(), qd_host);
  }
  SimStatus status() override { return status_; }
  void clear_status() override { status_ = {}; }
  void synchronize() override {}
  bool on_device() const override { return false; }
  std::string strategy() const override { return openmp_ ? "openmp-aba" : "serial-aba"; }

 private:
  // One thread's workspace: the ABA's scratch and the step's arrays.
  struct Work {
    Work(const ModelTpl<S>& model, std::size_t n)
        : data(model, false), q(n), qd(n), tau(n), buffer(6 * n),
          scratch{buffer.data(), buffer.data() + n, buffer.data() + 2 * n, buffer.data() + 3 * n,
                  buffer.data() + 4 * n, buffer.data() + 5 * n} {}
    Work(Work&& o) noexcept = default;
    DataTpl<S> data;
    std::vector<S> q, qd, tau;  // (n) the instance's state and torques
    std::vector<S> buffer;      // (6 n) StepScratch's arrays
    StepScratch<S> scratch;
  };

  using StepFn = Index (*)(const SimSetup<S>&, DataTpl<S>&, const StepScratch<S>&, S*, S*, const S*,
                           const Force<S>*);

  // One instance's step for effect set E and integrator I: step_instance over the ABA.
  template <unsigned E, Integrator I>
  static Index step_one(const SimSetup<S>& setup, DataTpl<S>& data, const StepScratch<S>& w, S* q, S* qd,
                        const S* tau, const Force<S>* fext) {
    const ModelTpl<S>& model = setup.model;
    auto fd = [&](const S* qa, const S* qda, const S* t, const S* armature, S* qdd) -> Index {
      return aba(model, data, qa, qda, t, qdd, (E & kExternal) ? fext : nullptr, armature).failed_dof;
    };
    return step_instance<E, I>(model.nv(), setup.dt, setup.coef.data(),
                               setup.armature.empty() ? nullptr : setup.armature.data(), q, qd, tau, w, fd);
  }

  // Every (integrator, effect set) instantiation, indexed integrator * 32 + effects.
  template <std::size_t... K>
  static constexpr std::array<StepFn, sizeof...(K)> make_table(std::index_sequence<K...>) {
    return {&step_one<unsigned(K % kEffectSets), Integrator(K / kEffectSets)>...};
  }
  static const std::array<StepFn, kIntegrators * kEffectSets>& table() {
    static const auto t = make_table(std::make_index_sequence<kIntegrators * kEffectSets>{});
    return t;
  }

  const SimSetup<S>& setup_;  // the Simulator's, which outlives its backend
  bool openmp_;
  int threads_ = 1;
  std::vector<S> q_, qd_;          // (nv x B) state, q[i * B + b]
  std::vector<Force<S>> wrenches_; // (B x nv) per-step wrenches, or empty
  std::vector<Work> work_;         // one per thread
  StepFn step_ = nullptr;
  SimStatus status_;
};

}  // namespace

template <class S>
std::unique_ptr<SimBackend<S>> make_cpu_sim_backend(const SimSetup<S>& setup, bool openmp) {
  return std::make_unique<CpuSimBackend<S>>(setup, openmp);
}

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
    setup_.wrenches.assign(static_cast<std::size_t>(nv), Force<S>::zero());
    for (const SceneWrench& w : scene.wrenches) setup_.wrenches[w.body] += w.wrench.template cast<S>();
    setup_.wrenches_per_step = scene.wrenches_per_step;
  }
  setup_.threads = scene.threads;
  switch (backend) {
    case BackendKind::Serial: backend_ = detail::make_cpu_sim_backend(setup_, false); break;
    case BackendKind::OpenMP:
#if !SCANDYN_HAS_OPENMP
      throw BackendError("backend 'openmp' is not available in this build");
#endif
      backend_ = detail::make_cpu_sim_backend(setup_, true);
      break;
    case BackendKind::Cuda: backend_ = detail::make_cuda_sim_backend(setup_); break;
  }
  random_ = std::make_unique<Random>(initial_.seed);
  reset_all();
}

template <class S>
Simulator<S>::~Simulator() = default;

template <class S>
void Simulator<S>::step(const BatchView<const S>& tau) {
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
  // in chunks, so a reset of 10^7 instances needs no 10^7-row buffer
  const Index chunk = std::max<Index>(1, std::min<Index>(B, (1 << 20) / std::max<Index>(1, n)));
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
  std::vector<S> q(n * B), qd(n * B);
  read_state(q.data(), qd.data());
  const Model model = setup_.model.template cast<double>();
  std::vector<JointCoefficients<double>> coef(n);
  for (std::size_t i = 0; i < n; ++i) {
    const JointCoefficients<S>& c = setup_.coef[i];
    coef[i] = {double(c.damping), double(c.stiffness), double(c.rest), double(c.lower), double(c.upper),
               double(c.limit_stiffness), double(c.limit_damping)};
  }
  std::vector<double> e(B), qb(n), qdb(n);
  for (std::size_t b = 0; b < B; ++b) {
    for (std::size_t i = 0; i < n; ++i) qb[i] = double(q[i * B + b]), qdb[i] = double(qd[i * B + b]);
    e[b] = mechanical_energy(model, setup_.effects, coef.data(), qb.data(), qdb.data());
  }
  return e;
}

template class Simulator<float>;
template class Simulator<double>;
namespace detail {
template std::unique_ptr<SimBackend<float>> make_cpu_sim_backend(const SimSetup<float>&, bool);
template std::unique_ptr<SimBackend<double>> make_cpu_sim_backend(const SimSetup<double>&, bool);
#if !SCANDYN_HAS_CUDA
template std::unique_ptr<SimBackend<float>> make_cuda_sim_backend(const SimSetup<float>&);
template std::unique_ptr<SimBackend<double>> make_cuda_sim_backend(const SimSetup<double>&);
#endif
}  // namespace detail

}  // namespace sim
}  // namespace scandyn
