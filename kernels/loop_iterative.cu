// kernels/loop_iterative.cu: the iterative closed-loop forward dynamics on a CUDA device
// (scandyn/cuda/loop_iterative.hpp): sim::IterativeLoopSolver::forward_dynamics's CGLS
// (src/sim/iterative_loops.cpp, fd_solve) with its tree passes one thread per chain and
// its loop rows one thread per loop.
#include "scandyn/cuda/loop_iterative.hpp"

#include <cuda_runtime.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "scandyn/algorithm/loop_chains.hpp"
#include "scandyn/algorithm/loop_iterative.hpp"
#include "scandyn/algorithm/loop_projection.hpp"
#include "scandyn/algorithm/loops.hpp"

namespace scandyn::cuda {

namespace {

using Clock = std::chrono::steady_clock;

// Adds the seconds from its construction to its destruction to `total`, also when the
// scope ends by an exception (the solver's per-call timings).
struct AddElapsed {
  double& total;
  Clock::time_point t0 = Clock::now();
  ~AddElapsed() { total += std::chrono::duration<double>(Clock::now() - t0).count(); }
};

std::string sci(double x) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.3g", x);
  return buf;
}

void check(cudaError_t e, const char* what) {
  if (e != cudaSuccess)
    throw LoopError(std::string("CUDA iterative loop solver: ") + what + ": " + cudaGetErrorString(e));
}

// A device array of T, freed on destruction.
template <class T>
struct Dev {
  T* p = nullptr;
  std::size_t n = 0;
  void alloc(std::size_t count, const char* what) {
    n = count;
    check(cudaMalloc(reinterpret_cast<void**>(&p), (count ? count : 1) * sizeof(T)), what);
  }
  void upload(const T* host, std::size_t count, cudaStream_t s) {
    check(cudaMemcpyAsync(p, host, count * sizeof(T), cudaMemcpyHostToDevice, s), "copy to the device");
  }
  Dev() = default;
  Dev(const Dev&) = delete;
  Dev& operator=(const Dev&) = delete;
  ~Dev() {
    if (p) cudaFree(p);
  }
};

constexpr int kThreads = 128;
// per-chain kernels: one warp per block, so that the few chain threads (10^3 on
// cloth:1000:1000) spread over the multiprocessors (each thread's walk is latency-bound)
constexpr int kChainThreads = 32;
constexpr int kReduceThreads = 256, kReduceBlocks = 512;
int grid(long n, int t = kThreads) { return static_cast<int>(n > 0 ? (n + t - 1) / t : 1); }

// ---- tree passes: one thread per chain [cs[c], cs[c + 1]) ----------------------------

template <class S>
__global__ void k_body_motion(const Body<S>* bodies, const Index* cs, Index nc, const S* q, const S* qd,
                              Transform<S>* X0, Motion<S>* v, Motion<S>* a) {
  const Index c = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (c >= nc) return;
  loop_body_motion_range(bodies, cs[c], cs[c + 1], q, qd, X0, v, a);
}

template <class S>
__global__ void k_joint_transforms(const Body<S>* bodies, Index n, const S* q, Transform<S>* Xup) {
  const Index i = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (i >= n) return;
  Xup[i] = joint_transform(bodies[i], q[i]);
}

template <class S>
__global__ void k_aba_factor(const Body<S>* bodies, const Index* cs, Index nc, Vec3<S> gravity, const S* q,
                             const S* qd, const S* tau, Transform<S>* Xup, Force<S>* U, S* D, S* qdd0, Motion<S>* v,
                             Motion<S>* c, Motion<S>* a, ABInertia<S>* IA, Force<S>* pA, S* u, int* failed) {
  const Index ch = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (ch >= nc) return;
  const Index r =
      loop_aba_factor_range(bodies, cs[ch], cs[ch + 1], gravity, q, qd, tau, Xup, U, D, qdd0, v, c, a, IA, pA, u);
  // the CPU's pass 2 stops at the highest failing body: the largest over the chains
  if (r >= 0) atomicMax(failed, static_cast<int>(r));
}

template <class S>
__global__ void k_joint_motion(const Body<S>* bodies, const Index* cs, Index nc, const Transform<S>* Xup, const S* x,
                               Motion<S>* acc) {
  const Index c = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (c >= nc) return;
  loop_joint_motion_range(bodies, cs[c], cs[c + 1], Xup, x, acc);
}

// M^-1 J^T w: the body wrenches gathered per body (loop_body_wrench), then the tree's
// response (s = M^-1 J^T w, acc its body accelerations).
template <class S>
__global__ void k_response(const Body<S>* bodies, const Index* cs, Index nc, const LoopRow<S>* rows,
                           const Index* row_of, const Index* side_start, const Index* side, const Transform<S>* X0,
                           const Transform<S>* Xup, const Force<S>* U, const S* D, const S* w, Force<S>* f,
                           Force<S>* pA, S* s, Motion<S>* acc) {
  const Index c = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (c >= nc) return;
  const Index b = cs[c], e = cs[c + 1];
  for (Index i = b; i < e; ++i) f[i] = loop_body_wrench(rows, row_of, side_start, side, i, X0, w);
  loop_tree_response_range(bodies, b, e, Xup, U, D, f, pA, s, acc);
}

template <class S>
__global__ void k_response_blocks(const Body<S>* bodies, const Index* cs, Index nc, const Transform<S>* Xup,
                                  const Force<S>* U, const S* D, Mat6<S>* Omega) {
  const Index c = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (c >= nc) return;
  loop_response_blocks_range(bodies, cs[c], cs[c + 1], Xup, U, D, Omega);
}

// ---- loop rows: one thread per loop ----------------------------------------------------

template <class S>
__global__ void k_loop_gamma(const Body<S>* bodies, Index n, const LoopRow<S>* rows, Index nl, const Index* row_of,
                             const Transform<S>* X0, const Motion<S>* v, const Motion<S>* a, S* gamma) {
  const Index k = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (k >= nl) return;
  loop_rows(bodies, n, rows + k, Index(1), X0, v, a, static_cast<S*>(nullptr), static_cast<S*>(nullptr),
            gamma + row_of[k]);
}

template <class S>
__global__ void k_rows_apply(const LoopRow<S>* rows, Index nl, const Index* row_of, const Transform<S>* X0,
                             const Motion<S>* acc, S* out) {
  const Index k = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (k >= nl) return;
  loop_rows_apply(rows + k, Index(1), X0, acc, out + row_of[k]);
}

// Loop k's diagonal block of J Omega J^T: its floored inverse into inv (36 per loop), or
// (diag non-null) its largest diagonal entry into diag[k].
template <class S>
__global__ void k_blocks(const LoopRow<S>* rows, Index nl, const Transform<S>* X0, const Mat6<S>* Omega, S floor,
                         S* inv, S* diag) {
  const Index k = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (k >= nl) return;
  S blk[36];
  const LoopRow<S> l = rows[k];
  const int d = l.rows();
  loop_schur_block(l, X0, Omega, blk);
  if (diag) {
    S big = S(0);
    for (int i = 0; i < d; ++i) big = blk[i * d + i] > big ? blk[i * d + i] : big;
    diag[k] = big;
    return;
  }
  symmetric_pseudo_inverse(blk, d, floor);
  S* out = inv + 36 * static_cast<std::size_t>(k);
  for (int e = 0; e < d * d; ++e) out[e] = blk[e];
}

// z = W r: block Jacobi (inv non-null) or the identity.
template <class S>
__global__ void k_precondition(const LoopRow<S>* rows, Index nl, const Index* row_of, const S* inv, const S* r,
                               S* z) {
  const Index k = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (k >= nl) return;
  const int d = rows[k].rows();
  const Index row = row_of[k];
  if (!inv) {
    for (int i = 0; i < d; ++i) z[row + i] = r[row + i];
    return;
  }
  const S* B = inv + 36 * static_cast<std::size_t>(k);
  S in[6];
  for (int j = 0; j < d; ++j) in[j] = r[row + j];
  for (int i = 0; i < d; ++i) {
    S s = S(0);
    for (int j = 0; j < d; ++j) s += B[i * d + j] * in[j];
    z[row + i] = s;
  }
}

// phi (the loops' residual) at the poses X0, v, a of loop_body_motion: one thread per loop.
template <class S>
__global__ void k_loop_phi(const Body<S>* bodies, Index n, const LoopRow<S>* rows, Index nl, const Index* row_of,
                           const Transform<S>* X0, const Motion<S>* v, const Motion<S>* a, S* phi) {
  const Index k = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (k >= nl) return;
  loop_rows(bodies, n, rows + k, Index(1), X0, v, a, phi + row_of[k], static_cast<S*>(nullptr),
            static_cast<S*>(nullptr));
}

// The unit tree's J^T w (the projection's): per chain, the bodies' wrenches gathered
// (loop_body_wrench) and loop_joint_forces' backward pass over the chain (its subtree:
// the chain's later bodies; the same sums in the same order as the host's pass).
template <class S>
__global__ void k_joint_forces(const Body<S>* bodies, const Index* cs, Index nc, const LoopRow<S>* rows,
                               const Index* row_of, const Index* side_start, const Index* side,
                               const Transform<S>* X0, const Transform<S>* Xup, const S* w, Force<S>* F, S* tau) {
  const Index c = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (c >= nc) return;
  const Index b = cs[c], e = cs[c + 1];
  for (Index i = b; i < e; ++i) F[i] = loop_body_wrench(rows, row_of, side_start, side, i, X0, w);
  for (Index i = e - 1; i >= b; --i) {
    const Body<S>& body = bodies[i];
    tau[i] = joint_project(body, F[i]);
    if (body.parent >= b) F[body.parent] += Xup[i].apply_transpose(F[i]);
  }
}

// ---- vectors -----------------------------------------------------------------------

// out = -a - b (b = -gamma - J qdd0) or (sub) a - b
template <class S>
__global__ void k_combine(Index m, const S* a, const S* b, S* out, bool sub) {
  const Index k = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (k >= m) return;
  out[k] = sub ? a[k] - b[k] : -a[k] - b[k];
}

// One CGLS step (fd_solve's): alpha = gamma / delta, skipped when delta is not positive
// and finite (the host then stops, as the CPU does before its update).
template <class S>
__global__ void k_cg_step(Index m, Index n, double gamma, const double* delta_p, S* lambda, const S* pl, S* res,
                          const S* Jp, S* w, const S* WJp, S* x, const S* px) {
  const Index i = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  const double delta = *delta_p;
  if (!(delta > 0) || !isfinite(delta)) return;
  const double alpha = gamma / delta;
  const S as = static_cast<S>(alpha);
  if (i < m) {
    lambda[i] += as * pl[i];
    res[i] -= as * Jp[i];
    w[i] -= as * WJp[i];
  }
  if (i < n) x[i] += as * px[i];
}

template <class S>
__global__ void k_cg_direction(Index m, Index n, double beta, S* pl, const S* w, S* Jp, const S* Js, S* px,
                               const S* s) {
  const Index i = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  const S bs = static_cast<S>(beta);
  if (i < m) pl[i] = w[i] + bs * pl[i], Jp[i] = Js[i] + bs * Jp[i];
  if (i < n) px[i] = s[i] + bs * px[i];
}

// y += c x (n)
template <class S>
__global__ void k_axpy(Index n, double c, const S* x, S* y) {
  const Index i = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (i < n) y[i] += static_cast<S>(c) * x[i];
}

// One step of the projection's CGLS (unit_solve's): delta = q.Wq + mu p.p, alpha =
// gamma / delta, skipped when delta is not positive and finite (the host then stops
// before the update, as the CPU does).
template <class S>
__global__ void k_unit_step(Index m, Index n, double gamma, double mu, const double* qwq, const double* pp, S* x,
                            const S* p, S* res, const S* q, S* wres, const S* wq) {
  const Index i = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  const double delta = *qwq + mu * *pp;
  if (!(delta > 0) || !isfinite(delta)) return;
  const double alpha = gamma / delta;
  const S as = static_cast<S>(alpha);
  if (i < n) x[i] += as * p[i];
  if (i < m) res[i] -= as * q[i], wres[i] -= as * wq[i];
}

// p = s + beta p (n)
template <class S>
__global__ void k_unit_direction(Index n, double beta, S* p, const S* s) {
  const Index i = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (i < n) p[i] = s[i] + static_cast<S>(beta) * p[i];
}

template <class S>
__global__ void k_add(Index n, const S* a, const S* b, S* out) {
  const Index i = static_cast<Index>(blockIdx.x * blockDim.x + threadIdx.x);
  if (i < n) out[i] = a[i] + b[i];
}

// Reductions in double, fixed order (kReduceBlocks partials, then one block): Op 0 sum
// a_i b_i; Op 1 max |a_i|, a non-finite a_i counting as infinite.
template <int Op>
__device__ double combine(double x, double y) {
  return Op == 0 ? x + y : (x > y ? x : y);
}
template <class S, int Op>
__global__ void k_reduce(const S* a, const S* b, long n, double* partial) {
  __shared__ double sh[kReduceThreads];
  double acc = 0;
  for (long i = blockIdx.x * static_cast<long>(blockDim.x) + threadIdx.x; i < n;
       i += static_cast<long>(gridDim.x) * blockDim.x) {
    const double ai = static_cast<double>(a[i]);
    if (Op == 0) acc += ai * static_cast<double>(b[i]);
    else acc = combine<1>(acc, isfinite(ai) ? fabs(ai) : INFINITY);
  }
  sh[threadIdx.x] = acc;
  __syncthreads();
  for (int s = blockDim.x / 2; s > 0; s >>= 1) {
    if (threadIdx.x < s) sh[threadIdx.x] = combine<Op>(sh[threadIdx.x], sh[threadIdx.x + s]);
    __syncthreads();
  }
  if (threadIdx.x == 0) partial[blockIdx.x] = sh[0];
}
template <int Op>
__global__ void k_reduce_final(const double* partial, int np, double* out) {
  __shared__ double sh[kReduceThreads];
  double acc = 0;
  for (int i = threadIdx.x; i < np; i += blockDim.x) acc = combine<Op>(acc, partial[i]);
  sh[threadIdx.x] = acc;
  __syncthreads();
  for (int s = blockDim.x / 2; s > 0; s >>= 1) {
    if (threadIdx.x < s) sh[threadIdx.x] = combine<Op>(sh[threadIdx.x], sh[threadIdx.x + s]);
    __syncthreads();
  }
  if (threadIdx.x == 0) *out = sh[0];
}


// The device scalars (double): slots of Impl::scalars.
enum Slot { kDelta = 0, kRR, kGamma1, kA, kB, kC, kD, kPP, kSlots };

}  // namespace

