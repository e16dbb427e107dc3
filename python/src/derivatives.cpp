// python/src/derivatives.cpp: the analytical derivatives from Python: the derivative
// engines of inverse and forward dynamics (make_id_derivatives, make_fd_derivatives;
// scandyn/engine.hpp), the second-order derivatives of inverse dynamics
// (make_id_second_derivatives: four (B, nv, nv, nv) tensors), the directional derivatives of forward dynamics (JVP, VJP:
// make_fd_directional_derivatives; host arrays only) and the derivatives of the simulator's step and rollouts
// (scandyn/sim/step_derivatives.hpp). Registered by module.cpp (bind_derivatives);
// the torch.autograd.Function and jax.custom_vjp wrappers over them are
// python/scandyn/autograd.py, which allocates every result (an array of the inputs'
// kind on their device) and passes it here as out.
//
// Arrays are read as module.cpp's engines read them (arrays.hpp: host memory or one
// CUDA device, one dtype, their own strides, no copy). Host arrays run the engine's
// compute() (or RolloutDerivatives' calls); CUDA arrays the CUDA engine's async call on
// the caller's stream (engines.hpp's queue_on_device for the two engines;
// cuda::CudaStepDerivatives::compute_async and cuda::CudaRolloutDerivatives'
// *_async for the step and the rollouts), no synchronisation: the failed DoFs of a
// CUDA call go to the caller's (B,) int32 device array (status_of_step_failures
// decodes them once read back).
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/shared_ptr.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/vector.h>

#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <tuple>
#include <vector>

#include "arrays.hpp"
#include "engines.hpp"
#include "scandyn/batch.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scandyn/sim/step_derivatives.hpp"
#include "shared.hpp"

#if SCANDYN_HAS_CUDA
#include "scandyn/cuda/rollout_derivatives.hpp"
#include "scandyn/cuda/second_derivatives.hpp"
#include "scandyn/cuda/step_derivatives.hpp"
#endif

namespace nb = nanobind;
using namespace nb::literals;

