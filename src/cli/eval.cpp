// src/cli/eval.cpp: `scandyn eval`, dynamics of the states in a CSV file.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <type_traits>

#include "engines.hpp"
#include "hybrid.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "cli.hpp"
#include "kinematics_columns.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/io/states.hpp"

namespace scandyn::cli {
namespace {

constexpr Algo kAllAlgos[] = {Algo::Id, Algo::Fd, Algo::Mass, Algo::Bias, Algo::DId, Algo::DFd, Algo::D2Id};

// --algo id,fd,...: the requested set in output order (id, fd, mass, bias, did, dfd, d2id);
// fk and jac (kinematics, columns after the dynamics') set the flags.
std::vector<Algo> parse_algo_list(const std::string& list, bool& fk, bool& jac) {
  bool wanted[std::size(kAllAlgos)] = {};
  std::size_t start = 0;
  for (;;) {
    const std::size_t comma = list.find(',', start);
    const std::string item =
        list.substr(start, comma == std::string::npos ? std::string::npos : comma - start);
    Algo a;
    if (item == "fk" || item == "jac") {
      (item == "fk" ? fk : jac) = true;
    } else if (!parse_algo(item, a)) {
      throw UsageError("unknown --algo value '" + item +
                       "' (expected a comma-separated list of id, fd, mass, bias, did, dfd, d2id, fk, jac)");
    } else {
      wanted[static_cast<int>(a)] = true;
    }
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  std::vector<Algo> algos;
  for (Algo a : kAllAlgos)
    if (wanted[static_cast<int>(a)]) algos.push_back(a);
  return algos;
}

// Without --algo: each of id, fd, bias whose inputs are all in the file.
std::vector<Algo> default_algos(const StateColumns& cols, const std::string& source) {
  std::vector<Algo> algos;
  for (Algo a : {Algo::Id, Algo::Fd, Algo::Bias})
    if (cols.supports(a)) algos.push_back(a);
  if (algos.empty()) {
    // name the first missing column of each
    std::string lacks;
    for (Algo a : {Algo::Id, Algo::Fd, Algo::Bias}) {
      for (Family f : algo_inputs(a)) {
        const Index i = cols.first_missing(f);
        if (i < 0) continue;
        lacks += std::string(lacks.empty() ? "" : ", ") + algo_name(a) + " lacks column " + family_prefix(f) +
                 std::to_string(i);
        break;
      }
    }
    throw DataError(source + ": no algorithm has all its input columns: " + lacks +
                    " (id needs q, qd, qdd; fd needs q, qd, tau; bias needs q, qd; mass needs q and --algo mass)");
  }
  return algos;
}

std::string format_count(double x) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.4g", x);
  return buf;
}

// Rows are evaluated in chunks, so memory stays bounded for any file length.
constexpr std::size_t kMaxChunkRows = 4096;
std::size_t chunk_rows(std::size_t values_per_row) {
  constexpr std::size_t kValuesPerChunk = std::size_t(1) << 22;  // 32 MiB of doubles
  return std::clamp<std::size_t>(kValuesPerChunk / std::max<std::size_t>(values_per_row, 1), 1,
                                 kMaxChunkRows);
}

// Rows per chunk for this file and selection (kinematics_width: the fk and jac columns).
std::size_t chunk_rows(const CsvReader& in, const std::vector<Algo>& algos, Index nv, std::size_t kinematics_width) {
  std::size_t width = kinematics_width;
  for (Algo a : algos) width += output_width(a, nv);
  return chunk_rows(in.columns().size() + width + kFamilies * static_cast<std::size_t>(nv));
}

// Reads, evaluates and writes the rows in chunks of `chunk` rows (at most
// kMaxChunkRows, the engines' max_batch), whatever the backend.
// kin: the fk and jac columns, after the algorithms', or null.
template <class S>
void eval_rows(const ModelTpl<S>& model, std::vector<std::unique_ptr<AlgoEngine<S>>>& engines,
               KinematicsColumns<S>* kin, CsvReader& in, const StateColumns& cols, const std::vector<Algo>& algos,
               std::size_t chunk, CsvWriter& out, std::size_t& rows, std::size_t& fell_back, std::size_t& retried) {
  const std::size_t nv = static_cast<std::size_t>(model.nv()), nq = static_cast<std::size_t>(model.nq());
  const std::vector<Index> quaternions = quaternion_offsets(model);
  std::vector<std::string> names;
  std::vector<std::size_t> offset;  // start of each algo's block in an output row
  for (Algo a : algos) {
    offset.push_back(names.size());
    for (std::string& n : output_columns(a, model.nv())) names.push_back(std::move(n));
  }
  const std::size_t kin_offset = names.size();
  if (kin) names.insert(names.end(), kin->names().begin(), kin->names().end());
  out.write_header(names);
  const std::size_t width = names.size();

  bool needed[kFamilies] = {false, false, false, false};
  needed[static_cast<int>(Family::Q)] = kin != nullptr;
  for (Algo a : algos)
    for (Family f : algo_inputs(a)) needed[static_cast<int>(f)] = true;

  std::vector<S> input[kFamilies];
  for (int f = 0; f < kFamilies; ++f)
    if (needed[f]) input[f].resize(chunk * (f == static_cast<int>(Family::Q) ? nq : nv));
  std::vector<std::vector<S>> result(algos.size());
  for (std::size_t k = 0; k < algos.size(); ++k)
    result[k].resize(chunk * output_width(algos[k], model.nv()));
  std::vector<S> kin_result(kin ? chunk * kin->width() : 0);
  std::vector<double> row, out_row(width);

  for (bool more = true; more;) {
    // read and validate up to chunk rows
    const std::size_t row0 = in.row() + 1;
    std::size_t count = 0;
    while (count < chunk && (more = in.next_row(row))) {
      if (!quaternions.empty() && needed[static_cast<int>(Family::Q)])
        normalize_quaternions(cols, quaternions, row.data(), in.where());
      for (int f = 0; f < kFamilies; ++f)
        if (needed[f])
          gather_family(cols, static_cast<Family>(f), row.data(),
                        input[f].data() + count * (f == static_cast<int>(Family::Q) ? nq : nv));
      ++count;
    }
    if (count == 0) break;
    rows += count;

    // evaluate
    const auto family_data = [&](Family f) -> const S* {
      return needed[static_cast<int>(f)] ? input[static_cast<int>(f)].data() : nullptr;
    };
    BatchIn<S> batch;
    batch.count = count;
    batch.q = family_data(Family::Q);
    batch.qd = family_data(Family::Qd);
    batch.qdd = family_data(Family::Qdd);
    batch.tau = family_data(Family::Tau);
    for (std::size_t k = 0; k < algos.size(); ++k) {
      const BatchStatus st = engines[k]->run(batch, result[k].data());
      fell_back += static_cast<std::size_t>(st.fell_back);
      retried += static_cast<std::size_t>(st.retried);
      if (!st.ok())  // the pivot of the method used, or the run-time check
        throw DataError(in.where(row0 + static_cast<std::size_t>(st.first_instance)) +
                        ": " + (algos[k] == Algo::DFd ? "forward-dynamics derivatives" : "forward dynamics") +
                        " failed: " + st.reason() +
                        (st.failure == Failure::ResidualTooLarge
                             ? "; --fallback double (float) or aba (jsi) computes such rows again, --fd-check-tol "
                               "sets the threshold, --fd-check off accepts the result"
                             : ""));
    }
    if (kin) kin->run(batch.q, count, kin_result.data(), kin->width());

    // write
    for (std::size_t b = 0; b < count; ++b) {
      for (std::size_t k = 0; k < algos.size() + (kin ? 1 : 0); ++k) {
        const bool is_kin = k == algos.size();  // the fk and jac block, after the algorithms'
        const std::size_t w = is_kin ? kin->width() : output_width(algos[k], model.nv());
        const std::size_t first = is_kin ? kin_offset : offset[k];
        const S* src = (is_kin ? kin_result.data() : result[k].data()) + b * w;
        for (std::size_t j = 0; j < w; ++j) {
          const double v = static_cast<double>(src[j]);
          if (!std::isfinite(v)) {
            throw DataError(in.where(row0 + b) + ": result " + names[first + j] +
                            " is not finite (" +
                            (std::isnan(v) ? "NaN"
                             : v > 0       ? "Inf"
                                           : "-Inf") +
                            ")");
          }
          out_row[first + j] = v;
        }
      }
      out.write_row(out_row.data(), width);
    }
  }
}

// Makes the engines (before the output file exists, so that a backend that cannot
// run leaves nothing behind), then evaluates the file.
template <class S>
void eval_file(const ModelTpl<S>& model, BackendOptions options, CsvReader& in, const StateColumns& cols,
               const std::vector<Algo>& algos, const KinematicsRequest& kinematics, const std::string& out_path) {
  // the fk and jac columns: 7 per frame, and 6 nv per frame
  const std::size_t nframes = kinematics.options.frames.size();
  const std::size_t kin_width = (kinematics.fk ? 7 * nframes : 0) +
                                (kinematics.jac ? 6 * nframes * static_cast<std::size_t>(model.nv()) : 0);
  const std::size_t chunk = chunk_rows(in, algos, model.nv(), kin_width);
  // host memory before anything large: per output column its name, the output row
  // and the chunk's results; per input column the parsed row; the gathered inputs;
  // the engines' workspaces (the nv x nv mass matrix per thread for fd by jsi)
  {
    const std::size_t nv = static_cast<std::size_t>(model.nv());
    double width = double(kin_width);
    for (Algo a : algos) width += double(output_width(a, model.nv()));
    const double ncols = double(in.columns().size());
    const bool jsi = std::find(algos.begin(), algos.end(), Algo::Fd) != algos.end() &&
                     (options.fd_method == FdMethod::Jsi || options.fallback_aba);
    const int threads = backend_threads(options.backend, options.threads);
    const double bytes = width * (48 + 8 + double(chunk) * sizeof(S)) + ncols * 48 +
                         double(kFamilies) * double(chunk) * double(nv) * sizeof(S) +
                         workspace_bytes(nv, threads, jsi, sizeof(S));
    std::string list;
    for (Algo a : algos) list += std::string(list.empty() ? "" : ",") + algo_name(a);
    if (kinematics.fk) list += list.empty() ? "fk" : ",fk";
    if (kinematics.jac) list += list.empty() ? "jac" : ",jac";
    require_host_memory("eval --algo " + list + " on " + printable(model.source) + " (" + std::to_string(nv) +
                            " DoF, " + format_count(width) + " output columns per row)",
                        bytes);
  }
  // Engines are sized for this file's chunk: the CUDA link scans' scratch grows
  // with rows x links, and the auto strategies choose by it (a few rows of a long
  // chain: scans across links on OpenMP too).
  options.max_batch = static_cast<Index>(chunk);
  std::vector<std::unique_ptr<AlgoEngine<S>>> engines;
  for (Algo a : algos) engines.push_back(std::make_unique<AlgoEngine<S>>(a, model, options));
  std::unique_ptr<KinematicsColumns<S>> kin;
  if (kinematics.any()) kin = std::make_unique<KinematicsColumns<S>>(model, kinematics, options);
  CsvWriter out(out_path);
  std::size_t rows = 0, fell_back = 0, retried = 0;
  eval_rows(model, engines, kin.get(), in, cols, algos, chunk, out, rows, fell_back, retried);
  out.commit();
  if (fell_back) std::fprintf(stderr, "scandyn: warning: %s\n", describe_fallbacks(fell_back, rows, "rows").c_str());
  if (retried) std::fprintf(stderr, "scandyn: warning: %s\n", describe_check_retries(retried, rows, "rows").c_str());
}

}  // namespace

int run_eval(const Args& args) {
  if (args.get("algo", "") == "hybrid") return run_eval_hybrid(args);
  if (args.has("loops") || generator_has_loops(args.required("model"))) return run_eval_loops(args);
  if (args.has("actuated")) throw UsageError("--actuated applies only to models with loops (--loops FILE)");
  if (args.has("prescribed")) throw UsageError("--prescribed applies only to --algo hybrid");
  const std::string& model_spec = args.required("model");
  const std::string& states_path = args.required("states");
  const std::string& out_path = args.required("out");
  std::vector<Algo> algos;
  bool fk = false, jac = false;
  if (args.has("algo")) algos = parse_algo_list(args.required("algo"), fk, jac);
  // eval checks forward dynamics by default: its time goes to reading and writing CSV
  const BackendOptions options = parse_backend_options(args, FdCheckMode::On);
  const Precision precision = parse_cli_precision(args);
  require_usable(options.backend);

  const Model model = load_cli_model(args);
  if (model.nv() == 0) throw DataError(model_spec + ": the model has no degrees of freedom");

  const KinematicsRequest kinematics = parse_kinematics_request(args, model, fk, jac);

  CsvReader in(states_path);
  const StateColumns cols = map_state_columns(in.columns(), model.nq(), model.nv(), states_path);
  if (algos.empty() && !kinematics.any()) algos = default_algos(cols, states_path);
  check_state_columns(cols, algos, states_path);
  if (kinematics.any() && !cols.complete(Family::Q))
    throw DataError(states_path + ": missing column q_" + std::to_string(cols.first_missing(Family::Q)) +
                    " (fk and jac need q)");

  if (precision == Precision::Double) {
    eval_file<double>(model, options, in, cols, algos, kinematics, out_path);
  } else {
    const ModelTpl<float> model_f = model.cast<float>();
    eval_file<float>(model_f, options, in, cols, algos, kinematics, out_path);
  }
  return kExitOk;
}

}  // namespace scandyn::cli