template <class S>
struct CudaIterativeLoopSolver<S>::Impl {
  static constexpr bool kFloat = sizeof(S) <= sizeof(float);
  Model host_model;
  LoopSet loops;
  CudaIterativeLoopOptions options;
  CudaIterativeLoopStats stats;
  std::unique_ptr<sim::IterativeLoopSolver> projector;  // project() on the host
  Index n = 0, m = 0, nl = 0, nc = 0;
  Vec3<S> gravity;
  double tolerance = 0, floor_coef = 0, jscale = 1;
  cudaStream_t stream = nullptr;
  // structure
  Dev<Body<S>> bodies;
  Dev<LoopRow<S>> rows;
  Dev<Index> chain_start, side_start, side, row_of;
  // per body
  Dev<Transform<S>> Xup, X0;
  Dev<Force<S>> U, f, pA;
  Dev<Motion<S>> v, c, a, acc;
  Dev<ABInertia<S>> IA;
  Dev<Mat6<S>> Omega;
  Dev<S> q, qd, tau, D, u, qdd0, x, px, s, qdd;
  // per row
  Dev<S> lambda, b, gamma, res, w, pl, Jp, Js, WJp, tmp, inv;
  Dev<double> partial, scalars;
  Dev<int> failed;
  double* host_scalars = nullptr;  // pinned (kSlots)
  std::vector<S> hq, hqd, htau, hout;
  bool lambda_zero = true;  // lambda known to be 0 on the device