namespace scandyn::py {
namespace {

using PyIdDerivatives = PyEngine<IdDerivatives>;
using PyFdDerivatives = PyEngine<FdDerivatives>;
using PyIdSecondDerivatives = PyEngine<IdSecondDerivatives>;
using PyFdDirectional = PyEngine<FdDirectionalDerivatives>;

// Every out array writable entry by entry and sharing no memory with the inputs.
void check_outs(std::initializer_list<std::pair<const OutArray*, const char*>> outs,
                std::initializer_list<std::pair<Extent, const char*>> inputs) {
  for (const auto& [o, name] : outs) {
    check_no_self_overlap(*o, name);
    check_out_alone(*o, inputs, name);
    for (const auto& [p, other] : outs)
      if (p != o && overlaps(extent_of(*o), extent_of(*p)))
        throw ShapeError(std::string(name) + " shares memory with " + other + ": pass separate arrays");
  }
}

// ---- the derivatives of inverse and forward dynamics --------------------------------

// Runs an inverse-dynamics derivative engine (first or second order) on (in, out) once
// its arguments are checked: the GIL released, the engine's mutex held; CUDA arrays
// queued on the caller's stream (queue_on_device), host arrays by compute().
template <class S, class PyE, class Out>
void id_engine_run(PyE& e, const Lead& lead, std::uintptr_t stream, const IdBatchIn<S>& in, const Out& out) {
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(e.mutex);
  if (lead.cuda)
    return queue_on_device<S>(e, lead, stream, [&](auto& c, cudaStream_t s) { return c.compute_async(in, out, s); });
  if constexpr (std::is_same_v<S, float>) e.ef->compute(in, out);
  else e.ed->compute(in, out);
}

// (dtau_dq, dtau_dqd, M) of (q, qd, qdd): (B, nv, nv) or (nv, nv) each
template <class S>
void id_derivatives_compute(PyIdDerivatives& e, const InArray& q, const InArray& qd, const InArray& qdd,
                            const OutArray& dq, const OutArray& dqd, const OutArray& M, std::uintptr_t stream) {
  const Index nv = e.nv();
  Lead lead;
  const IdBatchIn<S> in = id_inputs<S>(e.nq(), nv, q, qd, qdd, lead);
  const IdDerivativesOut<S> out{matrix_view_of<S>(dq, nv, "dtau_dq", lead),
                                matrix_view_of<S>(dqd, nv, "dtau_dqd", lead), matrix_view_of<S>(M, nv, "M", lead)};
  check_max_batch(lead, e.max_batch);
  check_outs({{&dq, "dtau_dq"}, {&dqd, "dtau_dqd"}, {&M, "M"}},
             {{extent_of(q), "q"}, {extent_of(qd), "qd"}, {extent_of(qdd), "qdd"}});
  id_engine_run<S>(e, lead, stream, in, out);
}

// (d2tau_dq2, d2tau_dqd2, d2tau_dqdqd, dM_dq) of (q, qd, qdd): (B, nv, nv, nv) or
// (nv, nv, nv) each
template <class S>
void id_second_derivatives_compute(PyIdSecondDerivatives& e, const InArray& q, const InArray& qd,
                                   const InArray& qdd, const OutArray& dq2, const OutArray& dqd2,
                                   const OutArray& dqdqd, const OutArray& dM, std::uintptr_t stream) {
  const Index nv = e.nv();
  Lead lead;
  const IdBatchIn<S> in = id_inputs<S>(nv, q, qd, qdd, lead);
  const IdSecondDerivativesOut<S> out{
      block_view_of<S>(dq2, nv, 3, "d2tau_dq2", lead), block_view_of<S>(dqd2, nv, 3, "d2tau_dqd2", lead),
      block_view_of<S>(dqdqd, nv, 3, "d2tau_dqdqd", lead), block_view_of<S>(dM, nv, 3, "dM_dq", lead)};
  check_max_batch(lead, e.max_batch);
  check_outs({{&dq2, "d2tau_dq2"}, {&dqd2, "d2tau_dqd2"}, {&dqdqd, "d2tau_dqdqd"}, {&dM, "dM_dq"}},
             {{extent_of(q), "q"}, {extent_of(qd), "qd"}, {extent_of(qdd), "qdd"}});
  id_engine_run<S>(e, lead, stream, in, out);
}

// qdd (B, nv) and (dqdd_dq, dqdd_dqd, dqdd_dtau = M^-1) of (q, qd, tau)
template <class S>
CallStatus fd_derivatives_compute(PyFdDerivatives& e, const InArray& q, const InArray& qd, const InArray& tau,
                                  const OutArray& qdd, const OutArray& dq, const OutArray& dqd, const OutArray& dtau,
                                  const std::optional<OutArray>& failed_dof, std::uintptr_t stream) {
  const Index nv = e.nv();
  Lead lead;
  const FdBatchIn<S> in = fd_inputs<S>(e.nq(), nv, q, qd, tau, lead);
  const FdDerivativesOut<S> out{matrix_view_of<S>(dq, nv, "dqdd_dq", lead),
                                matrix_view_of<S>(dqd, nv, "dqdd_dqd", lead),
                                matrix_view_of<S>(dtau, nv, "dqdd_dtau", lead), view_of<S>(qdd, nv, "qdd", lead, false)};
  check_max_batch(lead, e.max_batch);
  check_outs({{&qdd, "qdd"}, {&dq, "dqdd_dq"}, {&dqd, "dqdd_dqd"}, {&dtau, "dqdd_dtau"}},
             {{extent_of(q), "q"}, {extent_of(qd), "qd"}, {extent_of(tau), "tau"}});
  int* failed = nullptr;
  if (lead.cuda)
    failed = failed_dof_of(failed_dof, lead, "the forward-dynamics derivatives",
                           {{extent_of(qdd), "qdd"}, {extent_of(dq), "dqdd_dq"}, {extent_of(dqd), "dqdd_dqd"},
                            {extent_of(dtau), "dqdd_dtau"}});
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(e.mutex);
  if (lead.cuda) {
    queue_on_device<S>(e, lead, stream,
                       [&](auto& c, cudaStream_t s) { return c.compute_async(in, out, failed, s); });
    return queued_status();
  }
  BatchStatus st;
  if constexpr (std::is_same_v<S, float>) st = e.ef->compute(in, out);
  else st = e.ed->compute(in, out);
  return call_status(st, lead.batch);
}

// ---- the directional derivatives of forward dynamics (JVP, VJP) --------------------
//
// Host arrays only, on every backend (the cuda engine stages host views through its own
// device buffers; on device memory the library's ChainFdPlan::launch_jvp / launch_vjp
// are the way, not bound here). `x`: the directions (dq, dqd, dtau) or the weight w;
// `y`: qdd and the outputs (dqdd, or gq, gqd, gtau); (B, nv) or (nv,) each (q: (B, nq)).
template <class S, class Call>
CallStatus fd_directional_call(PyFdDirectional& e, const InArray& q, const InArray& qd, const InArray& tau,
                               std::initializer_list<std::pair<const InArray*, const char*>> x,
                               std::initializer_list<std::pair<const OutArray*, const char*>> y, Call&& call) {
  const Index nv = e.nv();
  Lead lead;
  const FdBatchIn<S> in = fd_inputs<S>(e.nq(), nv, q, qd, tau, lead);  // q: nq wide (quaternions)
  std::vector<BatchView<const S>> xv;
  std::vector<BatchView<S>> yv;
  for (const auto& [a, name] : x) xv.push_back(view_of<const S>(*a, nv, name, lead, false));
  for (const auto& [a, name] : y) yv.push_back(view_of<S>(*a, nv, name, lead, false));
  if (lead.cuda)
    throw DeviceError("the arrays are on " + where_str(true, lead.device) +
                      ", but the directional derivatives of forward dynamics take host arrays (NumPy, CPU "
                      "tensors) on every backend (backend 'cuda' copies them to its device and back)");
  check_max_batch(lead, e.max_batch);
  for (const auto& [o, name] : y) {
    check_no_self_overlap(*o, name);
    check_out_alone(*o, {{extent_of(q), "q"}, {extent_of(qd), "qd"}, {extent_of(tau), "tau"}}, name);
    for (const auto& [a, other] : x) check_out_alone(*o, {{extent_of(*a), other}}, name);
    for (const auto& [p, other] : y)
      if (p != o && overlaps(extent_of(*o), extent_of(*p)))
        throw ShapeError(std::string(name) + " shares memory with " + other + ": pass separate arrays");
  }
  BatchStatus st;
  {
    nb::gil_scoped_release release;
    std::lock_guard<std::mutex> lock(e.mutex);
    std::optional<cuda::DeviceScope> scope;  // a cuda engine: its device current while it runs
    if (e.made_on >= 0) enter_device(scope, e.made_on);
    if constexpr (std::is_same_v<S, float>) st = call(*e.ef, in, xv, yv);
    else st = call(*e.ed, in, xv, yv);
  }
  return call_status(st, lead.batch);
}

BackendOptions engine_options(const std::string& backend, Index max_batch, int threads) {
  BackendOptions o;
  o.backend = parse_backend(backend);
  if (max_batch < 1) throw ShapeError("max_batch must be at least 1, got " + std::to_string(max_batch));
  o.max_batch = max_batch;
  o.threads = threads;
  return o;
}

// The engine's __init__(model, dtype, backend, max_batch, threads=0, device=-1):
// make(model of the dtype's precision, options) builds the library engine.
template <class Class, class Make>
void def_derivative_init(Class& cls, Make make) {
  using E = typename Class::Type;
  cls.def(
      "__init__",
      [make](E* self, std::shared_ptr<PyModel> model, const std::string& dtype, const std::string& backend,
             Index max_batch, int threads, int device) {
        const BackendOptions o = engine_options(backend, max_batch, threads);
        init_engine(self, std::move(model), dtype, max_batch, device,
                    [&](const ModelTpl<float>& md) { return make(md, o); },
                    [&](const ModelTpl<double>& md) { return make(md, o); });
      },
      "model"_a, "dtype"_a, "backend"_a, "max_batch"_a, "threads"_a = 0, "device"_a = -1);
}

template <class Class>
void def_derivative_engine(Class& cls) {
  def_engine_properties(cls);
  cls.def_prop_ro("method", [](const typename Class::Type&) { return std::string("aba"); });
}

// ---- the step and rollout derivatives -----------------------------------------------

// The (T, B, nv) sequence `a` as a StepSequence (any strides), B = lead.batch.
template <class T, class A>
sim::StepSequence<T> sequence_of(const A& a, Index nv, const char* name, Lead& lead, Index T_expected = -1) {
  using S = std::remove_const_t<T>;
  check_device(a, name, lead);
  if (!has_dtype<S>(a))
    throw DTypeError(std::string(name) + " has dtype " + dtype_name(a.dtype()) + ", expected " + scalar_name<S>() +
                     " (every array of a call shares one dtype, the StepDerivatives' dtype)");
  if (a.ndim() != 3 || Index(a.shape(1)) != lead.batch || Index(a.shape(2)) != nv ||
      (T_expected >= 0 && Index(a.shape(0)) != T_expected))
    throw ShapeError(std::string(name) + " has shape " + shape_str(a) + ", expected (" +
                     (T_expected >= 0 ? std::to_string(T_expected) : std::string("T")) + ", " +
                     std::to_string(lead.batch) + ", " + std::to_string(nv) + ")");
  sim::StepSequence<T> s;
  s.first.data = static_cast<T*>(const_cast<void*>(static_cast<const void*>(a.data())));
  s.first.batch = lead.batch;
  s.first.dof_stride = a.stride(2);
  s.first.batch_stride = a.stride(1);
  s.time_stride = a.stride(0);
  s.steps = Index(a.shape(0));
  return s;
}

// The step and rollout derivatives of one scene (JSON text), in precision S, on one
// backend (cuda: on one device, made current for every call).
template <class S>
class PyStepDerivatives {
 public:
  PyStepDerivatives(const std::string& scene_json, const std::string& source, const std::string& base_dir,
                    const std::string& backend, int device) {
    sim::Scene scene = sim::parse_scene(scene_json, source, base_dir);
    scene.instances = 1;  // the setup only: one instance's state
    sim_ = std::make_unique<sim::Simulator<S>>(scene, BackendKind::Serial);
    options_.backend = parse_backend(backend);
    options_.max_batch = 1;
#if SCANDYN_HAS_CUDA
    if (options_.backend == BackendKind::Cuda) {
      std::optional<cuda::DeviceScope> scope;
      enter_device(scope, device);
      int current = 0;
      if (cudaGetDevice(&current) == cudaSuccess) device_ = current;
      // every call, host or device arrays, runs the CUDA rollouts (as sim::RolloutDerivatives on cuda)
      cuda_rollout_ = std::make_unique<cuda::CudaRolloutDerivatives<S>>(sim_->setup(), options_);
      return;
    }
#endif
    (void)device;
    rollout_ = std::make_unique<sim::RolloutDerivatives<S>>(sim_->setup(), options_);
  }
  Index nv() const { return sim_->nv(); }
  Index nq() const { return sim_->setup().model.nq(); }
  double dt() const { return double(sim_->setup().dt); }
  // (joint type, first position index, first DoF index) per body: what the Python
  // side needs to map gradients between q's nq coordinates and its nv-dim tangent
  std::vector<std::tuple<std::string, Index, Index>> joints() const {
    std::vector<std::tuple<std::string, Index, Index>> out;
    for (const Body<S>& b : sim_->setup().model.bodies) {
      const char* type = b.type == JointType::Free ? "free"
                         : b.type == JointType::Spherical ? "spherical"
                         : b.type == JointType::Prismatic ? "prismatic" : "revolute";
      out.emplace_back(type, b.idx_q, b.idx_v);
    }
    return out;
  }
  int device() const { return device_; }
  std::string backend() const { return to_string(options_.backend); }

