// python/src/engines.hpp: an engine of the library as the extension module's bindings
// hold it (module.cpp's four dynamics engines, kinematics.cpp's Kinematics), shared
// by them:
//   PyEngine<E>      the engine E<float> or E<double> with its model and max_batch;
//   init_engine      makes it (on a CUDA device: the device given, else the current one;
//                    BackendOptions::devices: one engine per device, scandyn/sharded.hpp);
//   engine_device    the CUDA ordinal of a cuda engine, -1 for the CPU backends and for
//                    an engine sharded over several devices;
//   engine_devices   the devices of its shards (a sharded engine), [device] (cuda), [] (CPU);
//   queue_on_device  the device path: the CUDA engine's compute_async() on the caller's
//                    stream for arrays on its device (DeviceError for arrays on another
//                    device, an engine of a CPU backend or one sharded over several
//                    devices), no copy, no synchronisation;
//   CallStatus       what a call that can fail reports (module.cpp binds it as
//                    scandyn.Status), call_status, failed_dof_of (the caller's failed-DoF
//                    array of a CUDA call).
#pragma once

#include <nanobind/nanobind.h>

#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "arrays.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/sharded.hpp"
#include "shared.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>

#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/hybrid_dynamics.hpp"
#include "scandyn/cuda/constrained_dynamics.hpp"
#include "scandyn/cuda/derivatives.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/cuda/kinematics.hpp"
#include "scandyn/cuda/mass_matrix.hpp"
#include "scandyn/cuda/second_derivatives.hpp"
#endif

namespace scandyn::py {

namespace nb = nanobind;

#if !SCANDYN_HAS_CUDA
using cudaStream_t = struct CUstream_st*;  // the type of the device path's lambdas; never called
#endif

// One engine of the library in float or double, with the model it was made for.
// compute() calls are serialised (an engine's scratch is not shared between
// calls); the GIL is released while it runs.
template <template <class> class E>
struct PyEngine {
  std::shared_ptr<PyModel> model;
  bool is_float = false;
  Index max_batch = 1;
  std::unique_ptr<E<float>> ef;
  std::unique_ptr<E<double>> ed;
  std::mutex mutex;
  int made_on = -1;  // the device current when a CUDA engine was made (init_engine), else -1

