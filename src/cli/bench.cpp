// src/cli/bench.cpp: `scandyn bench`, times one algorithm on a batch of random
// states and prints one row of the benchmark CSV (DESIGN.md's columns) per way of
// calling the backend: the host-memory call, and for CUDA first the
// device-resident batch (every algorithm but --fd hybrid, which has the
// host-memory row only).
#include <unistd.h>

#include <algorithm>
#include <charconv>
#include <chrono>
#include <cmath>
#include <limits>
#include <cstdio>
#include <random>

#include "engines.hpp"
#include "hybrid.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "cli.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/accuracy.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/simulator.hpp"
#include "kinematics_columns.hpp"
#include "simulator_cli.hpp"

namespace scandyn::cli {
namespace {

constexpr const char* kBenchHeader =
    "algo,strategy,backend,precision,model,links,instances,seconds_per_call,evals_per_second,"
    "max_rel_err";
constexpr std::uint64_t kSeed = 42;                    // random states are repeatable

// The model column: a generator spec as given, a file's base name without ".urdf".
std::string model_label(const std::string& spec) {
  if (is_generator_spec(spec)) return spec;
  std::string base = spec.substr(spec.rfind('/') == std::string::npos ? 0 : spec.rfind('/') + 1);
  const std::string ext = ".urdf";
  if (base.size() > ext.size() && base.compare(base.size() - ext.size(), ext.size(), ext) == 0)
    base.resize(base.size() - ext.size());
  return base;
}

std::size_t parse_instances(const std::string& text) {
  unsigned long long v = 0;
  const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
  if (ec != std::errc() || ptr != text.data() + text.size() || v < 1 || v > 1000000000)
    throw UsageError("--instances must be an integer from 1 to 1e9, got '" + text + "'");
  return static_cast<std::size_t>(v);
}

double parse_min_time(const std::string& text) {
  double v = 0;
  if (!parse_number(text, v) || !std::isfinite(v) || v < 0)
    throw UsageError("--min-time must be a number of seconds >= 0, got '" + text + "'");
  return v;
}

std::string format_g(double x, int digits) {
  char buf[40];
  std::snprintf(buf, sizeof buf, "%.*g", digits, x);
  return buf;
}

// Random inputs of the benchmark, in double: q (count x nq), qd, then qdd (used as
// tau for fd) (count x nv each), uniform in [-1, 1], drawn in that order from one
// seeded stream; the quaternions in q (at quaternions, from quaternion_offsets)
// normalised.
struct RandomStates {
  std::size_t nq = 0, nv = 0;
  std::vector<double> q, qd, third;
  RandomStates(std::size_t count, std::size_t nq_, std::size_t nv_, const std::vector<Index>& quaternions)
      : nq(nq_), nv(nv_) {
    std::mt19937_64 rng(kSeed);
    std::uniform_real_distribution<double> uniform(-1.0, 1.0);
    for (std::vector<double>* v : {&q, &qd, &third}) {
      v->resize(count * (v == &q ? nq : nv));
      for (double& x : *v) x = uniform(rng);
    }
    for (std::size_t b = 0; b < count; ++b)
      for (Index k : quaternions) {
        double* x = q.data() + b * nq + static_cast<std::size_t>(k);
        const double n = std::sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2] + x[3] * x[3]);
        for (int j = 0; j < 4; ++j) x[j] /= n;
      }
  }
};

template <class S>
BatchIn<S> make_batch(Algo algo, std::size_t count, const std::vector<S>& q,
                      const std::vector<S>& qd, const std::vector<S>& third) {
  BatchIn<S> in;
  in.count = count;
  in.q = q.data();
  if (algo != Algo::Mass) in.qd = qd.data();
  if (algo == Algo::Id || algo == Algo::DId || algo == Algo::D2Id) in.qdd = third.data();
  if (algo == Algo::Fd || algo == Algo::DFd) in.tau = third.data();
  return in;
}

// A failed pivot is an error; the forward-dynamics check's flags are a warning (the
// row's max_rel_err shows the error; instances whose pivot failed too are caught as
// outputs that are not finite).
void check(const BatchStatus& st) {
  if (!st.ok() && st.failure == Failure::ResidualTooLarge) {
    std::fprintf(stderr, "scandyn: warning: bench: %s\n", st.message().c_str());
    return;
  }
  if (!st.ok())
    throw DataError("bench: instance " + std::to_string(st.first_instance) + ": forward dynamics failed: " +
                    st.reason());
}

