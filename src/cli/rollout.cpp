// src/cli/rollout.cpp: `scandyn rollout`, runs a scene for N steps and writes the
// trajectory (CSV, or a NumPy .npy array) through the atomic writer; a progress
// bar on stderr when stderr is a terminal.
#include <unistd.h>

#include <charconv>
#include <cmath>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <string>
#include <vector>

#include "cli.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/io/output_file.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/io/npy.hpp"
#include "scandyn/sim/simulator.hpp"
#include "rollout_torques.hpp"
#include "simulator_cli.hpp"

namespace scandyn::cli {
namespace {

long long parse_count(const std::string& flag, const std::string& text, long long lo, long long hi) {
  long long v = 0;
  const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
  if (ec != std::errc() || ptr != text.data() + text.size() || v < lo || v > hi)
    throw UsageError("--" + flag + " must be an integer from " + std::to_string(lo) + " to " + std::to_string(hi) +
                     ", got '" + text + "'");
  return v;
}

bool ends_with(const std::string& s, const char* suffix) {
  const std::size_t n = std::strlen(suffix);
  return s.size() >= n && s.compare(s.size() - n, n, suffix) == 0;
}

// "\r[#####.....]  45%  450/1000 steps" on stderr, at most every 0.1 s
class Progress {
 public:
  Progress(long long total, bool on) : total_(total), on_(on) {}
  void update(long long done) {
    if (!on_) return;
    const auto now = std::chrono::steady_clock::now();
    if (done < total_ && now - last_ < std::chrono::milliseconds(100)) return;
    last_ = now;
    const int width = 30;
    const int filled = total_ > 0 ? static_cast<int>(width * done / total_) : width;
    std::fprintf(stderr, "\rrollout [%s%s] %3d%%  %lld/%lld steps", std::string(filled, '#').c_str(),
                 std::string(width - filled, '.').c_str(), total_ > 0 ? static_cast<int>(100 * done / total_) : 100,
                 done, total_);
    std::fflush(stderr);
  }
  void finish() {
    if (on_) std::fputs("\n", stderr);
  }