  ~Impl() {
    if (host_scalars) cudaFreeHost(host_scalars);
    if (stream) cudaStreamDestroy(stream);
  }

  void launched(const char* what) { check(cudaGetLastError(), what); }

  // scalars[slot] = sum a b (Op 0) or max |a| (Op 1), asynchronously
  template <int Op>
  void reduce(const S* a_, const S* b_, long len, int slot) {
    const int blocks = static_cast<int>(std::min<long>(kReduceBlocks, std::max<long>(1, (len + kReduceThreads - 1) / kReduceThreads)));
    k_reduce<S, Op><<<blocks, kReduceThreads, 0, stream>>>(a_, b_, len, partial.p);
    k_reduce_final<Op><<<1, kReduceThreads, 0, stream>>>(partial.p, blocks, scalars.p + slot);
    launched("reduction");
  }
  // slots [0, count) to the host (one synchronisation)
  void fetch(int count) {
    check(cudaMemcpyAsync(host_scalars, scalars.p, sizeof(double) * count, cudaMemcpyDeviceToHost, stream),
          "copy of the scalars");
    check(cudaStreamSynchronize(stream), "a solve's kernels");
    ++stats.syncs;
  }

  void joint_motion_rows(const S* xx, S* out) {  // out = J xx
    k_joint_motion<<<grid(nc, kChainThreads), kChainThreads, 0, stream>>>(bodies.p, chain_start.p, nc, Xup.p, xx, acc.p);
    k_rows_apply<<<grid(nl), kThreads, 0, stream>>>(rows.p, nl, row_of.p, X0.p, acc.p, out);
    launched("J x");
  }
  void response(const S* ww, S* Js_out) {  // s = M^-1 J^T ww, Js_out = J s
    k_response<<<grid(nc, kChainThreads), kChainThreads, 0, stream>>>(bodies.p, chain_start.p, nc, rows.p, row_of.p, side_start.p, side.p,
                                                  X0.p, Xup.p, U.p, D.p, ww, f.p, pA.p, s.p, acc.p);
    k_rows_apply<<<grid(nl), kThreads, 0, stream>>>(rows.p, nl, row_of.p, X0.p, acc.p, Js_out);
    launched("the tree's response");
    ++stats.applies;
  }
  void precondition(const S* r, S* z) {
    k_precondition<<<grid(nl), kThreads, 0, stream>>>(
        rows.p, nl, row_of.p, options.preconditioner == sim::LoopPreconditioner::None ? nullptr : inv.p, r, z);
    launched("the preconditioner");
  }
  void copy(S* dst, const S* src, Index len) {
    check(cudaMemcpyAsync(dst, src, sizeof(S) * static_cast<std::size_t>(len), cudaMemcpyDeviceToDevice, stream),
          "copy on the device");
  }