  // (q', qd') (B, nv) and J = d(q', qd') / d(q, qd, tau), rows (q', qd'), columns (q, qd,
  // tau). J: (B, 2 nv, 3 nv) of any strides on the host; on a CUDA device entry-major,
  // J[b, r, c] at (r * 3 nv + c) * B + b (the (B, 2 nv, 3 nv) view of strides (1, 3 nv B,
  // B), or that memory as a (2 nv, 3 nv, B) C-contiguous array), with `blocks` (6 nv^2 B
  // entries of device memory) for the kernel's six blocks before they are copied into J.
  CallStatus jacobian(const InArray& q, const InArray& qd, const InArray& tau, const OutArray& q_next,
                      const OutArray& qd_next, const OutArray& J, const std::optional<OutArray>& blocks,
                      const std::optional<OutArray>& failed_dof, std::uintptr_t stream) {
    const Index n = nv();
    Lead lead;
    const FdBatchIn<S> in = fd_inputs<S>(nq(), n, q, qd, tau, lead);
    const BatchView<S> qn = view_of<S>(q_next, nq(), "q_next", lead, false);
    const BatchView<S> qdn = view_of<S>(qd_next, n, "qd_next", lead, false);
    const Index B = lead.batch;
    check_device(J, "J", lead);
    if (!has_dtype<S>(J)) throw DTypeError("J has dtype " + dtype_name(J.dtype()) + ", expected " + scalar_name<S>());
    // J's strides in entries along (instance, row, column)
    std::ptrdiff_t sb = 0, sr = 0, sc = 0;
    if (J.ndim() == 3 && Index(J.shape(0)) == B && Index(J.shape(1)) == 2 * n && Index(J.shape(2)) == 3 * n)
      sb = J.stride(0), sr = J.stride(1), sc = J.stride(2);
    else if (lead.cuda && J.ndim() == 3 && Index(J.shape(0)) == 2 * n && Index(J.shape(1)) == 3 * n &&
             Index(J.shape(2)) == B)
      sr = J.stride(0), sc = J.stride(1), sb = J.stride(2);
    else
      throw ShapeError("J has shape " + shape_str(J) + ", expected (" + std::to_string(B) + ", " +
                       std::to_string(2 * n) + ", " + std::to_string(3 * n) + ")");
    check_outs({{&q_next, "q_next"}, {&qd_next, "qd_next"}, {&J, "J"}},
               {{extent_of(q), "q"}, {extent_of(qd), "qd"}, {extent_of(tau), "tau"}});
    const std::size_t nn = std::size_t(n) * n, Bs = std::size_t(B);
    S* const Jd = static_cast<S*>(J.data());
    if (lead.cuda) {
#if SCANDYN_HAS_CUDA
      if (options_.backend != BackendKind::Cuda) throw DeviceError(not_cuda(lead));
      if (device_ != lead.device) throw DeviceError(other_device(lead));
      if (!(sc == B && sr == 3 * n * B && (B == 1 || sb == 1)))
        throw ShapeError("J on a CUDA device must be entry-major (J[b, r, c] at (r * 3 nv + c) * B + b: strides (1, " +
                         std::to_string(3 * n * B) + ", " + std::to_string(B) + ")), as scandyn.autograd makes it");
      if (!blocks) throw ShapeError("blocks: the step Jacobian on CUDA arrays needs 6 nv^2 B entries of scratch");
      Lead l = lead;
      check_device(*blocks, "blocks", l);
      if (!has_dtype<S>(*blocks) || blocks->ndim() != 1 || blocks->shape(0) != 6 * nn * Bs ||
          (blocks->shape(0) > 1 && blocks->stride(0) != 1))
        throw ShapeError("blocks has shape " + shape_str(*blocks) + ", expected a contiguous (" +
                         std::to_string(6 * nn * Bs) + ",) array of the call's dtype");
      check_outs({{&*blocks, "blocks"}, {&J, "J"}}, {{extent_of(q), "q"}, {extent_of(qd), "qd"}, {extent_of(tau), "tau"}});
      int* failed = failed_dof_of(failed_dof, lead, "the step Jacobian", {{extent_of(J), "J"}, {extent_of(*blocks), "blocks"}});
      S* const scratch = static_cast<S*>(blocks->data());
      auto bv = [&](int k) { return BatchView<S>{scratch + k * nn * Bs, B, static_cast<std::ptrdiff_t>(B), 1}; };
      nb::gil_scoped_release release;
      std::lock_guard<std::mutex> lock(mutex_);
      std::optional<cuda::DeviceScope> scope;
      enter_device(scope, lead.device);
      auto* c = dynamic_cast<cuda::CudaStepDerivatives<S>*>(&step_engine(B));
      if (!c) throw DeviceError(not_cuda(lead));
      const cudaStream_t s = reinterpret_cast<cudaStream_t>(stream);
      cudaError_t err = c->compute_async(in, {bv(0), bv(1), bv(2), bv(3), bv(4), bv(5), qn, qdn}, failed, s);
      // block (r, c), entry-major (entry (i, j) of instance b at (i n + j) B + b): its row i
      // is n B consecutive entries, as row r n + i of J from column c n on
      const std::size_t width = std::size_t(n) * Bs * sizeof(S);
      for (int k = 0; k < 6 && err == cudaSuccess; ++k)
        err = cudaMemcpy2DAsync(Jd + (std::size_t(k / 3) * n * 3 * n + std::size_t(k % 3) * n) * Bs, 3 * width,
                                scratch + k * nn * Bs, width, width, std::size_t(n), cudaMemcpyDeviceToDevice, s);
      check_launch(err);
      return queued_status();
#else
      (void)blocks, (void)failed_dof, (void)stream;
      throw_no_cuda_backend(lead.device);
#endif
    }
    BatchStatus st;
    {
      nb::gil_scoped_release release;
      std::lock_guard<std::mutex> lock(mutex_);
      std::optional<cuda::DeviceScope> scope;
      if (device_ >= 0) enter_device(scope, device_);
      std::vector<S> scratch(6 * Bs * nn);
      auto bv = [&](int k) { return BatchView<S>::aos(scratch.data() + k * Bs * nn, n * n, B); };
      st = step_engine(B).compute(in, {bv(0), bv(1), bv(2), bv(3), bv(4), bv(5), qn, qdn});
      for (int k = 0; k < 6; ++k)
        for (std::size_t b = 0; b < Bs; ++b)
          for (std::size_t i = 0; i < std::size_t(n); ++i)
            for (std::size_t j = 0; j < std::size_t(n); ++j)
              Jd[std::ptrdiff_t(b) * sb + std::ptrdiff_t((k / 3) * n + i) * sr +
                 std::ptrdiff_t((k % 3) * n + j) * sc] = scratch[k * Bs * nn + b * nn + i * n + j];
    }
    return call_status(st, B);
  }