// Every output value must be finite: the first that is not is an error naming the
// instance and the output (random states in [-1, 1] on a valid model: a non-finite
// result means the model or the precision overflows).
template <class S>
void check_finite_outputs(Algo algo, Index nv, const std::vector<S>& out, std::size_t count, const std::string& row) {
  const std::size_t w = output_width(algo, nv);
  for (std::size_t b = 0; b < count; ++b)
    for (std::size_t j = 0; j < w; ++j) {
      const double v = static_cast<double>(out[b * w + j]);
      if (std::isfinite(v)) continue;
      throw DataError("bench: instance " + std::to_string(b) + ": result " + output_columns(algo, nv).at(j) +
                      " is not finite (" + (std::isnan(v) ? "NaN" : v > 0 ? "Inf" : "-Inf") + ") in the " + row +
                      " call; nothing printed");
    }
}

// One row of results: a way of calling the backend, its time and error.
struct Timing {
  std::string strategy;  // as the engine reports it
  double seconds_per_call = 0;
  double max_rel_err = 0;
};

// Instances compared with the serial double reference: every one up to this many,
// beyond it this many spread evenly over the batch (every stride-th: each device's
// shard of a sharded engine included), so that a 2x10^7 batch's row does not spend
// minutes in the reference.
constexpr std::size_t kMaxComparedInstances = 1000000;
// The same for d2id, whose reference costs 2 nv first-order passes per instance (60
// us for iiwa, 150 us for hyq on one core): 10^4 instances keep a row's comparison
// within seconds.
constexpr std::size_t kMaxComparedSecondOrder = 10000;

// max over instances of max_i |x_i - ref_i| / max(1, max_i |ref_i|); NaN if any x is NaN.
double max_rel_err_vs_reference(const Model& model, Algo algo, const RandomStates& states,
                                std::size_t count, const std::vector<double>& x) {
  const std::size_t nv = static_cast<std::size_t>(model.nv());
  const std::size_t width = output_width(algo, model.nv());
  BackendOptions serial;
  serial.fd_method = algo == Algo::Fd ? FdMethod::Aba : FdMethod::Auto;
  AlgoEngine<double> reference(algo, model, serial);
  std::vector<double> ref(width);
  double worst = 0;
  const std::size_t compared = algo == Algo::D2Id ? kMaxComparedSecondOrder : kMaxComparedInstances;
  const std::size_t stride = (count + compared - 1) / compared;
  for (std::size_t b = 0; b < count; b += stride) {
    BatchIn<double> in = make_batch(algo, 1, states.q, states.qd, states.third);
    const std::size_t k = b * nv;
    in.q += b * states.nq;
    if (in.qd) in.qd += k;
    if (in.qdd) in.qdd += k;
    if (in.tau) in.tau += k;
    check(reference.run(in, ref.data()));
    const double e = rel_err(x.data() + b * width, ref.data(), width);
    if (std::isnan(e)) return e;
    worst = std::max(worst, e);
  }
  return worst;
}

// Seconds per call: calls(n) makes n calls and returns when all are complete. After
// a first call, calls go in rounds sized from the time per call so far (at most
// doubling), until min_time seconds have passed, so that the clock (and a device's
// synchronisation) is read rarely when calls are short.
template <class F>
double time_calls(double min_time, F&& calls) {
  using Clock = std::chrono::steady_clock;
  std::size_t done = 0, n = 1;
  double elapsed = 0;
  const Clock::time_point t0 = Clock::now();
  for (;;) {
    calls(n);
    done += n;
    elapsed = std::chrono::duration<double>(Clock::now() - t0).count();
    if (elapsed >= min_time && elapsed > 0) break;
    const double per_call = elapsed / static_cast<double>(done);
    const double wanted = per_call > 0 ? (min_time - elapsed) / per_call + 1 : 2.0 * n;
    n = static_cast<std::size_t>(std::clamp(wanted, 1.0, 2.0 * n));
  }
  return elapsed / static_cast<double>(done);
}

// A device-resident batch's row: a warm-up call, then rounds of queued calls, each
// round waited for; check_status sees the warm-up's and the last call's status; the
// last call's results are read into out (max_rel_err is the caller's).
template <class S, class Check>
Timing time_resident(ResidentBatch<S>& r, double min_time, Check&& check_status, S* out) {
  r.launch();
  check_status(r.status());
  Timing t;
  t.strategy = r.strategy();
  t.seconds_per_call = time_calls(min_time, [&](std::size_t n) {
    for (std::size_t k = 0; k < n; ++k) r.launch();
    r.wait();
  });
  check_status(r.status());
  r.read(out);
  return t;
}