  Engine& engine() const { return is_float ? static_cast<Engine&>(*ef) : static_cast<Engine&>(*ed); }
  std::string strategy() const { return engine().strategy(); }
  std::string backend() const { return to_string(engine().backend()); }
  bool exact() const { return engine().exact(); }
  std::string dtype() const { return is_float ? "float32" : "float64"; }
  Index nv() const { return model->md.nv(); }
  Index nq() const { return model->md.nq(); }            // entries of q (quaternions: nq > nv)
  Index nbodies() const { return model->md.nbodies(); }  // wrenches of fext
};

// ---- CUDA: the device path ------------------------------------------------------

// enter_device (a device current for a scope): shared.hpp

// The sharded engine behind e (scandyn/sharded.hpp), or null.
template <template <class> class E>
const ShardedEngine* sharded_of(const PyEngine<E>& e) {
  return dynamic_cast<const ShardedEngine*>(&e.engine());
}


#if SCANDYN_HAS_CUDA
template <class S>
cuda::CudaInverseDynamics<S>* as_cuda(InverseDynamics<S>* e) { return dynamic_cast<cuda::CudaInverseDynamics<S>*>(e); }
template <class S>
cuda::CudaBiasForces<S>* as_cuda(BiasForces<S>* e) { return dynamic_cast<cuda::CudaBiasForces<S>*>(e); }
template <class S>
cuda::CudaMassMatrix<S>* as_cuda(MassMatrix<S>* e) { return dynamic_cast<cuda::CudaMassMatrix<S>*>(e); }
template <class S>
cuda::CudaForwardDynamics<S>* as_cuda(ForwardDynamics<S>* e) { return dynamic_cast<cuda::CudaForwardDynamics<S>*>(e); }
template <class S>
cuda::CudaKinematics<S>* as_cuda(Kinematics<S>* e) { return dynamic_cast<cuda::CudaKinematics<S>*>(e); }
template <class S>
// (either CUDA strategy: one thread per instance, or the parallel chain hybrid)
cuda::CudaHybridEngine<S>* as_cuda(HybridDynamics<S>* e) { return dynamic_cast<cuda::CudaHybridEngine<S>*>(e); }
template <class S>
cuda::CudaConstrainedForwardDynamics<S>* as_cuda(ConstrainedForwardDynamics<S>* e) {
  return dynamic_cast<cuda::CudaConstrainedForwardDynamics<S>*>(e);
}
template <class S>
cuda::CudaIdDerivatives<S>* as_cuda(IdDerivatives<S>* e) { return dynamic_cast<cuda::CudaIdDerivatives<S>*>(e); }
template <class S>
cuda::CudaFdDerivatives<S>* as_cuda(FdDerivatives<S>* e) { return dynamic_cast<cuda::CudaFdDerivatives<S>*>(e); }
template <class S>
cuda::CudaIdSecondDerivatives<S>* as_cuda(IdSecondDerivatives<S>* e) {
  return dynamic_cast<cuda::CudaIdSecondDerivatives<S>*>(e);
}
// The directional derivatives' CUDA engine is internal to kernels/chain_directional.cu
// (host views only): the engine itself when it runs on cuda (its device: made_on).
template <class S>
Engine* as_cuda(FdDirectionalDerivatives<S>* e) { return e && e->backend() == BackendKind::Cuda ? e : nullptr; }
// The CUDA ordinal an engine reports (device()), or -1 for one that does not say (the
// derivative engines): PyEngine::made_on then names it.
template <class E>
auto device_of_impl(const E& e, int) -> decltype(int(e.device())) { return e.device(); }
template <class E>
int device_of_impl(const E&, long) { return -1; }
template <class E>
int device_of(const E& e) { return device_of_impl(e, 0); }
template <class S>
int device_of(const cuda::CudaBiasForces<S>& e) { return e.inverse_dynamics().device(); }
// The device of the CUDA engine c of e.
template <template <class> class E, class C>
int cuda_device_of(const PyEngine<E>& e, const C& c) {
  const int d = device_of(c);
  return d >= 0 ? d : e.made_on;
}
#endif

// The engine's device: its CUDA ordinal (for an engine sharded over one device, that
// one), -1 for the CPU backends and for an engine sharded over several devices.
template <template <class> class E>
int engine_device(const PyEngine<E>& e) {
  if (const ShardedEngine* sh = sharded_of(e)) {
    const int d = sh->shard_device(0);
    for (int k = 1; k < sh->shard_count(); ++k)
      if (sh->shard_device(k) != d) return -1;
    return d;
  }
#if SCANDYN_HAS_CUDA
  if (e.is_float) {
    if (auto* c = as_cuda(e.ef.get())) return cuda_device_of(e, *c);
  } else if (auto* c = as_cuda(e.ed.get())) {
    return cuda_device_of(e, *c);
  }
#endif
  return -1;
}

// The devices the engine computes on: one entry per shard of a sharded engine (a device
// named twice: two shards there), [device] for a cuda engine, [] for the CPU backends.
template <template <class> class E>
std::vector<int> engine_devices(const PyEngine<E>& e) {
  if (const ShardedEngine* sh = sharded_of(e)) {
    std::vector<int> d;
    for (int k = 0; k < sh->shard_count(); ++k) d.push_back(sh->shard_device(k));
    return d;
  }
  const int d = engine_device(e);
  return d >= 0 ? std::vector<int>{d} : std::vector<int>{};
}

// The DeviceError of CUDA arrays (on `device`) handed to a build without the CUDA backend.
[[noreturn]] inline void throw_no_cuda_backend(int device) {
  throw DeviceError("the arrays are on " + where_str(true, device) +
                    ", but this build of scandyn has no CUDA backend (pip install . where nvcc is found)");
}

// Queues `queue(cuda_engine, stream)` (its compute_async) for arrays on CUDA device
// lead.device, on the caller's stream; checks that the engine is a CUDA engine of
// that device (an engine sharded over that one device: its shard); throws BackendError
// for a launch error. No synchronisation.
template <class S, template <class> class E, class Queue>
void queue_on_device(PyEngine<E>& e, const Lead& lead, std::uintptr_t stream, Queue&& queue) {
#if SCANDYN_HAS_CUDA
  E<S>* base = nullptr;
  if constexpr (std::is_same_v<S, float>) base = e.ef.get();
  else base = e.ed.get();
  if (ShardedEngine* sh = dynamic_cast<ShardedEngine*>(static_cast<Engine*>(base))) {
    const std::vector<int> devices = engine_devices(e);
    if (sh->shard_count() != 1)
      throw DeviceError("the arrays are on " + where_str(true, lead.device) +
                        ", but this engine shards host batches over CUDA devices " + devices_string(devices) +
                        " (devices=): CUDA arrays run on their own device, not sharded; make an engine with device=" +
                        std::to_string(lead.device) + " (or devices=[" + std::to_string(lead.device) +
                        "], or no devices=) for them");
    base = dynamic_cast<E<S>*>(&sh->shard_engine(0));
  }
  auto* c = as_cuda(base);
  if (!c)
    throw DeviceError("the arrays are on " + where_str(true, lead.device) + ", but this engine runs on backend '" +
                      e.backend() + "': make it with backend='cuda' (the function API's backend='auto' follows "
                      "the arrays)");
  if (cuda_device_of(e, *c) != lead.device)
    throw DeviceError("the arrays are on " + where_str(true, lead.device) + ", but this engine was made on " +
                      where_str(true, cuda_device_of(e, *c)) + ": make one with device=" + std::to_string(lead.device));
  std::optional<cuda::DeviceScope> scope;
  enter_device(scope, lead.device);
  const cudaError_t err = queue(*c, reinterpret_cast<cudaStream_t>(stream));
  if (err != cudaSuccess)
    throw BackendError(std::string("backend 'cuda': queuing the computation on the caller's stream failed: ") +
                       cudaGetErrorName(err) + ": " + cudaGetErrorString(err));
#else
  (void)e, (void)stream, (void)queue;
  throw_no_cuda_backend(lead.device);
#endif
}

// ---- what a call reports ------------------------------------------------------

// What a forward-dynamics call reports: BatchStatus with its per-instance failed DoFs copied.
struct CallStatus {
  Index failed = 0, first_instance = -1, first_dof = -1, fell_back = 0;
  Index retried = 0;  // flagged by the run-time check, fixed by a fallback
  std::string reason, message;
  std::vector<int> failed_dof;  // per instance: -1 or the DoF that failed (empty when ok)
  bool queued = false;          // CUDA arrays: the call was queued; the failed DoFs are in the
                                // caller's device array once the stream reaches them
};

// What a call queued on the caller's stream reports (its failures land in the caller's
// device array).
inline CallStatus queued_status() {
  CallStatus r;
  r.queued = true;
  return r;
}

inline CallStatus call_status(const BatchStatus& st, Index batch) {
  CallStatus r;
  r.failed = st.failed;
  r.first_instance = st.first_instance;
  r.first_dof = st.first_dof;
  r.fell_back = st.fell_back;
  r.retried = st.retried;
  if (!st.ok()) {
    r.reason = st.reason();
    r.message = st.message();
    if (st.failed_dof) r.failed_dof.assign(st.failed_dof, st.failed_dof + batch);
  }
  return r;
}

// The failed-DoF array of a CUDA call: the caller's (B,) int32 array on the arrays' device.
inline int* failed_dof_of(const std::optional<OutArray>& failed_dof, const Lead& lead, const char* what,
                   std::initializer_list<std::pair<Extent, const char*>> outputs) {
  if (!failed_dof)
    throw ShapeError(std::string("failed_dof: ") + what + " on CUDA arrays needs a (B,) int32 array on the same device");
  const OutArray& f = *failed_dof;
  Lead l = lead;
  check_device(f, "failed_dof", l);
  if (f.dtype() != nb::dtype<int32_t>() || f.ndim() != 1 || Index(f.shape(0)) != lead.batch ||
      (lead.batch > 1 && f.stride(0) != 1))
    throw ShapeError("failed_dof has shape " + shape_str(f) + " and dtype " + dtype_name(f.dtype()) +
                     ", expected a contiguous (" + std::to_string(lead.batch) + ",) int32 array");
  check_out_alone(f, outputs, "failed_dof");
  return static_cast<int*>(f.data());
}

template <template <class> class E, class MakeF, class MakeD>
void init_engine(PyEngine<E>* self, std::shared_ptr<PyModel> model, const std::string& dtype, Index max_batch,
                 int device, MakeF make_f, MakeD make_d) {
  if (dtype != "float32" && dtype != "float64")
    throw DTypeError("dtype must be float32 or float64, got " + dtype);
  const bool is_float = dtype == "float32";
  auto* e = new (self) PyEngine<E>();
  e->model = std::move(model);
  e->is_float = is_float;
  e->max_batch = max_batch;
  try {
    nb::gil_scoped_release release;
#if SCANDYN_HAS_CUDA
    std::optional<cuda::DeviceScope> scope;  // a CUDA engine lives on the device current at construction
    enter_device(scope, device);
#else
    (void)device;
#endif
    if (is_float)
      e->ef = make_f(e->model->template get<float>());
    else
      e->ed = make_d(e->model->template get<double>());
#if SCANDYN_HAS_CUDA
    int current = -1;
    if (e->engine().backend() == BackendKind::Cuda && cudaGetDevice(&current) == cudaSuccess) e->made_on = current;
#endif
  } catch (...) {
    e->~PyEngine<E>();
    throw;
  }
}

// The read-only properties every engine class of the module has: strategy, backend,
// exact, dtype, nv, device, devices, max_batch (cls: an nb::class_<PyEngine<E>>).
template <class Class>
void def_engine_properties(Class& cls) {
  using T = typename Class::Type;
  cls.def_prop_ro("strategy", &T::strategy)
      .def_prop_ro("backend", &T::backend)
      .def_prop_ro("exact", &T::exact)
      .def_prop_ro("dtype", &T::dtype)
      .def_prop_ro("nv", &T::nv)
      .def_prop_ro("device", [](const T& e) { return engine_device(e); })
      .def_prop_ro("devices", [](const T& e) { return engine_devices(e); })
      .def_ro("max_batch", &T::max_batch);
}

}  // namespace scandyn::py
