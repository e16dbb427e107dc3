// kernels/fd_dense.cu: forward dynamics by CRBA + cuSOLVER's batched Cholesky for
// models beyond the thread-per-instance kernels (scandyn/cuda/fd_dense.hpp).
#include <cuda_runtime.h>

#include <cmath>
#include <string>
#include <vector>

#include "crba_block.hpp"
#include "scandyn/algorithm/steps.hpp"
#include "scandyn/cuda/fd_dense.hpp"
#include "staging.hpp"

#if SCANDYN_HAS_CUSOLVER
#include <cusolverDn.h>
#endif

namespace scandyn {
namespace cuda {
namespace {

using detail::kCrbaBlock;

// One block per instance b: Xup, the composite inertias and M (both triangles; M
// holds n * n entries per instance, M(i, j) at entry i * n + j); with kRhs also the
// right-hand side tau - h.
template <class S, bool kRhs>
__global__ void __launch_bounds__(kCrbaBlock)
    crba_kernel(const Body<S>* __restrict__ body, const int* __restrict__ parent, int n, BatchView<const S> q,
                BatchView<S> M, Transform<S>* Xup, Inertia<S>* Ic, BatchView<const S> tau,
                const S* __restrict__ h /* soa nv x B */, S* rhs) {
  const int b = blockIdx.x, B = gridDim.x;
  Transform<S>* X = Xup + std::size_t(b) * n;
  Inertia<S>* I = Ic + std::size_t(b) * n;
  S* const Mb = M.data + std::ptrdiff_t(b) * M.batch_stride;  // instance b's entries
  const std::ptrdiff_t ms = M.dof_stride;                     // between entries e and e + 1
  auto at = [&](int i, int j) -> S& { return Mb[std::ptrdiff_t(std::size_t(i) * n + j) * ms]; };
  for (int i = threadIdx.x; i < n; i += blockDim.x) {
    X[i] = joint_transform(body[i], q.at(i, b));
    I[i] = body[i].I;
    if constexpr (kRhs) rhs[std::size_t(b) * n + i] = tau.at(i, b) - h[std::size_t(i) * B + b];
  }
  for (std::size_t k = threadIdx.x; k < std::size_t(n) * n; k += blockDim.x) Mb[std::ptrdiff_t(k) * ms] = S(0);
  __syncthreads();
  if (threadIdx.x == 0) {  // leaves to root, the reference's order
    for (int i = n - 1; i >= 0; --i)
      if (parent[i] >= 0) I[parent[i]] += crba_composite_step(X[i], I[i]);
  }
  __syncthreads();
  for (int i = threadIdx.x; i < n; i += blockDim.x) {  // column i, carried to the root
    Force<S> F = crba_column_force(body[i], I[i]);
    at(i, i) = joint_project(body[i], F);
    for (int j = i; parent[j] >= 0;) {
      F = crba_column_step(X[j], F);
      j = parent[j];
      const S Mij = joint_project(body[j], F);
      at(i, j) = Mij;
      at(j, i) = Mij;
    }
  }
}

// qdd of the instances whose factorisation and solution are fine; failed_dof.
template <class S>
__global__ void finish_kernel(int n, int B, const int* __restrict__ info, const S* __restrict__ x, BatchView<S> qdd,
                              int* failed_dof) {
  const int b = blockIdx.x * blockDim.x + threadIdx.x;
  if (b >= B) return;
  const S* xb = x + std::size_t(b) * n;
  int failed = info[b] > 0 ? info[b] - 1 : -1;  // the leading minor of order info[b]
  for (int i = 0; failed < 0 && i < n; ++i)
    if (!isfinite(xb[i])) failed = i;
  failed_dof[b] = failed;
  if (failed < 0)
    for (int i = 0; i < n; ++i) qdd.at(i, b) = xb[i];
}

template <class S>
__global__ void pointers_kernel(S* base, std::size_t stride, int B, S** out) {
  const int b = blockIdx.x * blockDim.x + threadIdx.x;
  if (b < B) out[b] = base + stride * b;
}

constexpr std::size_t kAlign = 256;
std::size_t aligned(std::size_t x) { return (x + kAlign - 1) / kAlign * kAlign; }

// bytes of this plan's own buffers (besides the CRBA's and the bias plan's)
template <class S>
std::size_t own_bytes(Index nv, Index max_batch) {
  const std::size_t n = std::size_t(nv), B = std::size_t(max_batch);
  return aligned(B * n * n * sizeof(S)) + aligned(B * n * sizeof(S)) + aligned(B * n * sizeof(S)) /* h */ +
         aligned(B * sizeof(int)) /* info */ + aligned(sizeof(int)) + 2 * aligned(B * sizeof(S*)) +
         aligned(sizeof(S)) /* zero */;
}

}  // namespace

// ---- CrbaBlocks (kernels/crba_block.hpp) ---------------------------------------------

namespace detail {

template <class S>
std::size_t CrbaBlocks<S>::bytes_needed(Index nv, Index max_batch) {
  const std::size_t n = std::size_t(nv), B = std::size_t(max_batch);
  return aligned(n * sizeof(Body<S>)) + aligned(n * sizeof(int)) + aligned(B * n * sizeof(Transform<S>)) +
         aligned(B * n * sizeof(Inertia<S>));
}

template <class S>
CrbaBlocks<S>::CrbaBlocks(const ModelTpl<S>& model, Index max_batch) : nv_(model.nv()), max_batch_(max_batch) {
  if (max_batch_ < 0) throw BackendError("backend 'cuda': max_batch " + std::to_string(max_batch_) + " is negative");
  const std::size_t n = std::size_t(nv_), B = std::size_t(max_batch_);
  bytes_ = bytes_needed(nv_, max_batch_);
  block_ = device_malloc(bytes_, [&](std::size_t free_bytes, std::size_t total_bytes) {
    return "backend 'cuda': the CRBA (a thread block per instance) for max_batch " + std::to_string(max_batch_) +
           " instances of a " + std::to_string(nv_) + "-DoF model in " + (sizeof(S) == 4 ? "float" : "double") +
           " needs " + std::to_string(bytes_) +
           " bytes of device memory (the bodies, and each instance's transforms and composite inertias); the "
           "device has " + std::to_string(free_bytes) + " bytes free of " + std::to_string(total_bytes);
  });
  char* at = static_cast<char*>(block_);
  auto take = [&at](std::size_t bytes) {
    char* here = at;
    at += aligned(bytes);
    return here;
  };
  body_ = reinterpret_cast<Body<S>*>(take(n * sizeof(Body<S>)));
  parent_ = reinterpret_cast<int*>(take(n * sizeof(int)));
  Xup_ = reinterpret_cast<Transform<S>*>(take(B * n * sizeof(Transform<S>)));
  Ic_ = reinterpret_cast<Inertia<S>*>(take(B * n * sizeof(Inertia<S>)));
  std::vector<int> parent(n);
  for (Index i = 0; i < nv_; ++i) parent[i] = model.bodies[i].parent;
  try {
    check(cudaMemcpy(body_, model.bodies.data(), n * sizeof(Body<S>), cudaMemcpyHostToDevice),
          "copying the bodies to the device");
    check(cudaMemcpy(parent_, parent.data(), n * sizeof(int), cudaMemcpyHostToDevice),
          "copying the parents to the device");
    // pageable copies may return before their DMA ends: finish before any launch
    check(cudaDeviceSynchronize(), "preparing the CRBA's buffers");
  } catch (...) {
    cudaFree(block_);
    throw;
  }
}

template <class S>
CrbaBlocks<S>::~CrbaBlocks() {
  if (block_) cudaFree(block_);
}

template <class S>
cudaError_t CrbaBlocks<S>::launch(const BatchView<const S>& q, const BatchView<S>& M, cudaStream_t stream) const {
  const Index B = q.batch;
  if (B < 0 || M.batch != B || B > max_batch_) return cudaErrorInvalidValue;
  if (B == 0 || nv_ == 0) return cudaSuccess;
  if (!q.data || !M.data) return cudaErrorInvalidValue;
  crba_kernel<S, false><<<unsigned(B), kCrbaBlock, 0, stream>>>(body_, parent_, int(nv_), q, M, Xup_, Ic_,
                                                               BatchView<const S>{}, nullptr, nullptr);
  return cudaGetLastError();
}

template <class S>
cudaError_t CrbaBlocks<S>::launch_with_rhs(const BatchView<const S>& q, const BatchView<S>& M,
                                           const BatchView<const S>& tau, const S* h, S* rhs,
                                           cudaStream_t stream) const {
  const Index B = q.batch;
  if (B < 0 || M.batch != B || tau.batch != B || B > max_batch_) return cudaErrorInvalidValue;
  if (B == 0 || nv_ == 0) return cudaSuccess;
  if (!q.data || !M.data || !tau.data || !h || !rhs) return cudaErrorInvalidValue;
  crba_kernel<S, true><<<unsigned(B), kCrbaBlock, 0, stream>>>(body_, parent_, int(nv_), q, M, Xup_, Ic_, tau, h, rhs);
  return cudaGetLastError();
}

template class CrbaBlocks<float>;
template class CrbaBlocks<double>;

}  // namespace detail

// ---- DenseJsiPlan ---------------------------------------------------------------------

template <class S>
struct DenseJsiPlan<S>::Impl {
  std::unique_ptr<IdScanPlan<S>> bias;
  std::unique_ptr<detail::CrbaBlocks<S>> crba;  // M (and tau - h), one block per instance
  void* block = nullptr;
  std::size_t bytes = 0;
  S* M = nullptr;
  S* rhs = nullptr;
  S* h = nullptr;
  int* info = nullptr;
  int* solve_info = nullptr;
  S** Mptr = nullptr;
  S** rhsptr = nullptr;
  S* zero = nullptr;
#if SCANDYN_HAS_CUSOLVER
  cusolverDnHandle_t handle = nullptr;
#endif
  ~Impl() {
#if SCANDYN_HAS_CUSOLVER
    if (handle) cusolverDnDestroy(handle);
#endif
    if (block) cudaFree(block);
  }
};

template <class S>
std::size_t DenseJsiPlan<S>::bytes_needed(const ModelTpl<S>& model, Index max_batch) {
  return own_bytes<S>(model.nv(), max_batch) + detail::CrbaBlocks<S>::bytes_needed(model.nv(), max_batch) +
         IdScanPlan<S>::bytes_needed(model, max_batch);
}

template <class S>
std::size_t DenseJsiPlan<S>::device_bytes() const {
  return impl_->bytes + (impl_->crba ? impl_->crba->device_bytes() : 0) +
         (impl_->bias ? impl_->bias->device_bytes() : 0);
}

template <class S>
DenseJsiPlan<S>::DenseJsiPlan(const ModelTpl<S>& model, Index max_batch)
    : nv_(model.nv()), max_batch_(max_batch), impl_(std::make_unique<Impl>()) {
#if !SCANDYN_HAS_CUSOLVER
  (void)model;
  throw BackendError("backend 'cuda': forward dynamics beyond the thread-per-instance kernels' DoF needs cuSOLVER, "
                     "which this build was configured without");
#else
  if (max_batch_ < 0) throw BackendError("backend 'cuda': max_batch " + std::to_string(max_batch_) + " is negative");
  const std::size_t n = std::size_t(nv_), B = std::size_t(max_batch_);
  impl_->bytes = own_bytes<S>(nv_, max_batch_);
  std::size_t free_bytes = 0, total_bytes = 0;
  detail::check(cudaMemGetInfo(&free_bytes, &total_bytes), "cudaMemGetInfo");
  const std::size_t need = bytes_needed(model, max_batch_);
  if (need > free_bytes)
    throw BackendError("backend 'cuda': forward dynamics by CRBA + batched Cholesky for max_batch " +
                       std::to_string(max_batch_) + " instances of a " + std::to_string(nv_) + "-DoF model in " +
                       (sizeof(S) == 4 ? "float" : "double") + " needs " + std::to_string(need) +
                       " bytes of device memory (the mass matrices alone " + std::to_string(B * n * n * sizeof(S)) +
                       "); the device has " + std::to_string(free_bytes) + " bytes free of " +
                       std::to_string(total_bytes));
  impl_->bias = std::make_unique<IdScanPlan<S>>(model, max_batch_);
  impl_->crba = std::make_unique<detail::CrbaBlocks<S>>(model, max_batch_);
  detail::check(cudaMalloc(&impl_->block, impl_->bytes), "cudaMalloc of the forward-dynamics buffers");
  char* at = static_cast<char*>(impl_->block);
  auto take = [&at](std::size_t bytes) {
    char* here = at;
    at += aligned(bytes);
    return here;
  };
  impl_->M = reinterpret_cast<S*>(take(B * n * n * sizeof(S)));
  impl_->rhs = reinterpret_cast<S*>(take(B * n * sizeof(S)));
  impl_->h = reinterpret_cast<S*>(take(B * n * sizeof(S)));
  impl_->info = reinterpret_cast<int*>(take(B * sizeof(int)));
  impl_->solve_info = reinterpret_cast<int*>(take(sizeof(int)));
  impl_->Mptr = reinterpret_cast<S**>(take(B * sizeof(S*)));
  impl_->rhsptr = reinterpret_cast<S**>(take(B * sizeof(S*)));
  impl_->zero = reinterpret_cast<S*>(take(sizeof(S)));
  detail::check(cudaMemset(impl_->zero, 0, sizeof(S)), "cudaMemset");
  if (B > 0) {
    const unsigned blocks = unsigned((B + 127) / 128);
    pointers_kernel<S><<<blocks, 128>>>(impl_->M, n * n, int(B), impl_->Mptr);
    pointers_kernel<S><<<blocks, 128>>>(impl_->rhs, n, int(B), impl_->rhsptr);
    detail::check(cudaGetLastError(), "setting up the batched solver's pointers");
  }
  // pageable copies may return before their DMA ends: finish before any launch
  detail::check(cudaDeviceSynchronize(), "preparing the forward-dynamics buffers");
  if (cusolverDnCreate(&impl_->handle) != CUSOLVER_STATUS_SUCCESS)
    throw BackendError("backend 'cuda': cusolverDnCreate failed");
#endif
}

template <class S>
DenseJsiPlan<S>::~DenseJsiPlan() = default;

template <class S>
cudaError_t DenseJsiPlan<S>::launch(const FdBatchIn<S>& in, const BatchView<S>& qdd, int* failed_dof,
                                    cudaStream_t stream) {
#if !SCANDYN_HAS_CUSOLVER
  (void)in, (void)qdd, (void)failed_dof, (void)stream;
  return cudaErrorNotSupported;
#else
  const Index B = in.q.batch;
  if (B < 0 || in.qd.batch != B || in.tau.batch != B || qdd.batch != B || B > max_batch_) return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  if (!in.q.data || !in.qd.data || !in.tau.data || !qdd.data || !failed_dof) return cudaErrorInvalidValue;
  Impl& m = *impl_;
  const int n = int(nv_);
  // h = RNEA(q, qd, 0) - sum J^T fext (qdd: one zero read by every entry)
  const IdBatchIn<S> id{in.q, in.qd, BatchView<const S>{m.zero, B, 0, 0}, in.fext};
  cudaError_t err = m.bias->launch(id, BatchView<S>::soa(m.h, nv_, B), stream);
  if (err != cudaSuccess) return err;
  // M (instance b's n x n matrix at M + b n^2) and rhs = tau - h
  err = m.crba->launch_with_rhs(in.q, BatchView<S>::aos(m.M, nv_ * nv_, B), in.tau, m.h, m.rhs, stream);
  if (err != cudaSuccess) return err;
  if (cusolverDnSetStream(m.handle, stream) != CUSOLVER_STATUS_SUCCESS) return cudaErrorUnknown;
  cusolverStatus_t st;
  if constexpr (sizeof(S) == 4) {
    st = cusolverDnSpotrfBatched(m.handle, CUBLAS_FILL_MODE_LOWER, n, m.Mptr, n, m.info, int(B));
    if (st == CUSOLVER_STATUS_SUCCESS)
      st = cusolverDnSpotrsBatched(m.handle, CUBLAS_FILL_MODE_LOWER, n, 1, m.Mptr, n, m.rhsptr, n, m.solve_info,
                                   int(B));
  } else {
    st = cusolverDnDpotrfBatched(m.handle, CUBLAS_FILL_MODE_LOWER, n, m.Mptr, n, m.info, int(B));
    if (st == CUSOLVER_STATUS_SUCCESS)
      st = cusolverDnDpotrsBatched(m.handle, CUBLAS_FILL_MODE_LOWER, n, 1, m.Mptr, n, m.rhsptr, n, m.solve_info,
                                   int(B));
  }
  if (st != CUSOLVER_STATUS_SUCCESS) return cudaErrorUnknown;
  finish_kernel<S><<<unsigned((B + 127) / 128), 128, 0, stream>>>(n, int(B), m.info, m.rhs, qdd, failed_dof);
  return cudaGetLastError();
#endif
}

template class DenseJsiPlan<float>;
template class DenseJsiPlan<double>;

}  // namespace cuda
}  // namespace scandyn
