// src/cli/engines.cpp: the command line's algorithms on the library's engines.
#include "engines.hpp"

#include <array>
#include <cmath>
#include <stdexcept>

#include "cli.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/sharded.hpp"

namespace scandyn::cli {

namespace {

// parse(value of --flag), its BackendError as "--flag: unknown ..." (exit 2)
template <class F>
auto parse_flag(const Args& args, const char* flag, const char* fallback, F&& parse) {
  try {
    return parse(args.get(flag, fallback));
  } catch (const BackendError& e) {
    throw UsageError(std::string("--") + flag + ": " + e.what());
  }
}

}  // namespace

Precision parse_cli_precision(const Args& args) { return parse_flag(args, "precision", "double", parse_precision); }

BackendOptions parse_backend_options(const Args& args, FdCheckMode default_check) {
  BackendOptions o;
  o.backend = parse_flag(args, "backend", "serial", parse_backend);
  o.strategy = parse_flag(args, "strategy", "auto", parse_strategy);
  o.fd_method = parse_flag(args, "fd", "auto", parse_fd_method);
  o.simd = parse_flag(args, "simd", "auto", parse_cpu_simd);
  if (args.has("threads")) {
    const std::string& t = args.required("threads");
    double v = 0;
    if (!parse_number(t, v) || v < 1 || v > 4096 || v != std::floor(v))
      throw UsageError("--threads must be an integer from 1 to 4096, got '" + t + "'");
    o.threads = static_cast<int>(v);
  }
  if (args.has("fallback")) {
    // a comma-separated list of aba and double
    const std::string& list = args.required("fallback");
    for (std::size_t at = 0; at <= list.size();) {
      const std::size_t end = std::min(list.find(',', at), list.size());
      const std::string name = list.substr(at, end - at);
      if (name == "aba") {
        if (o.fd_method != FdMethod::Jsi) throw UsageError("--fallback aba applies only to --fd jsi");
        o.fallback_aba = true;
      } else if (name == "double") {
        if (parse_cli_precision(args) != Precision::Float)
          throw UsageError("--fallback double applies only to --precision float");
        o.fallback_double = true;
      } else {
        throw UsageError("unknown --fallback value '" + name + "' (expected aba, double or aba,double)");
      }
      at = end + 1;
    }
  }
  if (args.has("devices")) {
    o.devices = parse_flag(args, "devices", "current", parse_devices);
    if (!o.devices.empty() && o.backend != BackendKind::Cuda)
      throw UsageError("--devices applies only to --backend cuda (backend '" + std::string(to_string(o.backend)) + "')");
  }
  o.fd_check = default_check;
  if (args.has("fd-check")) o.fd_check = parse_flag(args, "fd-check", "auto", parse_fd_check);
  if (args.has("fd-check-tol")) {
    const std::string& t = args.required("fd-check-tol");
    double v = 0;
    if (!parse_number(t, v) || !(v > 0) || !std::isfinite(v))
      throw UsageError("--fd-check-tol must be a positive number, got '" + t + "'");
    (parse_cli_precision(args) == Precision::Float ? o.fd_check_tol_float : o.fd_check_tol_double) = v;
  }
  if (o.fallback_double && o.fd_check == FdCheckMode::Off)
    throw UsageError("--fallback double recomputes the rows the forward-dynamics check flags; it needs the check "
                     "(not --fd-check off)");
  return o;
}

void require_usable(BackendKind backend) {
  const std::string why = backend_unusable(backend);
  if (why.empty()) return;
  // a backend this build lacks already names itself; a device that is missing does not
  throw UsageError(why.rfind("backend '", 0) == 0 ? why : std::string("backend '") + to_string(backend) + "': " + why,
                   false);
}

std::string describe_check_retries(std::size_t retried, std::size_t total, const char* unit) {
  return "the forward-dynamics check flagged " + std::to_string(retried) + " of " + std::to_string(total) + " " +
         unit + " (estimated error of qdd above --fd-check-tol); " + (retried == 1 ? "it was" : "they were") +
         " computed again by the fallback (--fallback) and passed";
}

std::string describe_fallbacks(std::size_t fell_back, std::size_t total, const char* unit) {
  return "forward dynamics by jsi failed on " + std::to_string(fell_back) + " of " + std::to_string(total) + " " +
         unit + " (mass matrix pivot not positive); " + (fell_back == 1 ? "it was" : "they were") +
         " computed by aba (--fallback aba)";
}

// ---- AlgoEngine -----------------------------------------------------------------

namespace {

// The three blocks of did / dfd (nv x nv each) or of d2id (nv^3 each) in an
// instance-major output row of 3 n values (n = nv^2, nv^3): block k of instance b at
// out[b * 3 n + k n], row-major.
template <class S>
std::array<BatchView<S>, 3> derivative_blocks(S* out, Algo algo, Index nv, Index B) {
  const std::ptrdiff_t n = static_cast<std::ptrdiff_t>(output_width(algo, nv) / 3);
  std::array<BatchView<S>, 3> v;
  for (int k = 0; k < 3; ++k) v[k] = BatchView<S>{out + k * n, B, 1, 3 * n};
  return v;
}

}  // namespace

template <class S>
AlgoEngine<S>::AlgoEngine(Algo algo, const ModelTpl<S>& model, const BackendOptions& o)
    : algo_(algo), nv_(model.nv()), nq_(model.nq()) {
  try {
    switch (algo) {
      case Algo::Id: id_ = make_inverse_dynamics(model, o); break;
      case Algo::Bias: bias_ = make_bias_forces(model, o); break;
      case Algo::Mass: mass_ = make_mass_matrix(model, o); break;
      case Algo::Fd: fd_ = make_forward_dynamics(model, o); break;
      case Algo::DId: did_ = make_id_derivatives(model, o); break;
      case Algo::DFd: dfd_ = make_fd_derivatives(model, o); break;
      case Algo::D2Id: d2id_ = make_id_second_derivatives(model, o); break;
    }
  } catch (const BackendError& e) {
    // no device, a model beyond a kernel's limit, a method the model cannot take, no memory
    throw UsageError(algo == Algo::Fd ? std::string("--fd ") + to_string(o.fd_method) + ": " + e.what() : e.what(),
                     false);
  }
}

template <class S>
AlgoEngine<S>::~AlgoEngine() = default;

template <class S>
const Engine& AlgoEngine<S>::engine() const {
  if (id_) return *id_;
  if (bias_) return *bias_;
  if (mass_) return *mass_;
  if (did_) return *did_;
  if (dfd_) return *dfd_;
  if (d2id_) return *d2id_;
  return *fd_;
}

template <class S>
BatchStatus AlgoEngine<S>::run(const BatchIn<S>& in, S* out) {
  const Index B = static_cast<Index>(in.count), nv = nv_, nq = nq_;
  using V = BatchView<const S>;
  try {
    switch (algo_) {
      case Algo::Id:
        id_->compute(IdBatchIn<S>{V::aos(in.q, nq, B), V::aos(in.qd, nv, B), V::aos(in.qdd, nv, B)},
                     BatchView<S>::aos(out, nv, B));
        return {};
      case Algo::Bias:
        bias_->compute(BiasBatchIn<S>{V::aos(in.q, nq, B), V::aos(in.qd, nv, B)}, BatchView<S>::aos(out, nv, B));
        return {};
      case Algo::Mass:
        mass_->compute(V::aos(in.q, nq, B), BatchView<S>::aos(out, nv * nv, B));
        return {};
      case Algo::Fd:
        return fd_->compute(FdBatchIn<S>{V::aos(in.q, nq, B), V::aos(in.qd, nv, B), V::aos(in.tau, nv, B)},
                            BatchView<S>::aos(out, nv, B));
      case Algo::DId: {
        const auto block = derivative_blocks(out, algo_, nv, B);
        did_->compute(IdBatchIn<S>{V::aos(in.q, nq, B), V::aos(in.qd, nv, B), V::aos(in.qdd, nv, B)},
                      IdDerivativesOut<S>{block[0], block[1], block[2]});
        return {};
      }
      case Algo::DFd: {
        const auto block = derivative_blocks(out, algo_, nv, B);
        return dfd_->compute(FdBatchIn<S>{V::aos(in.q, nq, B), V::aos(in.qd, nv, B), V::aos(in.tau, nv, B)},
                             FdDerivativesOut<S>{block[0], block[1], block[2], {}});
      }
      case Algo::D2Id: {
        const auto block = derivative_blocks(out, algo_, nv, B);
        d2id_->compute(IdBatchIn<S>{V::aos(in.q, nq, B), V::aos(in.qd, nv, B), V::aos(in.qdd, nv, B)},
                       IdSecondDerivativesOut<S>{block[0], block[1], block[2], {}});
        return {};
      }
    }
  } catch (const BackendError& e) {
    throw DataError(e.what());  // a CUDA error during the computation
  }
  return {};
}

template <class S>
std::string AlgoEngine<S>::strategy() const {
  const Engine& e = engine();
  return e.strategy() + (e.backend() == BackendKind::Cuda ? "-host" : "");
}

template <class S>
bool AlgoEngine<S>::exact() const {
  // bench's fd reference is the serial aba
  return engine().exact() && (algo_ != Algo::Fd || fd_->method() == FdMethod::Aba);
}

template <class S>
std::unique_ptr<ResidentBatch<S>> AlgoEngine<S>::resident(const BatchIn<S>& in) {
#if SCANDYN_HAS_CUDA
  if (engine().backend() == BackendKind::Cuda)
    return make_resident_batch<S>(algo_, const_cast<Engine&>(engine()), nv_, nq_, in);
#endif
  (void)in;
  return nullptr;
}

template class AlgoEngine<float>;
template class AlgoEngine<double>;

}  // namespace scandyn::cli