// Times algo on the batch: a row for the engine's run() on host memory and,
// first, one for the batch in the backend's own memory when it has one (CUDA;
// resident() is null otherwise). A forward dynamics that fails is an error in
// either row: checked after the warm-up call (before any timing) and, for the
// resident batch, again on the last timed call's results, whose error the row
// reports.
template <class S>
std::vector<Timing> time_algo(const Model& model, const ModelTpl<S>& model_s, BackendOptions options, Algo algo,
                              const RandomStates& states, std::size_t count, double min_time, bool float_precision) {
  const std::vector<S> q(states.q.begin(), states.q.end());
  const std::vector<S> qd(states.qd.begin(), states.qd.end());
  const std::vector<S> third(states.third.begin(), states.third.end());
  std::vector<S> out(count * output_width(algo, model.nv()));
  const BatchIn<S> in = make_batch(algo, count, q, qd, third);
  options.max_batch = static_cast<Index>(count);
  AlgoEngine<S> engine(algo, model_s, options);
  // float always differs from the double reference; double only off the reference's path
  const bool measure = float_precision || !engine.exact();
  auto error = [&] {
    return measure ? max_rel_err_vs_reference(model, algo, states, count, std::vector<double>(out.begin(), out.end()))
                   : 0.0;
  };
  // a failed forward dynamics, named by the method used
  const auto check_fd = [](const BatchStatus& st) { check(st); };
  std::vector<Timing> rows;

  if (std::unique_ptr<ResidentBatch<S>> resident = engine.resident(in)) {
    Timing t = time_resident(*resident, min_time, check_fd, out.data());
    check_finite_outputs(algo, model.nv(), out, count, "device-resident");
    t.max_rel_err = error();
    rows.push_back(t);
  }  // (device memory of the resident batch released here)

  // warm-up call, then whole calls until min_time has passed
  std::fill(out.begin(), out.end(), std::numeric_limits<S>::quiet_NaN());  // untouched entries show
  const BatchStatus first = engine.run(in, out.data());
  check_fd(first);
  if (first.fell_back)
    std::fprintf(stderr, "scandyn: warning: %s\n",
                 describe_fallbacks(static_cast<std::size_t>(first.fell_back), count, "instances").c_str());
  if (first.retried)
    std::fprintf(stderr, "scandyn: warning: %s\n",
                 describe_check_retries(static_cast<std::size_t>(first.retried), count, "instances").c_str());
  Timing t;
  t.strategy = engine.strategy();
  t.seconds_per_call = time_calls(min_time, [&](std::size_t n) {
    for (std::size_t k = 0; k < n; ++k) engine.run(in, out.data());
  });
  check_finite_outputs(algo, model.nv(), out, count, "host");
  t.max_rel_err = error();
  rows.push_back(t);
  return rows;
}

// ---- --algo fk, jac ------------------------------------------------------------

// Times the frame poses (fk) or Jacobians (jac) of --frames (default every frame) on
// the batch, as time_algo does: a device-resident row first on cuda, then the
// engine on host memory. The error is against the serial double engine.
template <class S>
std::vector<Timing> time_kinematics(const Model& model, const ModelTpl<S>& model_s, BackendOptions options,
                                    const KinematicsRequest& request, const RandomStates& states,
                                    std::size_t count, double min_time, bool float_precision) {
  const std::vector<S> q(states.q.begin(), states.q.end());
  options.max_batch = static_cast<Index>(count);
  KinematicsColumns<S> columns(model_s, request, options);
  const std::size_t width = columns.width();
  std::vector<S> out(count * width);
  const bool measure = float_precision || !columns.engine().exact();
  const auto error = [&] {
    if (!measure) return 0.0;
    KinematicsColumns<double> reference(model, request, BackendOptions{});
    std::vector<double> ref(width);
    double worst = 0;
    for (std::size_t b = 0; b < count; ++b) {
      reference.run(states.q.data() + b * static_cast<std::size_t>(model.nv()), 1, ref.data(), width);
      const std::vector<double> x(out.begin() + b * width, out.begin() + (b + 1) * width);
      const double e = rel_err(x.data(), ref.data(), width);
      if (std::isnan(e)) return e;
      worst = std::max(worst, e);
    }
    return worst;
  };
  const auto check_finite = [&](const char* row) {
    for (std::size_t k = 0; k < out.size(); ++k)
      if (!std::isfinite(static_cast<double>(out[k])))
        throw DataError("bench: instance " + std::to_string(k / width) + ": result " + columns.names()[k % width] +
                        " is not finite in the " + row + " call; nothing printed");
  };
  std::vector<Timing> rows;
#if SCANDYN_HAS_CUDA
  if (options.backend == BackendKind::Cuda) {
    std::unique_ptr<ResidentBatch<S>> resident = make_resident_kinematics(
        columns.engine(), model.nv(), q.data(), count, columns.fk_width(), columns.jac_width());
    resident->launch();
    Timing t;
    t.strategy = resident->strategy();
    t.seconds_per_call = time_calls(min_time, [&](std::size_t n) {
      for (std::size_t k = 0; k < n; ++k) resident->launch();
      resident->wait();
    });
    resident->read(out.data());
    check_finite("device-resident");
    t.max_rel_err = error();
    rows.push_back(t);
  }
#endif
  std::fill(out.begin(), out.end(), std::numeric_limits<S>::quiet_NaN());
  columns.run(q.data(), count, out.data(), width);  // warm-up
  Timing t;
  t.strategy = columns.engine().strategy() + (options.backend == BackendKind::Cuda ? "-host" : "");
  t.seconds_per_call = time_calls(min_time, [&](std::size_t n) {
    for (std::size_t k = 0; k < n; ++k) columns.run(q.data(), count, out.data(), width);
  });
  check_finite("host");
  t.max_rel_err = error();
  rows.push_back(t);
  return rows;
}

