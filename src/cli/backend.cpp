// src/cli/backend.cpp: the backend table and the serial reference backend.
#include "backend.hpp"

#include "cli.hpp"
#include "csv.hpp"
#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/build_config.hpp"

#include <algorithm>
#include <cmath>

#ifdef _OPENMP
#include <omp.h>
#endif

namespace scandyn::cli {

const char* algo_name(Algo algo) {
  switch (algo) {
    case Algo::Id: return "id";
    case Algo::Fd: return "fd";
    case Algo::Mass: return "mass";
    case Algo::Bias: return "bias";
  }
  return "?";
}

const char* fd_method_name(FdMethod fd) {
  switch (fd) {
    case FdMethod::Auto: return "auto";
    case FdMethod::Aba: return "aba";
    case FdMethod::Jsi: return "jsi";
    case FdMethod::Hybrid: return "hybrid";
    case FdMethod::Parallel: return "parallel";
  }
  return "?";
}

const char* precision_name(Precision p) { return p == Precision::Double ? "double" : "float"; }

bool parse_algo(const std::string& name, Algo& algo) {
  for (Algo a : {Algo::Id, Algo::Fd, Algo::Mass, Algo::Bias}) {
    if (name == algo_name(a)) {
      algo = a;
      return true;
    }
  }
  return false;
}

bool parse_fd_method(const std::string& name, FdMethod& fd) {
  for (FdMethod f : {FdMethod::Auto, FdMethod::Aba, FdMethod::Jsi, FdMethod::Hybrid, FdMethod::Parallel}) {
    if (name == fd_method_name(f)) {
      fd = f;
      return true;
    }
  }
  return false;
}

Precision parse_precision(const std::string& name) {
  for (Precision p : {Precision::Double, Precision::Float})
    if (name == precision_name(p)) return p;
  throw UsageError("unknown --precision value '" + name + "' (expected double or float)");
}

std::string algo_list(AlgoSet algos, const char* sep) {
  std::string out;
  for (Algo a : {Algo::Id, Algo::Fd, Algo::Mass, Algo::Bias}) {
    if (!(algos & algo_bit(a))) continue;
    if (!out.empty()) out += sep;
    out += algo_name(a);
  }
  return out;
}

std::size_t output_width(Algo algo, Index nv) {
  const std::size_t n = static_cast<std::size_t>(nv);
  return algo == Algo::Mass ? n * n : n;
}

std::vector<std::string> output_columns(Algo algo, Index nv) {
  std::vector<std::string> names;
  names.reserve(output_width(algo, nv));
  if (algo == Algo::Mass) {
    for (Index i = 0; i < nv; ++i)
      for (Index j = 0; j < nv; ++j)
        names.push_back("M_" + std::to_string(i) + "_" + std::to_string(j));
    return names;
  }
  const char* prefix = algo == Algo::Id ? "tau_id_" : algo == Algo::Fd ? "qdd_fd_" : "h_";
  for (Index i = 0; i < nv; ++i) names.push_back(prefix + std::to_string(i));
  return names;
}

std::string describe_fd_failure(FdMethod fd, const Status& status, bool fallback_aba) {
  const std::string pivot = " pivot at DoF " + std::to_string(status.failed_dof) + " is not positive";
  if (fd == FdMethod::Jsi && fallback_aba)  // what is left failed both: the status is the ABA's
    return "mass matrix pivot not positive, and by --fallback aba the articulated inertia" + pivot;
  return (fd == FdMethod::Jsi ? "mass matrix" : "articulated inertia") + pivot;
}

// ---- CPU backends ---------------------------------------------------------------

namespace {

// Serial (one thread) or OpenMP (threads over instances). Inverse dynamics goes
// through the library's batched engine, which also provides the scan strategies
// across links; the other algorithms run the reference per instance, one
// preallocated DataTpl per thread. The nv x nv workspaces that fd_jsi alone needs
// are made on the first JSI call (a 10^5-link rope would need 80 GB).
template <class S>
class CpuEvaluator final : public Evaluator<S> {
 public:
  CpuEvaluator(const ModelTpl<S>& model, BackendKind kind, const EvalOptions& o) : model_(model) {
    BackendOptions bo;
    bo.backend = kind;
    bo.strategy = o.strategy;
    bo.threads = kind == BackendKind::Serial ? 1 : o.threads;
    bo.max_batch = static_cast<Index>(o.max_batch);
    id_ = make_inverse_dynamics<S>(model, bo);
    threads_ = kind == BackendKind::Serial ? 1 : (o.threads > 0 ? o.threads : max_threads());
    for (int t = 0; t < threads_; ++t) data_.emplace_back(model, false);
    max_batch_ = static_cast<Index>(o.max_batch);
    chain_ = is_chain(model);
    openmp_ = kind == BackendKind::OpenMP;
    fallback_ = o.fallback_aba;
    if (o.fd == FdMethod::Hybrid)
      throw UsageError("--fd hybrid runs on --backend cuda only (articulated inertias on the host, the other passes "
                       "as device scans); on the CPU use --fd parallel, aba or jsi", false);
    if (fd_method(o.fd) == FdMethod::Parallel && (o.algos & algo_bit(Algo::Fd))) parallel_engine();
  }

