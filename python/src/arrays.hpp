// python/src/arrays.hpp: caller arrays (nb::ndarray: the buffer protocol or DLPack)
// as the engines read them, shared by the extension module's bindings (module.cpp,
// kinematics.cpp): where a call's arrays live (host memory or one CUDA device,
// DeviceError otherwise), their dtype (DTypeError) and shapes (ShapeError), the
// BatchView of a (B, nv) or (nv,) array with its own strides (no copy), and the
// checks an output passes (no entry shared with another, no memory shared with an
// input).
#pragma once

#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <initializer_list>
#include <limits>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "scandyn/engine.hpp"
#include "shared.hpp"

namespace scandyn::py {

namespace nb = nanobind;

using InArray = nb::ndarray<nb::ro>;
using OutArray = nb::ndarray<>;

template <class S>
bool has_dtype(const nb::ndarray<nb::ro>& a) {
  return a.dtype() == nb::dtype<S>();
}
template <class S>
bool has_dtype(const nb::ndarray<>& a) {
  return a.dtype() == nb::dtype<S>();
}

inline std::string dtype_name(nb::dlpack::dtype t) {
  const char* kind = t.code == uint8_t(nb::dlpack::dtype_code::Float)   ? "float"
                     : t.code == uint8_t(nb::dlpack::dtype_code::Int)   ? "int"
                     : t.code == uint8_t(nb::dlpack::dtype_code::UInt)  ? "uint"
                     : t.code == uint8_t(nb::dlpack::dtype_code::Bool)  ? "bool"
                     : t.code == uint8_t(nb::dlpack::dtype_code::Complex) ? "complex"
                                                                         : "dtype code " ;
  return std::string(kind) + std::to_string(t.bits);
}

// scalar_name, shape_str: shared.hpp

// Where an argument's data lie: [lo, hi) bytes, for overlap checks.
struct Extent {
  const char* lo;
  const char* hi;
};
template <class A>
Extent extent_of(const A& a) {
  const char* p = static_cast<const char*>(a.data());
  const std::ptrdiff_t item = a.dtype().bits / 8;
  std::ptrdiff_t lo = 0, hi = 0;
  for (size_t i = 0; i < a.ndim(); ++i) {
    if (a.shape(i) == 0) return {p, p};
    const std::ptrdiff_t span = std::ptrdiff_t(a.shape(i) - 1) * a.stride(i) * item;
    (span < 0 ? lo : hi) += span;
  }
  return {p + lo, p + hi + item};
}
inline bool overlaps(Extent a, Extent b) { return a.lo < b.hi && b.lo < a.hi && a.lo != a.hi && b.lo != b.hi; }

// The common leading shape of a call: B instances, or one state ((nv,) arrays),
// and where the call's arrays are (set by the first array, checked for the others).
struct Lead {
  bool single = false;  // (nv,) arrays: one instance
  Index batch = 0;
  bool placed = false;  // the device below is set
  bool cuda = false;    // on a CUDA device (else host memory)
  int device = 0;       // the CUDA device's ordinal
};

inline std::string where_str(bool cuda, int device) {
  return cuda ? "CUDA device " + std::to_string(device) : std::string("host memory");
}

// Host memory (DLPack CPU or CUDA-pinned host) or one CUDA device for every array of a call.
template <class A>
void check_device(const A& a, const char* name, Lead& lead) {
  const int type = a.device_type();
  const bool host = type == nb::device::cpu::value || type == nb::device::cuda_host::value;
  if (!host && type != nb::device::cuda::value)
    throw DeviceError(std::string(name) + " is on DLPack device type " + std::to_string(type) +
                      ": scandyn takes host memory or CUDA device memory");
  const bool cuda = !host;
  const int device = cuda ? a.device_id() : 0;
  if (!lead.placed) {
    lead.placed = true;
    lead.cuda = cuda;
    lead.device = device;
  } else if (cuda != lead.cuda || device != lead.device) {
    throw DeviceError(std::string(name) + " is in " + where_str(cuda, device) + ", the call's first array in " +
                      where_str(lead.cuda, lead.device) +
                      ": every array of a call is on one device (scandyn copies nothing between devices)");
  }
}

// The BatchView of a (B, nv) or (nv,) array `a` (nv per instance). Checks device,
// dtype and shape against `lead` (set from the first array when batch < 0).
template <class T, class A>
BatchView<T> view_of(const A& a, Index nv, const char* name, Lead& lead, bool first, const char* dim = "nv") {
  using S = std::remove_const_t<T>;
  check_device(a, name, lead);
  if (!has_dtype<S>(a))
    throw DTypeError(std::string(name) + " has dtype " + dtype_name(a.dtype()) + ", expected " + scalar_name<S>() +
                     " (every array of a call shares one dtype, which sets the precision)");
  const size_t nd = a.ndim();
  auto shape = [&] {
    std::string s = "(";
    for (size_t i = 0; i < nd; ++i) s += (i ? ", " : "") + std::to_string(a.shape(i));
    return s + (nd == 1 ? ",)" : ")");
  };
  if (nd != 1 && nd != 2)
    throw ShapeError(std::string(name) + " has shape " + shape() + ", expected (" + dim + ",) or (B, " + dim +
                     ") with " + dim + " = " + std::to_string(nv));
  if (Index(a.shape(nd - 1)) != nv || a.shape(nd - 1) != size_t(Index(a.shape(nd - 1))))
    throw ShapeError(std::string(name) + " has shape " + shape() + ": its last dimension must be the model's " + dim +
                     " = " + std::to_string(nv));
  const bool single = nd == 1;
  if (nd == 2 && a.shape(0) > size_t(std::numeric_limits<Index>::max()))
    throw ShapeError(std::string(name) + ": batch of " + std::to_string(a.shape(0)) + " instances is too large");
  const Index batch = single ? 1 : Index(a.shape(0));
  if (first) {
    lead.single = single;
    lead.batch = batch;
  } else if (single != lead.single || batch != lead.batch) {
    throw ShapeError(std::string(name) + " has shape " + shape() + ", but the first array's leading shape is " +
                     (lead.single ? std::string("() (one state)") : "(" + std::to_string(lead.batch) + ",)") +
                     ": every array of a call has the same leading shape");
  }
  BatchView<T> v;
  v.data = static_cast<T*>(const_cast<void*>(static_cast<const void*>(a.data())));
  v.batch = batch;
  v.dof_stride = a.stride(nd - 1);
  v.batch_stride = single ? 0 : a.stride(0);
  return v;
}

// The BatchView of a (B, nv, ..., nv) or (nv, ..., nv) out array of `rank` trailing
// nv dimensions (rank 2: one nv x nv matrix per instance, as the mass matrix and the
// derivative engines write them; rank 3: one nv^3 tensor, the second derivatives'):
// entry (i, j[, k]) of instance b at data[(i * nv + j)[* nv + k] * s + b * sb], so each
// instance's block must be row-major (a C-contiguous array, a slice of one along the
// batch, or the entry-major view of the CUDA results: (1, nv B, B), (1, nv^2 B, nv B,
// B)). Checks device, dtype and shape against `lead` (set by the call's first array).
template <class S>
BatchView<S> block_view_of(const OutArray& out, Index nv, int rank, const char* name, Lead& lead) {
  check_device(out, name, lead);
  if (!has_dtype<S>(out))
    throw DTypeError(std::string(name) + " has dtype " + dtype_name(out.dtype()) + ", expected " + scalar_name<S>());
  const size_t nd = out.ndim();
  const size_t want = (lead.single ? 0 : 1) + static_cast<size_t>(rank);
  bool shape_ok = nd == want && (lead.single || Index(out.shape(0)) == lead.batch);
  for (int k = 1; shape_ok && k <= rank; ++k) shape_ok = Index(out.shape(nd - k)) == nv;
  if (!shape_ok) {
    std::string expected = lead.single ? "(" : "(" + std::to_string(lead.batch) + ", ";
    for (int k = 0; k < rank; ++k) expected += std::to_string(nv) + (k + 1 < rank ? ", " : ")");
    throw ShapeError(std::string(name) + " has shape " + shape_str(out) + ", expected " + expected);
  }
  const std::ptrdiff_t s = out.stride(nd - 1);
  bool row_major = true;  // stride(nd - k) = s nv^(k - 1)
  std::ptrdiff_t step = s;
  for (int k = 2; k <= rank; ++k) row_major = row_major && out.stride(nd - k) == (step *= nv);
  if (nv > 1 && !row_major)
    throw ShapeError(std::string(name) +
                     (rank == 2 ? ": each instance's (nv, nv) block must be row-major (strides (nv * s, s) for its "
                                  "last two dimensions)"
                                : ": each instance's (nv, nv, nv) block must be row-major (strides (nv^2 s, nv s, "
                                  "s) for its last three dimensions)") +
                     ", as a C-contiguous array or a slice along the batch dimension of one");
  BatchView<S> M;
  M.data = static_cast<S*>(out.data());
  M.batch = lead.batch;
  M.dof_stride = s;
  M.batch_stride = lead.single ? 0 : out.stride(0);
  return M;
}

// A (B, nv, nv) or (nv, nv) out array: block_view_of of rank 2.
template <class S>
BatchView<S> matrix_view_of(const OutArray& out, Index nv, const char* name, Lead& lead) {
  return block_view_of<S>(out, nv, 2, name, lead);
}

// The inputs (q, qd, qdd) of an inverse-dynamics engine's call: q (B, nq) or (nq,), qd
// and qdd (B, nv) or (nv,); lead: their batch and device. (The first-order derivative
// engines take quaternion models, nq > nv.)
template <class S>
IdBatchIn<S> id_inputs(Index nq, Index nv, const InArray& q, const InArray& qd, const InArray& qdd, Lead& lead) {
  IdBatchIn<S> in;
  in.q = view_of<const S>(q, nq, "q", lead, true, nq == nv ? "nv" : "nq");
  in.qd = view_of<const S>(qd, nv, "qd", lead, false);
  in.qdd = view_of<const S>(qdd, nv, "qdd", lead, false);
  return in;
}
// ... on a model with nq = nv (the second-order derivative engine)
template <class S>
IdBatchIn<S> id_inputs(Index nv, const InArray& q, const InArray& qd, const InArray& qdd, Lead& lead) {
  return id_inputs<S>(nv, nv, q, qd, qdd, lead);
}

// The inputs (q, qd, tau) of a forward-dynamics engine's call, as id_inputs.
template <class S>
FdBatchIn<S> fd_inputs(Index nq, Index nv, const InArray& q, const InArray& qd, const InArray& tau, Lead& lead) {
  FdBatchIn<S> in;
  in.q = view_of<const S>(q, nq, "q", lead, true, nq == nv ? "nv" : "nq");
  in.qd = view_of<const S>(qd, nv, "qd", lead, false);
  in.tau = view_of<const S>(tau, nv, "tau", lead, false);
  return in;
}
// ... on a model with nq = nv (the directional, loop and step engines)
template <class S>
FdBatchIn<S> fd_inputs(Index nv, const InArray& q, const InArray& qd, const InArray& tau, Lead& lead) {
  return fd_inputs<S>(nv, nv, q, qd, tau, lead);
}

// Out arrays: distinct elements must not share memory (a broadcast view would have
// threads race on one entry).
// (No allocation: called on every call, after the shape checks, with at most 4 dimensions:
// the kinematics' (B, F, 4, 4) and (B, F, 6, nv).)
template <class A>
void check_no_self_overlap(const A& a, const char* name) {
  constexpr size_t kMaxDims = 4;
  std::pair<std::ptrdiff_t, std::ptrdiff_t> dims[kMaxDims];  // |stride|, extent
  size_t nd = 0;
  for (size_t i = 0; i < a.ndim(); ++i) {
    if (a.shape(i) == 0) return;
    if (a.shape(i) > 1) {
      if (nd == kMaxDims) throw ShapeError(std::string(name) + " has more than 4 dimensions");
      dims[nd++] = {std::abs(std::ptrdiff_t(a.stride(i))), std::ptrdiff_t(a.shape(i))};
    }
  }
  for (size_t k = 1; k < nd; ++k)  // insertion sort by |stride| (std::sort on 4 entries trips -Warray-bounds)
    for (size_t j = k; j > 0 && dims[j] < dims[j - 1]; --j) std::swap(dims[j], dims[j - 1]);
  std::ptrdiff_t need = 1;
  for (size_t k = 0; k < nd; ++k) {
    const auto [stride, n] = dims[k];
    if (stride < need)
      throw ShapeError(std::string(name) + " has overlapping entries (strides that make two entries share memory, "
                       "e.g. a broadcast view): an output must be writable entry by entry");
    need = stride * n;
  }
}

// An output (named out_name) sharing no memory with the call's other arrays.
template <class A>
void check_out_alone(const A& out, std::initializer_list<std::pair<Extent, const char*>> inputs,
                     const char* out_name = "out") {
  const Extent e = extent_of(out);
  for (const auto& [in, name] : inputs)
    if (overlaps(e, in))
      throw ShapeError(std::string(out_name) + " shares memory with " + name +
                       ": the engines read inputs while writing outputs; pass a separate array");
}

inline void check_max_batch(const Lead& lead, Index max_batch) {
  if (lead.batch > max_batch)
    throw ShapeError("a batch of " + std::to_string(lead.batch) + " instances exceeds this engine's max_batch = " +
                     std::to_string(max_batch));
}

}  // namespace scandyn::py
