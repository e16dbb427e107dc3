// The CUDA driver of the chain forward dynamics' JVP and VJP
// (ChainFdPlan::launch_jvp / launch_vjp, scandyn/cuda/chain_fd.hpp): the walks of
// scandyn/algorithm/chain_directional.hpp, one thread per chunk, the level scans of
// chain_scan.cuh, after the plan's own forward-dynamics passes (kernels/chain_fd.cu).
#include <cuda_runtime.h>

#include <memory>
#include <string>
#include <vector>

#include "chain_scan.cuh"
#include "staging.hpp"
#include "scandyn/cuda/chain_fd.hpp"

namespace scandyn {
namespace cuda {

namespace {

// ---- JVP ----
template <class S>
__global__ void jvp_first_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, Affine6<S>* dv_agg) {
  SCANDYN_CHUNK_INDEX;
  subtree_force_local(d, s, e);
  dv_agg[c] = jvp_velocity_aggregate(d, s, e);
}

// the walks of dv, da and dF: chunk_walk_kernel over jvp_velocity_walk,
// jvp_acceleration_walk and jvp_force_walk (chain_scan.cuh)

// ---- VJP ----
// F locally, the rest solve's pass-2 aggregates (u = M^-1 w).
template <class S>
__global__ void vjp_first_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, Affine6<S>* z_agg) {
  SCANDYN_CHUNK_INDEX;
  subtree_force_local(d, s, e);
  z_agg[c] = vjp_rest_bias_aggregate(d, s, e);
}

template <class S>
__global__ void vjp_bias_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, const Vec6<S>* z_carry,
                                Affine6<S>* agg) {
  SCANDYN_CHUNK_INDEX;
  agg[c] = bias_walk(d.rest, s, e, z_carry[c]);
}

// The rest solve's pass 3 (u in x, Fbar in dv), then RA, gtau and RV's aggregate.
template <class S>
__global__ void vjp_solve_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, const Vec6<S>* carry,
                                 Affine6<S>* agg) {
  SCANDYN_CHUNK_INDEX;
  acceleration_walk(d.rest, s, e, carry[c]);
  agg[c] = vjp_adjoint_walk(d, s, e, carry[c]);
}

template <class S>
__global__ void vjp_rv_kernel(const ChainDirectionalData<S> d, ChunkRange r, Index chunks, const Vec6<S>* carry) {
  SCANDYN_CHUNK_INDEX;
  vjp_rv_walk(d, s, e, carry[c]);
}

// One call's chunked passes over count links: the level sizes, level 0's chunk range
// r, its chunks (one thread each) in nb blocks of kBlock, and scan(forward), the
// Affine6 level scan of level 0's aggregates agg[0] into the carries carry[0].
template <class S>
struct AffineScans {
  std::vector<Index> size;
  ChunkRange r;
  Index chunks;
  unsigned nb;
  Affine6<S>* const* agg;
  Vec6<S>* const* carry;
  Index fan_in;
  cudaStream_t stream;

  AffineScans(Index count, Index chunk, Index fan_in_, Affine6<S>* const* agg_, Vec6<S>* const* carry_,
              cudaStream_t stream_)
      : size(level_sizes(count, chunk, fan_in_)),
        r{chunk, count},
        chunks(size[0]),
        nb(blocks(chunks)),
        agg(agg_),
        carry(carry_),
        fan_in(fan_in_),
        stream(stream_) {}
  cudaError_t scan(bool forward) const { return scan_levels(size, agg, carry, fan_in, forward, stream); }
};

}  // namespace

template <class S>
ChainDirectionalData<S> ChainFdPlan<S>::directional_data(const FdBatchIn<S>& in, const BatchView<S>& qdd,
                                                         int* failed) const {
  ChainDirectionalData<S> d;
  d.fd = data<false>(in, qdd, failed);
  // the chain at rest: v, w, fext, a null, no gravity; tau and qdd set by the caller
  d.rest = d.fd;
  d.rest.v = nullptr;
  d.rest.w = nullptr;
  d.rest.fext = nullptr;
  d.rest.a = nullptr;
  d.rest.a0 = Motion<S>::zero();
  d.fd.IA_out = IA_;  // pass 1's IA (fd only)
  d.fd.pA_out = F_;   // pass 2's pA, then F (fd only)
  d.F = F_;
  d.dv = dv_;
  d.df = df_;
  d.x = x_;
  return d;
}