  // q (T, B, nq), qd (T, B, nv): the states after each step of tau (T, B, nv) from (q0
  // (B, nq), qd0 (B, nv)); the multi-DoF joints' tangents below are nv-dimensional
  CallStatus rollout(const InArray& q0, const InArray& qd0, const InArray& tau, const OutArray& q, const OutArray& qd,
                     const std::optional<OutArray>& failed_dof, std::uintptr_t stream) {
    const Index n = nv();
    Lead lead;
    const auto x0 = view_of<const S>(q0, nq(), "q0", lead, true);
    const auto xd0 = view_of<const S>(qd0, n, "qd0", lead, false);
    const auto u = sequence_of<const S>(tau, n, "tau", lead);
    const Index T = u.steps;
    const auto x = sequence_of<S>(q, nq(), "q", lead, T), xd = sequence_of<S>(qd, n, "qd", lead, T);
    check_outs({{&q, "q"}, {&qd, "qd"}}, {{extent_of(q0), "q0"}, {extent_of(qd0), "qd0"}, {extent_of(tau), "tau"}});
    return run(lead, failed_dof, stream, {{extent_of(q), "q"}, {extent_of(qd), "qd"}},
               [&](auto& r) { return r.rollout(x0, xd0, u, x, xd); },
               [&](auto& r, int* f, cudaStream_t s) { return r.rollout_async(x0, xd0, u, x, xd, f, s); });
  }

