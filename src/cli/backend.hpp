// src/cli/backend.hpp: what `scandyn eval` and `scandyn bench` run, and where.
//
// An Evaluator computes one algorithm for a batch of instances; a backend is an
// entry of the table in backend.cpp that makes Evaluators for a model and says
// which algorithms they compute. Adding a backend means adding an Evaluator and a
// table entry; giving a backend one more algorithm means computing it in the
// Evaluator's run() and adding it to the entry's AlgoSet. eval's CSV reading,
// chunking and writing and bench's states, timing and rows are shared by all.
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/backend.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/model/model.hpp"

namespace scandyn::cli {

enum class Algo { Id, Fd, Mass, Bias };
// Forward-dynamics methods (--fd): auto resolves by backend and shape (see
// Evaluator::fd_method); hybrid and parallel take unbranched chains hanging from the base.
enum class FdMethod { Auto, Aba, Jsi, Hybrid, Parallel };
enum class Precision { Double, Float };

const char* algo_name(Algo algo);         // "id", "fd", "mass", "bias"
const char* fd_method_name(FdMethod fd);  // "auto", "aba", "jsi", "hybrid", "parallel"
const char* precision_name(Precision p);  // "double", "float"
// Parses a name as written on the command line; false if unknown.
bool parse_algo(const std::string& name, Algo& algo);
bool parse_fd_method(const std::string& name, FdMethod& fd);
// The --precision value; throws UsageError if unknown.
Precision parse_precision(const std::string& name);

// A set of algorithms: bit (1 << algo) for each member.
using AlgoSet = unsigned;
constexpr AlgoSet algo_bit(Algo algo) { return 1u << static_cast<unsigned>(algo); }
constexpr AlgoSet kEveryAlgo =
    algo_bit(Algo::Id) | algo_bit(Algo::Fd) | algo_bit(Algo::Mass) | algo_bit(Algo::Bias);
// The members' names joined by sep, in the order id, fd, mass, bias.
std::string algo_list(AlgoSet algos, const char* sep);

// Values per instance that algo writes: nv, or nv * nv for Mass.
std::size_t output_width(Algo algo, Index nv);
// Output column names: tau_id_<i>, qdd_fd_<i>, M_<i>_<j> (row-major) or h_<i>.
std::vector<std::string> output_columns(Algo algo, Index nv);

// A batch of count instances, instance-major: entry i of instance b is at [b * nv + i].
// Inputs an algorithm does not read may be null: id reads q, qd, qdd; fd reads
// q, qd, tau; mass reads q; bias reads q, qd.
template <class S>
struct BatchIn {
  std::size_t count = 0;
  const S* q = nullptr;
  const S* qd = nullptr;
  const S* qdd = nullptr;
  const S* tau = nullptr;
};

// Outcome of a batched call: the first instance whose forward dynamics failed.
struct BatchStatus {
  std::size_t instance = 0;  // meaningful when !ok()
  Status status;             // the failing instance's status
  bool ok() const { return status.ok(); }
};

// A batch copied once into a backend's own memory (a CUDA device's), so that the
// benchmark can time the computation without the transfers: launch() queues one
// call on all the batch's instances, wait() returns when every queued call is done.
template <class S>
class ResidentBatch {
 public:
  virtual ~ResidentBatch() = default;
  virtual void launch() = 0;                  // asynchronous; throws DataError
  virtual void wait() = 0;                    // throws DataError for a failed call
  // Copies the last call's results to out (count x output_width, instance-major,
  // as Evaluator::run writes them). Waits first.
  virtual void read(S* out) = 0;
  // The first instance of the last call whose forward dynamics failed, as run()
  // reports it (a failed instance's outputs are not written); ok for algorithms
  // that cannot fail. Waits first.
  virtual BatchStatus status() = 0;
  virtual std::string strategy() const = 0;  // the benchmark's strategy column
};

// Evaluates algorithms on batches for one model (which must outlive it).
template <class S>
class Evaluator {
 public:
  virtual ~Evaluator() = default;
  // Writes count x output_width(algo) values to out, instance-major, all in host
  // memory. fd selects the forward-dynamics method (ignored for the other
  // algorithms). Stops at the first instance whose factorisation fails. Called
  // only for algorithms of the backend's AlgoSet, with count <= max_batch.
  virtual BatchStatus run(Algo algo, FdMethod fd, const BatchIn<S>& in, S* out) = 0;
  // The forward-dynamics method run() uses when fd is requested (Auto resolved):
  // on the CPU backends aba, or parallel for chains (from the base) of at least 4096
  // links on openmp; on CUDA the engine's choice (aba up to 64 DoF, parallel for
  // longer chains from the base, else jsi). Failure messages (describe_fd_failure) name the
  // pivot of the method used.
  virtual FdMethod fd_method(FdMethod requested) const = 0;
  // How run() computes algo, for the benchmark's strategy column: recursion,
  // scan-local or scan-world for id; aba or jsi for fd; crba for mass; recursion
  // for bias (CPU); for CUDA the engine's strategy with "-host" (host buffers
  // staged through the device): thread-host or scan-local-host (id, bias),
  // aba_thread-host, jsi_thread-host, ... (fd), crba_thread-host or
  // crba_block-host (mass).
  virtual std::string strategy(Algo algo, FdMethod fd) const = 0;
  // True when run() performs exactly the serial double reference's arithmetic for
  // this S (the same functions in the same order), so that its error against the
  // reference is known without measuring: 0 in double.
  virtual bool exact(Algo algo, FdMethod fd) const = 0;
  // The batch in the backend's own memory, for timing without transfers; null
  // (the default) for backends that compute in host memory, and where the backend
  // has no device-resident call for algo and fd (CUDA's --fd hybrid).
  virtual std::unique_ptr<ResidentBatch<S>> resident(Algo algo, FdMethod fd, const BatchIn<S>& in) {
    (void)algo, (void)fd, (void)in;
    return nullptr;
  }
  // Instances of the last run() of fd whose JSI factorisation failed and that were
  // computed by aba instead (EvalOptions::fallback_aba); 0 without the fallback.
  virtual std::size_t fallbacks() const { return 0; }
};

// How an evaluator is made: the inverse-dynamics strategy (Auto: by shape), the
// thread count (0: all), the largest batch run() will get and the algorithms it
// will be asked for (0: not known). A backend prepares the engines of those
// algorithms when it is made, so that one it cannot run here fails before any
// output exists; others are made on first use.
struct EvalOptions {
  IdStrategy strategy = IdStrategy::Auto;
  int threads = 0;
  std::size_t max_batch = 1;
  AlgoSet algos = 0;
  FdMethod fd = FdMethod::Auto;  // the forward-dynamics method fd will be asked for
  bool fallback_aba = false;     // --fallback aba: a failed JSI factorisation is redone by aba
};

template <class S>
using EvaluatorFactory = std::unique_ptr<Evaluator<S>> (*)(const ModelTpl<S>&, const EvalOptions&);

// One row of the backend table. A backend known by name but not compiled into
// this build has null factories.
struct Backend {
  const char* name;
  EvaluatorFactory<double> make_double;
  EvaluatorFactory<float> make_float;
  AlgoSet algos;  // the algorithms its evaluators compute
  // Why the backend cannot run on this machine, "" when it can; null: always can.
  std::string (*unusable)();
  bool available() const { return make_double != nullptr; }
  bool provides(Algo algo) const { return (algos & algo_bit(algo)) != 0; }
};

// --strategy, --threads and --fd of eval and bench; throws UsageError for bad values.
class Args;
EvalOptions parse_eval_options(const Args& args);

// The stderr warning line for instances that fell back from JSI to aba, e.g.
// "forward dynamics by jsi failed on 3 of 100 rows (mass matrix pivot not
// positive); they were computed by aba (--fallback aba)".
std::string describe_fallbacks(std::size_t fell_back, std::size_t total, const char* unit);

// The backend called name. Throws UsageError if it is unknown or not in this build.
const Backend& find_backend(const std::string& name);

// Throws UsageError (no --help hint) unless the backend computes every algorithm
// of algos, e.g. "backend 'x' does not provide --algo mass (it provides: id, fd,
// bias)" (every backend of this build provides all four).
// default_from: for a selection eval made without --algo, the states file whose
// columns selected it (the message then says so); empty otherwise.
void require_algos(const Backend& backend, AlgoSet algos, const std::string& default_from = "");

// Throws UsageError (no --help hint) when the backend cannot run on this machine:
// "backend 'cuda': no usable CUDA device: <why>".
void require_usable(const Backend& backend);

// The serial reference backend (always available): instances in turn, inverse
// dynamics by the recursion unless options.strategy asks for a scan form.
template <class S>
std::unique_ptr<Evaluator<S>> make_serial_evaluator(const ModelTpl<S>& model, const EvalOptions& options);

#if SCANDYN_HAS_CUDA
// The CUDA backend (backend_cuda.cpp): id and bias by the CUDA inverse-dynamics
// engine (one GPU thread per instance up to 64 DoF, link scans beyond), fd by the
// CUDA forward-dynamics engine of the --fd method, mass by the CUDA mass-matrix
// engine (CRBA: a GPU thread per instance up to 64 DoF, a thread block beyond).
// Throws UsageError (no --help hint) when an engine of options.algos cannot be
// made: no usable device, a model beyond the kernels' DoF limit, a strategy the
// backend does not have, a max_batch that does not fit in device memory.
template <class S>
std::unique_ptr<Evaluator<S>> make_cuda_evaluator(const ModelTpl<S>& model, const EvalOptions& options);
// Why CUDA cannot run here ("no usable CUDA device: ..."), "" when it can.
std::string cuda_unusable();
#endif

// One-line description of a failed forward dynamics, e.g.
// "articulated inertia pivot at DoF 3 is not positive"; with fallback_aba (--fd jsi
// --fallback aba: the instance failed the JSI and then the ABA) both, the DoF the ABA's.
std::string describe_fd_failure(FdMethod fd, const Status& status, bool fallback_aba = false);

}  // namespace scandyn::cli