// ---- --algo step ---------------------------------------------------------------

// Steps compared with the double serial reference for max_rel_err, and the most
// instances compared.
constexpr int kStepErrSteps = 10;
constexpr Index kStepErrInstances = 1000;

// q and qd of the first count instances, instance-major (count x (nq + nv)).
template <class S>
std::vector<double> state_rows(sim::Simulator<S>& s, Index count) {
  const std::size_t n = static_cast<std::size_t>(s.nv()), nq = static_cast<std::size_t>(s.nq());
  const std::size_t B = static_cast<std::size_t>(s.batch()), w = nq + n;
  std::vector<S> q(nq * B), qd(n * B);
  s.read_state(q.data(), qd.data());
  std::vector<double> rows(static_cast<std::size_t>(count) * w);
  for (std::size_t b = 0; b < static_cast<std::size_t>(count); ++b) {
    for (std::size_t i = 0; i < nq; ++i) rows[b * w + i] = q[i * B + b];
    for (std::size_t i = 0; i < n; ++i) rows[b * w + nq + i] = qd[i * B + b];
  }
  return rows;
}

template <class S>
Timing time_steps(const sim::Scene& scene, BackendKind backend, double min_time) {
  const std::unique_ptr<sim::Simulator<S>> made =
      make_simulator<S>(scene, backend, 2.0 * double(scene.instances) * double(scene.nv()) * sizeof(S));
  sim::Simulator<S>& s = *made;
  // error: the first instances after kStepErrSteps steps against the double serial reference
  const Index count = std::min<Index>(s.batch(), kStepErrInstances);
  for (int k = 0; k < kStepErrSteps; ++k) s.step();
  const std::vector<double> x = state_rows(s, count);
  sim::Scene ref_scene = scene;
  ref_scene.instances = count;
  ref_scene.devices.clear();  // the reference runs on the host
  sim::Simulator<double> ref(ref_scene, BackendKind::Serial);
  for (int k = 0; k < kStepErrSteps; ++k) ref.step();
  const std::vector<double> r = state_rows(ref, count);
  const std::size_t nq = static_cast<std::size_t>(s.nq()), w = nq + static_cast<std::size_t>(s.nv());
  if (!s.status().ok() || !ref.status().ok())
    throw DataError(scene.path + ": " + sim::failure_message(s.status().ok() ? ref.status() : s.status()));
  for (const auto* rows : {&x, &r}) {
    for (std::size_t k = 0; k < rows->size(); ++k) {
      if (std::isfinite((*rows)[k])) continue;
      const std::size_t b = k / w, j = k % w;
      throw DataError(scene.path + ": step " + std::to_string(kStepErrSteps) + ": the state is not finite in instance " +
                      std::to_string(b) + " (" + (j < nq ? "q_" : "qd_") + std::to_string(j < nq ? j : j - nq) + " = " +
                      (std::isnan((*rows)[k]) ? "nan" : (*rows)[k] > 0 ? "inf" : "-inf") + ", " +
                      (rows == &x ? "the benchmarked simulator" : "the double serial reference") +
                      "; the simulation overflowed); nothing printed");
    }
  }
  Timing t;
  for (Index b = 0; b < count; ++b) {
    const double e = rel_err(x.data() + b * w, r.data() + b * w, w);
    t.max_rel_err = std::isnan(e) || std::isnan(t.max_rel_err) ? NAN : std::max(t.max_rel_err, e);
  }
  // timing: whole steps of all instances, synchronised after each round
  s.step();
  s.synchronize();
  t.seconds_per_call = time_calls(min_time, [&](std::size_t n) {
    for (std::size_t k = 0; k < n; ++k) s.step();
    s.synchronize();
  });
  t.strategy = s.strategy() + ":" + sim::to_string(s.setup().integrator) + ":" + sim::effect_names(scene.effects);
  return t;
}

