// src/factor_graph/gpu_sparse_cholesky.cpp: cuSOLVER's sparse Cholesky (csrchol) on
// the factor graph's normal equations (scandyn/factor_graph/gpu_sparse_cholesky.hpp).
// Host code over the CUDA runtime and cuSOLVER; no kernels of its own.
#include "scandyn/factor_graph/gpu_sparse_cholesky.hpp"

#if SCANDYN_HAS_FACTOR_GRAPH_GPU
// the csrchol routines are marked deprecated in favour of cuDSS, which is not used
#define DISABLE_CUSOLVER_DEPRECATED
#include <cuda_runtime.h>
#include <cusolverSp.h>
#include <cusolverSp_LOWLEVEL_PREVIEW.h>
#include <cusparse.h>

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "scandyn/factor_graph/normal_equations.hpp"

namespace scandyn::factor_graph {

namespace {

const char* status_name(cusolverStatus_t s) {
  switch (s) {
    case CUSOLVER_STATUS_SUCCESS: return "CUSOLVER_STATUS_SUCCESS";
    case CUSOLVER_STATUS_NOT_INITIALIZED: return "CUSOLVER_STATUS_NOT_INITIALIZED";
    case CUSOLVER_STATUS_ALLOC_FAILED: return "CUSOLVER_STATUS_ALLOC_FAILED (out of device memory)";
    case CUSOLVER_STATUS_INVALID_VALUE: return "CUSOLVER_STATUS_INVALID_VALUE";
    case CUSOLVER_STATUS_ARCH_MISMATCH: return "CUSOLVER_STATUS_ARCH_MISMATCH";
    case CUSOLVER_STATUS_EXECUTION_FAILED: return "CUSOLVER_STATUS_EXECUTION_FAILED";
    case CUSOLVER_STATUS_INTERNAL_ERROR: return "CUSOLVER_STATUS_INTERNAL_ERROR";
    case CUSOLVER_STATUS_MATRIX_TYPE_NOT_SUPPORTED: return "CUSOLVER_STATUS_MATRIX_TYPE_NOT_SUPPORTED";
    default: return "cusolverStatus_t error";
  }
}

}  // namespace

struct GpuSparseCholesky::Impl {
  NormalEquations ne;  // the column scaling D, D At's values, the refined solve
  NormalMatrix B;      // P (D A^T A D + beta I) P^T in CSR, on the host
  double beta = 0;
  cusolverSpHandle_t handle = nullptr;
  cusparseMatDescr_t descr = nullptr;  // general matrix, 0-based
  csrcholInfo_t info = nullptr;        // cuSOLVER's symbolic and numeric factor
  int* d_row_ptr = nullptr;            // (n + 1) B's row pointers, device
  int* d_col_idx = nullptr;            // (nnz_B) B's columns, device
  double* d_val = nullptr;             // (nnz_B) B's values, device
  void* d_work = nullptr;              // cuSOLVER's factorisation / solve workspace
  double* d_b = nullptr;               // (n) permuted right-hand side, device
  double* d_z = nullptr;               // (n) permuted solution, device
  std::vector<double> h_b, h_z;        // (n) the same on the host

  Impl(const SparseMatrix& At, const std::vector<Index>& order) : B(At, order) {}
  ~Impl() {
    cudaFree(d_z);
    cudaFree(d_b);
    cudaFree(d_work);
    cudaFree(d_val);
    cudaFree(d_col_idx);
    cudaFree(d_row_ptr);
    if (info) cusolverSpDestroyCsrcholInfo(info);
    if (descr) cusparseDestroyMatDescr(descr);
    if (handle) cusolverSpDestroy(handle);
  }