  Impl(const Model& model, const LoopSet& loops_in, const CudaIterativeLoopOptions& opt)
      : host_model(model), loops(loops_in), options(opt) {
    if (options.preconditioner != sim::LoopPreconditioner::BlockJacobi &&
        options.preconditioner != sim::LoopPreconditioner::None)
      throw LoopError(std::string("CUDA iterative loop solver: preconditioner ") +
                      sim::loop_preconditioner_name(options.preconditioner) +
                      " is not on the GPU (its sweeps are sequential): use block-jacobi or none");
    if (options.max_iterations < 1 || options.tolerance < 0)
      throw LoopError("CUDA iterative loop solver: the tolerance must not be negative and max_iterations at least 1");
    const ModelTpl<S> ms = model.template cast<S>();
    const std::vector<LoopRow<S>> hrows = loop_rows_of<S>(loops);
    const LoopChainLayout lay = loop_chain_layout(ms, hrows);  // (throws for other trees)
    tolerance = options.tolerance > 0 ? options.tolerance
                                      : (kFloat ? kCudaIterativeLoopToleranceFloat : sim::kIterativeLoopTolerance);
    floor_coef = kFloat ? kCudaIterativeLoopFloorFloat : sim::kIterativeLoopFloor;
    n = ms.nv(), m = loops.rows(), nl = static_cast<Index>(hrows.size());
    nc = static_cast<Index>(lay.chain_start.size()) - 1;
    gravity = ms.gravity;
    int count = 0;
    if (cudaGetDeviceCount(&count) != cudaSuccess || count == 0)
      throw LoopError("CUDA iterative loop solver: no usable CUDA device");
    if (options.device < 0 || options.device >= count)
      throw LoopError("CUDA iterative loop solver: no CUDA device " + std::to_string(options.device));
    check(cudaSetDevice(options.device), "cudaSetDevice");
    check(cudaStreamCreateWithFlags(&stream, cudaStreamNonBlocking), "stream");
    check(cudaMallocHost(reinterpret_cast<void**>(&host_scalars), sizeof(double) * kSlots), "pinned scalars");
    const std::size_t N = static_cast<std::size_t>(n), M = static_cast<std::size_t>(m);
    bodies.alloc(N, "bodies"), rows.alloc(hrows.size(), "loops");
    chain_start.alloc(lay.chain_start.size(), "chains"), side_start.alloc(lay.side_start.size(), "loop sides");
    side.alloc(lay.side.size(), "loop sides"), row_of.alloc(lay.row_of.size(), "rows");
    const char* mem = "device memory for the per-body arrays";
    Xup.alloc(N, mem), X0.alloc(N, mem), U.alloc(N, mem), f.alloc(N, mem), pA.alloc(N, mem);
    v.alloc(N, mem), c.alloc(N, mem), a.alloc(N, mem), acc.alloc(N, mem), IA.alloc(N, mem);
    Omega.alloc(N, mem);
    for (Dev<S>* d : {&q, &qd, &tau, &D, &u, &qdd0, &x, &px, &s, &qdd}) d->alloc(N, mem);
    const char* rmem = "device memory for the per-row arrays";
    for (Dev<S>* d : {&lambda, &b, &gamma, &res, &w, &pl, &Jp, &Js, &WJp, &tmp}) d->alloc(M, rmem);
    inv.alloc(36 * hrows.size(), "device memory for the blocks' inverses");
    partial.alloc(kReduceBlocks, "reduction"), scalars.alloc(kSlots, "reduction"), failed.alloc(1, "flag");
    bodies.upload(ms.bodies.data(), N, stream), rows.upload(hrows.data(), hrows.size(), stream);
    chain_start.upload(lay.chain_start.data(), lay.chain_start.size(), stream);
    side_start.upload(lay.side_start.data(), lay.side_start.size(), stream);
    side.upload(lay.side.data(), lay.side.size(), stream);
    row_of.upload(lay.row_of.data(), lay.row_of.size(), stream);
    check(cudaMemsetAsync(lambda.p, 0, sizeof(S) * (M ? M : 1), stream), "memset");
    check(cudaMemsetAsync(scalars.p, 0, sizeof(double) * kSlots, stream), "memset");
    hq.resize(N), hqd.resize(N), htau.resize(N), hout.resize(std::max(N, M));
    // L_J: the unit tree's diagonal blocks at q = 0
    check(cudaMemsetAsync(q.p, 0, sizeof(S) * (N ? N : 1), stream), "memset");
    if (nl > 0) {
      k_body_motion<<<grid(nc, kChainThreads), kChainThreads, 0, stream>>>(bodies.p, chain_start.p, nc, q.p, static_cast<const S*>(nullptr),
                                                       X0.p, v.p, a.p);
      k_joint_transforms<<<grid(n), kThreads, 0, stream>>>(bodies.p, n, q.p, Xup.p);
      k_response_blocks<<<grid(nc, kChainThreads), kChainThreads, 0, stream>>>(bodies.p, chain_start.p, nc, Xup.p,
                                                           static_cast<const Force<S>*>(nullptr),
                                                           static_cast<const S*>(nullptr), Omega.p);
      k_blocks<<<grid(nl), kThreads, 0, stream>>>(rows.p, nl, X0.p, Omega.p, S(0), static_cast<S*>(nullptr), tmp.p);
      launched("L_J");
      reduce<1>(tmp.p, static_cast<const S*>(nullptr), nl, 0);
      fetch(1);
      const double big = host_scalars[0];
      jscale = big > 0 ? std::sqrt(big) : 1.0;
    }
    check(cudaStreamSynchronize(stream), "setup");
  }

