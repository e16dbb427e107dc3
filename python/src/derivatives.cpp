// python/src/derivatives.cpp: the analytical derivatives from Python, host arrays
// (NumPy, C-contiguous, float32 or float64): the derivative engines of inverse and
// forward dynamics (make_id_derivatives, make_fd_derivatives; scandyn/engine.hpp)
// and the derivatives of the simulator's step and rollouts
// (scandyn/sim/step_derivatives.hpp). Registered by module.cpp (bind_derivatives);
// the torch.autograd.Function and jax.custom_vjp wrappers over them are
// python/scandyn/autograd.py. Results are new NumPy arrays.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>

#include <memory>
#include <string>
#include <vector>

#include "scandyn/engine.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scandyn/sim/step_derivatives.hpp"
#include "shared.hpp"

namespace nb = nanobind;

namespace scandyn::py {
namespace {

template <class S>
using In = nb::ndarray<const S, nb::c_contig, nb::device::cpu>;

// A new NumPy array of the given shape owning v's memory.
template <class S>
nb::object new_array(std::vector<S>&& v, const std::vector<size_t>& shape) {
  auto* owner = new std::vector<S>(std::move(v));
  nb::capsule del(owner, [](void* p) noexcept { delete static_cast<std::vector<S>*>(p); });
  return nb::cast(nb::ndarray<nb::numpy, S>(owner->data(), shape.size(), shape.data(), del));
}

// (B, n) of an array of shape (B, n) or (n,) named `name`, with n = nv.
template <class A>
Index batch_of(const A& a, Index nv, const char* name) {
  if ((a.ndim() == 1 || a.ndim() == 2) && static_cast<Index>(a.shape(a.ndim() - 1)) == nv)
    return a.ndim() == 1 ? 1 : static_cast<Index>(a.shape(0));
  throw ShapeError(std::string(name) + " has shape " + shape_str(a) + ", expected (B, " + std::to_string(nv) +
                   ") or (" + std::to_string(nv) + ",)");
}
template <class A>
void same_batch(const A& a, Index nv, Index B, const char* name) {
  if (batch_of(a, nv, name) != B)
    throw ShapeError(std::string(name) + " has shape " + shape_str(a) + ", expected " + std::to_string(B) +
                     " instances like q");
}

BackendOptions options_of(const std::string& backend, Index B) {
  BackendOptions o;
  o.backend = parse_backend(backend);
  o.max_batch = std::max<Index>(B, 1);
  return o;
}

// (dtau_dq, dtau_dqd, M), each (B, nv, nv)
template <class S>
nb::tuple id_derivatives(PyModel& pm, In<S> q, In<S> qd, In<S> qdd, const std::string& backend) {
  const ModelTpl<S>& model = pm.get<S>();
  const Index nv = model.nv(), B = batch_of(q, nv, "q");
  same_batch(qd, nv, B, "qd"), same_batch(qdd, nv, B, "qdd");
  const std::size_t count = static_cast<std::size_t>(B) * nv * nv;
  std::vector<S> a(count), b(count), c(count);
  using V = BatchView<const S>;
  make_id_derivatives(model, options_of(backend, B))
      ->compute({V::aos(q.data(), nv, B), V::aos(qd.data(), nv, B), V::aos(qdd.data(), nv, B)},
                {BatchView<S>::aos(a.data(), nv * nv, B), BatchView<S>::aos(b.data(), nv * nv, B),
                 BatchView<S>::aos(c.data(), nv * nv, B)});
  const size_t Bs = static_cast<size_t>(B), n = static_cast<size_t>(nv);
  return nb::make_tuple(new_array(std::move(a), {Bs, n, n}), new_array(std::move(b), {Bs, n, n}),
                        new_array(std::move(c), {Bs, n, n}));
}

// (qdd (B, nv), dqdd_dq, dqdd_dqd, dqdd_dtau (B, nv, nv))
template <class S>
nb::tuple fd_derivatives(PyModel& pm, In<S> q, In<S> qd, In<S> tau, const std::string& backend) {
  const ModelTpl<S>& model = pm.get<S>();
  const Index nv = model.nv(), B = batch_of(q, nv, "q");
  same_batch(qd, nv, B, "qd"), same_batch(tau, nv, B, "tau");
  const std::size_t count = static_cast<std::size_t>(B) * nv * nv;
  std::vector<S> a(count), b(count), c(count), qdd(static_cast<std::size_t>(B) * nv);
  using V = BatchView<const S>;
  const BatchStatus st = make_fd_derivatives(model, options_of(backend, B))
                             ->compute({V::aos(q.data(), nv, B), V::aos(qd.data(), nv, B), V::aos(tau.data(), nv, B)},
                                       {BatchView<S>::aos(a.data(), nv * nv, B), BatchView<S>::aos(b.data(), nv * nv, B),
                                        BatchView<S>::aos(c.data(), nv * nv, B), BatchView<S>::aos(qdd.data(), nv, B)});
  if (!st.ok()) throw BackendError("the forward-dynamics derivatives failed: " + st.message());
  const size_t Bs = static_cast<size_t>(B), n = static_cast<size_t>(nv);
  return nb::make_tuple(new_array(std::move(qdd), {Bs, n}), new_array(std::move(a), {Bs, n, n}),
                        new_array(std::move(b), {Bs, n, n}), new_array(std::move(c), {Bs, n, n}));
}

// The step and rollout derivatives of one scene (JSON text), in precision S.
template <class S>
class PyStepDerivatives {
 public:
  PyStepDerivatives(const std::string& scene_json, const std::string& source, const std::string& base_dir,
                    const std::string& backend) {
    sim::Scene scene = sim::parse_scene(scene_json, source, base_dir);
    scene.instances = 1;  // the setup only: one instance's state
    sim_ = std::make_unique<sim::Simulator<S>>(scene, BackendKind::Serial);
    options_ = options_of(backend, 1);
    rollout_ = std::make_unique<sim::RolloutDerivatives<S>>(sim_->setup(), options_);
  }
  Index nv() const { return sim_->nv(); }
  double dt() const { return double(sim_->setup().dt); }