  // (gq0, gqd0 (B, nv), gtau (T, B, nv)) for the loss gradients gq, gqd (T, B, nv); gq
  // and gq0 in the tangent of q (local increments: scandyn/sim/manifold_step_derivatives.hpp)
  CallStatus vjp(const InArray& q0, const InArray& qd0, const InArray& tau, const InArray& gq, const InArray& gqd,
                 const OutArray& gq0, const OutArray& gqd0, const OutArray& gtau,
                 const std::optional<OutArray>& failed_dof, std::uintptr_t stream) {
    const Index n = nv();
    Lead lead;
    const auto x0 = view_of<const S>(q0, nq(), "q0", lead, true);
    const auto xd0 = view_of<const S>(qd0, n, "qd0", lead, false);
    const auto u = sequence_of<const S>(tau, n, "tau", lead);
    const Index T = u.steps;
    const auto g = sequence_of<const S>(gq, n, "gq", lead, T), gd = sequence_of<const S>(gqd, n, "gqd", lead, T);
    const auto o0 = view_of<S>(gq0, n, "gq0", lead, false), od0 = view_of<S>(gqd0, n, "gqd0", lead, false);
    const auto ou = sequence_of<S>(gtau, n, "gtau", lead, T);
    check_outs({{&gq0, "gq0"}, {&gqd0, "gqd0"}, {&gtau, "gtau"}},
               {{extent_of(q0), "q0"}, {extent_of(qd0), "qd0"}, {extent_of(tau), "tau"}, {extent_of(gq), "gq"},
                {extent_of(gqd), "gqd"}});
    return run(lead, failed_dof, stream, {{extent_of(gq0), "gq0"}, {extent_of(gqd0), "gqd0"}, {extent_of(gtau), "gtau"}},
               [&](auto& r) { return r.vjp(x0, xd0, u, g, gd, o0, od0, ou); },
               [&](auto& r, int* f, cudaStream_t s) { return r.vjp_async(x0, xd0, u, g, gd, o0, od0, ou, f, s); });
  }

