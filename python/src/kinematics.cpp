// python/src/kinematics.cpp: the Kinematics engine (frame poses and frame Jacobians,
// scandyn/engine.hpp) in the extension module, in float and double.
//
// compute(q, poses, J): q (nv,) or (B, nv); poses (F, 4, 4) / (B, F, 4, 4) for the
// matrix format or (F, 7) / (B, F, 7) for position + quaternion; J (F, 6, nv) /
// (B, F, 6, nv); either output may be None (not computed). Each array is read with
// its own strides, no copy: q any strides; within an instance, an output's entries
// must be one stride apart in C order (a C-contiguous array, or a slice of one along
// the batch dimension). Host memory only, as the other engines of the module.
#include <nanobind/ndarray.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/shared_ptr.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/vector.h>

#include <algorithm>
#include <optional>
#include <string>
#include <vector>

#include "shared.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/frames.hpp"

namespace nb = nanobind;
using namespace nb::literals;

namespace scandyn::py {
namespace {

using InArray = nb::ndarray<nb::ro>;
using OutArray = nb::ndarray<>;

template <class S, class A>
void check_array(const A& a, const char* name) {
  if (a.device_type() != nb::device::cpu::value)
    throw DeviceError(std::string(name) + " is not in host memory: pass host (NumPy / CPU) arrays");
  if (a.dtype() != nb::dtype<S>())
    throw DTypeError(std::string(name) + " must have dtype " + scalar_name<S>() +
                     " (every array of a call shares one dtype, which sets the precision)");
}

// An output's view: `a` has shape lead + block (lead: () or (B,)), and the entries of
// one instance's block are one stride apart in C order.
template <class S>
BatchView<S> block_view(const OutArray& a, const std::vector<size_t>& block, bool single, Index B,
                        const char* name) {
  check_array<S>(a, name);
  const size_t lead = single ? 0 : 1;
  bool ok = a.ndim() == lead + block.size() && (single || Index(a.shape(0)) == B);
  for (size_t i = 0; ok && i < block.size(); ++i) ok = a.shape(lead + i) == block[i];
  if (!ok) {
    std::string want = single ? "(" : "(" + std::to_string(B) + ", ";
    for (size_t i = 0; i < block.size(); ++i) want += (i ? ", " : "") + std::to_string(block[i]);
    throw ShapeError(std::string(name) + " has shape " + shape_str(a) + ", expected " + want + ")");
  }
  const std::ptrdiff_t s = a.stride(a.ndim() - 1);
  std::ptrdiff_t expect = s;
  for (size_t i = block.size(); i-- > 0;) {
    if (block[i] > 1 && a.stride(lead + i) != expect)
      throw ShapeError(std::string(name) + ": each instance's block must be C-ordered with one stride (a "
                       "C-contiguous array, or a slice of one along the batch dimension)");
    expect *= std::ptrdiff_t(block[i]);
  }
  if (s == 0 && expect == 0 && size_t(std::count_if(block.begin(), block.end(), [](size_t n) { return n > 1; })))
    throw ShapeError(std::string(name) + " has overlapping entries (a zero stride)");
  return {static_cast<S*>(a.data()), B, s, single ? 0 : a.stride(0)};
}

struct PyKinematics {
  std::shared_ptr<PyModel> model;
  bool is_float = false;
  Index max_batch = 1;
  KinematicsOptions options;
  std::vector<std::string> frame_names;  // (F)
  std::unique_ptr<Kinematics<float>> ef;
  std::unique_ptr<Kinematics<double>> ed;
  std::mutex mutex;