  // fd_solve of src/sim/iterative_loops.cpp on the device
  bool fd_solve(double target, bool any, int& it, double& rnorm) {
    it = 0;
    if (any) {
      response(lambda.p, Js.p);
      copy(x.p, s.p, n);
      k_combine<<<grid(m), kThreads, 0, stream>>>(m, b.p, Js.p, res.p, true);
    } else {
      check(cudaMemsetAsync(x.p, 0, sizeof(S) * std::max<std::size_t>(1, n), stream), "memset");
      copy(res.p, b.p, m);
    }
    reduce<0>(res.p, res.p, m, kRR);
    fetch(kRR + 1);
    rnorm = std::sqrt(host_scalars[kRR]);
    if (rnorm <= target) return true;
    precondition(res.p, w.p);
    response(w.p, Js.p);
    reduce<0>(w.p, Js.p, m, kGamma1);
    fetch(kGamma1 + 1);
    double gamma_h = host_scalars[kGamma1];
    const double gamma0 = gamma_h;
    copy(pl.p, w.p, m), copy(px.p, s.p, n), copy(Jp.p, Js.p, m);
    bool least_squares = false;
    sim::LeastSquaresStop stop{kFloat ? 1e-6 : 1e-14, kFloat ? 1e-4 : 1e-12};
    const Index len = std::max(m, n);
    while (it < options.max_iterations && gamma_h > 0) {
      precondition(Jp.p, WJp.p);
      reduce<0>(Jp.p, WJp.p, m, kDelta);
      k_cg_step<<<grid(len), kThreads, 0, stream>>>(m, n, gamma_h, scalars.p + kDelta, lambda.p, pl.p, res.p, Jp.p,
                                                    w.p, WJp.p, x.p, px.p);
      launched("CGLS step");
      reduce<0>(res.p, res.p, m, kRR);
      response(w.p, Js.p);  // the next iteration's, before the test (one synchronisation)
      reduce<0>(w.p, Js.p, m, kGamma1);
      fetch(kGamma1 + 1);
      const double delta = host_scalars[kDelta];
      if (!(delta > 0) || !std::isfinite(delta)) break;
      ++it;
      rnorm = std::sqrt(host_scalars[kRR]);
      if (!std::isfinite(rnorm)) return false;
      if (rnorm <= target) break;
      const double gamma1 = host_scalars[kGamma1];
      if (stop.least_squares(rnorm, std::sqrt(gamma1 / gamma0))) {
        least_squares = true;
        break;
      }
      const double beta = gamma1 / gamma_h;
      gamma_h = gamma1;
      k_cg_direction<<<grid(len), kThreads, 0, stream>>>(m, n, beta, pl.p, w.p, Jp.p, Js.p, px.p, s.p);
      launched("CGLS direction");
    }
    // the true residual b - J x
    const double recurrence = rnorm;
    joint_motion_rows(x.p, Js.p);
    k_combine<<<grid(m), kThreads, 0, stream>>>(m, b.p, Js.p, res.p, true);
    reduce<0>(res.p, res.p, m, kRR);
    fetch(kRR + 1);
    rnorm = std::sqrt(host_scalars[kRR]);
    return rnorm <= target || (least_squares && rnorm <= 1.1 * recurrence + target);
  }

  // ---- the projection on the device (double; sim::IterativeLoopSolver::project's
  // unit_solve and Ops with block-Jacobi weights or none) ----
  Dev<S> ur, ures, uwres, uq, uwq, ux, up, us, uxbest, uv, uphi;
  Dev<Transform<S>> tX0;  // the trial points' poses and motions
  Dev<Motion<S>> tv, ta;
  bool proj_ready = false;
  double unit_scale = 1;
  // the last projection solve's ||r||, its target, allowance + floor, true residual
  double last_r0 = 0, last_target = 0, last_allowance = 0, last_residual_abs = 0;
  int last_proj_iterations = 0;
  double last_proj_residual = 0;

  void alloc_projection() {
    if (proj_ready) return;
    const std::size_t N = static_cast<std::size_t>(n), M = static_cast<std::size_t>(m);
    const char* mem = "device memory for the projection";
    for (Dev<S>* d : {&ur, &ures, &uwres, &uq, &uwq, &uphi}) d->alloc(M, mem);
    for (Dev<S>* d : {&ux, &up, &us, &uxbest, &uv}) d->alloc(N, mem);
    tX0.alloc(N, mem), tv.alloc(N, mem), ta.alloc(N, mem);
    proj_ready = true;
  }
  void to_device(S* dst, const double* src, Index len) {
    if (len <= 0) return;
    if constexpr (kFloat) {
      hout.resize(std::max<std::size_t>(hout.size(), static_cast<std::size_t>(len)));
      for (Index i = 0; i < len; ++i) hout[i] = static_cast<S>(src[i]);
      check(cudaMemcpyAsync(dst, hout.data(), sizeof(S) * len, cudaMemcpyHostToDevice, stream), "copy to the device");
      check(cudaStreamSynchronize(stream), "copy to the device");
    } else {
      check(cudaMemcpyAsync(dst, src, sizeof(S) * len, cudaMemcpyHostToDevice, stream), "copy to the device");
    }
  }
  void to_host(double* dst, const S* src, Index len) {
    if (len <= 0) return;
    if constexpr (kFloat) {
      hout.resize(std::max<std::size_t>(hout.size(), static_cast<std::size_t>(len)));
      check(cudaMemcpyAsync(hout.data(), src, sizeof(S) * len, cudaMemcpyDeviceToHost, stream), "copy to the host");
      check(cudaStreamSynchronize(stream), "copy to the host");
      for (Index i = 0; i < len; ++i) dst[i] = static_cast<double>(hout[i]);
    } else {
      check(cudaMemcpyAsync(dst, src, sizeof(S) * len, cudaMemcpyDeviceToHost, stream), "copy to the host");
      check(cudaStreamSynchronize(stream), "copy to the host");
    }
    ++stats.syncs;
  }
  void jt(const S* wrows, S* out) {  // out (n) = J^T wrows on the unit tree
    k_joint_forces<<<grid(nc, kChainThreads), kChainThreads, 0, stream>>>(
        bodies.p, chain_start.p, nc, rows.p, row_of.p, side_start.p, side.p, X0.p, Xup.p, wrows, f.p, out);
    launched("J^T w");
  }
  // ||a - b||_2 (m) with a scratch row vector
  double residual_norm(const S* a_, const S* b_, S* scratch) {
    k_combine<<<grid(m), kThreads, 0, stream>>>(m, a_, b_, scratch, true);
    reduce<0>(scratch, scratch, m, kRR);
    fetch(kSlots);
    return std::sqrt(host_scalars[kRR]);
  }