 private:
  long long total_;
  bool on_;
  std::chrono::steady_clock::time_point last_{};
};

// The first non-finite entry of the state (q: nq x B, qd: nv x B, SoA views), as
// "instance b (q_i = nan)", and how many instances have one; "" when all are finite.
template <class S>
std::string first_non_finite(const BatchView<const S>& q, const BatchView<const S>& qd, Index nq, Index nv,
                             long long& count) {
  std::string first;
  count = 0;
  // fast path: contiguous SoA state, all finite (the common case, every step)
  const auto all_finite = [&](const BatchView<const S>& v, Index rows) {
    if (v.dof_stride != v.batch || v.batch_stride != 1) return false;
    const std::size_t total = static_cast<std::size_t>(rows) * static_cast<std::size_t>(v.batch);
    bool ok = true;
    for (std::size_t k = 0; k < total; ++k) ok &= std::isfinite(v.data[k]);
    return ok;
  };
  if (all_finite(q, nq) && all_finite(qd, nv)) return first;
  for (Index b = 0; b < q.batch; ++b) {
    for (int part = 0; part < 2; ++part) {
      const BatchView<const S>& v = part ? qd : q;
      const Index rows = part ? nv : nq;
      Index i = 0;
      while (i < rows && std::isfinite(static_cast<double>(v.at(i, b)))) ++i;
      if (i == rows) continue;
      if (first.empty()) {
        const double x = static_cast<double>(v.at(i, b));
        first = "instance " + std::to_string(b) + " (" + (part ? "qd_" : "q_") + std::to_string(i) + " = " +
                (std::isnan(x) ? "nan" : x > 0 ? "inf" : "-inf") + ")";
      }
      ++count;
      break;
    }
  }
  return first;
}

// Outputs beyond this size are announced on stderr before the rollout starts.
constexpr double kLargeOutputBytes = 2.0 * (1ull << 30);

template <class S>
int rollout(const sim::Scene& scene, BackendKind backend, long long steps, long long every, const std::string& out_path,
            const std::string& tau_path, bool contacts) {
  // q has nq columns (a floating base's or ball joints' quaternions), qd nv
  const std::size_t n = static_cast<std::size_t>(scene.nv()), nb = static_cast<std::size_t>(scene.instances);
  const std::size_t nqs = static_cast<std::size_t>(scene.nq());
  // --contacts: 4 values per contact point (force, flag)
  const std::size_t np = contacts ? scene.contacts.points.size() : 0;
  // recorded steps: 0, every, 2 every, ..., and the last one
  const long long records = steps / every + 1 + (steps % every != 0);
  const bool npy = ends_with(out_path, ".npy");
  // the trajectory's size, checked before anything is made: %.17g numbers take up
  // to 24 bytes with the comma; a .npy record holds 1 + nq + nv (+ 4 P with --contacts)
  // scalars per instance
  const double values = static_cast<double>(records) * static_cast<double>(nb) * static_cast<double>(1 + nqs + n + 4 * np);
  const double out_bytes = npy ? values * sizeof(S) : values * 24.0;
  const std::string what = "the trajectory of " + std::to_string(records) + " records x " + std::to_string(nb) +
                           " instances x " + std::to_string(1 + nqs + n + 4 * np) + " values";
  require_disk_space(out_path, what, out_bytes);
  // a large output is said before the first step (it fits: checked above)
  if (out_bytes > kLargeOutputBytes)
    std::fprintf(stderr, "scandyn: %s: %s takes about %s (--every records fewer steps)\n", printable(out_path).c_str(),
                 what.c_str(), format_bytes(out_bytes).c_str());
  const double tau_bytes = tau_path.empty() ? 0.0 : RolloutTorques<S>::host_bytes(scene.instances, scene.nv());
  const double contact_bytes = static_cast<double>(np * nb) * sizeof(sim::ContactReading<S>);
  const std::unique_ptr<sim::Simulator<S>> made = make_simulator<S>(
      scene, backend, static_cast<double>((nqs + n) * nb) * sizeof(S) + tau_bytes + contact_bytes + (2u << 20));
  sim::Simulator<S>& sim = *made;
  const Index nv = sim.nv(), nq = sim.nq(), B = sim.batch();
  // --tau: checked (shape, dtype, size; the constant shapes' values) before the output is made
  std::unique_ptr<RolloutTorques<S>> tau;
  if (!tau_path.empty())
    tau = std::make_unique<RolloutTorques<S>>(tau_path, steps, B, nv, sim.torques_on_device(), sim.stream());
  AtomicFileWriter file(out_path);
  // a signal (SIGINT, SIGTERM, SIGHUP) ends the loop at the next step: the records
  // written so far are published (.npy with its shape fixed up), exit 128 + signal
  const SignalGuard guard;
  std::vector<S> q(nqs * nb), qd(n * nb);
  std::vector<sim::ContactReading<S>> readings(np * nb);  // (B x P), zeros before the first step
  std::string text;
  const char* const descr = sizeof(S) == 4 ? "<f4" : "<f8";
  const long long width = 1 + static_cast<long long>(nq) + static_cast<long long>(nv) + 4 * static_cast<long long>(np);
  std::size_t header_size = 0;
  if (npy) {
    if (!little_endian()) throw DataError("rollout: .npy output is written on little-endian machines only");
    const std::string header = npy_header(descr, {records, B, width});
    header_size = header.size();
    file.write(header);
  } else {
    text = "step,time,instance";
    for (Index i = 0; i < nq; ++i) text += ",q_" + std::to_string(i);
    for (Index i = 0; i < nv; ++i) text += ",qd_" + std::to_string(i);
    for (std::size_t k = 0; k < np; ++k) {
      const std::string c = std::to_string(k);
      text += ",cf_" + c + "_x,cf_" + c + "_y,cf_" + c + "_z,contact_" + c;
    }
    text += "\n";
    file.write(text);
  }
  std::vector<S> row(1 + nqs + n + 4 * np);
  long long written = 0;  // records written
  // a state that is not finite stops the rollout (exit 1, nothing written)
  auto check_finite = [&](long long step, const BatchView<const S>& qv, const BatchView<const S>& qdv) {
    long long bad = 0;
    const std::string first = first_non_finite(qv, qdv, nq, nv, bad);
    if (!first.empty())
      throw DataError(scene.path + ": step " + std::to_string(step) + ": the state is not finite in " +
                      std::to_string(bad) + " of " + std::to_string(B) + " instances, first " + first +
                      " (the simulation overflowed: smaller dt, coefficients or initial state)");
  };
  auto record = [&](long long step) {
    sim.read_state(q.data(), qd.data());
    if (np > 0 && step > 0) sim.read_contact_forces(readings.data());
    check_finite(step, BatchView<const S>::soa(q.data(), nq, B), BatchView<const S>::soa(qd.data(), nv, B));
    ++written;
    const double t = static_cast<double>(step) * scene.dt;
    for (std::size_t b = 0; b < nb; ++b) {
      if (npy) {
        row[0] = S(t);
        for (std::size_t i = 0; i < nqs; ++i) row[1 + i] = q[i * nb + b];
        for (std::size_t i = 0; i < n; ++i) row[1 + nqs + i] = qd[i * nb + b];
        for (std::size_t k = 0; k < np; ++k) {
          const sim::ContactReading<S>& c = readings[b * np + k];
          S* const out = row.data() + 1 + nqs + n + 4 * k;
          out[0] = c.force.x, out[1] = c.force.y, out[2] = c.force.z, out[3] = S(c.in_contact);
        }
        file.write(std::string_view(reinterpret_cast<const char*>(row.data()), row.size() * sizeof(S)));
      } else {
        text = std::to_string(step) + ",";
        append_number(text, t);
        text += "," + std::to_string(b);
        for (std::size_t i = 0; i < nqs; ++i) text += ",", append_number(text, double(q[i * nb + b]));
        for (std::size_t i = 0; i < n; ++i) text += ",", append_number(text, double(qd[i * nb + b]));
        for (std::size_t k = 0; k < np; ++k) {
          const sim::ContactReading<S>& c = readings[b * np + k];
          for (S x : {c.force.x, c.force.y, c.force.z}) text += ",", append_number(text, double(x));
          text += c.in_contact ? ",1" : ",0";
        }
        text += "\n";
        file.write(text);
      }
    }
  };
  Progress progress(steps, ::isatty(STDERR_FILENO) != 0);
  record(0);
  for (long long s = 1; s <= steps; ++s) {
    if (const int sig = SignalGuard::pending()) {
      progress.finish();
      if (npy && !file.streaming()) file.patch(0, npy_header(descr, {written, B, width}, header_size));
      file.commit();
      std::fprintf(stderr, "scandyn: %s: interrupted by signal %d before step %lld; %s holds the %lld records written so far\n",
                   scene.path.c_str(), sig, s, printable(out_path).c_str(), written);
      return 128 + sig;
    }
    if (tau) sim.step(tau->for_step(s));
    else sim.step();
    // host-resident state (serial, openmp): checked after every step, in place
    if (!sim.on_device()) {
      const BatchView<S> qv = sim.q(), qdv = sim.qd();
      check_finite(s, BatchView<const S>{qv.data, qv.batch, qv.dof_stride, qv.batch_stride},
                   BatchView<const S>{qdv.data, qdv.batch, qdv.dof_stride, qdv.batch_stride});
    }
    if (s % every == 0 || s == steps) {
      record(s);
      const BatchStatus st = sim.status();
      if (!st.ok()) {
        progress.finish();
        throw DataError(scene.path + ": step " + std::to_string(s) + ": " + sim::failure_message(st));
      }
    }
    progress.update(s);
  }
  progress.finish();
  file.commit();
  return kExitOk;
}

}  // namespace

int run_rollout(const Args& args) {
  const std::string& scene_path = args.required("scene");
  const long long steps = parse_count("steps", args.required("steps"), 0, 1000000000);
  const std::string& out = args.required("out");
  const long long every = parse_count("every", args.get("every", "1"), 1, 1000000000);
  if (out != "-" && !ends_with(out, ".csv") && !ends_with(out, ".npy"))
    throw UsageError("--out must name a .csv or .npy file (or be - for CSV on stdout), got '" + out + "'");
  sim::Scene scene;
  try {
    scene = sim::load_scene(scene_path);
  } catch (const sim::SceneError& e) {
    throw DataError(e.what());
  }
  const bool contacts = args.has("contacts");
  if (contacts && !(scene.effects & sim::kContacts))
    throw UsageError("--contacts: the scene " + scene.path + " declares no effects.contacts", false);
  const BackendKind backend = scene_backend(scene, args);
  scene_devices(scene, backend, args);
  const std::string tau = args.get("tau", "");
  if (args.has("tau") && tau.empty()) throw UsageError("--tau needs a .npy file");
  return scene.precision == Precision::Float ? rollout<float>(scene, backend, steps, every, out, tau, contacts)
                                                  : rollout<double>(scene, backend, steps, every, out, tau, contacts);
}

}  // namespace scandyn::cli