  // (q', qd', J) with J (B, 2 nv, 3 nv): rows (q', qd'), columns (q, qd, tau)
  nb::tuple jacobian(In<S> q, In<S> qd, In<S> tau) {
    const Index nv = this->nv(), B = batch_of(q, nv, "q");
    same_batch(qd, nv, B, "qd"), same_batch(tau, nv, B, "tau");
    if (!engine_ || engine_max_ < B) {
      BackendOptions o = options_;
      o.max_batch = std::max<Index>(B, 1);
      engine_ = sim::make_step_derivatives(sim_->setup(), o);
      engine_max_ = o.max_batch;
    }
    const std::size_t n = static_cast<std::size_t>(nv), Bs = static_cast<std::size_t>(B);
    std::vector<S> qn(Bs * n), qdn(Bs * n), J(Bs * 6 * n * n);
    // block (r, c) of instance b at J + b * 6 n^2 + r * 3 n^2 + c * n, rows of 3 n: a strided view
    auto block = [&](int r, int c) {
      return BatchView<S>{J.data() + r * 3 * n * n + c * n, B, 1, static_cast<std::ptrdiff_t>(6 * n * n)};
    };
    // entry (i, j) of a block at i * nv + j of the view's nv * nv entries: dof_stride 1
    // does not fit rows of 3 nv, so the blocks are written contiguously and spread below
    std::vector<S> blocks(6 * Bs * n * n);
    auto bv = [&](int k) { return BatchView<S>::aos(blocks.data() + k * Bs * n * n, nv * nv, B); };
    using V = BatchView<const S>;
    const BatchStatus st = engine_->compute({V::aos(q.data(), nv, B), V::aos(qd.data(), nv, B), V::aos(tau.data(), nv, B)},
                                            {bv(0), bv(1), bv(2), bv(3), bv(4), bv(5), BatchView<S>::aos(qn.data(), nv, B),
                                             BatchView<S>::aos(qdn.data(), nv, B)});
    if (!st.ok()) throw BackendError("the step derivatives failed: " + st.message());
    for (int k = 0; k < 6; ++k) {
      const BatchView<S> dst = block(k / 3, k % 3);
      for (std::size_t b = 0; b < Bs; ++b)
        for (std::size_t i = 0; i < n; ++i)
          for (std::size_t j = 0; j < n; ++j)
            dst.data[b * dst.batch_stride + i * 3 * n + j] = blocks[k * Bs * n * n + b * n * n + i * n + j];
    }
    return nb::make_tuple(new_array(std::move(qn), {Bs, n}), new_array(std::move(qdn), {Bs, n}),
                          new_array(std::move(J), {Bs, 2 * n, 3 * n}));
  }

  // (q, qd), each (T, B, nv): the states after each step
  nb::tuple rollout(In<S> q0, In<S> qd0, In<S> tau) {
    const Index nv = this->nv(), B = batch_of(q0, nv, "q0");
    same_batch(qd0, nv, B, "qd0");
    const Index T = steps_of(tau, B, "tau");
    const std::size_t count = static_cast<std::size_t>(T) * B * nv;
    std::vector<S> q(count), qd(count);
    check(rollout_->rollout(view(q0, B), view(qd0, B), seq(tau.data(), B, T), seq(q.data(), B, T), seq(qd.data(), B, T)));
    return nb::make_tuple(new_array(std::move(q), shape3(T, B)), new_array(std::move(qd), shape3(T, B)));
  }