int run_bench_step(const Args& args) {
  if (args.has("model")) throw UsageError("--algo step takes --scene, not --model");
  for (const char* f : {"fd", "strategy", "threads"})
    if (args.has(f)) throw UsageError(std::string("--") + f + " does not apply to --algo step");
  const std::string& scene_path = args.required("scene");
  const double min_time = parse_min_time(args.get("min-time", "0.5"));
  sim::Scene scene;
  try {
    scene = sim::load_scene(scene_path);
  } catch (const sim::SceneError& e) {
    throw DataError(e.what());
  }
  if (args.has("instances")) scene.instances = static_cast<Index>(parse_instances(args.required("instances")));
  const BackendKind backend = scene_backend(scene, args);
  scene_devices(scene, backend, args);
  if (args.has("precision"))
    scene.precision = parse_cli_precision(args);
  const Timing t = scene.precision == Precision::Float ? time_steps<float>(scene, backend, min_time)
                                                            : time_steps<double>(scene, backend, min_time);
  const std::string row = std::string("step,") + t.strategy + "," + to_string(backend) + "," +
                          to_string(scene.precision) + "," + model_label(scene.model_spec) + "," +
                          std::to_string(scene.nv()) + "," + std::to_string(scene.instances) + "," +
                          format_g(t.seconds_per_call, 6) + "," + format_g(double(scene.instances) / t.seconds_per_call, 6) +
                          "," + format_g(t.max_rel_err, 6);
  if (args.has("csv")) append_csv_line(args.required("csv"), kBenchHeader, row);
  if (::isatty(STDOUT_FILENO)) std::puts(kBenchHeader);
  std::puts(row.c_str());
  return kExitOk;
}

// ---- --algo hybrid -------------------------------------------------------------

// The hybrid dynamics on the states' q, qd and third (qdd at prescribed DoFs, tau at
// the others), timed on host memory; max_rel_err of [qdd, tau] per instance against
// the double serial engine (0 for the serial double engine, which is that reference).
template <class S>
Timing time_hybrid(const Model& model, const ModelTpl<S>& model_s, const std::vector<unsigned char>& mask,
                   BackendOptions options, const RandomStates& states, std::size_t count, double min_time) {
  const Index n = model.nv(), B = static_cast<Index>(count);
  const std::size_t nv = static_cast<std::size_t>(n);
  const std::vector<S> q(states.q.begin(), states.q.end()), qd(states.qd.begin(), states.qd.end());
  const std::vector<S> third(states.third.begin(), states.third.end());
  std::vector<S> qdd(count * nv, std::numeric_limits<S>::quiet_NaN()), tau(qdd);
  options.max_batch = B;
  std::unique_ptr<HybridDynamics<S>> engine;
  try {
    engine = make_hybrid_dynamics(model_s, mask, options);
  } catch (const BackendError& e) {
    throw UsageError(std::string("--algo hybrid: ") + e.what(), false);
  }
  using V = BatchView<const S>;
  const HybridBatchIn<S> in{V::aos(q.data(), n, B), V::aos(qd.data(), n, B), V::aos(third.data(), n, B),
                            V::aos(third.data(), n, B)};
  const auto run = [&] {
    const BatchStatus st = engine->compute(in, BatchView<S>::aos(qdd.data(), n, B), BatchView<S>::aos(tau.data(), n, B));
    if (!st.ok())
      throw DataError("bench: instance " + std::to_string(st.first_instance) + ": hybrid dynamics failed: " +
                      st.reason());
  };
  run();
  Timing t;
  t.strategy = engine->strategy() + (engine->backend() == BackendKind::Cuda ? "-host" : "");
  t.seconds_per_call = time_calls(min_time, [&](std::size_t calls) {
    for (std::size_t k = 0; k < calls; ++k) run();
  });
  if (std::is_same<S, double>::value && engine->exact()) return t;
  Data d(model, false);
  std::vector<double> x(2 * nv), ref(2 * nv);
  for (std::size_t b = 0; b < count; ++b) {
    const std::size_t k = b * nv;
    const Status st = hybrid_dynamics(model, d, &states.q[k], &states.qd[k], mask.data(), &states.third[k],
                                      &states.third[k], ref.data(), ref.data() + nv);
    if (!st.ok()) throw DataError("bench: instance " + std::to_string(b) + ": the reference hybrid dynamics failed");
    for (std::size_t i = 0; i < nv; ++i) x[i] = double(qdd[k + i]), x[nv + i] = double(tau[k + i]);
    const double e = rel_err(x.data(), ref.data(), 2 * nv);
    t.max_rel_err = std::isnan(e) || std::isnan(t.max_rel_err) ? NAN : std::max(t.max_rel_err, e);
  }
  return t;
}