  // (dq, dqd) (T, B, nv): the trajectory's tangent along (dq0, dqd0, dtau)
  CallStatus jvp(const InArray& q0, const InArray& qd0, const InArray& tau, const InArray& dq0, const InArray& dqd0,
                 const InArray& dtau, const OutArray& dq, const OutArray& dqd, const std::optional<OutArray>& failed_dof,
                 std::uintptr_t stream) {
    const Index n = nv();
    Lead lead;
    const auto x0 = view_of<const S>(q0, nq(), "q0", lead, true);
    const auto xd0 = view_of<const S>(qd0, n, "qd0", lead, false);
    const auto u = sequence_of<const S>(tau, n, "tau", lead);
    const Index T = u.steps;
    const auto v0 = view_of<const S>(dq0, n, "dq0", lead, false), vd0 = view_of<const S>(dqd0, n, "dqd0", lead, false);
    const auto du = sequence_of<const S>(dtau, n, "dtau", lead, T);
    const auto o = sequence_of<S>(dq, n, "dq", lead, T), od = sequence_of<S>(dqd, n, "dqd", lead, T);
    check_outs({{&dq, "dq"}, {&dqd, "dqd"}},
               {{extent_of(q0), "q0"}, {extent_of(qd0), "qd0"}, {extent_of(tau), "tau"}, {extent_of(dq0), "dq0"},
                {extent_of(dqd0), "dqd0"}, {extent_of(dtau), "dtau"}});
    return run(lead, failed_dof, stream, {{extent_of(dq), "dq"}, {extent_of(dqd), "dqd"}},
               [&](auto& r) { return r.jvp(x0, xd0, u, v0, vd0, du, o, od); },
               [&](auto& r, int* f, cudaStream_t s) { return r.jvp_async(x0, xd0, u, v0, vd0, du, o, od, f, s); });
  }

 private:
  std::string not_cuda(const Lead& lead) const {
    return "the arrays are on " + where_str(true, lead.device) + ", but these step derivatives run on backend '" +
           backend() + "': make them with backend='cuda' or 'auto'";
  }
  std::string other_device(const Lead& lead) const {
    return "the arrays are on " + where_str(true, lead.device) + ", but these step derivatives were made on " +
           where_str(true, device_) + " (scandyn.autograd.StepDerivatives makes one per device)";
  }
  static void check_launch(int err) {
#if SCANDYN_HAS_CUDA
    if (err != cudaSuccess)
      throw BackendError(std::string("backend 'cuda': queuing the step derivatives on the caller's stream failed: ") +
                         cudaGetErrorName(cudaError_t(err)) + ": " + cudaGetErrorString(cudaError_t(err)));
#else
    (void)err;
#endif
  }

  // A rollout call: host arrays through host(r) (RolloutDerivatives, or the CUDA
  // rollouts' host calls on backend cuda), CUDA arrays through device(r, failed, stream).
  template <class Host, class Device>
  CallStatus run(const Lead& lead, const std::optional<OutArray>& failed_dof, std::uintptr_t stream,
                 std::initializer_list<std::pair<Extent, const char*>> outputs, Host&& host, Device&& device) {
    if (lead.cuda) {
#if SCANDYN_HAS_CUDA
      if (!cuda_rollout_) throw DeviceError(not_cuda(lead));
      if (device_ != lead.device) throw DeviceError(other_device(lead));
      int* failed = failed_dof_of(failed_dof, lead, "the rollout derivatives", outputs);
      nb::gil_scoped_release release;
      std::lock_guard<std::mutex> lock(mutex_);
      std::optional<cuda::DeviceScope> scope;
      enter_device(scope, lead.device);
      check_launch(device(*cuda_rollout_, failed, reinterpret_cast<cudaStream_t>(stream)));
      return queued_status();
#else
      (void)failed_dof, (void)stream, (void)outputs, (void)device;
      throw_no_cuda_backend(lead.device);
#endif
    }
    BatchStatus st;
    {
      nb::gil_scoped_release release;
      std::lock_guard<std::mutex> lock(mutex_);
#if SCANDYN_HAS_CUDA
      if (cuda_rollout_) {
        std::optional<cuda::DeviceScope> scope;
        enter_device(scope, device_);
        st = host(*cuda_rollout_);
      } else {
        st = host(*rollout_);
      }
#else
      st = host(*rollout_);
#endif
    }
    return call_status(st, lead.batch);
  }

