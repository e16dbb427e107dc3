// python/src/module.cpp: the extension module scandyn._scandyn (nanobind).
//
// A thin layer over the library: models (load_model), the four engines of the
// engine API (scandyn/engine.hpp) in float and double, and the conversion of
// caller arrays (nb::ndarray: the buffer protocol or DLPack) into BatchViews with
// the arrays' own strides. No algorithm and no instance loop lives here; nothing is
// copied: an array that cannot be described by a BatchView is an error.
//
// Checks done here (each raises an exception of scandyn.errors, python/scandyn/errors.py):
//   - device: every array of a call in host memory, or every one on the same CUDA
//     device (DeviceError otherwise). Host arrays go to the engine's compute(); CUDA
//     arrays to the CUDA engine's compute_async() on the caller's stream (a
//     cudaStream_t passed as an integer by the Python layer): one launch, no copy,
//     no synchronisation (DeviceError for a CUDA array and an engine of another
//     backend or device);
//   - dtype: every array in the engine's precision (DTypeError);
//   - shape: (nv,) for one state or (B, nv) for a batch, every input and out with the
//     same leading shape, B <= max_batch; (.., nv, nv) for the mass matrix with each
//     instance's block row-major (ShapeError);
//   - out: writable, entries that do not overlap one another or any input (ShapeError);
//   - fext: (.., nv, 6) C-contiguous (the engines read Force structs), [moment; force].
// The four dynamics engines take devices= (BackendOptions::devices, parse_devices' text):
// a cuda engine that shards host batches across those devices (scandyn/sharded.hpp);
// CUDA arrays run on their own device only (engines.hpp's queue_on_device).
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/shared_ptr.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/vector.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <initializer_list>
#include <limits>
#include <memory>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/sharded.hpp"
#include "arrays.hpp"
#include "engines.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "shared.hpp"
#if SCANDYN_PY_SPARSE_LOOPS  // python/CMakeLists.txt: linked with scandyn_factor_graph (CHOLMOD)
#include "scandyn/factor_graph/sparse_constrained_dynamics.hpp"
#endif

namespace nb = nanobind;
using namespace nb::literals;