template <class S>
cudaError_t ChainFdPlan<S>::launch_jvp(const FdBatchIn<S>& in, const BatchView<const S>& dq,
                                       const BatchView<const S>& dqd, const BatchView<const S>& dtau,
                                       const BatchView<S>& qdd, const BatchView<S>& dqdd, int* failed,
                                       cudaStream_t stream) {
  const Index B = in.q.batch;
  if (!directional()) return cudaErrorNotSupported;
  if (B > max_batch_ || B < 0 || dq.batch != B || dqd.batch != B || dtau.batch != B || dqdd.batch != B)
    return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  cudaError_t err = cudaMemsetAsync(failed, 0xff, static_cast<std::size_t>(B) * sizeof(int), stream);  // -1
  if (err != cudaSuccess) return err;
  ChainDirectionalData<S> d = directional_data(in, qdd, failed);
  d.dq = dq;
  d.dqd = dqd;
  d.dtau = dtau;
  d.rest.tau = BatchView<const S>::aos(x_, n_, B);
  d.rest.qdd = dqdd;
  if ((err = passes(d.fd, stream)) != cudaSuccess) return err;  // v, U, D, a, IA, pA; qdd
  const AffineScans<S> k(d.count(), chunk_, fan_in_, aff_.data(), aff_carry_.data(), stream);
  // F (locally) and dv (forward)
  jvp_first_kernel<<<k.nb, kBlock, 0, stream>>>(d, k.r, k.chunks, aff_[0]);
  if ((err = k.scan(true)) != cudaSuccess) return err;
  chunk_walk_kernel<&jvp_velocity_walk<S>><<<k.nb, kBlock, 0, stream>>>(d, k.r, k.chunks, aff_carry_[0], aff_[0]);
  // da (forward), df
  if ((err = k.scan(true)) != cudaSuccess) return err;
  chunk_walk_kernel<&jvp_acceleration_walk<S>><<<k.nb, kBlock, 0, stream>>>(d, k.r, k.chunks, aff_carry_[0], aff_[0]);
  // dF (backward), dtau - r
  if ((err = k.scan(false)) != cudaSuccess) return err;
  chunk_walk_kernel<&jvp_force_walk<S>><<<k.nb, kBlock, 0, stream>>>(d, k.r, k.chunks, aff_carry_[0], aff_[0]);
  if ((err = cudaGetLastError()) != cudaSuccess) return err;
  // dqdd = M^-1 (dtau - r): passes 2 and 3 at rest
  return finish(d.rest, stream);
}

template <class S>
cudaError_t ChainFdPlan<S>::launch_vjp(const FdBatchIn<S>& in, const BatchView<const S>& w, const BatchView<S>& qdd,
                                       const BatchView<S>& gq, const BatchView<S>& gqd, const BatchView<S>& gtau,
                                       int* failed, cudaStream_t stream) {
  const Index B = in.q.batch;
  if (!directional()) return cudaErrorNotSupported;
  if (B > max_batch_ || B < 0 || w.batch != B || gq.batch != B || gqd.batch != B || gtau.batch != B)
    return cudaErrorInvalidValue;
  if (B == 0) return cudaSuccess;
  cudaError_t err = cudaMemsetAsync(failed, 0xff, static_cast<std::size_t>(B) * sizeof(int), stream);  // -1
  if (err != cudaSuccess) return err;
  ChainDirectionalData<S> d = directional_data(in, qdd, failed);
  d.gq = gq;
  d.gqd = gqd;
  d.gtau = gtau;
  d.rest.tau = w;
  d.rest.qdd = BatchView<S>::aos(x_, n_, B);  // u
  d.rest.a = dv_;                              // Fbar
  d.rest.pA_out = df_;                         // pA of the rest problem
  if ((err = passes(d.fd, stream)) != cudaSuccess) return err;  // v, U, D, a, IA, pA; qdd
  const AffineScans<S> k(d.count(), chunk_, fan_in_, aff_.data(), aff_carry_.data(), stream);
  // F (locally) and the rest solve's pass 2 (backward)
  vjp_first_kernel<<<k.nb, kBlock, 0, stream>>>(d, k.r, k.chunks, aff_[0]);
  if ((err = k.scan(false)) != cudaSuccess) return err;
  vjp_bias_kernel<<<k.nb, kBlock, 0, stream>>>(d, k.r, k.chunks, aff_carry_[0], aff_[0]);
  // the rest solve's pass 3 (u = M^-1 w in x, Fbar in dv); RA, gtau, RV's aggregates
  if ((err = k.scan(true)) != cudaSuccess) return err;
  vjp_solve_kernel<<<k.nb, kBlock, 0, stream>>>(d, k.r, k.chunks, aff_carry_[0], aff_[0]);
  // RV (backward); gq, gqd
  if ((err = k.scan(false)) != cudaSuccess) return err;
  vjp_rv_kernel<<<k.nb, kBlock, 0, stream>>>(d, k.r, k.chunks, aff_carry_[0]);
  return cudaGetLastError();
}