  FdMethod fd_method(FdMethod requested) const override {
    if (requested != FdMethod::Auto) return requested;
    return openmp_ && chain_ && model_.nv() >= 4096 ? FdMethod::Parallel : FdMethod::Aba;
  }

  BatchStatus run(Algo algo, FdMethod fd, const BatchIn<S>& in, S* out) override {
    const Index nv = model_.nv();
    const std::size_t n = static_cast<std::size_t>(nv);
    if (algo == Algo::Id) {
      const Index B = static_cast<Index>(in.count);
      IdBatchIn<S> id{BatchView<const S>::aos(in.q, nv, B), BatchView<const S>::aos(in.qd, nv, B),
                      BatchView<const S>::aos(in.qdd, nv, B)};
      id_->compute(id, BatchView<S>::aos(out, nv, B));
      return {};
    }
    fd = fd_method(fd);
    if (algo == Algo::Fd && fd == FdMethod::Hybrid)
      throw UsageError("--fd hybrid runs on --backend cuda only", false);
    if (algo == Algo::Fd && fd == FdMethod::Parallel) {
      const Index B = static_cast<Index>(in.count);
      std::vector<int>& failed = failed_;
      failed.assign(in.count, -1);
      const FdBatchIn<S> fin{BatchView<const S>::aos(in.q, nv, B), BatchView<const S>::aos(in.qd, nv, B),
                             BatchView<const S>::aos(in.tau, nv, B), nullptr};
      parallel_engine().compute(fin, BatchView<S>::aos(out, nv, B), failed.data());
      BatchStatus st;
      for (std::size_t b = 0; b < in.count; ++b)
        if (failed[b] >= 0) {
          st.instance = b;
          st.status = Status{failed[b]};
          break;
        }
      return st;
    }
    fallbacks_ = 0;
    if (algo == Algo::Fd && fd == FdMethod::Jsi && jsi_.empty())
      for (int t = 0; t < threads_; ++t) jsi_.emplace_back(model_, true);
    const std::size_t width = output_width(algo, nv);
    const long long count = static_cast<long long>(in.count);
    // first failing instance, if any
    long long failed = count;
    Status failed_status;
    // instance b on thread slot t; 1 when --fallback aba recomputed it
    auto one = [&](long long b, int t) -> int {
      const std::size_t k = static_cast<std::size_t>(b) * n;
      S* o = out + static_cast<std::size_t>(b) * width;
      Status st;
      int fell = 0;
      switch (algo) {
        case Algo::Bias: bias_forces(model_, data_[t], in.q + k, in.qd + k, o); break;
        case Algo::Mass: crba(model_, data_[t], in.q + k, o); break;
        case Algo::Fd:
          if (fd == FdMethod::Aba) {
            st = aba(model_, data_[t], in.q + k, in.qd + k, in.tau + k, o);
          } else {
            const FdFallbackStatus fs = fd_jsi_or_aba(model_, jsi_[t], in.q + k, in.qd + k, in.tau + k, o, fallback_);
            st = fs.status;
            fell = fs.fell_back ? 1 : 0;
          }
          break;
        case Algo::Id: break;
      }
      if (!st.ok()) {
#pragma omp critical(scandyn_cli_fd_failure)
        if (b < failed) {
          failed = b;
          failed_status = st;
        }
      }
      return fell;
    };
    long long fell_back = 0;  // instances recomputed by aba (--fallback aba)
    if (threads_ > 1 && count > 1) {
#pragma omp parallel for num_threads(threads_) schedule(static) reduction(+ : fell_back)
      for (long long b = 0; b < count; ++b) fell_back += one(b, thread_index());
    } else {
      // no parallel region at all: entering one, even a serialized one, costs about
      // as much as a 7-DoF bias or mass call (~0.4 us)
      for (long long b = 0; b < count; ++b) fell_back += one(b, 0);
    }
    fallbacks_ = static_cast<std::size_t>(fell_back);
    BatchStatus st;
    if (failed < count) {
      st.instance = static_cast<std::size_t>(failed);
      st.status = failed_status;
    }
    return st;
  }