  // The step-Jacobian engine for B instances (made again, larger, when B grows); the
  // caller holds mutex_ and has made the device current.
  sim::StepDerivatives<S>& step_engine(Index B) {
    if (!engine_ || engine_max_ < B) {
      BackendOptions o = options_;
      o.max_batch = std::max<Index>(B, 1);
      engine_.reset();  // the old engine's memory goes first
      engine_ = sim::make_step_derivatives(sim_->setup(), o);
      engine_max_ = o.max_batch;
    }
    return *engine_;
  }

  std::unique_ptr<sim::Simulator<S>> sim_;  // holds the setup
  BackendOptions options_;
  int device_ = -1;  // cuda: the device the objects were made on
  std::mutex mutex_;
  std::unique_ptr<sim::RolloutDerivatives<S>> rollout_;  // serial, openmp
#if SCANDYN_HAS_CUDA
  std::unique_ptr<cuda::CudaRolloutDerivatives<S>> cuda_rollout_;  // cuda
#endif
  std::unique_ptr<sim::StepDerivatives<S>> engine_;
  Index engine_max_ = 0;
};

template <class S>
void bind_step(nb::module_& m, const char* name) {
  using P = PyStepDerivatives<S>;
  nb::class_<P>(m, name)
      .def(nb::init<const std::string&, const std::string&, const std::string&, const std::string&, int>(),
           "scene_json"_a, "source"_a, "base_dir"_a, "backend"_a, "device"_a = -1)
      .def_prop_ro("nv", &P::nv)
      .def_prop_ro("nq", &P::nq)
      .def_prop_ro("joints", &P::joints)
      .def_prop_ro("dt", &P::dt)
      .def_prop_ro("device", &P::device)
      .def_prop_ro("backend", &P::backend)
      .def("jacobian", &P::jacobian, "q"_a, "qd"_a, "tau"_a, "q_next"_a, "qd_next"_a, "J"_a, "blocks"_a = nb::none(),
           "failed_dof"_a = nb::none(), "stream"_a = 0)
      .def("rollout", &P::rollout, "q0"_a, "qd0"_a, "tau"_a, "q"_a, "qd"_a, "failed_dof"_a = nb::none(),
           "stream"_a = 0)
      .def("vjp", &P::vjp, "q0"_a, "qd0"_a, "tau"_a, "gq"_a, "gqd"_a, "gq0"_a, "gqd0"_a, "gtau"_a,
           "failed_dof"_a = nb::none(), "stream"_a = 0)
      .def("jvp", &P::jvp, "q0"_a, "qd0"_a, "tau"_a, "dq0"_a, "dqd0"_a, "dtau"_a, "dq"_a, "dqd"_a,
           "failed_dof"_a = nb::none(), "stream"_a = 0);
}

}  // namespace

void bind_derivatives(nb::module_& m) {
  nb::class_<PyIdDerivatives> id(m, "IdDerivatives");
  def_derivative_init(id, [](const auto& md, const BackendOptions& o) { return make_id_derivatives(md, o); });
  id.def("compute",
           [](PyIdDerivatives& e, const InArray& q, const InArray& qd, const InArray& qdd, const OutArray& dq,
              const OutArray& dqd, const OutArray& M, std::uintptr_t stream) {
             if (e.is_float) id_derivatives_compute<float>(e, q, qd, qdd, dq, dqd, M, stream);
             else id_derivatives_compute<double>(e, q, qd, qdd, dq, dqd, M, stream);
           },
           "q"_a, "qd"_a, "qdd"_a, "dtau_dq"_a, "dtau_dqd"_a, "M"_a, "stream"_a = 0);
  def_derivative_engine(id);

  nb::class_<PyIdSecondDerivatives> id2(m, "IdSecondDerivatives");
  def_derivative_init(id2, [](const auto& md, const BackendOptions& o) { return make_id_second_derivatives(md, o); });
  id2.def("compute",
          [](PyIdSecondDerivatives& e, const InArray& q, const InArray& qd, const InArray& qdd, const OutArray& dq2,
             const OutArray& dqd2, const OutArray& dqdqd, const OutArray& dM, std::uintptr_t stream) {
            if (e.is_float) id_second_derivatives_compute<float>(e, q, qd, qdd, dq2, dqd2, dqdqd, dM, stream);
            else id_second_derivatives_compute<double>(e, q, qd, qdd, dq2, dqd2, dqdqd, dM, stream);
          },
          "q"_a, "qd"_a, "qdd"_a, "d2tau_dq2"_a, "d2tau_dqd2"_a, "d2tau_dqdqd"_a, "dM_dq"_a, "stream"_a = 0);
  def_engine_properties(id2);

  nb::class_<PyFdDerivatives> fd(m, "FdDerivatives");
  def_derivative_init(fd, [](const auto& md, const BackendOptions& o) { return make_fd_derivatives(md, o); });
  fd.def("compute",
           [](PyFdDerivatives& e, const InArray& q, const InArray& qd, const InArray& tau, const OutArray& qdd,
              const OutArray& dq, const OutArray& dqd, const OutArray& dtau, const std::optional<OutArray>& failed_dof,
              std::uintptr_t stream) {
             return e.is_float ? fd_derivatives_compute<float>(e, q, qd, tau, qdd, dq, dqd, dtau, failed_dof, stream)
                               : fd_derivatives_compute<double>(e, q, qd, tau, qdd, dq, dqd, dtau, failed_dof, stream);
           },
           "q"_a, "qd"_a, "tau"_a, "qdd"_a, "dqdd_dq"_a, "dqdd_dqd"_a, "dqdd_dtau"_a, "failed_dof"_a = nb::none(),
           "stream"_a = 0);
  def_derivative_engine(fd);

  // The directional derivatives of forward dynamics (make_fd_directional_derivatives):
  // __init__(model, dtype, backend, max_batch, threads=0, device=-1, method="auto").
  nb::class_<PyFdDirectional> fdd(m, "FdDirectionalDerivatives");
  fdd.def(
      "__init__",
      [](PyFdDirectional* self, std::shared_ptr<PyModel> model, const std::string& dtype, const std::string& backend,
         Index max_batch, int threads, int device, const std::string& method) {
        BackendOptions o = engine_options(backend, max_batch, threads);
        o.fd_method = parse_fd_method(method);
        init_engine(self, std::move(model), dtype, max_batch, device,
                    [&](const ModelTpl<float>& md) { return make_fd_directional_derivatives(md, o); },
                    [&](const ModelTpl<double>& md) { return make_fd_directional_derivatives(md, o); });
      },
      "model"_a, "dtype"_a, "backend"_a, "max_batch"_a, "threads"_a = 0, "device"_a = -1, "method"_a = "auto");
  fdd.def(
      "jvp",
      [](PyFdDirectional& e, const InArray& q, const InArray& qd, const InArray& tau, const InArray& dq,
         const InArray& dqd, const InArray& dtau, const OutArray& qdd, const OutArray& dqdd) {
        auto run = [&](auto tag) {
          using S = decltype(tag);
          return fd_directional_call<S>(e, q, qd, tau, {{&dq, "dq"}, {&dqd, "dqd"}, {&dtau, "dtau"}},
                                        {{&qdd, "qdd"}, {&dqdd, "dqdd"}}, [](auto& eng, const auto& in, auto& x, auto& y) {
                                          return eng.jvp(in, x[0], x[1], x[2], y[0], y[1]);
                                        });
        };
        return e.is_float ? run(float()) : run(double());
      },
      "q"_a, "qd"_a, "tau"_a, "dq"_a, "dqd"_a, "dtau"_a, "qdd"_a, "dqdd"_a);
  fdd.def(
      "vjp",
      [](PyFdDirectional& e, const InArray& q, const InArray& qd, const InArray& tau, const InArray& w,
         const OutArray& qdd, const OutArray& gq, const OutArray& gqd, const OutArray& gtau) {
        auto run = [&](auto tag) {
          using S = decltype(tag);
          return fd_directional_call<S>(e, q, qd, tau, {{&w, "w"}}, {{&qdd, "qdd"}, {&gq, "gq"}, {&gqd, "gqd"},
                                        {&gtau, "gtau"}}, [](auto& eng, const auto& in, auto& x, auto& y) {
                                          return eng.vjp(in, x[0], y[0], y[1], y[2], y[3]);
                                        });
        };
        return e.is_float ? run(float()) : run(double());
      },
      "q"_a, "qd"_a, "tau"_a, "w"_a, "qdd"_a, "gq"_a, "gqd"_a, "gtau"_a);
  def_engine_properties(fdd);

  // The status of a CUDA step or rollout call from its failed DoFs read back (B ints: -1,
  // a pivot's DoF, or -2 - i for a result not finite at DoF i): summarize_step_failures.
  m.def("status_of_step_failures",
        [](const nb::ndarray<const int, nb::ndim<1>, nb::c_contig, nb::device::cpu>& failed) {
          const Index B = Index(failed.shape(0));
          std::vector<int> codes(failed.data(), failed.data() + B);
          return call_status(summarize_step_failures(codes.data(), B), B);
        },
        "failed_dof"_a);

  bind_step<double>(m, "StepDerivatives64");
  bind_step<float>(m, "StepDerivatives32");
}

}  // namespace scandyn::py
