// src/cli/backend.hpp: what `scandyn eval` and `scandyn bench` run, and where.
//
// An Evaluator computes one algorithm for a batch of instances; a backend is an
// entry of the table in backend.cpp that makes Evaluators for a model. Adding a
// backend (OpenMP, CUDA) means adding an Evaluator and a table entry.
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/backend.hpp"
#include "scandyn/model/model.hpp"

namespace scandyn::cli {

enum class Algo { Id, Fd, Mass, Bias };
enum class FdMethod { Aba, Jsi };
enum class Precision { Double, Float };

const char* algo_name(Algo algo);         // "id", "fd", "mass", "bias"
const char* fd_method_name(FdMethod fd);  // "aba", "jsi"
const char* precision_name(Precision p);  // "double", "float"
// Parses a name as written on the command line; false if unknown.
bool parse_algo(const std::string& name, Algo& algo);
bool parse_fd_method(const std::string& name, FdMethod& fd);
// The --precision value; throws UsageError if unknown.
Precision parse_precision(const std::string& name);

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

// Evaluates algorithms on batches for one model (which must outlive it).
template <class S>
class Evaluator {
 public:
  virtual ~Evaluator() = default;
  // Writes count x output_width(algo) values to out, instance-major. fd selects
  // the forward-dynamics method (ignored for the other algorithms). Stops at the
  // first instance whose factorisation fails.
  virtual BatchStatus run(Algo algo, FdMethod fd, const BatchIn<S>& in, S* out) = 0;
  // How algo is computed, for the benchmark's strategy column: recursion,
  // scan-local or scan-world for id; aba or jsi for fd; crba for mass; recursion for bias.
  virtual std::string strategy(Algo algo, FdMethod fd) const = 0;
};

// How an evaluator is made: the inverse-dynamics strategy (Auto: by shape), the
// thread count (0: all) and the largest batch run() will get.
struct EvalOptions {
  IdStrategy strategy = IdStrategy::Auto;
  int threads = 0;
  std::size_t max_batch = 1;
};

template <class S>
using EvaluatorFactory = std::unique_ptr<Evaluator<S>> (*)(const ModelTpl<S>&, const EvalOptions&);

// One row of the backend table. A backend known by name but not compiled into
// this build has null factories.
struct Backend {
  const char* name;
  EvaluatorFactory<double> make_double;
  EvaluatorFactory<float> make_float;
  bool available() const { return make_double != nullptr; }
};

// --strategy and --threads of eval and bench; throws UsageError for bad values.
class Args;
EvalOptions parse_eval_options(const Args& args);

// The backend called name. Throws UsageError if it is unknown or not available.
const Backend& find_backend(const std::string& name);

// The serial reference backend (always available): instances in turn, inverse
// dynamics by the recursion unless options.strategy asks for a scan form.
template <class S>
std::unique_ptr<Evaluator<S>> make_serial_evaluator(const ModelTpl<S>& model, const EvalOptions& options);

// One-line description of a failed forward dynamics, e.g.
// "articulated inertia pivot at DoF 3 is not positive".
std::string describe_fd_failure(FdMethod fd, const Status& status);

}  // namespace scandyn::cli