  std::size_t fallbacks() const override { return fallbacks_; }

  std::string strategy(Algo algo, FdMethod fd) const override {
    if (algo == Algo::Id) return id_->strategy();
    if (algo == Algo::Fd) {
      const FdMethod m = fd_method(fd);
      return m == FdMethod::Jsi && fallback_ ? "jsi+aba" : fd_method_name(m);
    }
    return algo == Algo::Mass ? "crba" : "recursion";
  }

  // the reference functions themselves, except the scan forms and JSI
  bool exact(Algo algo, FdMethod fd) const override {
    if (algo == Algo::Id) return id_->strategy() == "recursion";
    return !(algo == Algo::Fd && fd_method(fd) != FdMethod::Aba);
  }

 private:
  static int max_threads() {
#ifdef _OPENMP
    return omp_get_max_threads();
#else
    return 1;
#endif
  }
  static int thread_index() {
#ifdef _OPENMP
    return omp_get_thread_num();
#else
    return 0;
#endif
  }

  static bool is_chain(const ModelTpl<S>& m) {  // what the chain forward dynamics takes
    return m.nv() > 0 && first_branching_body(m) < 0;
  }
  ChainForwardDynamics<S>& parallel_engine() {
    if (!parallel_) {
      try {
        parallel_ = std::make_unique<ChainForwardDynamics<S>>(model_, std::max<Index>(max_batch_, 1), threads_);
      } catch (const BackendError& e) {
        throw UsageError(std::string("--fd parallel: ") + e.what(), false);
      }
    }
    return *parallel_;
  }