  // unit_solve of src/sim/iterative_loops.cpp: x = J^T (J J^T + mu W^-1)^-1 r by CGLS on
  // (J^T W J + mu I) x = J^T W r over the unit tree, with its rounds, stops and
  // acceptance on the true residual (read that function's comment).
  void unit_solve(const double* rh, double mu_in, double floor, double allowance, double* xh, bool& converged) {
    const double tol = tolerance;
    const double mu = std::max(mu_in, kLoopRankTolerance * unit_scale);
    const std::size_t N1 = std::max<std::size_t>(1, static_cast<std::size_t>(n));
    to_device(ur.p, rh, m);
    copy(ures.p, ur.p, m);
    check(cudaMemsetAsync(ux.p, 0, sizeof(S) * N1, stream), "memset");
    check(cudaMemsetAsync(uxbest.p, 0, sizeof(S) * N1, stream), "memset");
    reduce<0>(ures.p, ures.p, m, kRR);
    fetch(kSlots);
    const double r0 = std::sqrt(host_scalars[kRR]);
    const double target = tol * r0 + floor;
    double rn = r0, sn = 0, s0 = 0;
    int it = 0;
    converged = rn <= target;
    double best = r0;
    bool damped = false;
    const Index len = std::max(m, n);
    for (int round = 0; round < 4 && !converged && it < options.max_iterations; ++round) {
      const double round_start = rn;
      if (round > 0) {  // the true residual at x
        joint_motion_rows(ux.p, uq.p);
        rn = residual_norm(ur.p, uq.p, ures.p);
        if (mu_in == 0 && rn <= target) {
          converged = true;
          break;
        }
      }
      precondition(ures.p, uwres.p);
      jt(uwres.p, us.p);
      k_axpy<<<grid(n), kThreads, 0, stream>>>(n, -mu, ux.p, us.p);
      reduce<0>(us.p, us.p, n, kGamma1);
      fetch(kSlots);
      sn = std::sqrt(host_scalars[kGamma1]);
      if (round == 0) s0 = sn;
      double gamma = sn * sn;
      copy(up.p, us.p, n);
      bool normal = sn <= tol * s0;
      while (!normal && it < options.max_iterations && gamma > 0) {
        joint_motion_rows(up.p, uq.p);
        precondition(uq.p, uwq.p);
        reduce<0>(uq.p, uwq.p, m, kDelta);
        reduce<0>(up.p, up.p, n, kPP);
        k_unit_step<<<grid(len), kThreads, 0, stream>>>(m, n, gamma, mu, scalars.p + kDelta, scalars.p + kPP, ux.p,
                                                        up.p, ures.p, uq.p, uwres.p, uwq.p);
        launched("projection step");
        reduce<0>(ures.p, ures.p, m, kRR);
        // the next normal residual, before the tests (one synchronisation per iteration)
        jt(uwres.p, us.p);
        k_axpy<<<grid(n), kThreads, 0, stream>>>(n, -mu, ux.p, us.p);
        reduce<0>(us.p, us.p, n, kGamma1);
        fetch(kSlots);
        ++stats.applies;
        const double delta = host_scalars[kDelta] + mu * host_scalars[kPP];
        if (!(delta > 0) || !std::isfinite(delta)) break;
        ++it;
        rn = std::sqrt(host_scalars[kRR]);
        if (!std::isfinite(rn)) break;
        if (rn < best) best = rn, copy(uxbest.p, ux.p, n);
        if (mu_in == 0 && rn <= target) {
          converged = true;
          break;
        }
        const double gamma1 = host_scalars[kGamma1];
        sn = std::sqrt(gamma1);
        if (sn <= tol * s0) {
          normal = true;
          break;
        }
        const double beta = gamma1 / gamma;
        gamma = gamma1;
        k_unit_direction<<<grid(n), kThreads, 0, stream>>>(n, beta, up.p, us.p);
        launched("projection direction");
      }
      if (converged) {  // the recurrence's residual at the target: the true one too, else another round
        joint_motion_rows(ux.p, uq.p);
        if (residual_norm(ur.p, uq.p, uwq.p) <= target) break;
        converged = false;
        continue;
      }
      if (!normal) break;
      if (mu_in != 0 || !(rn <= 0.5 * round_start)) {
        converged = true;
        damped = mu_in == 0;
        break;
      }
    }
    if (mu_in == 0 && !(rn <= best)) {
      copy(ux.p, uxbest.p, n);
      rn = best;
      converged = converged || rn <= target;
    }
    reduce<1>(ux.p, static_cast<const S*>(nullptr), n, kD);
    fetch(kSlots);
    if (!(host_scalars[kD] < INFINITY)) {
      check(cudaMemsetAsync(ux.p, 0, sizeof(S) * N1, stream), "memset");
      converged = false;
    }
    last_r0 = r0, last_target = target, last_allowance = allowance + floor;
    if (mu_in == 0) {  // the acceptance, on the true residual r - J x
      joint_motion_rows(ux.p, uq.p);
      rn = residual_norm(ur.p, uq.p, uwq.p);
      const bool within = rn <= target || (damped && rn <= allowance + floor);
      converged = std::isfinite(rn) && within && (converged || rn <= target);
    }
    to_host(xh, ux.p, n);
    ++stats.proj_solves;
    stats.proj_iterations += it;
    last_proj_iterations = it;
    last_proj_residual = r0 > 0 ? rn / r0 : 0;
    last_residual_abs = rn;
  }