namespace scandyn::py {
void bind_simulator(nb::module_& m);  // python/src/simulator.cpp
namespace {

// ---- errors: C++ exceptions translated to scandyn.errors classes ---------------

// ShapeError, DTypeError, DeviceError: shared.hpp (shared with kinematics.cpp)

void raise_as(const char* cls, const char* what) {
  nb::object type = nb::module_::import_("scandyn.errors").attr(cls);
  PyErr_SetString(type.ptr(), what);
}

// ---- models --------------------------------------------------------------------

// PyModel: shared.hpp

std::shared_ptr<PyModel> load(const std::string& spec, bool allow_nonphysical_inertia, bool floating_base) {
  BuildOptions options;
  options.require_physical_inertia = !allow_nonphysical_inertia;
  options.floating_base = floating_base;
  auto m = std::make_shared<PyModel>();
  {
    nb::gil_scoped_release release;  // a rope of 10^6 links takes a while
    m->md = load_model(spec, options);
  }
  return m;
}

// ---- arrays ------------------------------------------------------------------

// InArray, OutArray, Lead, view_of, the device / dtype / shape / overlap checks:
// arrays.hpp (shared with kinematics.cpp)

// fext: (nv, 6) or (B, nv, 6), C-contiguous, Force<S> = [moment; force] per body.
template <class S>
const Force<S>* fext_of(const std::optional<InArray>& f, Index nv, Lead& lead) {
  if (!f) return nullptr;
  const InArray& a = *f;
  check_device(a, "fext", lead);
  if (!has_dtype<S>(a))
    throw DTypeError("fext has dtype " + dtype_name(a.dtype()) + ", expected " + scalar_name<S>() +
                     " (every array of a call shares one dtype)");
  const size_t want = lead.single ? 2 : 3;
  bool ok = a.ndim() == want && Index(a.shape(want - 2)) == nv && a.shape(want - 1) == 6 &&
            (lead.single || Index(a.shape(0)) == lead.batch);
  if (!ok)
    throw ShapeError("fext has shape " + shape_str(a) + ", expected " +
                     (lead.single ? std::string("(") : "(" + std::to_string(lead.batch) + ", ") + std::to_string(nv) +
                     ", 6): one wrench [moment; force] per body, in the body's frame");
  // C-contiguous: the engines read fext[b * nv + i] as a Force struct
  std::ptrdiff_t expect = 1;
  for (size_t i = a.ndim(); i-- > 0;) {
    if (a.shape(i) > 1 && a.stride(i) != expect)
      throw ShapeError("fext must be C-contiguous (the engines read it as packed [moment; force] structs); "
                       "it is strided: pass numpy.ascontiguousarray(fext)");
    expect *= std::ptrdiff_t(a.shape(i));
  }
  static_assert(sizeof(Force<S>) == 6 * sizeof(S), "Force<S> is six packed scalars");
  return static_cast<const Force<S>*>(a.data());
}

// devices: BackendOptions::devices as parse_devices reads it ("current", "all", "0,1"); the
// Python layer passes a list of ordinals joined by commas.
BackendOptions options_of(const std::string& backend, Index max_batch, const std::string& strategy,
                          const std::string& method, bool fallback_aba, int threads,
                          const std::string& devices = "current") {
  BackendOptions o;
  o.backend = parse_backend(backend);
  o.strategy = parse_strategy(strategy);
  o.fd_method = parse_fd_method(method);
  o.fallback_aba = fallback_aba;
  o.threads = threads;
  if (max_batch < 1) throw ShapeError("max_batch must be at least 1, got " + std::to_string(max_batch));
  o.max_batch = max_batch;
  o.devices = parse_devices(devices);
  return o;
}

// ---- engines -------------------------------------------------------------------
// ---- engines -------------------------------------------------------------------

// PyEngine, init_engine, engine_device and the CUDA device path (queue_on_device):
// engines.hpp (shared with kinematics.cpp)

using PyId = PyEngine<InverseDynamics>;
using PyBias = PyEngine<BiasForces>;
using PyMass = PyEngine<MassMatrix>;
using PyFd = PyEngine<ForwardDynamics>;

template <class S>
void id_compute(PyId& e, const InArray& q, const InArray& qd, const InArray& qdd, const OutArray& out,
                const std::optional<InArray>& fext, std::uintptr_t stream) {
  const Index nv = e.nv();
  Lead lead;
  IdBatchIn<S> in;
  in.q = view_of<const S>(q, e.nq(), "q", lead, true, e.nq() == e.nv() ? "nv" : "nq");
  in.qd = view_of<const S>(qd, nv, "qd", lead, false);
  in.qdd = view_of<const S>(qdd, nv, "qdd", lead, false);
  BatchView<S> tau = view_of<S>(out, nv, "out", lead, false);
  in.fext = fext_of<S>(fext, e.nbodies(), lead);
  check_max_batch(lead, e.max_batch);
  check_no_self_overlap(out, "out");
  check_out_alone(out, {{extent_of(q), "q"}, {extent_of(qd), "qd"}, {extent_of(qdd), "qdd"}});
  if (fext) check_out_alone(out, {{extent_of(*fext), "fext"}});
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(e.mutex);
  if (lead.cuda)
    return queue_on_device<S>(e, lead, stream, [&](auto& c, cudaStream_t s) { return c.compute_async(in, tau, s); });
  if constexpr (std::is_same_v<S, float>) e.ef->compute(in, tau);
  else e.ed->compute(in, tau);
}

template <class S>
void bias_compute(PyBias& e, const InArray& q, const InArray& qd, const OutArray& out,
                  const std::optional<InArray>& fext, std::uintptr_t stream) {
  const Index nv = e.nv();
  Lead lead;
  BiasBatchIn<S> in;
  in.q = view_of<const S>(q, e.nq(), "q", lead, true, e.nq() == e.nv() ? "nv" : "nq");
  in.qd = view_of<const S>(qd, nv, "qd", lead, false);
  BatchView<S> h = view_of<S>(out, nv, "out", lead, false);
  in.fext = fext_of<S>(fext, e.nbodies(), lead);
  check_max_batch(lead, e.max_batch);
  check_no_self_overlap(out, "out");
  check_out_alone(out, {{extent_of(q), "q"}, {extent_of(qd), "qd"}});
  if (fext) check_out_alone(out, {{extent_of(*fext), "fext"}});
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(e.mutex);
  if (lead.cuda)
    return queue_on_device<S>(e, lead, stream, [&](auto& c, cudaStream_t s) { return c.compute_async(in, h, s); });
  if constexpr (std::is_same_v<S, float>) e.ef->compute(in, h);
  else e.ed->compute(in, h);
}

template <class S>
void mass_compute(PyMass& e, const InArray& q, const OutArray& out, std::uintptr_t stream) {
  const Index nv = e.nv();
  Lead lead;
  BatchView<const S> qv = view_of<const S>(q, e.nq(), "q", lead, true, e.nq() == e.nv() ? "nv" : "nq");
  BatchView<S> M = matrix_view_of<S>(out, nv, "out", lead);
  check_max_batch(lead, e.max_batch);
  check_no_self_overlap(out, "out");
  check_out_alone(out, {{extent_of(q), "q"}});
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(e.mutex);
  if (lead.cuda)
    return queue_on_device<S>(e, lead, stream, [&](auto& c, cudaStream_t s) { return c.compute_async(qv, M, s); });
  if constexpr (std::is_same_v<S, float>) e.ef->compute(qv, M);
  else e.ed->compute(qv, M);
}

// CallStatus, call_status, failed_dof_of: engines.hpp (shared with derivatives.cpp)

// The status of a CUDA call from its failed DoFs read back by the caller (B ints:
// -1 or the DoF whose pivot failed), for the method `method` ran.
CallStatus status_of_failed_dofs(const nb::ndarray<const int, nb::ndim<1>, nb::c_contig, nb::device::cpu>& failed,
                                 const std::string& method) {
  const Index B = Index(failed.shape(0));
  return call_status(summarize_failures(failed.data(), B, pivot_failure(parse_fd_method(method))), B);
}

template <class S>
CallStatus fd_compute(PyFd& e, const InArray& q, const InArray& qd, const InArray& tau, const OutArray& out,
                    const std::optional<InArray>& fext, const std::optional<OutArray>& failed_dof,
                    std::uintptr_t stream) {
  const Index nv = e.nv();
  Lead lead;
  FdBatchIn<S> in;
  in.q = view_of<const S>(q, e.nq(), "q", lead, true, e.nq() == e.nv() ? "nv" : "nq");
  in.qd = view_of<const S>(qd, nv, "qd", lead, false);
  in.tau = view_of<const S>(tau, nv, "tau", lead, false);
  BatchView<S> qdd = view_of<S>(out, nv, "out", lead, false);
  in.fext = fext_of<S>(fext, e.nbodies(), lead);
  check_max_batch(lead, e.max_batch);
  check_no_self_overlap(out, "out");
  check_out_alone(out, {{extent_of(q), "q"}, {extent_of(qd), "qd"}, {extent_of(tau), "tau"}});
  if (fext) check_out_alone(out, {{extent_of(*fext), "fext"}});
  int* failed = nullptr;  // CUDA arrays: the caller's (B,) int32 array on the same device
  if (lead.cuda) failed = failed_dof_of(failed_dof, lead, "forward dynamics", {{extent_of(out), "out"}});
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(e.mutex);
  if (lead.cuda) {
    queue_on_device<S>(e, lead, stream,
                       [&](auto& c, cudaStream_t s) { return c.compute_async(in, qdd, failed, s); });
    return queued_status();
  }
  BatchStatus st;
  if constexpr (std::is_same_v<S, float>) st = e.ef->compute(in, qdd);
  else st = e.ed->compute(in, qdd);
  return call_status(st, lead.batch);
}

// ---- hybrid dynamics ---------------------------------------------------------------

using PyHybrid = PyEngine<HybridDynamics>;

// qdd_out, tau_out = hybrid dynamics of (q, qd, qdd at the prescribed DoFs, tau at the others).
template <class S>
CallStatus hybrid_compute(PyHybrid& e, const InArray& q, const InArray& qd, const InArray& qdd, const InArray& tau,
                          const OutArray& qdd_out, const OutArray& tau_out, const std::optional<InArray>& fext,
                          const std::optional<OutArray>& failed_dof, std::uintptr_t stream) {
  const Index nv = e.nv();
  Lead lead;
  HybridBatchIn<S> in;
  in.q = view_of<const S>(q, e.nq(), "q", lead, true, e.nq() == e.nv() ? "nv" : "nq");
  in.qd = view_of<const S>(qd, nv, "qd", lead, false);
  in.qdd = view_of<const S>(qdd, nv, "qdd", lead, false);
  in.tau = view_of<const S>(tau, nv, "tau", lead, false);
  BatchView<S> qo = view_of<S>(qdd_out, nv, "qdd_out", lead, false);
  BatchView<S> to = view_of<S>(tau_out, nv, "tau_out", lead, false);
  in.fext = fext_of<S>(fext, e.nbodies(), lead);
  check_max_batch(lead, e.max_batch);
  for (const auto& [a, name] : {std::pair<const OutArray*, const char*>{&qdd_out, "qdd_out"}, {&tau_out, "tau_out"}}) {
    check_no_self_overlap(*a, name);
    check_out_alone(*a, {{extent_of(q), "q"}, {extent_of(qd), "qd"}, {extent_of(qdd), "qdd"}, {extent_of(tau), "tau"}},
                    name);
    if (fext) check_out_alone(*a, {{extent_of(*fext), "fext"}}, name);
  }
  check_out_alone(tau_out, {{extent_of(qdd_out), "qdd_out"}}, "tau_out");
  int* failed = nullptr;
  if (lead.cuda)
    failed = failed_dof_of(failed_dof, lead, "hybrid dynamics",
                           {{extent_of(qdd_out), "qdd_out"}, {extent_of(tau_out), "tau_out"}});
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(e.mutex);
  if (lead.cuda) {
    queue_on_device<S>(e, lead, stream,
                       [&](auto& c, cudaStream_t s) { return c.compute_async(in, qo, to, failed, s); });
    return queued_status();
  }
  BatchStatus st;
  if constexpr (std::is_same_v<S, float>) st = e.ef->compute(in, qo, to);
  else st = e.ed->compute(in, qo, to);
  return call_status(st, lead.batch);
}

// ---- closed loops --------------------------------------------------------------------

// A loop set with the model it was made for (its bodies are that model's indices).
struct PyLoops {
  std::shared_ptr<PyModel> model;
  LoopSet loops;
};

using PyConstrained = PyEngine<ConstrainedForwardDynamics>;

Index rows_of(const PyConstrained& e) { return e.is_float ? e.ef->rows() : e.ed->rows(); }

// qdd_out, lambda_out = closed-loop forward dynamics of (q, qd, tau).
template <class S>
CallStatus constrained_compute(PyConstrained& e, const InArray& q, const InArray& qd, const InArray& tau,
                               const OutArray& qdd_out, const OutArray& lambda_out, const std::optional<InArray>& fext,
                               const std::optional<OutArray>& failed_dof, std::uintptr_t stream) {
  const Index nv = e.nv(), m = rows_of(e);
  Lead lead;
  FdBatchIn<S> in = fd_inputs<S>(nv, q, qd, tau, lead);
  BatchView<S> qo = view_of<S>(qdd_out, nv, "qdd_out", lead, false);
  BatchView<S> lo = view_of<S>(lambda_out, m, "lambda_out", lead, false, "m");
  in.fext = fext_of<S>(fext, e.nbodies(), lead);
  check_max_batch(lead, e.max_batch);
  for (const auto& [a, name] :
       {std::pair<const OutArray*, const char*>{&qdd_out, "qdd_out"}, {&lambda_out, "lambda_out"}}) {
    check_no_self_overlap(*a, name);
    check_out_alone(*a, {{extent_of(q), "q"}, {extent_of(qd), "qd"}, {extent_of(tau), "tau"}}, name);
    if (fext) check_out_alone(*a, {{extent_of(*fext), "fext"}}, name);
  }
  check_out_alone(lambda_out, {{extent_of(qdd_out), "qdd_out"}}, "lambda_out");
  int* failed = nullptr;
  if (lead.cuda)
    failed = failed_dof_of(failed_dof, lead, "closed-loop forward dynamics",
                           {{extent_of(qdd_out), "qdd_out"}, {extent_of(lambda_out), "lambda_out"}});
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(e.mutex);
  if (lead.cuda) {
    queue_on_device<S>(e, lead, stream,
                       [&](auto& c, cudaStream_t s) { return c.compute_async(in, qo, lo, failed, s); });
    return queued_status();
  }
  BatchStatus st;
  if constexpr (std::is_same_v<S, float>) st = e.ef->compute(in, qo, lo);
  else st = e.ed->compute(in, qo, lo);
  return call_status(st, lead.batch);
}

// phi, velocity (J qd) of (q, qd); either output may be None.
template <class S>
void residual_compute(PyConstrained& e, const InArray& q, const InArray& qd, const std::optional<OutArray>& phi,
                      const std::optional<OutArray>& velocity, std::uintptr_t stream) {
  const Index nv = e.nv(), m = rows_of(e);
  Lead lead;
  const BatchView<const S> qv = view_of<const S>(q, nv, "q", lead, true);
  const BatchView<const S> qdv = view_of<const S>(qd, nv, "qd", lead, false);
  BatchView<S> pv{}, vv{};
  for (const auto& [a, v, name] : {std::tuple<const std::optional<OutArray>*, BatchView<S>*, const char*>{
                                       &phi, &pv, "phi"}, {&velocity, &vv, "velocity"}}) {
    if (!*a) continue;
    *v = view_of<S>(**a, m, name, lead, false, "m");
    check_no_self_overlap(**a, name);
    check_out_alone(**a, {{extent_of(q), "q"}, {extent_of(qd), "qd"}}, name);
  }
  if (phi && velocity) check_out_alone(*velocity, {{extent_of(*phi), "phi"}}, "velocity");
  check_max_batch(lead, e.max_batch);
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(e.mutex);
  if (lead.cuda)
    return queue_on_device<S>(e, lead, stream,
                              [&](auto& c, cudaStream_t s) { return c.residual_async(qv, qdv, pv, vv, s); });
  if constexpr (std::is_same_v<S, float>) e.ef->residual(qv, qdv, pv, vv);
  else e.ed->residual(qv, qdv, pv, vv);
}

}  // namespace
}  // namespace scandyn::py

