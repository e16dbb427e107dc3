// kernels/staging.hpp (internal): what the CUDA engines' host paths share.
//
// The engines' compute() takes HOST views with any strides, copies them into one
// device buffer, launches, and copies the outputs back. This header holds that
// machinery once, for CudaInverseDynamics (inverse_dynamics.cu) and
// CudaForwardDynamics (forward_dynamics.cu):
//   check(), error_string()   CUDA errors as BackendError;
//   StagingBuffer             the device, a non-blocking stream and one buffer,
//                             with the "does not fit" message naming the bytes
//                             needed and free;
//   Staging, plan(), copy()   how one host view is laid out in the buffer and
//                             the copies between the two.
// Not installed: it is no part of the public API.
#pragma once

#include <cuda_runtime.h>

#include <cstddef>
#include <cstdlib>
#include <string>

#include "scandyn/engine.hpp"
#include "scandyn/cuda/device.hpp"

namespace scandyn {
namespace cuda {
namespace detail {

inline std::string error_string(cudaError_t err) {
  const char* s = cudaGetErrorString(err);
  return std::string(s ? s : "unknown CUDA error") + " (" + std::to_string(static_cast<int>(err)) + ")";
}

inline void check(cudaError_t err, const char* what) {
  if (err != cudaSuccess) {
    (void)cudaGetLastError();  // clear a non-sticky error so the next call starts clean
    throw BackendError(std::string("backend 'cuda': ") + what + ": " + error_string(err));
  }
}

// `bytes` of device memory on the current device, first checked against the memory
// free there. When they do not fit, or cudaMalloc fails, throws
// BackendError(too_large(free_bytes, total_bytes) + why), why being "" or
// ": cudaMalloc failed with <error>": too_large says who needs how many bytes of
// what (built only on failure).
template <class TooLarge>
void* device_malloc(std::size_t bytes, TooLarge&& too_large) {
  std::size_t free_bytes = 0, total_bytes = 0;
  check(cudaMemGetInfo(&free_bytes, &total_bytes), "cudaMemGetInfo");
  if (bytes > free_bytes) throw BackendError(too_large(free_bytes, total_bytes));
  void* p = nullptr;
  const cudaError_t err = cudaMalloc(&p, bytes);
  if (err != cudaSuccess) {
    (void)cudaGetLastError();
    throw BackendError(too_large(free_bytes, total_bytes) + ": cudaMalloc failed with " + error_string(err));
  }
  return p;
}

// The device current at construction, a non-blocking stream, and `bytes` of device
// memory for an engine's staging buffers. Throws BackendError when no device is
// usable, or when the bytes do not fit (naming them, what they hold, and the bytes
// free on the device).
class StagingBuffer {
 public:
  // max_batch instances of an nv-DoF model; `arrays` names what the buffer holds
  // (e.g. "q, qd, qdd, tau and fext"), per_instance is its bytes per instance.
  StagingBuffer(Index max_batch, Index nv, const char* precision, const char* arrays, std::size_t per_instance) {
    if (max_batch < 0) throw BackendError("backend 'cuda': max_batch " + std::to_string(max_batch) + " is negative");
    const Result<int> count = device_count();
    if (!count) throw BackendError("backend 'cuda': " + count.error);
    if (count.value == 0)
      throw BackendError("backend 'cuda': no usable CUDA device: the CUDA runtime reports 0 devices");
    check(cudaGetDevice(&device_), "cudaGetDevice");
    bytes_ = per_instance * static_cast<std::size_t>(max_batch);
    check(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking), "cudaStreamCreateWithFlags");
    if (bytes_ == 0) return;
    try {
      buffer_ = device_malloc(bytes_, [&](std::size_t free_bytes, std::size_t total_bytes) {
        const Result<DeviceInfo> info = device_info(device_);
        return "backend 'cuda': max_batch " + std::to_string(max_batch) + " instances of a " + std::to_string(nv) +
               "-DoF model in " + precision + " need " + std::to_string(bytes_) + " bytes of device memory (" +
               arrays + ": " + std::to_string(per_instance) + " bytes per instance); device " +
               std::to_string(device_) + " (" + (info ? info.value.name : std::string("?")) + ") has " +
               std::to_string(free_bytes) + " bytes free of " + std::to_string(total_bytes);
      });
    } catch (...) {
      cudaStreamDestroy(stream_);
      throw;
    }
  }
  ~StagingBuffer() {
    if (buffer_) cudaFree(buffer_);
    if (stream_) cudaStreamDestroy(stream_);
  }
  StagingBuffer(const StagingBuffer&) = delete;
  StagingBuffer& operator=(const StagingBuffer&) = delete;

