// kernels/id_instances.cu: batched inverse dynamics, one thread per instance.
//
// The layers of scandyn/cuda/inverse_dynamics.hpp: rnea_instance (the header) ->
// id_instances_kernel -> launch_id_instances -> CudaInverseDynamics (host staging
// for compute(), the plain launch for compute_async()).
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdlib>
#include <string>
#include <type_traits>

#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"

namespace scandyn {
namespace cuda {

// ---- the model as kernel parameter --------------------------------------------

namespace {

template <int C, class S>
ThreadModelParams<S, C> make_params(const ModelTpl<S>& model) {
  ThreadModelParams<S, C> p{};  // zero-filled, unused bodies included
  const Index n = model.nv();
  p.nv = n;
  p.a0 = base_acceleration(model.gravity);
  for (Index i = 0; i < n; ++i) {
    const Index parent = model.bodies[i].parent;
    if (parent >= i || parent < -1)
      throw BackendError("backend 'cuda': body " + std::to_string(i) + " has parent " + std::to_string(parent) +
                         " (bodies must come after their parent)");
    p.body[i] = model.bodies[i];
    if (parent < 0) p.flags[i] |= kParentIsBase;
    else if (parent == i - 1) p.flags[i] |= kParentIsPrev;
    else p.flags[parent] |= kStacked;  // a child that is not the next body
  }
  return p;
}

}  // namespace

template <class S>
ThreadModel<S>::ThreadModel(const ModelTpl<S>& model) : nv_(model.nv()) {
  if (nv_ > kMaxThreadDofs)
    throw BackendError("backend 'cuda': model '" + model.name + "' has " + std::to_string(nv_) +
                       " DoF; the thread-per-instance kernels take at most " + std::to_string(kMaxThreadDofs) +
                       " (per-thread state is sized at compile time)");
  if (nv_ <= 8) capacity_ = 8, params_ = make_params<8>(model);
  else if (nv_ <= 16) capacity_ = 16, params_ = make_params<16>(model);
  else if (nv_ <= 32) capacity_ = 32, params_ = make_params<32>(model);
  else capacity_ = 64, params_ = make_params<64>(model);
}

// ---- kernel and launch ---------------------------------------------------------

namespace {

template <class T>
__device__ __forceinline__ DofColumn<T> column(const BatchView<T>& v, long long b) {
  return {v.data + b * v.batch_stride, v.dof_stride};
}

}  // namespace

// One thread per instance b < B: the RNEA of instance b.
template <class S, int C>
__global__ void __launch_bounds__(kIdInstancesBlock)
    id_instances_kernel(const __grid_constant__ ThreadModelParams<S, C> model, const IdBatchIn<S> batch_in,
                        const BatchView<S> tau_out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= batch_in.q.batch) return;
  const Force<S>* fext = batch_in.fext ? batch_in.fext + b * model.nv : nullptr;
  rnea_instance<S, C>(model, column(batch_in.q, b), column(batch_in.qd, b), column(batch_in.qdd, b), fext,
                      column(tau_out, b));
}

template <class S>
cudaError_t launch_id_instances(const ThreadModel<S>& model, const IdBatchIn<S>& batch_in,
                                const BatchView<S>& tau_out, cudaStream_t stream) {
  const Index B = batch_in.q.batch;
  if (B < 0 || batch_in.qd.batch != B || batch_in.qdd.batch != B || tau_out.batch != B) return cudaErrorInvalidValue;
  if (B == 0 || model.nv() == 0) return cudaSuccess;
  if (!batch_in.q.data || !batch_in.qd.data || !batch_in.qdd.data || !tau_out.data) return cudaErrorInvalidValue;
  const unsigned blocks = static_cast<unsigned>((static_cast<long long>(B) + kIdInstancesBlock - 1) / kIdInstancesBlock);
  std::visit(
      [&](const auto& params) {
        using P = std::decay_t<decltype(params)>;
        id_instances_kernel<S, P::capacity>
            <<<blocks, kIdInstancesBlock, 0, stream>>>(params, batch_in, tau_out);
      },
      model.params());
  return cudaGetLastError();
}

// ---- host staging for compute() ---------------------------------------------------

namespace {

std::string error_string(cudaError_t err) {
  const char* s = cudaGetErrorString(err);
  return std::string(s ? s : "unknown CUDA error") + " (" + std::to_string(static_cast<int>(err)) + ")";
}

void check(cudaError_t err, const char* what) {
  if (err != cudaSuccess) {
    (void)cudaGetLastError();  // clear a non-sticky error so the next call starts clean
    throw BackendError(std::string("backend 'cuda': ") + what + ": " + error_string(err));
  }
}

std::ptrdiff_t sign(std::ptrdiff_t s) { return s < 0 ? -1 : 1; }

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
};

template <class T>
Staging plan(const BatchView<T>& v, Index nv, std::size_t capacity, bool output) {
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
    throw BackendError("backend 'cuda': the tau view has a zero stride: its entries overlap");
  const bool rows_b = std::abs(bs) == 1, rows_d = std::abs(ds) == 1;
  if (rows_b || rows_d) {
    // runs along the unit stride; the other stride is the pitch
    s.kind = Staging::Rows;
    const std::ptrdiff_t si = rows_b ? bs : ds, so = rows_b ? ds : bs;
    s.n_in = rows_b ? B : nv;
    s.n_out = rows_b ? nv : B;
    s.pitch = std::abs(so);
    if (s.pitch < s.n_in)  // only outputs get here (inputs fit the span)
      throw BackendError("backend 'cuda': the tau view's entries overlap (strides " + std::to_string(v.dof_stride) +
                         ", " + std::to_string(v.batch_stride) + ")");
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

}  // namespace

// ---- the engine -------------------------------------------------------------------

IdStrategy choose_cuda_strategy(Index nv, Index batch) {
  (void)batch;
  return nv <= kMaxThreadDofs ? IdStrategy::Recursion : IdStrategy::ScanLocal;
}

template <class S>
CudaInverseDynamics<S>::CudaInverseDynamics(const ModelTpl<S>& model, const BackendOptions& options)
    : nv_(model.nv()), max_batch_(options.max_batch) {
  if (options.strategy == IdStrategy::ScanWorld)
    throw BackendError("backend 'cuda': strategy 'scan-world' is not available on this backend "
                       "(use auto, recursion or scan-local)");
  if (max_batch_ < 0) throw BackendError("backend 'cuda': max_batch " + std::to_string(max_batch_) + " is negative");
  const IdStrategy strategy =
      options.strategy == IdStrategy::Auto ? choose_cuda_strategy(nv_, max_batch_) : options.strategy;
  if (strategy == IdStrategy::Recursion && nv_ > kMaxThreadDofs)
    throw BackendError("backend 'cuda': model '" + model.name + "' has " + std::to_string(nv_) +
                       " DoF; strategy 'recursion' (a thread per instance) takes at most " +
                       std::to_string(kMaxThreadDofs) + " (use auto or scan-local)");
  const Result<int> count = device_count();
  if (!count) throw BackendError("backend 'cuda': " + count.error);
  if (count.value == 0) throw BackendError("backend 'cuda': no usable CUDA device: the CUDA runtime reports 0 devices");
  check(cudaGetDevice(&device_), "cudaGetDevice");

  // q, qd, qdd, tau (1 scalar per DoF each) and fext (6) for max_batch instances
  const std::size_t per_instance = 10 * static_cast<std::size_t>(nv_) * sizeof(S);
  const std::size_t staging = per_instance * static_cast<std::size_t>(max_batch_);
  const std::size_t scratch = strategy == IdStrategy::ScanLocal ? IdScanPlan<S>::bytes_needed(model, max_batch_) : 0;
  bytes_ = staging + scratch;
  std::size_t free_bytes = 0, total_bytes = 0;
  check(cudaMemGetInfo(&free_bytes, &total_bytes), "cudaMemGetInfo");
  auto too_large = [&](const std::string& why) {
    const Result<DeviceInfo> info = device_info(device_);
    return BackendError("backend 'cuda': max_batch " + std::to_string(max_batch_) + " instances of a " +
                        std::to_string(nv_) + "-DoF model in " + (sizeof(S) == 4 ? "float" : "double") +
                        " need " + std::to_string(bytes_) + " bytes of device memory (q, qd, qdd, tau and fext: " +
                        std::to_string(per_instance) + " bytes per instance" +
                        (scratch ? ", link-scan scratch: " + std::to_string(scratch) + " bytes" : std::string()) +
                        "); device " + std::to_string(device_) + " (" + (info ? info.value.name : std::string("?")) +
                        ") has " + std::to_string(free_bytes) + " bytes free of " + std::to_string(total_bytes) + why);
  };
  if (bytes_ > free_bytes) throw too_large("");
  if (strategy == IdStrategy::ScanLocal) scan_ = std::make_unique<IdScanPlan<S>>(model, max_batch_);
  else thread_ = std::make_unique<ThreadModel<S>>(model);
  check(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking), "cudaStreamCreateWithFlags");
  if (staging > 0) {
    const cudaError_t err = cudaMalloc(reinterpret_cast<void**>(&buffer_), staging);
    if (err != cudaSuccess) {
      (void)cudaGetLastError();
      cudaStreamDestroy(stream_);
      throw too_large(": cudaMalloc failed with " + error_string(err));
    }
  }
}

template <class S>
CudaInverseDynamics<S>::~CudaInverseDynamics() {
  if (buffer_) cudaFree(buffer_);
  if (stream_) cudaStreamDestroy(stream_);
}

template <class S>
cudaError_t CudaInverseDynamics<S>::compute_async(const IdBatchIn<S>& in, const BatchView<S>& tau,
                                                  cudaStream_t stream) {
  return scan_ ? scan_->launch(in, tau, stream) : launch_id_instances(*thread_, in, tau, stream);
}

template <class S>
void CudaInverseDynamics<S>::compute(const IdBatchIn<S>& in, const BatchView<S>& tau) {
  check_batch(in, tau, max_batch_);
  const Index B = in.q.batch;
  const Index nv = nv_;
  if (B == 0 || nv == 0) return;
  // staging buffers: nv x max_batch scalars each, then the wrenches
  const std::size_t cap = static_cast<std::size_t>(nv) * max_batch_;
  S* const dq = buffer_;
  S* const dqd = dq + cap;
  S* const dqdd = dqd + cap;
  S* const dtau = dqdd + cap;
  Force<S>* const dfext = reinterpret_cast<Force<S>*>(dtau + cap);

  // copy in, in whatever layout keeps the copies few
  const Staging sq = plan(in.q, nv, cap, false), sqd = plan(in.qd, nv, cap, false);
  const Staging sqdd = plan(in.qdd, nv, cap, false), stau = plan(tau, nv, cap, true);
  check(copy(sq, in.q, nv, dq, cudaMemcpyHostToDevice, stream_), "copying q to the device");
  check(copy(sqd, in.qd, nv, dqd, cudaMemcpyHostToDevice, stream_), "copying qd to the device");
  check(copy(sqdd, in.qdd, nv, dqdd, cudaMemcpyHostToDevice, stream_), "copying qdd to the device");
  if (in.fext)
    check(cudaMemcpyAsync(dfext, in.fext, static_cast<std::size_t>(B) * nv * sizeof(Force<S>), cudaMemcpyHostToDevice,
                          stream_),
          "copying fext to the device");
  // run
  const IdBatchIn<S> din{{dq + sq.dev_base, B, sq.dev_ds, sq.dev_bs},
                         {dqd + sqd.dev_base, B, sqd.dev_ds, sqd.dev_bs},
                         {dqdd + sqdd.dev_base, B, sqdd.dev_ds, sqdd.dev_bs},
                         in.fext ? dfext : nullptr};
  const BatchView<S> dtau_view{dtau + stau.dev_base, B, stau.dev_ds, stau.dev_bs};
  check(compute_async(din, dtau_view, stream_), scan_ ? "launching the link scans" : "launching id_instances_kernel");
  // copy out: tau's entries only
  check(copy(stau, tau, nv, dtau, cudaMemcpyDeviceToHost, stream_), "copying tau to the host");
  check(cudaStreamSynchronize(stream_), scan_ ? "running the link scans" : "running id_instances_kernel");
}

template <class S>
std::unique_ptr<InverseDynamics<S>> make_cuda_inverse_dynamics(const ModelTpl<S>& model,
                                                               const BackendOptions& options) {
  return std::make_unique<CudaInverseDynamics<S>>(model, options);
}

#define SCANDYN_INSTANTIATE(S)                                                                           \
  template class ThreadModel<S>;                                                                         \
  template class CudaInverseDynamics<S>;                                                                 \
  template cudaError_t launch_id_instances(const ThreadModel<S>&, const IdBatchIn<S>&, const BatchView<S>&, \
                                           cudaStream_t);                                                \
  template std::unique_ptr<InverseDynamics<S>> make_cuda_inverse_dynamics(const ModelTpl<S>&,            \
                                                                          const BackendOptions&);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace cuda
}  // namespace scandyn