NB_MODULE(_scandyn, m) {
  using namespace scandyn;
  using namespace scandyn::py;
  m.doc() = "scandyn's extension module: models and engines (see the scandyn package for the API)";
  m.attr("__version__") = SCANDYN_VERSION;
  m.attr("has_cuda") = bool(SCANDYN_HAS_CUDA);
  m.attr("has_openmp") = bool(SCANDYN_HAS_OPENMP);
  // the simulator's sparse loop path (scene "loop_solver": "sparse"; docs/loops.md):
  // the factor graph's CHOLMOD solver, registered at import when the module has it
  m.attr("has_sparse_loops") = bool(SCANDYN_PY_SPARSE_LOOPS);
#if SCANDYN_PY_SPARSE_LOOPS
  factor_graph::register_sparse_loop_solver();
#endif

  nb::register_exception_translator([](const std::exception_ptr& p, void*) {
    try {
      std::rethrow_exception(p);
    } catch (const ModelError& e) {
      raise_as("ModelError", e.what());
    } catch (const BackendError& e) {
      raise_as("BackendError", e.what());
    } catch (const ShapeError& e) {
      raise_as("ShapeError", e.what());
    } catch (const DTypeError& e) {
      raise_as("DTypeError", e.what());
    } catch (const DeviceError& e) {
      raise_as("DeviceError", e.what());
    } catch (const LoopError& e) {
      raise_as("LoopError", e.what());
    }
  });

  // ---- models
  nb::class_<PyModel>(m, "Model")
      .def_prop_ro("name", [](const PyModel& p) { return p.md.name; })
      .def_prop_ro("source", [](const PyModel& p) { return p.md.source; })
      .def_prop_ro("root_link", [](const PyModel& p) { return p.md.root_link; })
      .def_prop_ro("nv", [](const PyModel& p) { return p.md.nv(); })
      .def_prop_ro("nq", [](const PyModel& p) { return p.md.nq(); })
      .def_prop_ro("floating_base", [](const PyModel& p) { return p.md.floating_base(); })
      .def_prop_ro("joint_names", [](const PyModel& p) { return p.md.joint_names; })
      .def_prop_ro("link_names", [](const PyModel& p) { return p.md.link_names; })
      .def_prop_ro("parents",
                   [](const PyModel& p) {
                     std::vector<Index> r;
                     for (const auto& b : p.md.bodies) r.push_back(b.parent);
                     return r;
                   })
      .def_prop_ro("joint_types",
                   [](const PyModel& p) {
                     std::vector<std::string> r;
                     for (const auto& b : p.md.bodies)
                       r.push_back(b.type == JointType::Prismatic   ? "prismatic"
                                   : b.type == JointType::Spherical ? "spherical"
                                   : b.type == JointType::Free      ? "free"
                                                                    : "revolute");
                     return r;
                   })
      .def_prop_ro("q_lower", [](const PyModel& p) { return p.md.q_lower; })
      .def_prop_ro("q_upper", [](const PyModel& p) { return p.md.q_upper; })
      .def_prop_ro("gravity", [](const PyModel& p) {
        return std::vector<double>{p.md.gravity[0], p.md.gravity[1], p.md.gravity[2]};
      })
      .def_prop_ro("frames", [](const PyModel& p) { return p.md.frame_names; });
  m.def("load_model", &load, "spec"_a, "allow_nonphysical_inertia"_a = false, "floating_base"_a = false);
  m.def("is_generator_spec", &is_generator_spec, "spec"_a);
  m.def("find_model_file", [](const std::string& p) { return find_model_file(p); }, "path"_a);
  m.def("model_search_dirs", &model_search_dirs);
  m.def("backend_unusable", [](const std::string& b) { return backend_unusable(parse_backend(b)); }, "backend"_a);
  m.def("openmp_threads", &openmp_threads);
  m.def("parse_devices", &parse_devices, "text"_a);  // scandyn/sharded.hpp: "all", "current", "0,1"

  // ---- status
  nb::class_<CallStatus>(m, "Status")
      .def_ro("failed", &CallStatus::failed)
      .def_ro("first_instance", &CallStatus::first_instance)
      .def_ro("first_dof", &CallStatus::first_dof)
      .def_ro("fell_back", &CallStatus::fell_back)
      .def_ro("retried", &CallStatus::retried)
      .def_ro("reason", &CallStatus::reason)
      .def_ro("message", &CallStatus::message)
      .def_ro("failed_dof", &CallStatus::failed_dof)
      .def_ro("queued", &CallStatus::queued)
      .def_prop_ro("ok", [](const CallStatus& s) { return s.failed == 0; });
  m.def("status_of_failed_dofs", &status_of_failed_dofs, "failed_dof"_a, "method"_a);

  // ---- CUDA streams (the device path's one explicit wait, for JAX results)
  m.def("synchronize_stream", [](std::uintptr_t stream) {
#if SCANDYN_HAS_CUDA
    cudaError_t err;
    {
      nb::gil_scoped_release release;
      err = cudaStreamSynchronize(reinterpret_cast<cudaStream_t>(stream));
    }
    if (err != cudaSuccess)
      throw BackendError(std::string("backend 'cuda': waiting for the stream: ") + cudaGetErrorName(err) + ": " +
                         cudaGetErrorString(err));
#else
    (void)stream;
    throw BackendError("backend 'cuda' is not available in this build");
#endif
  }, "stream"_a);

  // ---- engines: (model, dtype, backend, max_batch, ...) and compute(..., out, fext)
  auto common = [](auto& cls) { def_engine_properties(cls); };  // engines.hpp

  nb::class_<PyId> id(m, "InverseDynamics");
  id.def("__init__",
         [](PyId* self, std::shared_ptr<PyModel> model, const std::string& dtype, const std::string& backend,
            Index max_batch, const std::string& strategy, int threads, int device, const std::string& devices) {
           BackendOptions o = options_of(backend, max_batch, strategy, "auto", false, threads, devices);
           init_engine(self, std::move(model), dtype, max_batch, device,
                       [&](const ModelTpl<float>& md) { return make_inverse_dynamics<float>(md, o); },
                       [&](const ModelTpl<double>& md) { return make_inverse_dynamics<double>(md, o); });
         },
         "model"_a, "dtype"_a, "backend"_a, "max_batch"_a, "strategy"_a = "auto", "threads"_a = 0, "device"_a = -1,
         "devices"_a = "current")
      .def("compute",
           [](PyId& e, const InArray& q, const InArray& qd, const InArray& qdd, const OutArray& out,
              const std::optional<InArray>& fext, std::uintptr_t stream) {
             if (e.is_float) id_compute<float>(e, q, qd, qdd, out, fext, stream);
             else id_compute<double>(e, q, qd, qdd, out, fext, stream);
           },
           "q"_a, "qd"_a, "qdd"_a, "out"_a, "fext"_a = nb::none(), "stream"_a = 0);
  common(id);

  nb::class_<PyBias> bias(m, "BiasForces");
  bias.def("__init__",
           [](PyBias* self, std::shared_ptr<PyModel> model, const std::string& dtype, const std::string& backend,
              Index max_batch, const std::string& strategy, int threads, int device, const std::string& devices) {
             BackendOptions o = options_of(backend, max_batch, strategy, "auto", false, threads, devices);
             init_engine(self, std::move(model), dtype, max_batch, device,
                         [&](const ModelTpl<float>& md) { return make_bias_forces<float>(md, o); },
                         [&](const ModelTpl<double>& md) { return make_bias_forces<double>(md, o); });
           },
           "model"_a, "dtype"_a, "backend"_a, "max_batch"_a, "strategy"_a = "auto", "threads"_a = 0, "device"_a = -1,
           "devices"_a = "current")
      .def("compute",
           [](PyBias& e, const InArray& q, const InArray& qd, const OutArray& out, const std::optional<InArray>& fext,
              std::uintptr_t stream) {
             if (e.is_float) bias_compute<float>(e, q, qd, out, fext, stream);
             else bias_compute<double>(e, q, qd, out, fext, stream);
           },
           "q"_a, "qd"_a, "out"_a, "fext"_a = nb::none(), "stream"_a = 0);
  common(bias);

  nb::class_<PyMass> mass(m, "MassMatrix");
  mass.def("__init__",
           [](PyMass* self, std::shared_ptr<PyModel> model, const std::string& dtype, const std::string& backend,
              Index max_batch, int threads, int device, const std::string& devices) {
             BackendOptions o = options_of(backend, max_batch, "auto", "auto", false, threads, devices);
             init_engine(self, std::move(model), dtype, max_batch, device,
                         [&](const ModelTpl<float>& md) { return make_mass_matrix<float>(md, o); },
                         [&](const ModelTpl<double>& md) { return make_mass_matrix<double>(md, o); });
           },
           "model"_a, "dtype"_a, "backend"_a, "max_batch"_a, "threads"_a = 0, "device"_a = -1,
           "devices"_a = "current")
      .def("compute",
           [](PyMass& e, const InArray& q, const OutArray& out, std::uintptr_t stream) {
             if (e.is_float) mass_compute<float>(e, q, out, stream);
             else mass_compute<double>(e, q, out, stream);
           },
           "q"_a, "out"_a, "stream"_a = 0);
  common(mass);

  nb::class_<PyFd> fd(m, "ForwardDynamics");
  fd.def("__init__",
         [](PyFd* self, std::shared_ptr<PyModel> model, const std::string& dtype, const std::string& backend,
            Index max_batch, const std::string& method, bool fallback_aba, int threads, const std::string& fd_check,
            double fd_check_tol, bool fallback_double, int device, const std::string& devices) {
           BackendOptions o = options_of(backend, max_batch, "auto", method, fallback_aba, threads, devices);
           o.fd_check = parse_fd_check(fd_check);
           if (fd_check_tol > 0) o.fd_check_tol_float = o.fd_check_tol_double = fd_check_tol;  // 0: the default
           o.fallback_double = fallback_double;
           init_engine(self, std::move(model), dtype, max_batch, device,
                       [&](const ModelTpl<float>& md) { return make_forward_dynamics<float>(md, o); },
                       [&](const ModelTpl<double>& md) { return make_forward_dynamics<double>(md, o); });
         },
         "model"_a, "dtype"_a, "backend"_a, "max_batch"_a, "method"_a = "auto", "fallback_aba"_a = false,
         "threads"_a = 0, "fd_check"_a = "auto", "fd_check_tol"_a = 0.0, "fallback_double"_a = false,
         "device"_a = -1, "devices"_a = "current")
      .def("compute",
           [](PyFd& e, const InArray& q, const InArray& qd, const InArray& tau, const OutArray& out,
              const std::optional<InArray>& fext, const std::optional<OutArray>& failed_dof, std::uintptr_t stream) {
             return e.is_float ? fd_compute<float>(e, q, qd, tau, out, fext, failed_dof, stream)
                               : fd_compute<double>(e, q, qd, tau, out, fext, failed_dof, stream);
           },
           "q"_a, "qd"_a, "tau"_a, "out"_a, "fext"_a = nb::none(), "failed_dof"_a = nb::none(), "stream"_a = 0)
      .def_prop_ro("method", [](const PyFd& e) {
        return std::string(to_string(e.is_float ? e.ef->method() : e.ed->method()));
      });
  common(fd);

  nb::class_<PyHybrid> hybrid(m, "HybridDynamics");
  hybrid.def("__init__",
             [](PyHybrid* self, std::shared_ptr<PyModel> model, const std::string& dtype, const std::string& backend,
                Index max_batch, const std::vector<int>& prescribed, int threads, int device) {
               const Index nv = model->md.nv();
               if (Index(prescribed.size()) != nv)
                 throw ShapeError("prescribed has " + std::to_string(prescribed.size()) + " entries, expected nv = " +
                                  std::to_string(nv) + " (nonzero: the DoF's acceleration is given)");
               const std::vector<unsigned char> mask(prescribed.begin(), prescribed.end());
               BackendOptions o = options_of(backend, max_batch, "auto", "auto", false, threads);
               init_engine(self, std::move(model), dtype, max_batch, device,
                           [&](const ModelTpl<float>& md) { return make_hybrid_dynamics<float>(md, mask, o); },
                           [&](const ModelTpl<double>& md) { return make_hybrid_dynamics<double>(md, mask, o); });
             },
             "model"_a, "dtype"_a, "backend"_a, "max_batch"_a, "prescribed"_a, "threads"_a = 0, "device"_a = -1)
      .def("compute",
           [](PyHybrid& e, const InArray& q, const InArray& qd, const InArray& qdd, const InArray& tau,
              const OutArray& qdd_out, const OutArray& tau_out, const std::optional<InArray>& fext,
              const std::optional<OutArray>& failed_dof, std::uintptr_t stream) {
             return e.is_float ? hybrid_compute<float>(e, q, qd, qdd, tau, qdd_out, tau_out, fext, failed_dof, stream)
                               : hybrid_compute<double>(e, q, qd, qdd, tau, qdd_out, tau_out, fext, failed_dof, stream);
           },
           "q"_a, "qd"_a, "qdd"_a, "tau"_a, "qdd_out"_a, "tau_out"_a, "fext"_a = nb::none(),
           "failed_dof"_a = nb::none(), "stream"_a = 0)
      .def_prop_ro("prescribed", [](const PyHybrid& e) {
        const auto& p = e.is_float ? e.ef->prescribed() : e.ed->prescribed();
        return std::vector<int>(p.begin(), p.end());
      });
  common(hybrid);

  // ---- closed loops (scandyn/algorithm/loops.hpp)
  nb::class_<PyLoops>(m, "Loops")
      .def_prop_ro("rows", [](const PyLoops& l) { return l.loops.rows(); })
      .def("__len__", [](const PyLoops& l) { return l.loops.loops.size(); })
      .def_prop_ro("json", [](const PyLoops& l) { return loops_json(l.loops); });
  m.def("load_loops", [](std::shared_ptr<PyModel> model, const std::string& path) {
    return PyLoops{model, load_loops(path, model->md)};
  }, "model"_a, "path"_a);
  m.def("parse_loops", [](std::shared_ptr<PyModel> model, const std::string& text, const std::string& source) {
    return PyLoops{model, parse_loops(text, source, model->md)};
  }, "model"_a, "text"_a, "source"_a);
  m.def("generator_loops", [](std::shared_ptr<PyModel> model) {
    return PyLoops{model, generator_loops(model->md.source, model->md)};
  }, "model"_a);

  nb::class_<PyConstrained> cfd(m, "ConstrainedForwardDynamics");
  cfd.def("__init__",
          [](PyConstrained* self, std::shared_ptr<PyModel> model, const std::string& dtype, const std::string& backend,
             Index max_batch, const PyLoops& loops, int threads, int device) {
            if (loops.model != model)
              throw LoopError("the loops were made for model '" + loops.model->md.name + "', not for this model '" +
                              model->md.name + "' (load them with this model)");
            BackendOptions o = options_of(backend, max_batch, "auto", "auto", false, threads);
            const LoopSet& ls = loops.loops;
            init_engine(self, std::move(model), dtype, max_batch, device,
                        [&](const ModelTpl<float>& md) { return make_constrained_forward_dynamics<float>(md, ls, o); },
                        [&](const ModelTpl<double>& md) { return make_constrained_forward_dynamics<double>(md, ls, o); });
          },
          "model"_a, "dtype"_a, "backend"_a, "max_batch"_a, "loops"_a, "threads"_a = 0, "device"_a = -1)
      .def("compute",
           [](PyConstrained& e, const InArray& q, const InArray& qd, const InArray& tau, const OutArray& qdd_out,
              const OutArray& lambda_out, const std::optional<InArray>& fext,
              const std::optional<OutArray>& failed_dof, std::uintptr_t stream) {
             return e.is_float
                        ? constrained_compute<float>(e, q, qd, tau, qdd_out, lambda_out, fext, failed_dof, stream)
                        : constrained_compute<double>(e, q, qd, tau, qdd_out, lambda_out, fext, failed_dof, stream);
           },
           "q"_a, "qd"_a, "tau"_a, "qdd_out"_a, "lambda_out"_a, "fext"_a = nb::none(), "failed_dof"_a = nb::none(),
           "stream"_a = 0)
      .def("residual",
           [](PyConstrained& e, const InArray& q, const InArray& qd, const std::optional<OutArray>& phi,
              const std::optional<OutArray>& velocity, std::uintptr_t stream) {
             if (e.is_float) residual_compute<float>(e, q, qd, phi, velocity, stream);
             else residual_compute<double>(e, q, qd, phi, velocity, stream);
           },
           "q"_a, "qd"_a, "phi"_a = nb::none(), "velocity"_a = nb::none(), "stream"_a = 0)
      .def_prop_ro("rows", [](const PyConstrained& e) { return rows_of(e); });
  common(cfd);

  bind_simulator(m);
  // ---- kinematics (python/src/kinematics.cpp)
  bind_kinematics(m);
  bind_derivatives(m);
}