#define SCANDYN_INSTANTIATE_CHAIN_DIRECTIONAL(S)                                                                   \
  template ChainDirectionalData<S> ChainFdPlan<S>::directional_data(const FdBatchIn<S>&, const BatchView<S>&, int*) \
      const;                                                                                                        \
  template cudaError_t ChainFdPlan<S>::launch_jvp(const FdBatchIn<S>&, const BatchView<const S>&,                  \
                                                  const BatchView<const S>&, const BatchView<const S>&,             \
                                                  const BatchView<S>&, const BatchView<S>&, int*, cudaStream_t);    \
  template cudaError_t ChainFdPlan<S>::launch_vjp(const FdBatchIn<S>&, const BatchView<const S>&,                  \
                                                  const BatchView<S>&, const BatchView<S>&, const BatchView<S>&,    \
                                                  const BatchView<S>&, int*, cudaStream_t);
SCANDYN_INSTANTIATE_CHAIN_DIRECTIONAL(float)
SCANDYN_INSTANTIATE_CHAIN_DIRECTIONAL(double)
#undef SCANDYN_INSTANTIATE_CHAIN_DIRECTIONAL

// ---- the engine: host views, staged through one device buffer -------------------

namespace {

template <class S>
class CudaFdDirectional final : public FdDirectionalDerivatives<S> {
 public:
  static constexpr int kIn = 6, kOut = 4;  // q, qd, tau, three directions (or w); qdd and three outputs

  CudaFdDirectional(const ModelTpl<S>& model, const BackendOptions& o)
      : n_(model.nv()), max_batch_(std::max<Index>(o.max_batch, 1)) {
    if (const std::string why = backend_unusable(BackendKind::Cuda); !why.empty())
      throw BackendError("backend 'cuda': " + why);
    plan_ = std::make_unique<ChainFdPlan<S>>(model, max_batch_, 0, 0, /*directional=*/true);
    const std::size_t N = static_cast<std::size_t>(n_) * max_batch_;
    const std::size_t bytes = (kIn + kOut) * N * sizeof(S) + N * sizeof(Force<S>) + max_batch_ * sizeof(int);
    detail::check(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking), "cudaStreamCreateWithFlags");
    const cudaError_t err = cudaMalloc(&buffer_, bytes);
    if (err != cudaSuccess) {
      (void)cudaGetLastError();
      throw BackendError("backend 'cuda': the directional derivatives' staging of " + std::to_string(n_) +
                         " DoF x " + std::to_string(max_batch_) + " instances needs " + std::to_string(bytes) +
                         " bytes of device memory (" + detail::error_string(err) + ")");
    }
    S* p = static_cast<S*>(buffer_);
    for (int k = 0; k < kIn + kOut; ++k) array_[k] = p + k * N;
    fext_ = reinterpret_cast<Force<S>*>(p + (kIn + kOut) * N);
    failed_ = reinterpret_cast<int*>(fext_ + N);
    host_.resize((kIn + kOut) * N);
    failed_host_.resize(static_cast<std::size_t>(max_batch_));
  }
  ~CudaFdDirectional() override {
    if (buffer_) cudaFree(buffer_);
    if (stream_) cudaStreamDestroy(stream_);
  }
  std::string strategy() const override { return "parallel"; }
  BackendKind backend() const override { return BackendKind::Cuda; }

  BatchStatus jvp(const FdBatchIn<S>& in, const BatchView<const S>& dq, const BatchView<const S>& dqd,
                  const BatchView<const S>& dtau, const BatchView<S>& qdd, const BatchView<S>& dqdd) override {
    const Index B = stage_in(in, {&dq, &dqd, &dtau}, qdd, {&dqdd});
    if (B == 0) return {};
    detail::check(plan_->launch_jvp(device_in(B), soa(3, B), soa(4, B), soa(5, B), out(6, B), out(7, B), failed_,
                                    stream_),
                  "launching the JVP");
    return stage_out(B, {&qdd, &dqdd});
  }

  BatchStatus vjp(const FdBatchIn<S>& in, const BatchView<const S>& w, const BatchView<S>& qdd,
                  const BatchView<S>& gq, const BatchView<S>& gqd, const BatchView<S>& gtau) override {
    const Index B = stage_in(in, {&w}, qdd, {&gq, &gqd, &gtau});
    if (B == 0) return {};
    detail::check(plan_->launch_vjp(device_in(B), soa(3, B), out(6, B), out(7, B), out(8, B), out(9, B), failed_,
                                    stream_),
                  "launching the VJP");
    return stage_out(B, {&qdd, &gq, &gqd, &gtau});
  }