int run_bench_hybrid(const Args& args) {
  for (const char* f : {"fd", "fallback", "strategy", "scene"})
    if (args.has(f)) throw UsageError(std::string("--") + f + " does not apply to --algo hybrid");
  if (!args.has("prescribed"))
    throw UsageError("--algo hybrid needs --prescribed LIST (DoF indices or joint names whose accelerations are given)");
  const std::string& model_spec = args.required("model");
  const std::size_t count = parse_instances(args.required("instances"));
  const BackendOptions options = parse_backend_options(args);
  const Precision precision = parse_cli_precision(args);
  const double min_time = parse_min_time(args.get("min-time", "0.5"));
  require_usable(options.backend);
  const Model model = load_cli_model(args);
  if (model.nv() == 0) throw DataError(model_spec + ": the model has no degrees of freedom");
  try {
    require_one_dof_joints(model, "bench --algo hybrid");
  } catch (const BackendError& e) {
    throw UsageError(e.what(), false);
  }
  const std::vector<unsigned char> mask = parse_prescribed(args.required("prescribed"), model);
  const std::size_t nv = static_cast<std::size_t>(model.nv()), scalar = precision == Precision::Float ? 4 : 8;
  require_host_memory("bench --algo hybrid on " + printable(model_spec) + " (" + std::to_string(nv) + " DoF), " +
                          std::to_string(count) + " instances in " + to_string(precision),
                      double(count) * nv * (3.0 * 8 + 5.0 * scalar) +
                          workspace_bytes(nv, backend_threads(options.backend, options.threads), false, scalar) +
                          workspace_bytes(nv, 1, false, 8));
  const RandomStates states(count, nv, nv, {});  // 1-DoF models: make_hybrid_dynamics refuses the others
  const Timing t = precision == Precision::Double
                       ? time_hybrid<double>(model, model, mask, options, states, count, min_time)
                       : time_hybrid<float>(model, model.cast<float>(), mask, options, states, count, min_time);
  const std::string row = "hybrid," + t.strategy + "," + to_string(options.backend) + "," + to_string(precision) +
                          "," + model_label(model_spec) + "," + std::to_string(nv) + "," + std::to_string(count) +
                          "," + format_g(t.seconds_per_call, 6) + "," +
                          format_g(double(count) / t.seconds_per_call, 6) + "," + format_g(t.max_rel_err, 6);
  if (args.has("csv")) append_csv_line(args.required("csv"), kBenchHeader, row);
  if (::isatty(STDOUT_FILENO)) std::puts(kBenchHeader);
  std::puts(row.c_str());
  return kExitOk;
}

// ---- models with closed loops ----------------------------------------------------

// The closed-loop forward dynamics (ConstrainedForwardDynamics) of `count` instances
// tiling kLoopStates random closed states (q near 0 projected onto the loops, qd in
// J's null space, tau in [-1, 1]); rows as time_algo's: on cuda first the
// device-resident batch, then the host-memory call. max_rel_err: [qdd, lambda] of the
// first kLoopStates instances against the Eigen reference constrained_forward_dynamics.
constexpr std::size_t kLoopStates = 256;

