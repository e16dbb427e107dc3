// scandyn/backend.hpp: batched inverse dynamics on a selectable backend (and the
// batch types of forward dynamics, whose engine is CUDA-only so far:
// scandyn/cuda/forward_dynamics.hpp).
//
// A batch holds B instances of one model. Per-DoF arrays are plain strided buffers:
// entry (DoF i, instance b) lives at data[i * dof_stride + b * batch_stride].
// scandyn's native layout is structure-of-arrays with the instance innermost,
// q[i * B + b] (BatchView::soa); an array of per-instance rows, q[b * nv + i], is
// BatchView::aos. Any other strides work too, so callers pass their own memory.
//
// An engine is made once per model, backend and precision; it owns all scratch
// for up to max_batch instances and allocates nothing in compute().
#pragma once

#include <memory>
#include <stdexcept>
#include <string>

#include "scandyn/algorithm/rnea_scan.hpp"

namespace scandyn {

template <class T>
struct BatchView {
  T* data = nullptr;
  Index batch = 0;                 // number of instances B
  std::ptrdiff_t dof_stride = 0;   // elements between DoF i and i + 1 of one instance
  std::ptrdiff_t batch_stride = 0; // elements between instance b and b + 1

  SCANDYN_HD T& at(Index dof, Index b) const { return data[dof * dof_stride + b * batch_stride]; }
  static BatchView soa(T* data, Index nv, Index B) { (void)nv; return {data, B, B, 1}; }
  static BatchView aos(T* data, Index nv, Index B) { return {data, B, 1, nv}; }
};

template <class S>
struct IdBatchIn {
  BatchView<const S> q, qd, qdd;      // (nv x B) joint positions, velocities, accelerations
  const Force<S>* fext = nullptr;     // optional (B x nv) body wrenches, fext[b * nv + i], body frames
};

// Throws BackendError unless q, qd, qdd and tau describe the same number of
// instances, at most max_batch, with non-null data when there is any.
template <class S>
void check_batch(const IdBatchIn<S>& in, const BatchView<S>& tau, Index max_batch);

// Forward dynamics' inputs: qdd = FD(q, qd, tau, fext).
template <class S>
struct FdBatchIn {
  BatchView<const S> q, qd, tau;      // (nv x B) joint positions, velocities, forces
  const Force<S>* fext = nullptr;     // optional (B x nv) body wrenches, fext[b * nv + i], body frames
};

// The same checks for q, qd, tau and qdd.
template <class S>
void check_batch(const FdBatchIn<S>& in, const BatchView<S>& qdd, Index max_batch);

enum class BackendKind { Serial, OpenMP, Cuda };

// How the work is split; Auto picks by shape (see choose_strategy).
enum class IdStrategy {
  Auto,
  Recursion,  // one instance at a time per thread, the serial RNEA recursion
  ScanLocal,  // scans over links, local-frame affine form
  ScanWorld,  // scans over links, world-frame form
};

struct BackendOptions {
  BackendKind backend = BackendKind::Serial;
  IdStrategy strategy = IdStrategy::Auto;
  int threads = 0;        // OpenMP threads, 0: omp_get_max_threads()
  Index max_batch = 1;    // largest batch compute() will be given
};

// Thrown for a backend that is not built or cannot run, or a batch that does not fit.
class BackendError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

template <class S>
class InverseDynamics {
 public:
  virtual ~InverseDynamics() = default;
  // tau (nv x B) = RNEA(q, qd, qdd) for every instance, gravity included.
  virtual void compute(const IdBatchIn<S>& in, const BatchView<S>& tau) = 0;
  // the strategy actually used, as in benchmark rows: recursion, scan-local, scan-world
  virtual std::string strategy() const = 0;
  virtual std::string backend() const = 0;
};

// Makes an engine; throws BackendError if the backend is not available in this build.
template <class S>
std::unique_ptr<InverseDynamics<S>> make_inverse_dynamics(const ModelTpl<S>& model, const BackendOptions& options);

// The OpenMP backend's choice for Auto: threads over instances (the recursion) when
// there are at least as many instances as threads or fewer than 4096 bodies;
// otherwise the local-frame scan across links. Measured crossovers:
// docs/accuracy-id-scan.md.
IdStrategy choose_strategy(Index nv, Index batch, int threads);

// Threads the OpenMP backend uses when BackendOptions::threads is 0
// (omp_get_max_threads(); 1 in a build without OpenMP).
int openmp_threads();

const char* to_string(BackendKind b);
const char* to_string(IdStrategy s);
BackendKind parse_backend(const std::string& name);   // throws BackendError
IdStrategy parse_strategy(const std::string& name);   // throws BackendError

}  // namespace scandyn