  // (gq0, gqd0 (B, nv), gtau (T, B, nv)) for the loss gradients gq, gqd (T, B, nv)
  nb::tuple vjp(In<S> q0, In<S> qd0, In<S> tau, In<S> gq, In<S> gqd) {
    const Index nv = this->nv(), B = batch_of(q0, nv, "q0");
    same_batch(qd0, nv, B, "qd0");
    const Index T = steps_of(tau, B, "tau");
    if (steps_of(gq, B, "gq") != T || steps_of(gqd, B, "gqd") != T)
      throw ShapeError("gq and gqd must have tau's " + std::to_string(T) + " steps");
    std::vector<S> g0(static_cast<std::size_t>(B) * nv), gd0(g0.size()), gt(static_cast<std::size_t>(T) * B * nv);
    check(rollout_->vjp(view(q0, B), view(qd0, B), seq(tau.data(), B, T), seq(gq.data(), B, T), seq(gqd.data(), B, T),
                        BatchView<S>::aos(g0.data(), nv, B), BatchView<S>::aos(gd0.data(), nv, B), seq(gt.data(), B, T)));
    const size_t Bs = static_cast<size_t>(B), n = static_cast<size_t>(nv);
    return nb::make_tuple(new_array(std::move(g0), {Bs, n}), new_array(std::move(gd0), {Bs, n}),
                          new_array(std::move(gt), shape3(T, B)));
  }

  // (dq, dqd), each (T, B, nv): the trajectory's tangent along (dq0, dqd0, dtau)
  nb::tuple jvp(In<S> q0, In<S> qd0, In<S> tau, In<S> dq0, In<S> dqd0, In<S> dtau) {
    const Index nv = this->nv(), B = batch_of(q0, nv, "q0");
    same_batch(qd0, nv, B, "qd0"), same_batch(dq0, nv, B, "dq0"), same_batch(dqd0, nv, B, "dqd0");
    const Index T = steps_of(tau, B, "tau");
    if (steps_of(dtau, B, "dtau") != T) throw ShapeError("dtau must have tau's " + std::to_string(T) + " steps");
    const std::size_t count = static_cast<std::size_t>(T) * B * nv;
    std::vector<S> dq(count), dqd(count);
    check(rollout_->jvp(view(q0, B), view(qd0, B), seq(tau.data(), B, T), view(dq0, B), view(dqd0, B),
                        seq(dtau.data(), B, T), seq(dq.data(), B, T), seq(dqd.data(), B, T)));
    return nb::make_tuple(new_array(std::move(dq), shape3(T, B)), new_array(std::move(dqd), shape3(T, B)));
  }

 private:
  // T of a (T, B, nv) array
  Index steps_of(const In<S>& a, Index B, const char* name) const {
    if (a.ndim() != 3 || static_cast<Index>(a.shape(1)) != B || static_cast<Index>(a.shape(2)) != nv())
      throw ShapeError(std::string(name) + " has shape " + shape_str(a) + ", expected (T, " + std::to_string(B) +
                       ", " + std::to_string(nv()) + ")");
    return static_cast<Index>(a.shape(0));
  }
  BatchView<const S> view(const In<S>& a, Index B) const { return BatchView<const S>::aos(a.data(), nv(), B); }
  template <class P>
  sim::StepSequence<P> seq(P* p, Index B, Index T) const {
    return {BatchView<P>::aos(p, nv(), B), static_cast<std::ptrdiff_t>(B) * nv(), T};
  }
  std::vector<size_t> shape3(Index T, Index B) const {
    return {static_cast<size_t>(T), static_cast<size_t>(B), static_cast<size_t>(nv())};
  }
  static void check(const BatchStatus& st) {
    if (!st.ok()) throw BackendError("the rollout derivatives failed: " + st.message());
  }
  std::unique_ptr<sim::Simulator<S>> sim_;  // holds the setup
  BackendOptions options_;
  std::unique_ptr<sim::RolloutDerivatives<S>> rollout_;
  std::unique_ptr<sim::StepDerivatives<S>> engine_;
  Index engine_max_ = 0;
};

template <class S>
void bind_step(nb::module_& m, const char* name) {
  nb::class_<PyStepDerivatives<S>>(m, name)
      .def(nb::init<const std::string&, const std::string&, const std::string&, const std::string&>(),
           nb::arg("scene_json"), nb::arg("source"), nb::arg("base_dir"), nb::arg("backend"))
      .def_prop_ro("nv", &PyStepDerivatives<S>::nv)
      .def_prop_ro("dt", &PyStepDerivatives<S>::dt)
      .def("jacobian", &PyStepDerivatives<S>::jacobian)
      .def("rollout", &PyStepDerivatives<S>::rollout)
      .def("vjp", &PyStepDerivatives<S>::vjp)
      .def("jvp", &PyStepDerivatives<S>::jvp);
}

}  // namespace

void bind_derivatives(nb::module_& m) {
  m.def("id_derivatives", &id_derivatives<double>, nb::arg("model"), nb::arg("q"), nb::arg("qd"), nb::arg("qdd"),
        nb::arg("backend"));
  m.def("id_derivatives", &id_derivatives<float>, nb::arg("model"), nb::arg("q"), nb::arg("qd"), nb::arg("qdd"),
        nb::arg("backend"));
  m.def("fd_derivatives", &fd_derivatives<double>, nb::arg("model"), nb::arg("q"), nb::arg("qd"), nb::arg("tau"),
        nb::arg("backend"));
  m.def("fd_derivatives", &fd_derivatives<float>, nb::arg("model"), nb::arg("q"), nb::arg("qd"), nb::arg("tau"),
        nb::arg("backend"));
  bind_step<double>(m, "StepDerivatives64");
  bind_step<float>(m, "StepDerivatives32");
}

}  // namespace scandyn::py