  const Engine& engine() const { return is_float ? static_cast<const Engine&>(*ef) : *ed; }
  Index nv() const { return model->md.nv(); }
  Index nq() const { return model->md.nq(); }  // entries of q (quaternions: nq > nv)
};

template <class S>
void compute(PyKinematics& e, const InArray& q, const std::optional<OutArray>& poses,
             const std::optional<OutArray>& J) {
  const Index nv = e.nv(), nq = e.nq();
  check_array<S>(q, "q");
  const std::string dim = nq == nv ? "nv" : "nq";
  if ((q.ndim() != 1 && q.ndim() != 2) || Index(q.shape(q.ndim() - 1)) != nq)
    throw ShapeError("q has shape " + shape_str(q) + ", expected (" + dim + ",) or (B, " + dim + ") with " + dim +
                     " = " + std::to_string(nq));
  const bool single = q.ndim() == 1;
  const Index B = single ? 1 : Index(q.shape(0));
  if (B > e.max_batch)
    throw ShapeError("a batch of " + std::to_string(B) + " instances exceeds this engine's max_batch = " +
                     std::to_string(e.max_batch));
  const BatchView<const S> qv{static_cast<const S*>(q.data()), B, q.stride(q.ndim() - 1), single ? 0 : q.stride(0)};
  const size_t F = e.options.frames.size();
  BatchView<S> pv{}, Jv{};
  if (poses) {
    const std::vector<size_t> block =
        e.options.pose == PoseFormat::Matrix ? std::vector<size_t>{F, 4, 4} : std::vector<size_t>{F, 7};
    pv = block_view<S>(*poses, block, single, B, "poses");
  }
  if (J) Jv = block_view<S>(*J, {F, 6, size_t(nv)}, single, B, "J");
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(e.mutex);
  if constexpr (std::is_same_v<S, float>) e.ef->compute(qv, pv, Jv);
  else e.ed->compute(qv, pv, Jv);
}

}  // namespace

void bind_kinematics(nb::module_& m) {
  nb::class_<PyKinematics> k(m, "Kinematics");
  k.def("__init__",
        [](PyKinematics* self, std::shared_ptr<PyModel> model, const std::string& dtype, const std::string& backend,
           Index max_batch, std::optional<std::vector<std::string>> frames, const std::string& reference,
           const std::string& pose, int threads) {
          if (dtype != "float32" && dtype != "float64")
            throw DTypeError("dtype must be float32 or float64, got " + dtype);
          if (max_batch < 1) throw ShapeError("max_batch must be at least 1, got " + std::to_string(max_batch));
          KinematicsOptions ko;
          if (reference == "local") ko.reference = FrameReference::Local;
          else if (reference != "world")
            throw nb::value_error(("reference must be 'world' or 'local', got '" + reference + "'").c_str());
          if (pose == "quaternion") ko.pose = PoseFormat::PositionQuaternion;
          else if (pose != "matrix")
            throw nb::value_error(("pose must be 'matrix' or 'quaternion', got '" + pose + "'").c_str());
          const Model& md = model->md;
          if (frames) {
            for (const std::string& name : *frames) ko.frames.push_back(frame_index(md, name));  // ModelError
          } else {
            for (size_t f = 0; f < md.frames.size(); ++f) ko.frames.push_back(Index(f));
          }
          BackendOptions o;
          o.backend = parse_backend(backend);
          o.max_batch = max_batch;
          o.threads = threads;
          auto* e = new (self) PyKinematics();
          e->model = std::move(model);
          e->is_float = dtype == "float32";
          e->max_batch = max_batch;
          e->options = ko;
          for (Index f : ko.frames) e->frame_names.push_back(md.frame_names[size_t(f)]);
          try {
            nb::gil_scoped_release release;
            if (e->is_float) e->ef = make_kinematics(e->model->get<float>(), o, ko);
            else e->ed = make_kinematics(e->model->get<double>(), o, ko);
          } catch (...) {
            e->~PyKinematics();
            throw;
          }
        },
        "model"_a, "dtype"_a, "backend"_a, "max_batch"_a, "frames"_a = nb::none(), "reference"_a = "world",
        "pose"_a = "matrix", "threads"_a = 0)
      .def("compute",
           [](PyKinematics& e, const InArray& q, const std::optional<OutArray>& poses,
              const std::optional<OutArray>& J) {
             if (e.is_float) compute<float>(e, q, poses, J);
             else compute<double>(e, q, poses, J);
           },
           "q"_a, "poses"_a = nb::none(), "J"_a = nb::none())
      .def_prop_ro("frames", [](const PyKinematics& e) { return e.frame_names; })
      .def_prop_ro("reference",
                   [](const PyKinematics& e) { return e.options.reference == FrameReference::Local ? "local" : "world"; })
      .def_prop_ro("pose",
                   [](const PyKinematics& e) { return e.options.pose == PoseFormat::Matrix ? "matrix" : "quaternion"; })
      .def_prop_ro("strategy", [](const PyKinematics& e) { return e.engine().strategy(); })
      .def_prop_ro("backend", [](const PyKinematics& e) { return std::string(to_string(e.engine().backend())); })
      .def_prop_ro("exact", [](const PyKinematics& e) { return e.engine().exact(); })
      .def_prop_ro("dtype", [](const PyKinematics& e) { return std::string(e.is_float ? "float32" : "float64"); })
      .def_prop_ro("nv", &PyKinematics::nv)
      .def_ro("max_batch", &PyKinematics::max_batch);
}

}  // namespace scandyn::py