  const ModelTpl<S>& model_;
  Index max_batch_ = 1;
  bool chain_ = false, openmp_ = false;
  std::unique_ptr<ChainForwardDynamics<S>> parallel_;  // --fd parallel, made on first use
  std::vector<int> failed_;                             // (batch) its failed links
  bool fallback_ = false;                               // --fallback aba
  std::size_t fallbacks_ = 0;                           // instances the last fd run() fell back
  int threads_ = 1;
  std::unique_ptr<InverseDynamics<S>> id_;  // batched inverse dynamics
  std::vector<DataTpl<S>> data_;            // (threads) without the mass-matrix workspace
  std::vector<DataTpl<S>> jsi_;             // (threads) with it, for fd_jsi
};

template <class S>
std::unique_ptr<Evaluator<S>> make_openmp_evaluator(const ModelTpl<S>& model, const EvalOptions& options) {
  return std::make_unique<CpuEvaluator<S>>(model, BackendKind::OpenMP, options);
}

// The backends this command knows: name, evaluator factories, the algorithms they
// compute and the check that the machine can run them. Entries with null factories are recognised names that this
// build does not contain (they get a clear error, not "unknown").
const Backend kBackends[] = {
    {"serial", &make_serial_evaluator<double>, &make_serial_evaluator<float>, kEveryAlgo, nullptr},
#if SCANDYN_HAS_OPENMP && defined(_OPENMP)
    {"openmp", &make_openmp_evaluator<double>, &make_openmp_evaluator<float>, kEveryAlgo, nullptr},
#else
    {"openmp", nullptr, nullptr, kEveryAlgo, nullptr},
#endif
#if SCANDYN_HAS_CUDA
    {"cuda", &make_cuda_evaluator<double>, &make_cuda_evaluator<float>, kEveryAlgo, &cuda_unusable},
#else
    {"cuda", nullptr, nullptr, 0, nullptr},
#endif
};

}  // namespace

template <class S>
std::unique_ptr<Evaluator<S>> make_serial_evaluator(const ModelTpl<S>& model, const EvalOptions& options) {
  return std::make_unique<CpuEvaluator<S>>(model, BackendKind::Serial, options);
}
template std::unique_ptr<Evaluator<double>> make_serial_evaluator(const ModelTpl<double>&, const EvalOptions&);
template std::unique_ptr<Evaluator<float>> make_serial_evaluator(const ModelTpl<float>&, const EvalOptions&);

EvalOptions parse_eval_options(const Args& args) {
  EvalOptions o;
  try {
    if (args.has("strategy")) o.strategy = parse_strategy(args.required("strategy"));
  } catch (const BackendError& e) {
    throw UsageError(std::string("--strategy: ") + e.what());
  }
  if (args.has("threads")) {
    const std::string& t = args.required("threads");
    double v = 0;
    if (!parse_number(t, v) || v < 1 || v > 4096 || v != std::floor(v))
      throw UsageError("--threads must be an integer from 1 to 4096, got '" + t + "'");
    o.threads = static_cast<int>(v);
  }
  if (args.has("fd") && !parse_fd_method(args.required("fd"), o.fd))
    throw UsageError("unknown --fd value '" + args.required("fd") + "' (expected auto, aba, jsi, hybrid or parallel)");
  if (args.has("fallback")) {
    if (args.required("fallback") != "aba")
      throw UsageError("unknown --fallback value '" + args.required("fallback") + "' (expected aba)");
    if (o.fd != FdMethod::Jsi) throw UsageError("--fallback aba applies only to --fd jsi");
    o.fallback_aba = true;
  }
  return o;
}

std::string describe_fallbacks(std::size_t fell_back, std::size_t total, const char* unit) {
  return "forward dynamics by jsi failed on " + std::to_string(fell_back) + " of " + std::to_string(total) + " " +
         unit + " (mass matrix pivot not positive); " + (fell_back == 1 ? "it was" : "they were") +
         " computed by aba (--fallback aba)";
}

const Backend& find_backend(const std::string& name) {
  std::string known;
  for (const Backend& b : kBackends) {
    if (name == b.name) {
      if (!b.available())
        throw UsageError("backend '" + name + "' is not available in this build", false);
      return b;
    }
    known += known.empty() ? "" : ", ";
    known += b.name;
  }
  throw UsageError("unknown --backend value '" + name + "' (known: " + known + ")");
}

void require_algos(const Backend& backend, AlgoSet algos, const std::string& default_from) {
  const AlgoSet missing = algos & ~backend.algos;
  if (!missing) return;
  std::string msg = std::string("backend '") + backend.name + "' does not provide --algo " +
                    algo_list(missing, ",") + " (it provides: " + algo_list(backend.algos, ", ") + ")";
  if (!default_from.empty()) {
    msg += "; without --algo, " + algo_list(missing, ",") + (missing & (missing - 1) ? " were" : " was") +
           " selected because " + default_from + " has the input columns: choose with --algo";
    if (algos & backend.algos) msg += ", e.g. --algo " + algo_list(algos & backend.algos, ",");
  }
  throw UsageError(msg, false);
}

void require_usable(const Backend& backend) {
  if (!backend.unusable) return;
  const std::string why = backend.unusable();
  if (!why.empty()) throw UsageError(std::string("backend '") + backend.name + "': " + why, false);
}

}  // namespace scandyn::cli