  // project_onto_loops' operations on the device (sim::IterativeLoopSolver::project's Ops)
  struct ProjOps {
    Impl& s;
    bool last_converged = true;
    double floor = 0, allowance = 0;
    bool residual(const double* xq, double* phi) {
      s.to_device(s.uv.p, xq, s.n);
      k_body_motion<<<grid(s.nc, kChainThreads), kChainThreads, 0, s.stream>>>(
          s.bodies.p, s.chain_start.p, s.nc, s.uv.p, static_cast<const S*>(nullptr), s.tX0.p, s.tv.p, s.ta.p);
      k_loop_phi<<<grid(s.nl), kThreads, 0, s.stream>>>(s.bodies.p, s.n, s.rows.p, s.nl, s.row_of.p, s.tX0.p, s.tv.p,
                                                         s.ta.p, s.uphi.p);
      s.launched("phi");
      s.to_host(phi, s.uphi.p, s.m);
      for (Index k = 0; k < s.m; ++k)
        if (!std::isfinite(phi[k])) return false;
      return true;
    }
    void factorize(const double* xq) {
      s.to_device(s.uv.p, xq, s.n);
      k_body_motion<<<grid(s.nc, kChainThreads), kChainThreads, 0, s.stream>>>(
          s.bodies.p, s.chain_start.p, s.nc, s.uv.p, static_cast<const S*>(nullptr), s.X0.p, s.v.p, s.a.p);
      k_joint_transforms<<<grid(s.n), kThreads, 0, s.stream>>>(s.bodies.p, s.n, s.uv.p, s.Xup.p);
      k_response_blocks<<<grid(s.nc, kChainThreads), kChainThreads, 0, s.stream>>>(
          s.bodies.p, s.chain_start.p, s.nc, s.Xup.p, static_cast<const Force<S>*>(nullptr),
          static_cast<const S*>(nullptr), s.Omega.p);
      s.launched("the unit tree's blocks");
      if (s.options.preconditioner == sim::LoopPreconditioner::None) {
        // Levenberg-Marquardt's scale without weights: J J^T's largest diagonal entry
        k_blocks<<<grid(s.nl), kThreads, 0, s.stream>>>(s.rows.p, s.nl, s.X0.p, s.Omega.p, S(0),
                                                        static_cast<S*>(nullptr), s.tmp.p);
        s.launched("J J^T's diagonal");
        s.template reduce<1>(s.tmp.p, static_cast<const S*>(nullptr), s.nl, kD);
        s.fetch(kSlots);
        const double big = s.host_scalars[kD];
        s.unit_scale = big > 0 ? big : 1.0;
      } else {  // block Jacobi's weights of J J^T (the scale 1: unit diagonal blocks)
        k_blocks<<<grid(s.nl), kThreads, 0, s.stream>>>(s.rows.p, s.nl, s.X0.p, s.Omega.p, S(kLoopBlockFloor),
                                                        s.inv.p, static_cast<S*>(nullptr));
        s.launched("block-Jacobi weights of J J^T");
        s.unit_scale = 1.0;
      }
    }
    void solve(const double* r, double mu, double* x) {
      s.unit_solve(r, mu, floor, allowance, x, last_converged);
      if (!last_converged && mu == 0) ++s.stats.proj_unconverged;
    }
    void apply(const double* v_in, double* out) {
      s.to_device(s.uv.p, v_in, s.n);
      s.joint_motion_rows(s.uv.p, s.uphi.p);
      s.to_host(out, s.uphi.p, s.m);
    }
    double damping_scale() const { return s.unit_scale; }
  };

  double project(double* qh, double* qdh, double tol, int iterations, LoopProjectionInfo* info) {
    const AddElapsed timer{stats.proj_seconds};
    check(cudaSetDevice(options.device), "cudaSetDevice");
    alloc_projection();
    auto norm = [](const double* x, Index len) {
      double t = 0;
      for (Index i = 0; i < len; ++i) t += x[i] * x[i];
      return std::sqrt(t);
    };
    ProjOps ops{*this};
    ops.floor = sim::kIterativeLoopFloor * jscale * std::max(norm(qh, n), norm(qdh, n));
    ops.allowance = std::sqrt(kLoopRankTolerance) * jscale * norm(qdh, n);
    LoopProjectionInfo out;
    const double phi = project_onto_loops(ops, n, m, qh, qdh, tol, iterations, &out);
    if (info) *info = out;
    if (m > 0 && !ops.last_converged)
      throw sim::LoopSolveNotConverged(
          "CUDA iterative loop solver: the velocity projection did not converge: ||J qd||_2 " + sci(last_residual_abs) +
          " after it (" + sci(last_r0) + " before; relative residual " + sci(last_proj_residual) + ") after " +
          std::to_string(last_proj_iterations) + " iterations (at most " + std::to_string(options.max_iterations) +
          "); accepted: at most " + sci(last_target) + " (tolerance " + sci(tolerance) +
          " of ||J qd||_2 before + 1e-12 L_J max(||q||_2, ||qd||_2)), or " + sci(last_allowance) +
          " where it stopped at the damped normal residual (1e-5 L_J ||qd||_2 + the same floor)");
    return phi;
  }

