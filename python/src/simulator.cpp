// python/src/simulator.cpp: scandyn._scandyn.Simulator, the batched simulator
// (scandyn/sim/simulator.hpp) from Python; registered by module.cpp
// (bind_simulator). The pure-Python layer is python/scandyn/simulator.py.
//
// A scene comes as a file path (sim::load_scene) or as JSON text (sim::parse_scene:
// a dict is serialised by the Python layer; no second scene parser). The simulator
// runs in the scene's precision, on the scene's backend or the one given.
//
// The state: q and qd are the simulator's own buffers, (nv x B) structure of arrays
// (entry (DoF i, instance b) at q[i * B + b]); state_view() hands them out as (B, nv)
// arrays with strides (1, B) (elements), whose owner is the Python Simulator, so a
// view keeps the simulator alive. Host memory on serial / openmp, device memory on
// cuda (DLPack device type 2 and the buffer's device); NumPy, torch or DLPack arrays.
//
// Streams (cuda): the simulator queues its work on its own stream. step() and
// reset() take the caller's stream (a cudaStream_t as an integer, 0 the legacy
// default stream; None: no ordering, the caller synchronises): the
// simulator's stream waits for the work queued on the caller's stream so far, and
// after the step the caller's stream waits for the step (events, no host
// synchronisation), so reading and writing q / qd on the caller's stream is ordered
// with the steps.
//
// Checks here (scandyn.errors exceptions): tau's device (host arrays for the CPU
// backends, the simulator's device for cuda), dtype (the simulator's precision) and
// shape ((B, nv), any strides); scene errors (SceneError with the library's
// one-line message); after a step with check=True, a failed status
// (SimulationError with sim::failure_message).
//
// Devices (cuda): the simulator is made on `device` (-1: the current CUDA device, e.g.
// torch.cuda.set_device(LOCAL_RANK) under torchrun), and every call that queues work
// (step, reset, synchronize, energy, status) makes the state's device current for its
// duration (enter_device, shared.hpp), so a simulator on device 1 steps from a thread
// whose current device is 0.
//
// Contacts (effects.contacts): contact_view() hands out the last step's readings
// (Simulator::contact_forces(), (B x P) ContactReading in the backend's memory) as
// zero-copy views of their fields, owned by the Python Simulator like q and qd.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/vector.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <memory>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <vector>

#include "scandyn/build_config.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "shared.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>
#endif

namespace nb = nanobind;
using namespace nb::literals;

namespace scandyn::py {
namespace {

// Raises the scandyn.errors exception `cls` with `what` (the GIL held): for the
// classes module.cpp's translator does not know (SceneError, SimulationError); the
// others are thrown as shared.hpp's types.
[[noreturn]] void fail(const char* cls, const std::string& what) {
  nb::object type = nb::module_::import_("scandyn.errors").attr(cls);
  PyErr_SetString(type.ptr(), what.c_str());
  throw nb::python_error();
}

#if SCANDYN_HAS_CUDA
void cuda_check(cudaError_t e, const char* what) {
  if (e != cudaSuccess) throw BackendError(std::string(what) + ": " + cudaGetErrorString(e));
}
#endif

// A Simulator<float> or Simulator<double>, with the events that order its stream
// with a caller's (cuda).
struct PySimulator {
  std::unique_ptr<sim::Simulator<float>> sf;
  std::unique_ptr<sim::Simulator<double>> sd;
  std::string scene_path;      // "" for a scene given as text
  std::string backend;         // "serial", "openmp" or "cuda"
  std::string backend_note;    // the scene said "auto": why not cuda ("" when cuda was chosen)
  bool backend_auto = false;
  int device = -1;             // cuda: the device holding the state
  void* caller_done = nullptr;  // cudaEvent_t: the caller's work before a step
  void* sim_done = nullptr;     // cudaEvent_t: the step
  std::mutex mutex;             // one call at a time (calls release the GIL)

