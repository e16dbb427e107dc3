// src/cli/engines.hpp: the algorithms `scandyn eval` and `scandyn bench` compute,
// each through the library's engine for the chosen backend (scandyn/engine.hpp).
// The command line only turns its flags into BackendOptions, its CSV rows into
// instance-major host batches, and the engines' errors into its exit codes.
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <vector>

#include "scandyn/build_config.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/io/states.hpp"

namespace scandyn::cli {

class Args;

// The states files' algorithms and columns (scandyn/io/states.hpp).
using io::Algo;
using io::AlgoSet;
using io::algo_bit;
using io::algo_name;
using io::output_columns;
using io::output_width;
using io::parse_algo;

// A batch of count instances, instance-major: entry i of instance b is at [b * nv + i].
// Inputs an algorithm does not read may be null: id reads q, qd, qdd; fd reads
// q, qd, tau; mass reads q; bias reads q, qd; did and d2id as id, dfd as fd.
template <class S>
struct BatchIn {
  std::size_t count = 0;
  const S* q = nullptr;  // count x nq
  const S* qd = nullptr;
  const S* qdd = nullptr;
  const S* tau = nullptr;
};

// --precision (default double); throws UsageError for a bad value.
Precision parse_cli_precision(const Args& args);

// --backend, --strategy, --threads, --fd, --fallback (aba, double), --fd-check
// (default default_check) and --fd-check-tol (the threshold of --precision) as
// BackendOptions (max_batch 1); throws UsageError for bad values.
BackendOptions parse_backend_options(const Args& args, FdCheckMode default_check = FdCheckMode::Auto);

// Throws UsageError (no --help hint) when the backend cannot run here:
// "backend 'cuda': no usable CUDA device: ...".
void require_usable(BackendKind backend);

// The batch copied once into a device's memory, so that bench can time the
// computation without the transfers (CUDA engines' compute_async()).
template <class S>
class ResidentBatch {
 public:
  virtual ~ResidentBatch() = default;
  virtual void launch() = 0;                  // asynchronous; throws DataError
  virtual void wait() = 0;                    // throws DataError for a failed call
  virtual void read(S* out) = 0;              // the last call's results, as AlgoEngine::run writes them
  virtual BatchStatus status() = 0;           // the last call's failures (fd)
  virtual std::string strategy() const = 0;   // the engine's strategy
};

// One algorithm's engine on one backend, called on instance-major host batches.
template <class S>
class AlgoEngine {
 public:
  // Makes the engine (options.max_batch instances); what the backend refuses (no
  // device, a model beyond a kernel's limit, a method the model cannot take, too
  // little memory) is a UsageError (exit 2) with the library's message.
  AlgoEngine(Algo algo, const ModelTpl<S>& model, const BackendOptions& options);
  ~AlgoEngine();

  // Writes count x output_width values to out. A failed computation (a CUDA error)
  // is a DataError; failed instances are in the status, their outputs unwritten.
  BatchStatus run(const BatchIn<S>& in, S* out);
  // The bench row's strategy: the engine's, with "-host" on cuda (host buffers,
  // staged through the device).
  std::string strategy() const;
  // True when run() is exactly the serial double reference bench compares with (aba
  // for fd).
  bool exact() const;
  // The batch in device memory (CUDA engines with compute_async), else null.
  std::unique_ptr<ResidentBatch<S>> resident(const BatchIn<S>& in);

 private:
  Algo algo_;
  Index nv_;
  Index nq_;  // entries of q per instance
  std::unique_ptr<InverseDynamics<S>> id_;
  std::unique_ptr<BiasForces<S>> bias_;
  std::unique_ptr<MassMatrix<S>> mass_;
  std::unique_ptr<ForwardDynamics<S>> fd_;
  std::unique_ptr<IdDerivatives<S>> did_;
  std::unique_ptr<FdDerivatives<S>> dfd_;
  std::unique_ptr<IdSecondDerivatives<S>> d2id_;
  const Engine& engine() const;
};

#if SCANDYN_HAS_CUDA
// The CUDA engines' device-resident batch (engines_cuda.cpp); null for an engine
// without compute_async (fd hybrid, and jsi with the aba fallback).
template <class S>
std::unique_ptr<ResidentBatch<S>> make_resident_batch(Algo algo, Engine& engine, Index nv, Index nq,
                                                     const BatchIn<S>& in);
#endif

#if SCANDYN_HAS_CUDA
// The kinematics engine's device-resident batch (engines_cuda.cpp): q copied once;
// per call compute_async() writing fk_width pose entries, then jac_width Jacobian
// entries, per instance (either width 0: not computed). read() gives rows of
// fk_width + jac_width values, as KinematicsColumns::run writes them.
template <class S>
std::unique_ptr<ResidentBatch<S>> make_resident_kinematics(Kinematics<S>& engine, Index nv, const S* q,
                                                           std::size_t count, std::size_t fk_width,
                                                           std::size_t jac_width);
#endif

#if SCANDYN_HAS_CUDA
// The closed-loop forward dynamics' device-resident batch (engines_cuda.cpp): q, qd,
// tau copied once; per call compute_async() writing nv qdd then m lambda entries per
// instance; read() gives rows of nv + m values.
template <class S>
std::unique_ptr<ResidentBatch<S>> make_resident_loops(ConstrainedForwardDynamics<S>& engine, Index nv, const S* q,
                                                      const S* qd, const S* tau, std::size_t count);
#endif

// The stderr warning for instances that fell back from jsi to aba, e.g. "forward
// dynamics by jsi failed on 3 of 100 rows (mass matrix pivot not positive); they
// were computed by aba (--fallback aba)".
std::string describe_fallbacks(std::size_t fell_back, std::size_t total, const char* unit);
// The stderr warning for instances the forward-dynamics check flagged and a retry
// fixed (BatchStatus::retried).
std::string describe_check_retries(std::size_t retried, std::size_t total, const char* unit);

}  // namespace scandyn::cli
