// src/cli/eval_hybrid.cpp: `scandyn eval --algo hybrid --prescribed LIST`: hybrid
// dynamics (Featherstone 2008, 9.2) of the states in a CSV file. The input reads
// q_<i>, qd_<i>, qdd_<i> at prescribed DoFs and tau_<i> at the others; the output
// has qdd_hd_<i> and tau_hd_<i> for every DoF (the given entries copied through).
#include "hybrid.hpp"

#include <algorithm>
#include <cmath>

#include "engines.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/io/states.hpp"

namespace scandyn::cli {

std::vector<unsigned char> parse_prescribed(const std::string& list, const Model& model, const std::string& flag) {
  const Index nv = model.nv();
  std::vector<unsigned char> mask(static_cast<std::size_t>(nv), 0);
  if (list.empty()) return mask;
  std::size_t start = 0;
  for (;;) {
    const std::size_t comma = list.find(',', start);
    const std::string item = list.substr(start, comma == std::string::npos ? std::string::npos : comma - start);
    if (item.empty()) throw UsageError("--" + flag + ": empty item in '" + printable(list) + "'");
    Index dof = -1;
    const auto name = std::find(model.joint_names.begin(), model.joint_names.end(), item);
    if (name != model.joint_names.end()) {
      dof = static_cast<Index>(name - model.joint_names.begin());
    } else if (item.find_first_not_of("0123456789") == std::string::npos && item.size() <= 9) {
      dof = static_cast<Index>(std::stol(item));
      if (dof >= nv)
        throw UsageError("--" + flag + ": DoF " + item + " is out of range (the model has " + std::to_string(nv) +
                         " DoF, 0 to " + std::to_string(nv - 1) + ")");
    } else {
      throw UsageError("--" + flag + ": '" + printable(item) + "' is neither a DoF index nor a joint of " +
                       printable(model.source) + " (scandyn info lists them)");
    }
    if (mask[static_cast<std::size_t>(dof)])
      throw UsageError("--" + flag + ": DoF " + std::to_string(dof) + " is listed twice");
    mask[static_cast<std::size_t>(dof)] = 1;
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  return mask;
}

namespace {

// Rows per chunk: the engines' max_batch, bounded memory for any file length.
constexpr std::size_t kChunkRows = 4096;

template <class S>
void eval_hybrid_file(const ModelTpl<S>& model, const std::vector<unsigned char>& mask, BackendOptions options,
                      CsvReader& in, const StateColumns& cols, const std::string& out_path) {
  const std::size_t nv = static_cast<std::size_t>(model.nv());
  const std::size_t chunk = std::clamp<std::size_t>((std::size_t(1) << 22) / (in.columns().size() + 6 * nv), 1,
                                                    kChunkRows);
  const int threads = backend_threads(options.backend, options.threads);
  require_host_memory("eval --algo hybrid on " + printable(model.source) + " (" + std::to_string(nv) + " DoF)",
                      double(chunk) * double(6 * nv) * sizeof(S) + double(in.columns().size()) * 56 +
                          workspace_bytes(nv, threads, false, sizeof(S)));
  options.max_batch = static_cast<Index>(chunk);
  std::unique_ptr<HybridDynamics<S>> engine;
  try {
    engine = make_hybrid_dynamics(model, mask, options);
  } catch (const BackendError& e) {
    throw UsageError(std::string("--algo hybrid: ") + e.what(), false);
  }
  CsvWriter out(out_path);
  std::vector<std::string> names;
  for (const char* prefix : {"qdd_hd_", "tau_hd_"})
    for (std::size_t i = 0; i < nv; ++i) names.push_back(prefix + std::to_string(i));
  out.write_header(names);

  // inputs and outputs, instance-major: q, qd, qdd, tau, qdd out, tau out
  std::vector<S> buf[6];
  for (auto& b : buf) b.assign(chunk * nv, S(0));
  std::vector<double> row, out_row(2 * nv);
  const std::vector<int>& qdd_col = cols.of(Family::Qdd);
  const std::vector<int>& tau_col = cols.of(Family::Tau);
  using V = BatchView<const S>;
  for (bool more = true; more;) {
    const std::size_t row0 = in.row() + 1;
    std::size_t count = 0;
    while (count < chunk && (more = in.next_row(row))) {
      gather_family(cols, Family::Q, row.data(), buf[0].data() + count * nv);
      gather_family(cols, Family::Qd, row.data(), buf[1].data() + count * nv);
      // the given entry of each DoF; the other stays 0 (not read)
      for (std::size_t i = 0; i < nv; ++i) {
        if (mask[i]) buf[2][count * nv + i] = static_cast<S>(row[static_cast<std::size_t>(qdd_col[i])]);
        else buf[3][count * nv + i] = static_cast<S>(row[static_cast<std::size_t>(tau_col[i])]);
      }
      ++count;
    }
    if (count == 0) break;
    const Index B = static_cast<Index>(count), n = model.nv();
    BatchStatus st;
    try {
      st = engine->compute(HybridBatchIn<S>{V::aos(buf[0].data(), n, B), V::aos(buf[1].data(), n, B),
                                            V::aos(buf[2].data(), n, B), V::aos(buf[3].data(), n, B)},
                           BatchView<S>::aos(buf[4].data(), n, B), BatchView<S>::aos(buf[5].data(), n, B));
    } catch (const BackendError& e) {
      throw DataError(e.what());
    }
    if (!st.ok())
      throw DataError(in.where(row0 + static_cast<std::size_t>(st.first_instance)) +
                      ": hybrid dynamics failed: " + st.reason());
    for (std::size_t b = 0; b < count; ++b) {
      for (std::size_t j = 0; j < 2 * nv; ++j) {
        const double v = static_cast<double>(j < nv ? buf[4][b * nv + j] : buf[5][b * nv + j - nv]);
        if (!std::isfinite(v))
          throw DataError(in.where(row0 + b) + ": result " + names[j] + " is not finite (" +
                          (std::isnan(v) ? "NaN" : v > 0 ? "Inf" : "-Inf") + ")");
        out_row[j] = v;
      }
      out.write_row(out_row.data(), 2 * nv);
    }
  }
  out.commit();
}

}  // namespace

int run_eval_hybrid(const Args& args) {
  const std::string& model_spec = args.required("model");
  const std::string& states_path = args.required("states");
  const std::string& out_path = args.required("out");
  if (!args.has("prescribed"))
    throw UsageError("--algo hybrid needs --prescribed LIST (DoF indices or joint names whose accelerations are given)");
  for (const char* f : {"fd", "fallback", "strategy"})
    if (args.has(f)) throw UsageError(std::string("--") + f + " does not apply to --algo hybrid");
  const BackendOptions options = parse_backend_options(args);
  const Precision precision = parse_cli_precision(args);
  require_usable(options.backend);
  const Model model = load_cli_model(args);
  if (model.nv() == 0) throw DataError(model_spec + ": the model has no degrees of freedom");
  try {
    require_one_dof_joints(model, "--algo hybrid");
  } catch (const BackendError& e) {
    throw UsageError(e.what(), false);
  }
  const std::vector<unsigned char> mask = parse_prescribed(args.required("prescribed"), model);

  CsvReader in(states_path);
  const StateColumns cols = map_state_columns(in.columns(), model.nv(), states_path);
  // q and qd complete; qdd at the prescribed DoFs, tau at the others
  for (Family f : {Family::Q, Family::Qd}) {
    const Index i = cols.first_missing(f);
    if (i >= 0)
      throw CsvError(states_path + ": missing column " + family_prefix(f) + std::to_string(i) +
                     " (needed by --algo hybrid)");
  }
  for (Index i = 0; i < model.nv(); ++i) {
    const bool given = mask[static_cast<std::size_t>(i)];
    if (cols.of(given ? Family::Qdd : Family::Tau)[static_cast<std::size_t>(i)] < 0)
      throw CsvError(states_path + ": missing column " + (given ? "qdd_" : "tau_") + std::to_string(i) +
                     " (needed by --algo hybrid: DoF " + std::to_string(i) + " is " +
                     (given ? "prescribed" : "not prescribed") + ")");
  }
  if (precision == Precision::Double) {
    eval_hybrid_file<double>(model, mask, options, in, cols, out_path);
  } else {
    const ModelTpl<float> model_f = model.cast<float>();
    eval_hybrid_file<float>(model_f, mask, options, in, cols, out_path);
  }
  return kExitOk;
}

}  // namespace scandyn::cli
