// src/cli/backend.cpp: the backend table and the serial reference backend.
#include "backend.hpp"

#include "cli.hpp"

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

const char* fd_method_name(FdMethod fd) { return fd == FdMethod::Aba ? "aba" : "jsi"; }

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
  for (FdMethod f : {FdMethod::Aba, FdMethod::Jsi}) {
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

std::string describe_fd_failure(FdMethod fd, const Status& status) {
  const char* what = fd == FdMethod::Aba ? "articulated inertia" : "mass matrix";
  return std::string(what) + " pivot at DoF " + std::to_string(status.failed_dof) +
         " is not positive";
}

// ---- serial reference backend -------------------------------------------------

namespace {

// Loops over the instances calling the serial reference algorithms with one
// preallocated DataTpl. Its nv x nv workspace, needed by fd_jsi alone, is
// allocated on the first JSI call (a 10^5-link rope would need 80 GB).
template <class S>
class SerialEvaluator final : public Evaluator<S> {
 public:
  explicit SerialEvaluator(const ModelTpl<S>& model) : model_(model), data_(model, false) {}

  BatchStatus run(Algo algo, FdMethod fd, const BatchIn<S>& in, S* out) override {
    const std::size_t n = static_cast<std::size_t>(model_.nv());
    const std::size_t width = output_width(algo, model_.nv());
    BatchStatus st;
    for (std::size_t b = 0; b < in.count; ++b) {
      const std::size_t k = b * n;
      S* o = out + b * width;
      switch (algo) {
        case Algo::Id: rnea(model_, data_, in.q + k, in.qd + k, in.qdd + k, o); break;
        case Algo::Bias: bias_forces(model_, data_, in.q + k, in.qd + k, o); break;
        case Algo::Mass: crba(model_, data_, in.q + k, o); break;
        case Algo::Fd:
          if (fd == FdMethod::Aba) {
            st.status = aba(model_, data_, in.q + k, in.qd + k, in.tau + k, o);
          } else {
            if (!jsi_data_) jsi_data_ = std::make_unique<DataTpl<S>>(model_, true);
            st.status = fd_jsi(model_, *jsi_data_, in.q + k, in.qd + k, in.tau + k, o);
          }
          if (!st.ok()) {
            st.instance = b;
            return st;
          }
          break;
      }
    }
    return st;
  }

 private:
  const ModelTpl<S>& model_;
  DataTpl<S> data_;                       // without the mass-matrix workspace
  std::unique_ptr<DataTpl<S>> jsi_data_;  // with it, for fd_jsi
};

// The backends this command knows. Entries with null factories are recognised
// names that this build does not contain (they get a clear error, not "unknown").
const Backend kBackends[] = {
    {"serial", &make_serial_evaluator<double>, &make_serial_evaluator<float>},
    {"openmp", nullptr, nullptr},
    {"cuda", nullptr, nullptr},
};

}  // namespace

template <class S>
std::unique_ptr<Evaluator<S>> make_serial_evaluator(const ModelTpl<S>& model) {
  return std::make_unique<SerialEvaluator<S>>(model);
}
template std::unique_ptr<Evaluator<double>> make_serial_evaluator(const ModelTpl<double>&);
template std::unique_ptr<Evaluator<float>> make_serial_evaluator(const ModelTpl<float>&);

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

}  // namespace scandyn::cli