 private:
  BatchView<const S> soa(int k, Index B) const { return BatchView<const S>::soa(array_[k], n_, B); }
  BatchView<S> out(int k, Index B) const { return BatchView<S>::soa(array_[k], n_, B); }
  FdBatchIn<S> device_in(Index B) const { return {soa(0, B), soa(1, B), soa(2, B), has_fext_ ? fext_ : nullptr}; }

  // checks the views, copies the inputs (n x B each, SoA) and fext to the device;
  // returns B
  Index stage_in(const FdBatchIn<S>& in, std::initializer_list<const BatchView<const S>*> x, const BatchView<S>& qdd,
                 std::initializer_list<const BatchView<S>*> y) {
    check_batch(in, qdd, max_batch_);
    const Index B = in.q.batch;
    for (const auto* v : x)
      if (v->batch != B || !v->data) throw BackendError("the directional derivatives: a direction's batch differs from q's");
    for (const auto* v : y)
      if (v->batch != B || !v->data) throw BackendError("the directional derivatives: an output's batch differs from q's");
    if (B == 0) return 0;
    const std::size_t NB = static_cast<std::size_t>(n_) * B;
    const BatchView<const S>* src[kIn] = {&in.q, &in.qd, &in.tau, nullptr, nullptr, nullptr};
    int k = 3;
    for (const auto* v : x) src[k++] = v;
    for (int a = 0; a < k; ++a) {
      S* h = host_.data() + a * NB;
      for (Index i = 0; i < n_; ++i)
        for (Index b = 0; b < B; ++b) h[i * B + b] = src[a]->at(i, b);
      detail::check(cudaMemcpyAsync(array_[a], h, NB * sizeof(S), cudaMemcpyHostToDevice, stream_), "copying the inputs");
    }
    has_fext_ = in.fext != nullptr;
    if (has_fext_)
      detail::check(cudaMemcpyAsync(fext_, in.fext, NB * sizeof(Force<S>), cudaMemcpyHostToDevice, stream_),
                    "copying fext");
    return B;
  }

  // copies the outputs (arrays 6, 7, ...) and the failures back, into the views
  BatchStatus stage_out(Index B, std::initializer_list<const BatchView<S>*> y) {
    const std::size_t NB = static_cast<std::size_t>(n_) * B;
    int k = 6;
    for (std::size_t a = 0; a < y.size(); ++a, ++k)
      detail::check(cudaMemcpyAsync(host_.data() + k * NB, array_[k], NB * sizeof(S), cudaMemcpyDeviceToHost, stream_),
                    "copying the outputs");
    detail::check(cudaMemcpyAsync(failed_host_.data(), failed_, B * sizeof(int), cudaMemcpyDeviceToHost, stream_),
                  "copying the failures");
    detail::check(cudaStreamSynchronize(stream_), "the directional derivatives");
    k = 6;
    for (const auto* v : y) {
      const S* h = host_.data() + k++ * NB;
      for (Index b = 0; b < B; ++b)
        if (failed_host_[b] < 0)
          for (Index i = 0; i < n_; ++i) v->at(i, b) = h[i * B + b];
    }
    return summarize_failures(failed_host_.data(), B, Failure::ArticulatedPivot);
  }

  Index n_ = 0, max_batch_ = 0;
  std::unique_ptr<ChainFdPlan<S>> plan_;
  cudaStream_t stream_ = nullptr;
  void* buffer_ = nullptr;        // device: 10 arrays (n x max_batch), fext, failed
  S* array_[kIn + kOut] = {};
  Force<S>* fext_ = nullptr;
  int* failed_ = nullptr;
  bool has_fext_ = false;
  std::vector<S> host_;           // host staging of the same arrays
  std::vector<int> failed_host_;  // (max_batch)
};

}  // namespace

template <class S>
std::unique_ptr<FdDirectionalDerivatives<S>> make_cuda_fd_directional_derivatives(const ModelTpl<S>& model,
                                                                                  const BackendOptions& o) {
  if (model.floating_base() || first_branching_body(model) >= 0)
    throw BackendError("backend 'cuda': the directional derivatives of forward dynamics take unbranched chains "
                       "hanging from a fixed base (the chain scans; use serial or openmp for other models)");
  return std::make_unique<CudaFdDirectional<S>>(model, o);
}
template std::unique_ptr<FdDirectionalDerivatives<float>> make_cuda_fd_directional_derivatives(
    const ModelTpl<float>&, const BackendOptions&);
template std::unique_ptr<FdDirectionalDerivatives<double>> make_cuda_fd_directional_derivatives(
    const ModelTpl<double>&, const BackendOptions&);

}  // namespace cuda
}  // namespace scandyn