template <class S>
std::vector<Timing> time_loops(const Model& model, const LoopSet& loops, BackendOptions options, std::size_t count,
                               double min_time) {
  const Index n = model.nv(), m = loops.rows();
  const std::size_t nv = static_cast<std::size_t>(n), w = nv + static_cast<std::size_t>(m);
  std::mt19937_64 rng(42);
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<double> q0(kLoopStates * nv), qd0(q0.size()), tau0(q0.size());
  for (std::size_t k = 0; k < kLoopStates; ++k) {
    double r = 1;
    for (int attempt = 0; attempt < 50 && r > 1e-12; ++attempt) {
      for (std::size_t i = 0; i < nv; ++i) q0[k * nv + i] = 0.2 * u(rng), qd0[k * nv + i] = u(rng);
      r = project_to_loops(model, loops, &q0[k * nv], &qd0[k * nv]);
    }
    if (r > 1e-12) throw DataError("bench: no closed state found for the loops of " + printable(model.source));
    for (std::size_t i = 0; i < nv; ++i) tau0[k * nv + i] = u(rng);
  }
  std::vector<S> q(count * nv), qd(q.size()), tau(q.size()), out(count * w);
  for (std::size_t b = 0; b < count; ++b)
    for (std::size_t i = 0; i < nv; ++i) {
      const std::size_t k = (b % kLoopStates) * nv + i;
      q[b * nv + i] = S(q0[k]), qd[b * nv + i] = S(qd0[k]), tau[b * nv + i] = S(tau0[k]);
    }
  options.max_batch = static_cast<Index>(count);
  const ModelTpl<S> model_s = model.cast<S>();
  std::unique_ptr<ConstrainedForwardDynamics<S>> engine;
  try {
    engine = make_constrained_forward_dynamics<S>(model_s, loops, options);
  } catch (const BackendError& e) {
    throw UsageError(std::string("closed loops: ") + e.what(), false);
  }
  const Index B = static_cast<Index>(count);
  using V = BatchView<const S>;
  const FdBatchIn<S> in{V::aos(q.data(), n, B), V::aos(qd.data(), n, B), V::aos(tau.data(), n, B), nullptr};
  // rows of nv qdd then m lambda per instance
  const BatchView<S> qdd{out.data(), B, 1, static_cast<std::ptrdiff_t>(w)};
  const BatchView<S> lambda{out.data() + nv, B, 1, static_cast<std::ptrdiff_t>(w)};
  auto fail = [&](const BatchStatus& st) {
    if (!st.ok()) throw DataError("bench: closed-loop forward dynamics failed: " + st.message());
  };
  auto error = [&] {
    double worst = 0;
    std::vector<double> ref(w), x(w);
    for (std::size_t b = 0; b < std::min(count, kLoopStates); ++b) {
      std::vector<double> qb(nv), qdb(nv), tb(nv);
      for (std::size_t i = 0; i < nv; ++i)
        qb[i] = double(q[b * nv + i]), qdb[i] = double(qd[b * nv + i]), tb[i] = double(tau[b * nv + i]);
      constrained_forward_dynamics(model, loops, qb.data(), qdb.data(), tb.data(), ref.data(), ref.data() + nv);
      for (std::size_t i = 0; i < w; ++i) x[i] = double(out[b * w + i]);
      const double e = rel_err(x.data(), ref.data(), w);
      if (std::isnan(e)) return e;
      worst = std::max(worst, e);
    }
    return worst;
  };
  std::vector<Timing> rows;
#if SCANDYN_HAS_CUDA
  if (engine->backend() == BackendKind::Cuda) {
    std::unique_ptr<ResidentBatch<S>> r = make_resident_loops(*engine, n, q.data(), qd.data(), tau.data(), count);
    Timing t = time_resident(*r, min_time, fail, out.data());
    t.max_rel_err = error();
    rows.push_back(t);
  }
#endif
  fail(engine->compute(in, qdd, lambda));
  Timing t;
  t.strategy = engine->strategy() + (engine->backend() == BackendKind::Cuda ? "-host" : "");
  t.seconds_per_call = time_calls(min_time, [&](std::size_t calls) {
    for (std::size_t k = 0; k < calls; ++k) fail(engine->compute(in, qdd, lambda));
  });
  t.max_rel_err = error();
  rows.push_back(t);
  return rows;
}

// `scandyn bench --model fivebar --algo fd ...` (a generator with loops, or --loops
// FILE): the closed-loop forward dynamics, one row per way of calling the backend.
int run_bench_loops(const Args& args) {
  for (const char* f : {"fd", "fallback", "strategy", "scene", "prescribed", "actuated"})
    if (args.has(f)) throw UsageError(std::string("--") + f + " does not apply to bench with loops");
  const std::string algo = args.get("algo", "fd");
  if (algo != "fd") throw UsageError("--algo " + algo + ": with loops, bench times fd (constrained forward dynamics)");
  const std::string& model_spec = args.required("model");
  const std::size_t count = parse_instances(args.required("instances"));
  const BackendOptions options = parse_backend_options(args);
  const Precision precision = parse_cli_precision(args);
  const double min_time = parse_min_time(args.get("min-time", "0.5"));
  require_usable(options.backend);
  const Model model = load_cli_model(args);
  const LoopSet loops = load_cli_loops(args, model);
  const std::size_t nv = static_cast<std::size_t>(model.nv()), scalar = precision == Precision::Float ? 4 : 8;
  require_host_memory("bench with loops on " + printable(model_spec) + ", " + std::to_string(count) + " instances",
                      double(count) * (4.0 * nv + loops.rows()) * scalar);
  const std::vector<Timing> rows = precision == Precision::Double
                                       ? time_loops<double>(model, loops, options, count, min_time)
                                       : time_loops<float>(model, loops, options, count, min_time);
  if (::isatty(STDOUT_FILENO)) std::puts(kBenchHeader);
  for (const Timing& t : rows) {
    const std::string row = "fd-loops," + t.strategy + "," + to_string(options.backend) + "," + to_string(precision) +
                            "," + model_label(model_spec) + "," + std::to_string(nv) + "," + std::to_string(count) +
                            "," + format_g(t.seconds_per_call, 6) + "," +
                            format_g(double(count) / t.seconds_per_call, 6) + "," + format_g(t.max_rel_err, 6);
    if (args.has("csv")) append_csv_line(args.required("csv"), kBenchHeader, row);
    std::puts(row.c_str());
  }
  return kExitOk;
}

}  // namespace

