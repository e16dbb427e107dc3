// python/src/kinematics.cpp: the Kinematics engine (frame poses and frame Jacobians,
// scandyn/engine.hpp) in the extension module, in float and double.
//
// compute(q, poses, J, stream): q (nq,) or (B, nq); poses (F, 4, 4) / (B, F, 4, 4)
// for the matrix format or (F, 7) / (B, F, 7) for position + quaternion; J (F, 6, nv)
// / (B, F, 6, nv); either output may be None (not computed). Each array is read with
// its own strides, no copy: q any strides; within an instance, an output's entries
// must be one stride apart in C order (a C-contiguous array, or a slice of one along
// the batch dimension). As the dynamics engines (module.cpp, through arrays.hpp and
// engines.hpp): every array in host memory (the engine's compute()) or every one on
// the CUDA engine's device (its compute_async() on the caller's stream: one launch,
// no copy, no synchronisation); DeviceError, DTypeError, ShapeError otherwise, and
// for outputs that overlap themselves, q or each other.
#include <nanobind/ndarray.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/shared_ptr.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/vector.h>

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "arrays.hpp"
#include "engines.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/frames.hpp"
#include "shared.hpp"

namespace nb = nanobind;
using namespace nb::literals;

namespace scandyn::py {
namespace {

using PyKinematics = PyEngine<Kinematics>;

const KinematicsOptions& kinematics_options(const PyKinematics& e) {
  return e.is_float ? e.ef->options() : e.ed->options();
}

// An output's view: `a` has shape lead + block (lead: () or (B,), as q's), on q's
// device, in precision S, and the entries of one instance's block are one stride
// apart in C order, no two of them in the same memory.
template <class S, size_t N>
BatchView<S> block_view(const OutArray& a, const size_t (&block)[N], Lead& lead, const char* name) {
  check_device(a, name, lead);
  if (!has_dtype<S>(a))
    throw DTypeError(std::string(name) + " has dtype " + dtype_name(a.dtype()) + ", expected " + scalar_name<S>() +
                     " (every array of a call shares one dtype, which sets the precision)");
  const size_t nl = lead.single ? 0 : 1;
  bool ok = a.ndim() == nl + N && (lead.single || Index(a.shape(0)) == lead.batch);
  for (size_t i = 0; ok && i < N; ++i) ok = a.shape(nl + i) == block[i];
  if (!ok) {
    std::string want = lead.single ? "(" : "(" + std::to_string(lead.batch) + ", ";
    for (size_t i = 0; i < N; ++i) want += (i ? ", " : "") + std::to_string(block[i]);
    throw ShapeError(std::string(name) + " has shape " + shape_str(a) + ", expected " + want + ")");
  }
  const std::ptrdiff_t s = a.stride(a.ndim() - 1);
  std::ptrdiff_t expect = s;
  for (size_t i = N; i-- > 0;) {
    if (block[i] > 1 && a.stride(nl + i) != expect)
      throw ShapeError(std::string(name) + ": each instance's block must be C-ordered with one stride (a "
                       "C-contiguous array, or a slice of one along the batch dimension)");
    expect *= std::ptrdiff_t(block[i]);
  }
  check_no_self_overlap(a, name);
  return {static_cast<S*>(a.data()), lead.batch, s, lead.single ? 0 : a.stride(0)};
}

template <class S>
void compute(PyKinematics& e, const InArray& q, const std::optional<OutArray>& poses,
             const std::optional<OutArray>& J, std::uintptr_t stream) {
  const Index nv = e.nv();
  const KinematicsOptions& ko = kinematics_options(e);
  Lead lead;
  const BatchView<const S> qv = view_of<const S>(q, e.nq(), "q", lead, true, e.nq() == nv ? "nv" : "nq");
  check_max_batch(lead, e.max_batch);
  const size_t F = ko.frames.size();
  const Extent qe = extent_of(q);
  BatchView<S> pv{}, Jv{};
  if (poses) {
    pv = ko.pose == PoseFormat::Matrix ? block_view<S>(*poses, {F, 4, 4}, lead, "poses")
                                       : block_view<S>(*poses, {F, 7}, lead, "poses");
    check_out_alone(*poses, {{qe, "q"}}, "poses");
  }
  if (J) {
    Jv = block_view<S>(*J, {F, 6, size_t(nv)}, lead, "J");
    check_out_alone(*J, {{qe, "q"}}, "J");
    if (poses) check_out_alone(*J, {{extent_of(*poses), "poses"}}, "J");
  }
  nb::gil_scoped_release release;
  std::lock_guard<std::mutex> lock(e.mutex);
  if (lead.cuda)
    return queue_on_device<S>(e, lead, stream, [&](auto& c, cudaStream_t s) { return c.compute_async(qv, pv, Jv, s); });
  if constexpr (std::is_same_v<S, float>) e.ef->compute(qv, pv, Jv);
  else e.ed->compute(qv, pv, Jv);
}

}  // namespace

void bind_kinematics(nb::module_& m) {
  nb::class_<PyKinematics> k(m, "Kinematics");
  k.def("__init__",
        [](PyKinematics* self, std::shared_ptr<PyModel> model, const std::string& dtype, const std::string& backend,
           Index max_batch, std::optional<std::vector<std::string>> frames, const std::string& reference,
           const std::string& pose, int threads, int device) {
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
          init_engine(self, std::move(model), dtype, max_batch, device,
                      [&](const ModelTpl<float>& mf) { return make_kinematics(mf, o, ko); },
                      [&](const ModelTpl<double>& mdd) { return make_kinematics(mdd, o, ko); });
        },
        "model"_a, "dtype"_a, "backend"_a, "max_batch"_a, "frames"_a = nb::none(), "reference"_a = "world",
        "pose"_a = "matrix", "threads"_a = 0, "device"_a = -1)
      .def("compute",
           [](PyKinematics& e, const InArray& q, const std::optional<OutArray>& poses,
              const std::optional<OutArray>& J, std::uintptr_t stream) {
             if (e.is_float) compute<float>(e, q, poses, J, stream);
             else compute<double>(e, q, poses, J, stream);
           },
           "q"_a, "poses"_a = nb::none(), "J"_a = nb::none(), "stream"_a = 0)
      .def_prop_ro("frames",
                   [](const PyKinematics& e) {
                     std::vector<std::string> names;  // (F)
                     for (Index f : kinematics_options(e).frames) names.push_back(e.model->md.frame_names[size_t(f)]);
                     return names;
                   })
      .def_prop_ro("reference",
                   [](const PyKinematics& e) {
                     return kinematics_options(e).reference == FrameReference::Local ? "local" : "world";
                   })
      .def_prop_ro("pose",
                   [](const PyKinematics& e) {
                     return kinematics_options(e).pose == PoseFormat::Matrix ? "matrix" : "quaternion";
                   });
  def_engine_properties(k);
  k.attr("cuda_max_dofs") = cuda::kMaxThreadDofs;  // the CUDA engine's largest model (one thread per instance)
}

}  // namespace scandyn::py