  void forward_dynamics(const double* qh, const double* qdh, const double* tauh, double* qddh, double* lambdah) {
    const AddElapsed timer{stats.fd_seconds};
    check(cudaSetDevice(options.device), "cudaSetDevice");
    for (Index i = 0; i < n; ++i) hq[i] = S(qh[i]), hqd[i] = S(qdh[i]), htau[i] = S(tauh[i]);
    q.upload(hq.data(), n, stream), qd.upload(hqd.data(), n, stream), tau.upload(htau.data(), n, stream);
    // X0, gamma = Jdot qd
    k_body_motion<<<grid(nc, kChainThreads), kChainThreads, 0, stream>>>(bodies.p, chain_start.p, nc, q.p, qd.p, X0.p, v.p, a.p);
    if (nl > 0)
      k_loop_gamma<<<grid(nl), kThreads, 0, stream>>>(bodies.p, n, rows.p, nl, row_of.p, X0.p, v.p, a.p, gamma.p);
    launched("body motion");
    // qdd0, U, D
    const int minus_one = -1;
    check(cudaMemcpyAsync(failed.p, &minus_one, sizeof(int), cudaMemcpyHostToDevice, stream), "flag");
    k_aba_factor<<<grid(nc, kChainThreads), kChainThreads, 0, stream>>>(bodies.p, chain_start.p, nc, gravity, q.p, qd.p, tau.p, Xup.p,
                                                    U.p, D.p, qdd0.p, v.p, c.p, a.p, IA.p, pA.p, u.p, failed.p);
    launched("articulated-body factor");
    // b = -gamma - J qdd0
    joint_motion_rows(qdd0.p, tmp.p);
    k_combine<<<grid(m), kThreads, 0, stream>>>(m, gamma.p, tmp.p, b.p, false);
    reduce<0>(gamma.p, gamma.p, m, kA);
    reduce<0>(tmp.p, tmp.p, m, kB);
    reduce<0>(qdd0.p, qdd0.p, n, kC);
    reduce<1>(lambda.p, static_cast<const S*>(nullptr), m, kD);
    int failed_h = -1;
    check(cudaMemcpyAsync(&failed_h, failed.p, sizeof(int), cudaMemcpyDeviceToHost, stream), "flag");
    fetch(kD + 1);
    if (failed_h >= 0)
      throw LoopError("CUDA iterative loop solver: the articulated-body pivot of DoF " + std::to_string(failed_h) +
                      " is not positive and finite");
    const double scale = std::sqrt(host_scalars[kA]) + std::sqrt(host_scalars[kB]);
    const double floor = floor_coef * jscale * std::sqrt(host_scalars[kC]);
    const double lmax = host_scalars[kD];
    const bool finite = lmax < INFINITY;
    if (!options.warm_start || !finite)
      check(cudaMemsetAsync(lambda.p, 0, sizeof(S) * std::max<std::size_t>(1, m), stream), "memset");
    const bool any = options.warm_start && finite && lmax > 0;
    const double target = tolerance * scale + floor;
    if (m > 0) {
      if (options.preconditioner == sim::LoopPreconditioner::BlockJacobi) {
        k_response_blocks<<<grid(nc, kChainThreads), kChainThreads, 0, stream>>>(bodies.p, chain_start.p, nc, Xup.p, U.p, D.p, Omega.p);
        k_blocks<<<grid(nl), kThreads, 0, stream>>>(rows.p, nl, X0.p, Omega.p, S(kLoopBlockFloor), inv.p,
                                                    static_cast<S*>(nullptr));
        launched("block-Jacobi weights");
      }
      int it = 0;
      double residual = 0;
      const bool ok = fd_solve(target, any, it, residual);
      residual /= scale > 0 ? scale : 1.0;
      ++stats.fd_solves;
      stats.fd_iterations += it;
      stats.last_iterations = it;
      stats.last_residual = residual;
      if (!ok) {
        check(cudaMemsetAsync(lambda.p, 0, sizeof(S) * m, stream), "memset");  // no warm start from a failed solve
        check(cudaStreamSynchronize(stream), "memset");
        throw sim::LoopSolveNotConverged(
            "CUDA iterative loop solver: conjugate gradients on J M^-1 J^T did not converge (relative residual " +
            sci(residual) + " after " + std::to_string(it) + " iterations, at most " +
            std::to_string(options.max_iterations) + "; tolerance " + sci(tolerance) + ")");
      }
    } else {
      check(cudaMemsetAsync(x.p, 0, sizeof(S) * std::max<std::size_t>(1, n), stream), "memset");
    }
    k_add<<<grid(n), kThreads, 0, stream>>>(n, qdd0.p, x.p, qdd.p);
    launched("qdd");
    check(cudaMemcpyAsync(hout.data(), qdd.p, sizeof(S) * n, cudaMemcpyDeviceToHost, stream), "copy of qdd");
    check(cudaStreamSynchronize(stream), "qdd");
    ++stats.syncs;
    for (Index i = 0; i < n; ++i) {
      qddh[i] = static_cast<double>(hout[i]);
      if (!std::isfinite(qddh[i])) {
        check(cudaMemsetAsync(lambda.p, 0, sizeof(S) * std::max<std::size_t>(1, m), stream), "memset");
        check(cudaStreamSynchronize(stream), "memset");
        throw sim::LoopSolveNotConverged("CUDA iterative loop solver: qdd of DoF " + std::to_string(i) +
                                         " is not finite");
      }
    }
    if (lambdah && m > 0) {
      check(cudaMemcpyAsync(hout.data(), lambda.p, sizeof(S) * m, cudaMemcpyDeviceToHost, stream), "copy of lambda");
      check(cudaStreamSynchronize(stream), "lambda");
      ++stats.syncs;
      for (Index k = 0; k < m; ++k) lambdah[k] = static_cast<double>(hout[k]);
    }
  }
};

template <class S>
CudaIterativeLoopSolver<S>::CudaIterativeLoopSolver(const Model& model, const LoopSet& loops,
                                                    const CudaIterativeLoopOptions& options)
    : impl_(std::make_unique<Impl>(model, loops, options)) {}

template <class S>
CudaIterativeLoopSolver<S>::~CudaIterativeLoopSolver() = default;

template <class S>
void CudaIterativeLoopSolver<S>::forward_dynamics(const double* q, const double* qd, const double* tau, double* qdd,
                                                  double* lambda) {
  impl_->forward_dynamics(q, qd, tau, qdd, lambda);
}

template <class S>
double CudaIterativeLoopSolver<S>::project(double* q, double* qd, double tol, int iterations,
                                           LoopProjectionInfo* info) {
  if (impl_->options.project_on_host || Impl::kFloat) {  // the host's projector (float: its double projection)
    if (!impl_->projector) {
      sim::IterativeLoopOptions o;
      o.preconditioner = impl_->options.preconditioner;
      impl_->projector = std::make_unique<sim::IterativeLoopSolver>(impl_->host_model, impl_->loops, o);
    }
    return impl_->projector->project(q, qd, tol, iterations, info);
  }
  return impl_->project(q, qd, tol, iterations, info);
}

template <class S>
const CudaIterativeLoopStats& CudaIterativeLoopSolver<S>::stats() const {
  return impl_->stats;
}
template <class S>
void CudaIterativeLoopSolver<S>::reset_stats() {
  impl_->stats = {};
}
template <class S>
const CudaIterativeLoopOptions& CudaIterativeLoopSolver<S>::options() const {
  return impl_->options;
}
template <class S>
double CudaIterativeLoopSolver<S>::jscale() const {
  return impl_->jscale;
}

template class CudaIterativeLoopSolver<double>;
template class CudaIterativeLoopSolver<float>;

std::unique_ptr<sim::LoopSolver> make_cuda_iterative_loop_solver(const Model& model, const LoopSet& loops) {
  return std::make_unique<CudaIterativeLoopSolver<double>>(model, loops);
}
std::unique_ptr<sim::LoopSolver> make_cuda_iterative_loop_solver_float(const Model& model, const LoopSet& loops) {
  return std::make_unique<CudaIterativeLoopSolver<float>>(model, loops);
}

namespace {
std::unique_ptr<sim::LoopSolver> make_cuda_iterative_loop_solver_none(const Model& model, const LoopSet& loops) {
  CudaIterativeLoopOptions o;
  o.preconditioner = sim::LoopPreconditioner::None;
  return std::make_unique<CudaIterativeLoopSolver<double>>(model, loops, o);
}
}  // namespace

sim::LoopSolverFactory cuda_iterative_loop_solver_factory(sim::LoopPreconditioner p) {
  if (p == sim::LoopPreconditioner::BlockJacobi) return &make_cuda_iterative_loop_solver;
  if (p == sim::LoopPreconditioner::None) return &make_cuda_iterative_loop_solver_none;
  throw LoopError(std::string("CUDA iterative loop solver: preconditioner ") + sim::loop_preconditioner_name(p) +
                  " is not on the GPU (its sweeps are sequential): use block-jacobi or none");
}

}  // namespace scandyn::cuda