int run_bench(const Args& args) {
  if (args.get("algo", "") == "step") return run_bench_step(args);
  if (args.get("algo", "") == "hybrid") return run_bench_hybrid(args);
  if (args.has("loops") || generator_has_loops(args.required("model"))) return run_bench_loops(args);
  if (args.has("prescribed")) throw UsageError("--prescribed applies only to --algo hybrid");
  if (args.has("scene")) throw UsageError("--scene applies only to --algo step");
  const std::string& model_spec = args.required("model");
  const std::string& algo_text = args.required("algo");
  const bool kinematics = algo_text == "fk" || algo_text == "jac";
  Algo algo = Algo::Id;  // (fk and jac: not an Algo)
  if (!kinematics && (args.has("frames") || args.has("reference")))
    throw UsageError(std::string("--") + (args.has("frames") ? "frames" : "reference") + " applies only to --algo fk or jac");
  if (!kinematics && !parse_algo(algo_text, algo))
    throw UsageError("unknown --algo value '" + args.required("algo") +
                     "' (expected id, fd, mass, bias, did, dfd, d2id, fk, jac or step)");
  if (args.has("fd") && algo != Algo::Fd) throw UsageError("--fd applies only to --algo fd");
  const std::size_t count = parse_instances(args.required("instances"));
  const BackendOptions options = parse_backend_options(args);
  if (args.has("strategy") && algo != Algo::Id) throw UsageError("--strategy applies only to --algo id");
  const Precision precision = parse_cli_precision(args);
  const double min_time = parse_min_time(args.get("min-time", "0.5"));
  require_usable(options.backend);

  const Model model = load_cli_model(args);
  if (model.nv() == 0) throw DataError(model_spec + ": the model has no degrees of freedom");
  const std::size_t nv = static_cast<std::size_t>(model.nv());
  // host memory: the random states in double (3 nv), the inputs and outputs in the
  // precision, the outputs again in double for the error, the engine's
  // workspaces (the nv x nv mass matrix per thread for jsi) and the reference's
  const std::size_t scalar = precision == Precision::Float ? 4 : 8;
  const KinematicsRequest request = parse_kinematics_request(args, model, algo_text == "fk", algo_text == "jac");
  const double width = kinematics ? double(request.options.frames.size()) * (request.fk ? 7.0 : 6.0 * double(nv))
                                  : double(output_width(algo, model.nv()));
  const bool jsi = algo == Algo::Fd && (options.fd_method == FdMethod::Jsi || options.fallback_aba);
  const double bytes = double(count) * (3.0 * double(model.nq()) * 8 + 3.0 * double(model.nq()) * scalar + width * scalar + width * 8) +
                       workspace_bytes(nv, backend_threads(options.backend, options.threads), jsi, scalar) +
                       workspace_bytes(nv, 1, false, 8) + 2 * width * 8;
  require_host_memory("bench --algo " + (kinematics ? algo_text : std::string(algo_name(algo))) + (algo == Algo::Fd ? std::string(" --fd ") + to_string(options.fd_method) : "") +
                          " on " + printable(model_spec) + " (" + std::to_string(nv) + " DoF), " +
                          std::to_string(count) + " instances in " + to_string(precision),
                      bytes);

  const RandomStates states(count, static_cast<std::size_t>(model.nq()), nv, quaternion_offsets(model));
  std::vector<Timing> timings;
  if (precision == Precision::Double) {
    timings = kinematics ? time_kinematics<double>(model, model, options, request, states, count, min_time, false)
                         : time_algo<double>(model, model, options, algo, states, count, min_time, false);
  } else {
    const ModelTpl<float> model_f = model.cast<float>();
    timings = kinematics ? time_kinematics<float>(model, model_f, options, request, states, count, min_time, true)
                         : time_algo<float>(model, model_f, options, algo, states, count, min_time, true);
  }

  std::string rows;  // one line per timing, without the last newline
  for (const Timing& t : timings) {
    if (!rows.empty()) rows += "\n";
    rows += (kinematics ? algo_text : std::string(algo_name(algo))) + "," + t.strategy + "," + to_string(options.backend) + "," + to_string(precision) +
            "," + model_label(model_spec) + (model.floating_base() ? "-floating" : "") + "," + std::to_string(nv) + "," + std::to_string(count) + "," +
            format_g(t.seconds_per_call, 6) + "," + format_g(double(count) / t.seconds_per_call, 6) + "," +
            format_g(t.max_rel_err, 6);
  }
  if (args.has("csv")) append_csv_line(args.required("csv"), kBenchHeader, rows);
  if (::isatty(STDOUT_FILENO)) std::puts(kBenchHeader);
  std::puts(rows.c_str());
  return kExitOk;
}

}  // namespace scandyn::cli