  bool is_float() const { return sf != nullptr; }
  template <class F>
  decltype(auto) visit(F&& f) {
    if (sf) return f(*sf);
    return f(*sd);
  }
  Index nv() { return visit([](auto& s) { return s.nv(); }); }
  Index nq() { return visit([](auto& s) { return s.nq(); }); }  // q's columns (> nv with quaternions)
  Index batch() { return visit([](auto& s) { return s.batch(); }); }
  bool on_device() { return visit([](auto& s) { return s.on_device(); }); }
  // The state's device current for a scope (cuda; nothing on the CPU backends).
  void enter(std::optional<cuda::DeviceScope>& scope) {
    if (on_device()) enter_device(scope, device);
  }

  ~PySimulator() {
#if SCANDYN_HAS_CUDA
    if (caller_done) cudaEventDestroy(static_cast<cudaEvent_t>(caller_done));
    if (sim_done) cudaEventDestroy(static_cast<cudaEvent_t>(sim_done));
#endif
  }

  // The simulator's stream waits for the work queued on `stream` so far.
  void after_caller(std::optional<std::uintptr_t> stream) {
#if SCANDYN_HAS_CUDA
    if (!on_device() || !stream) return;
    void* own = visit([](auto& s) { return s.stream(); });
    cuda_check(cudaEventRecord(static_cast<cudaEvent_t>(caller_done), reinterpret_cast<cudaStream_t>(*stream)),
               "ordering the simulator after the caller's stream");
    cuda_check(cudaStreamWaitEvent(static_cast<cudaStream_t>(own), static_cast<cudaEvent_t>(caller_done), 0),
               "ordering the simulator after the caller's stream");
#else
    (void)stream;
#endif
  }
  // `stream` waits for the simulator's work queued so far.
  void before_caller(std::optional<std::uintptr_t> stream) {
#if SCANDYN_HAS_CUDA
    if (!on_device() || !stream) return;
    void* own = visit([](auto& s) { return s.stream(); });
    cuda_check(cudaEventRecord(static_cast<cudaEvent_t>(sim_done), static_cast<cudaStream_t>(own)),
               "ordering the caller's stream after the simulator");
    cuda_check(cudaStreamWaitEvent(reinterpret_cast<cudaStream_t>(*stream), static_cast<cudaEvent_t>(sim_done), 0),
               "ordering the caller's stream after the simulator");
#else
    (void)stream;
#endif
  }
};

// The scene: a path (text empty) or JSON text (source names it in messages).
sim::Scene read_scene(const std::string& path, const std::optional<std::string>& text, const std::string& source,
                      const std::string& base_dir) {
  nb::gil_scoped_release release;  // a rope of 10^6 links takes a while
  return text ? sim::parse_scene(*text, source, base_dir) : sim::load_scene(path);
}

void init_simulator(PySimulator* self, const std::string& path, const std::optional<std::string>& text,
                    const std::string& source, const std::string& base_dir, const std::optional<std::string>& backend,
                    int device) {
  auto* p = new (self) PySimulator();
  try {
    sim::Scene scene;
    try {
      scene = read_scene(path, text, source, base_dir);
    } catch (const sim::SceneError& e) {
      fail("SceneError", e.what());
    }
    // backend: the scene's, or the one given ("auto": as a scene's "auto", sim::auto_backend)
    BackendKind kind = scene.backend;
    p->backend_auto = scene.backend_auto;
    p->backend_note = scene.backend_note;
    if (backend && *backend == "auto") {
      p->backend_auto = true;
      kind = sim::auto_backend(&p->backend_note);
    } else if (backend) {
      p->backend_auto = false;
      kind = parse_backend(*backend);
    }
    if (!p->backend_auto) p->backend_note.clear();
    p->scene_path = scene.path;
    p->backend = to_string(kind);
    std::optional<cuda::DeviceScope> scope;  // cuda: made on `device` (-1: the current one)
    if (kind == BackendKind::Cuda) enter_device(scope, device);
    {
      nb::gil_scoped_release release;
      if (scene.precision == Precision::Float)
        p->sf = std::make_unique<sim::Simulator<float>>(scene, kind);
      else
        p->sd = std::make_unique<sim::Simulator<double>>(scene, kind);
    }
#if SCANDYN_HAS_CUDA
    if (p->on_device()) {
      cudaPointerAttributes attr{};
      void* q = p->visit([](auto& s) -> void* { return s.q().data; });
      cuda_check(cudaPointerGetAttributes(&attr, q), "locating the simulator's state");
      p->device = attr.device;
      cudaEvent_t a = nullptr, b = nullptr;
      cuda_check(cudaEventCreateWithFlags(&a, cudaEventDisableTiming), "creating an event");
      p->caller_done = a;
      cuda_check(cudaEventCreateWithFlags(&b, cudaEventDisableTiming), "creating an event");
      p->sim_done = b;
    }
#endif
  } catch (...) {
    p->~PySimulator();
    throw;
  }
}

// A view of `ndim` dimensions of the simulator's own memory at `data` (element type
// dt, strides in elements), owned by the Python Simulator `self`: a NumPy array
// ("numpy"; host memory only), a torch tensor ("torch") or a nanobind array that
// speaks DLPack ("dlpack").
nb::object own_view(nb::handle self, PySimulator& p, void* data, size_t ndim, const size_t* shape,
                    const int64_t* strides, nb::dlpack::dtype dt, const std::string& framework) {
  const int device_type = p.on_device() ? int(nb::device::cuda::value) : int(nb::device::cpu::value);
  const int device_id = p.on_device() ? p.device : 0;
  if (framework == "numpy") {
    if (p.on_device()) throw DeviceError("the simulator's state is on the GPU: no NumPy view of it");
    return nb::cast(nb::ndarray<nb::numpy>(data, ndim, shape, self, strides, dt, device_type, device_id),
                    nb::rv_policy::reference);
  }
  if (framework == "torch")
    return nb::cast(nb::ndarray<nb::pytorch>(data, ndim, shape, self, strides, dt, device_type, device_id),
                    nb::rv_policy::reference);
  if (framework == "dlpack")
    return nb::cast(nb::ndarray<>(data, ndim, shape, self, strides, dt, device_type, device_id),
                    nb::rv_policy::reference);
  throw ShapeError("unknown array framework '" + framework + "' (numpy, torch, dlpack)");
}

// q as a (B, nq) array, qd as a (B, nv) one, strides (1, B): the simulator's own
// memory (nq = nv unless the model has quaternions: a floating base, ball joints).
nb::object state_view(nb::handle self, bool velocities, const std::string& framework) {
  PySimulator& p = nb::cast<PySimulator&>(self);
  const Index B = p.batch(), nv = velocities ? p.nv() : p.nq();
  void* data = p.visit([&](auto& s) -> void* { return velocities ? s.qd().data : s.q().data; });
  const size_t shape[2] = {size_t(B), size_t(nv)};
  const int64_t strides[2] = {1, int64_t(B)};
  const nb::dlpack::dtype dt = p.is_float() ? nb::dtype<float>() : nb::dtype<double>();
  return own_view(self, p, data, 2, shape, strides, dt, framework);
}

// The contact readings (sim::ContactReading, (B x P) in the backend's memory, entry
// b * P + k) seen through their fields: five scalars of the precision per reading
// (force x, y, z, depth, then the int in_contact padded to a scalar), so "force" is
// a (B, P, 3) array, "depth" (B, P) and "in_contact" (B, P) int32, strides (5 P, 5, 1)
// in scalars (in_contact: in int32s, 5 P s and 5 s with s = sizeof(S) / 4).
template <class S>
constexpr bool kReadingIsFiveScalars = std::is_standard_layout_v<sim::ContactReading<S>> &&
                                       sizeof(sim::ContactReading<S>) == 5 * sizeof(S) &&
                                       offsetof(sim::ContactReading<S>, depth) == 3 * sizeof(S) &&
                                       offsetof(sim::ContactReading<S>, in_contact) == 4 * sizeof(S);
static_assert(kReadingIsFiveScalars<float> && kReadingIsFiveScalars<double>,
              "contact_view's strides assume five scalars per ContactReading");

nb::object contact_view(nb::handle self, const std::string& field, const std::string& framework) {
  PySimulator& p = nb::cast<PySimulator&>(self);
  const Index P = p.visit([](auto& s) { return s.contact_count(); });
  if (P == 0) throw ShapeError("the scene declares no effects.contacts: no contact readings");
  const size_t B = size_t(p.batch());
  char* base = static_cast<char*>(p.visit([](auto& s) -> void* { return s.contact_forces(); }));
  const size_t scalar = p.is_float() ? sizeof(float) : sizeof(double);
  const nb::dlpack::dtype dt = p.is_float() ? nb::dtype<float>() : nb::dtype<double>();
  if (field == "force") {
    const size_t shape[3] = {B, size_t(P), 3};
    const int64_t strides[3] = {5 * int64_t(P), 5, 1};
    return own_view(self, p, base, 3, shape, strides, dt, framework);
  }
  const size_t shape[2] = {B, size_t(P)};
  if (field == "depth") {
    const int64_t strides[2] = {5 * int64_t(P), 5};
    return own_view(self, p, base + 3 * scalar, 2, shape, strides, dt, framework);
  }
  if (field == "in_contact") {
    const int64_t per = int64_t(5 * scalar / sizeof(int));  // a reading in ints
    const int64_t strides[2] = {per * int64_t(P), per};
    return own_view(self, p, base + 4 * scalar, 2, shape, strides, nb::dtype<int>(), framework);
  }
  throw ShapeError("unknown contact field '" + field + "' (force, depth, in_contact)");
}

// tau as the (nv x B) BatchView the simulator reads: a (B, nv) array, any strides,
// in the simulator's precision and memory.
template <class S>
BatchView<const S> torques_of(PySimulator& p, const nb::ndarray<nb::ro>& tau) {
  const Index B = p.batch(), nv = p.nv();
  const char* want = scalar_name<S>();
  if (tau.dtype() != nb::dtype<S>())
    throw DTypeError(std::string("tau has the wrong dtype: this simulator runs in ") + want +
                        " (the scene's precision); pass a " + want + " array");
  if (p.on_device()) {
    if (tau.device_type() != nb::device::cuda::value || tau.device_id() != p.device)
      throw DeviceError("tau must be on CUDA device " + std::to_string(p.device) +
                           " (the simulator's state is there); nothing is copied between devices");
  } else if (tau.device_type() != nb::device::cpu::value) {
    throw DeviceError("tau must be in host memory: this simulator runs on the CPU (backend '" + p.backend +
                         "')");
  }
  if (tau.ndim() != 2 || Index(tau.shape(0)) != B || Index(tau.shape(1)) != nv)
    throw ShapeError("tau has shape " + shape_str(tau) + ", expected (" + std::to_string(B) + ", " +
                        std::to_string(nv) + ") (num_instances, nv)");
  BatchView<const S> v;
  v.data = static_cast<const S*>(tau.data());
  v.batch = B;
  v.dof_stride = tau.stride(1);
  v.batch_stride = tau.stride(0);
  return v;
}

template <class S>
void step_as(PySimulator& p, sim::Simulator<S>& s, const std::optional<nb::ndarray<nb::ro>>& tau, Index count,
             bool check, std::optional<std::uintptr_t> stream) {
  const BatchView<const S> t = tau ? torques_of<S>(p, *tau) : BatchView<const S>{};
  BatchStatus st;
  long long steps = 0;
  double time = 0;
  {
    nb::gil_scoped_release release;
    std::lock_guard<std::mutex> lock(p.mutex);
    std::optional<cuda::DeviceScope> scope;
    p.enter(scope);
    p.after_caller(stream);
    for (Index k = 0; k < count; ++k) s.step(t);
    p.before_caller(stream);
    if (check) {
      st = s.status();  // cuda: synchronises
      if (!st.ok()) s.clear_status();
      steps = s.steps();
      time = s.time();
    }
  }
  if (!st.ok()) {
    char when[64];
    std::snprintf(when, sizeof when, "after step %lld (t = %g s): ", steps, time);
    fail("SimulationError", when + sim::failure_message(st));
  }
}

void step(PySimulator& p, const std::optional<nb::ndarray<nb::ro>>& tau, Index count, bool check,
          std::optional<std::uintptr_t> stream) {
  if (count < 0) throw ShapeError("step count must be >= 0, got " + std::to_string(count));
  if (p.sf)
    step_as(p, *p.sf, tau, count, check, stream);
  else
    step_as(p, *p.sd, tau, count, check, stream);
}

void reset(PySimulator& p, const std::optional<std::vector<Index>>& instances, std::optional<std::uintptr_t> stream) {
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(p.mutex);
  std::optional<cuda::DeviceScope> scope;
  p.enter(scope);
  p.after_caller(stream);
  p.visit([&](auto& s) {
    if (instances)
      s.reset(*instances);
    else
      s.reset_all();
  });
  p.before_caller(stream);
}

// Runs f(simulator) with the GIL released and the simulator's lock held.
template <class F>
auto locked(PySimulator& p, F&& f) {
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(p.mutex);
  std::optional<cuda::DeviceScope> scope;
  p.enter(scope);
  return p.visit(std::forward<F>(f));
}

// (failed, first_instance, first_dof, message) of the steps since clear_status()
std::tuple<Index, Index, Index, std::string> status(PySimulator& p) {
  const BatchStatus st = locked(p, [](auto& s) { return s.status(); });
  return {st.failed, st.first_instance, st.first_dof, sim::failure_message(st)};
}

}  // namespace

void bind_simulator(nb::module_& m) {
  nb::class_<PySimulator>(m, "Simulator")
      .def("__init__", &init_simulator, "path"_a, "text"_a.none(), "source"_a, "base_dir"_a, "backend"_a.none(),
           "device"_a = -1)
      .def("step", &step, "tau"_a.none(), "count"_a = 1, "check"_a = true, "stream"_a.none() = nb::none())
      .def("reset", &reset, "instances"_a.none(), "stream"_a.none() = nb::none())
      .def("status", &status)
      .def("clear_status", [](PySimulator& p) { locked(p, [](auto& s) { s.clear_status(); }); })
      .def("synchronize", [](PySimulator& p) { locked(p, [](auto& s) { s.synchronize(); }); })
      .def("energy", [](PySimulator& p) { return locked(p, [](auto& s) { return s.energy(); }); })
      .def("view", &state_view, "velocities"_a, "framework"_a)
      .def("contact_view", &contact_view, "field"_a, "framework"_a)
      .def_prop_ro("num_contact_points", [](PySimulator& p) { return p.visit([](auto& s) { return s.contact_count(); }); })
      .def_prop_ro("nv", &PySimulator::nv)
      .def_prop_ro("nq", &PySimulator::nq)
      .def_prop_ro("num_instances", &PySimulator::batch)
      .def_prop_ro("on_device", &PySimulator::on_device)
      .def_ro("device", &PySimulator::device)
      .def_ro("scene_path", &PySimulator::scene_path)
      .def_ro("backend", &PySimulator::backend)
      .def_ro("backend_auto", &PySimulator::backend_auto)
      .def_ro("backend_note", &PySimulator::backend_note)
      .def_prop_ro("dtype", [](PySimulator& p) { return p.is_float() ? "float32" : "float64"; })
      .def_prop_ro("t", [](PySimulator& p) { return p.visit([](auto& s) { return s.time(); }); })
      .def_prop_ro("steps", [](PySimulator& p) { return p.visit([](auto& s) { return s.steps(); }); })
      .def_prop_ro("dt", [](PySimulator& p) { return p.visit([](auto& s) { return double(s.setup().dt); }); })
      .def_prop_ro("strategy", [](PySimulator& p) { return p.visit([](auto& s) { return s.strategy(); }); })
      .def_prop_ro("stream", [](PySimulator& p) {
        return reinterpret_cast<std::uintptr_t>(p.visit([](auto& s) { return s.stream(); }));
      });
}

}  // namespace scandyn::py