  // "<call> failed (<why>) on the normal matrix of n unknowns, nnz entries"
  [[noreturn]] void fail(const char* call, const std::string& why) const {
    throw std::runtime_error("GpuSparseCholesky: " + std::string(call) + " failed (" + why +
                             ") on the normal matrix of " + std::to_string(B.n()) + " unknowns, " +
                             std::to_string(B.nnz()) + " entries");
  }
  void check(cudaError_t e, const char* call) const {
    if (e != cudaSuccess) fail(call, cudaGetErrorString(e));
  }
  void check(cusolverStatus_t s, const char* call) const {
    if (s != CUSOLVER_STATUS_SUCCESS) fail(call, status_name(s));
  }
  void check(cusparseStatus_t s, const char* call) const {
    if (s != CUSPARSE_STATUS_SUCCESS) fail(call, cusparseGetErrorString(s));
  }
  template <class T>
  void alloc(T*& p, std::size_t count, const char* what) {
    check(cudaMalloc(reinterpret_cast<void**>(&p), std::max<std::size_t>(count, 1) * sizeof(T)), what);
  }
};

GpuSparseCholesky::GpuSparseCholesky(const SparseMatrix& At, const std::vector<Index>& order, double beta)
    : impl_(std::make_unique<Impl>(At, order)) {
  Impl& m = *impl_;
  m.beta = beta;
  const Index n = m.B.n(), nnz = m.B.nnz();
  int devices = 0;
  m.check(cudaGetDeviceCount(&devices), "cudaGetDeviceCount");
  if (devices == 0) m.fail("cudaGetDeviceCount", "no CUDA device");
  m.check(cusolverSpCreate(&m.handle), "cusolverSpCreate");
  m.check(cusparseCreateMatDescr(&m.descr), "cusparseCreateMatDescr");
  m.check(cusparseSetMatType(m.descr, CUSPARSE_MATRIX_TYPE_GENERAL), "cusparseSetMatType");
  m.check(cusparseSetMatIndexBase(m.descr, CUSPARSE_INDEX_BASE_ZERO), "cusparseSetMatIndexBase");
  // B's pattern on the device
  m.alloc(m.d_row_ptr, static_cast<std::size_t>(n) + 1, "cudaMalloc (row pointers)");
  m.alloc(m.d_col_idx, static_cast<std::size_t>(nnz), "cudaMalloc (column indices)");
  m.alloc(m.d_val, static_cast<std::size_t>(nnz), "cudaMalloc (values)");
  m.alloc(m.d_b, static_cast<std::size_t>(n), "cudaMalloc (right-hand side)");
  m.alloc(m.d_z, static_cast<std::size_t>(n), "cudaMalloc (solution)");
  m.check(cudaMemcpy(m.d_row_ptr, m.B.row_ptr().data(), (static_cast<std::size_t>(n) + 1) * sizeof(int),
                     cudaMemcpyHostToDevice), "cudaMemcpy (row pointers)");
  m.check(cudaMemcpy(m.d_col_idx, m.B.col_idx().data(), static_cast<std::size_t>(nnz) * sizeof(int),
                     cudaMemcpyHostToDevice), "cudaMemcpy (column indices)");
  m.check(cudaMemset(m.d_val, 0, static_cast<std::size_t>(nnz) * sizeof(double)), "cudaMemset (values)");
  // symbolic analysis (elimination tree, supernodes, the factor's storage)
  m.check(cusolverSpCreateCsrcholInfo(&m.info), "cusolverSpCreateCsrcholInfo");
  m.check(cusolverSpXcsrcholAnalysis(m.handle, n, nnz, m.descr, m.d_row_ptr, m.d_col_idx, m.info),
          "cusolverSpXcsrcholAnalysis");
  std::size_t internal = 0, work = 0;
  m.check(cusolverSpDcsrcholBufferInfo(m.handle, n, nnz, m.descr, m.d_val, m.d_row_ptr, m.d_col_idx, m.info,
                                       &internal, &work),
          "cusolverSpDcsrcholBufferInfo");
  m.check(cudaMalloc(&m.d_work, std::max<std::size_t>(work, 1)), "cudaMalloc (cuSOLVER workspace)");
  m.check(cudaDeviceSynchronize(), "cusolverSpXcsrcholAnalysis (synchronize)");
  m.h_b.resize(static_cast<std::size_t>(n));
  m.h_z.resize(static_cast<std::size_t>(n));
  stats_.n = n;
  stats_.nnz_B = nnz;
  stats_.internal_bytes = internal;
  stats_.workspace_bytes = work;
}

GpuSparseCholesky::~GpuSparseCholesky() = default;

const std::vector<Index>& GpuSparseCholesky::row_ptr() const { return impl_->B.row_ptr(); }
const std::vector<Index>& GpuSparseCholesky::col_idx() const { return impl_->B.col_idx(); }
const std::vector<double>& GpuSparseCholesky::val() const { return impl_->B.val(); }

void GpuSparseCholesky::factorize(const SparseMatrix& At) {
  Impl& m = *impl_;
  const Index n = m.B.n(), nnz = m.B.nnz();
  // B = P (D A^T A D + beta I) P^T on the host, its values to the device
  m.ne.equilibrate(At);
  m.B.assemble(At, m.ne.scaled(), m.beta);
  m.check(cudaMemcpy(m.d_val, m.B.val().data(), static_cast<std::size_t>(nnz) * sizeof(double),
                     cudaMemcpyHostToDevice), "cudaMemcpy (values)");
  m.check(cusolverSpDcsrcholFactor(m.handle, n, nnz, m.descr, m.d_val, m.d_row_ptr, m.d_col_idx, m.info, m.d_work),
          "cusolverSpDcsrcholFactor");
  // a pivot <= 0 (B not positive definite) is reported as a zero pivot; a NaN pivot
  // (the square root of a negative one) is caught on diag(L)
  int position = -1;
  m.check(cusolverSpDcsrcholZeroPivot(m.handle, m.info, 0.0, &position), "cusolverSpDcsrcholZeroPivot");
  if (position < 0) {
    m.check(cusolverSpDcsrcholDiag(m.handle, m.info, m.d_z), "cusolverSpDcsrcholDiag");
    m.check(cudaMemcpy(m.h_z.data(), m.d_z, static_cast<std::size_t>(n) * sizeof(double), cudaMemcpyDeviceToHost),
            "cudaMemcpy (diag(L))");
    for (Index k = 0; k < n && position < 0; ++k)
      if (!(m.h_z[k] > 0) || !std::isfinite(m.h_z[k])) position = k;
  }
  if (position >= 0)
    throw std::runtime_error("GpuSparseCholesky: A^T A + beta I is not positive definite (pivot " +
                             std::to_string(position) + " of the ordered normal matrix of " + std::to_string(n) +
                             " unknowns): the factor graph's system is singular (redundant loop "
                             "constraints need beta > 0)");
}

void GpuSparseCholesky::solve(const SparseMatrix& At, const std::vector<double>& b, std::vector<double>& x,
                              int refine) {
  Impl& m = *impl_;
  const Index n = m.B.n();
  const std::vector<Index>& order = m.B.order();
  const std::size_t bytes = static_cast<std::size_t>(n) * sizeof(double);
  m.ne.solve(At, b, x, refine, [&](const double* rhs, double* y) {
    // B z = P rhs, y = P^T z
    for (Index k = 0; k < n; ++k) m.h_b[k] = rhs[order[k]];
    m.check(cudaMemcpy(m.d_b, m.h_b.data(), bytes, cudaMemcpyHostToDevice), "cudaMemcpy (right-hand side)");
    m.check(cusolverSpDcsrcholSolve(m.handle, n, m.d_b, m.d_z, m.info, m.d_work), "cusolverSpDcsrcholSolve");
    m.check(cudaMemcpy(m.h_z.data(), m.d_z, bytes, cudaMemcpyDeviceToHost), "cudaMemcpy (solution)");
    for (Index k = 0; k < n; ++k) y[order[k]] = m.h_z[k];
  });
}

}  // namespace scandyn::factor_graph
#endif