  int device() const { return device_; }
  cudaStream_t stream() const { return stream_; }
  void* data() const { return buffer_; }
  std::size_t bytes() const { return bytes_; }

 private:
  int device_ = 0;
  std::size_t bytes_ = 0;
  cudaStream_t stream_ = nullptr;
  void* buffer_ = nullptr;
};

inline std::ptrdiff_t sign(std::ptrdiff_t s) { return s < 0 ? -1 : 1; }

// How the nv x B entries of a host view are laid out in a staging buffer, and
// the copies between the two. Kinds:
//   Span      the host memory between the lowest and the highest entry, verbatim,
//             same strides on the device (inputs whose span fits the buffer; outputs
//             only when dense, so that nothing between entries is written);
//   Rows      one stride is +-1: runs of contiguous entries, one 2D copy, dense on
//             the device with the same orientation;
//   Elements  neither stride is +-1: one 2D copy per DoF with a one-element width.
struct Staging {
  enum Kind { Span, Rows, Elements } kind = Span;
  std::ptrdiff_t lo = 0;         // host offset (elements) of the lowest entry
  std::ptrdiff_t count = 0;      // Span: elements copied
  std::ptrdiff_t dev_base = 0;   // device view base = buffer + dev_base
  std::ptrdiff_t dev_ds = 0, dev_bs = 0;  // device view strides
  // Rows: n_out runs of n_in entries, host pitch `pitch` elements
  std::ptrdiff_t n_in = 0, n_out = 0, pitch = 0;

  // The device view of a buffer staged by this plan.
  template <class T>
  BatchView<T> device_view(T* buffer, Index B) const {
    return {buffer + dev_base, B, dev_ds, dev_bs};
  }
};

// The plan for view v (nv x B) in a buffer of `capacity` elements; `name` names
// an output view in errors ("tau", "qdd").
template <class T>
Staging plan(const BatchView<T>& v, Index nv, std::size_t capacity, bool output, const char* name = "tau") {
  const Index B = v.batch;
  // a stride along an extent of 1 is never used
  const std::ptrdiff_t ds = nv > 1 ? v.dof_stride : 0, bs = B > 1 ? v.batch_stride : 0;
  Staging s;
  std::ptrdiff_t hi = 0;
  for (std::ptrdiff_t e : {ds * (nv - 1), bs * (B - 1)}) (e < 0 ? s.lo : hi) += e;
  const std::ptrdiff_t span = hi - s.lo + 1;
  const bool soa_dense = (B == 1 || std::abs(bs) == 1) && (nv == 1 || std::abs(ds) == B);
  const bool aos_dense = (nv == 1 || std::abs(ds) == 1) && (B == 1 || std::abs(bs) == nv);
  if (output ? (soa_dense || aos_dense) : static_cast<std::size_t>(span) <= capacity) {
    s.kind = Staging::Span;
    s.count = span;
    s.dev_base = -s.lo;
    s.dev_ds = ds, s.dev_bs = bs;
    return s;
  }
  if (output && ((nv > 1 && ds == 0) || (B > 1 && bs == 0)))
    throw BackendError(std::string("backend 'cuda': the ") + name + " view has a zero stride: its entries overlap");
  const bool rows_b = std::abs(bs) == 1, rows_d = std::abs(ds) == 1;
  if (rows_b || rows_d) {
    // runs along the unit stride; the other stride is the pitch
    s.kind = Staging::Rows;
    const std::ptrdiff_t si = rows_b ? bs : ds, so = rows_b ? ds : bs;
    s.n_in = rows_b ? B : nv;
    s.n_out = rows_b ? nv : B;
    s.pitch = std::abs(so);
    if (s.pitch < s.n_in)  // only outputs get here (inputs fit the span)
      throw BackendError(std::string("backend 'cuda': the ") + name + " view's entries overlap (strides " +
                         std::to_string(v.dof_stride) + ", " + std::to_string(v.batch_stride) + ")");
    const std::ptrdiff_t dsi = sign(si), dso = sign(so) * s.n_in;
    s.dev_base = (si < 0 ? s.n_in - 1 : 0) + (so < 0 ? (s.n_out - 1) * s.n_in : 0);
    s.dev_ds = rows_b ? dso : dsi;
    s.dev_bs = rows_b ? dsi : dso;
    return s;
  }
  s.kind = Staging::Elements;
  if (bs == 0) {  // an input broadcast over instances, DoFs far apart: nv entries
    s.dev_base = ds < 0 ? nv - 1 : 0;
    s.dev_ds = sign(ds), s.dev_bs = 0;
  } else {        // DoF i's B entries to row i, dense
    s.dev_base = bs < 0 ? B - 1 : 0;
    s.dev_ds = B, s.dev_bs = sign(bs);
  }
  return s;
}

// Copies between the host view's entries and the staging buffer as planned.
template <class S, class T>
cudaError_t copy(const Staging& s, const BatchView<T>& v, Index nv, S* buffer, cudaMemcpyKind kind,
                 cudaStream_t stream) {
  constexpr std::size_t sz = sizeof(S);
  S* host = const_cast<S*>(v.data);
  auto copy2d = [&](S* dev, std::ptrdiff_t dpitch, S* h, std::ptrdiff_t hpitch, std::ptrdiff_t width,
                    std::ptrdiff_t height) {
    return kind == cudaMemcpyHostToDevice
               ? cudaMemcpy2DAsync(dev, dpitch * sz, h, hpitch * sz, width * sz, height, kind, stream)
               : cudaMemcpy2DAsync(h, hpitch * sz, dev, dpitch * sz, width * sz, height, kind, stream);
  };
  switch (s.kind) {
    case Staging::Span:
      return kind == cudaMemcpyHostToDevice
                 ? cudaMemcpyAsync(buffer, host + s.lo, s.count * sz, kind, stream)
                 : cudaMemcpyAsync(host + s.lo, buffer, s.count * sz, kind, stream);
    case Staging::Rows:
      return copy2d(buffer, s.n_in, host + s.lo, s.pitch, s.n_in, s.n_out);
    case Staging::Elements: {
      const Index B = v.batch;
      if (s.dev_bs == 0)
        return copy2d(buffer, 1, host + s.lo, std::abs(v.dof_stride), 1, nv);
      const std::ptrdiff_t first = v.batch_stride < 0 ? (B - 1) * v.batch_stride : 0;
      for (Index i = 0; i < nv; ++i) {
        const cudaError_t err = copy2d(buffer + static_cast<std::ptrdiff_t>(i) * B, 1,
                                       host + i * v.dof_stride + first, std::abs(v.batch_stride), 1, B);
        if (err != cudaSuccess) return err;
      }
      return cudaSuccess;
    }
  }
  return cudaErrorInvalidValue;
}

// The staging buffer of an engine holds, for max_batch instances (cap = nq x
// max_batch scalars each, nq >= nv the widest input): three inputs of widths[k] x B
// entries (q: nq, the others nv) in slots 0, 1, 2, the output in slot 3, then the
// wrenches (B x nbodies). Copies the inputs (names for errors) and fext in, on
// `stream`, and returns the device views of the inputs and the wrenches.
template <class S>
struct StagedInputs {
  BatchView<const S> in[3];
  const Force<S>* fext;
};
template <class S>
StagedInputs<S> stage_inputs(const BatchView<const S> (&in)[3], const char* const (&names)[3], const Force<S>* fext,
                             const Index (&widths)[3], Index nbodies, std::size_t cap, S* buffer,
                             cudaStream_t stream) {
  const Index B = in[0].batch;
  StagedInputs<S> out{};
  for (int k = 0; k < 3; ++k) {
    S* const slot = buffer + k * cap;
    const Staging st = plan(in[k], widths[k], cap, false);
    check(copy(st, in[k], widths[k], slot, cudaMemcpyHostToDevice, stream),
          (std::string("copying ") + names[k] + " to the device").c_str());
    out.in[k] = st.device_view<const S>(slot, B);
  }
  Force<S>* const dfext = reinterpret_cast<Force<S>*>(buffer + 4 * cap);
  if (fext)
    check(cudaMemcpyAsync(dfext, fext, static_cast<std::size_t>(B) * nbodies * sizeof(Force<S>),
                          cudaMemcpyHostToDevice, stream),
          "copying fext to the device");
  out.fext = fext ? dfext : nullptr;
  return out;
}
// Models of 1-DoF joints: every input nv wide, nv bodies.
template <class S>
StagedInputs<S> stage_inputs(const BatchView<const S> (&in)[3], const char* const (&names)[3], const Force<S>* fext,
                             Index nv, std::size_t cap, S* buffer, cudaStream_t stream) {
  return stage_inputs<S>(in, names, fext, {nv, nv, nv}, nv, cap, buffer, stream);
}

}  // namespace detail
}  // namespace cuda
}  // namespace scandyn
