// src/cli/main.cpp: the `scandyn` command: subcommand dispatch, usage, and the
// mapping of errors to one-line messages and exit codes (docs/cli.md).
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <string>
#include <vector>

#include "cli.hpp"
#include "scandyn/io/csv.hpp"
#include "scandyn/io/output_file.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/scene.hpp"
#if SCANDYN_CLI_SPARSE_LOOPS  // CMakeLists.txt: linked with scandyn_factor_graph (CHOLMOD)
#include "scandyn/factor_graph/sparse_constrained_dynamics.hpp"
#endif

namespace {

using namespace scandyn::cli;

const char* const kUsage =
    "usage: scandyn <command> [flags]\n"
    "\n"
    "commands:\n"
    "  info   print a model's summary and DoF order\n"
    "  eval   evaluate dynamics on the states of a CSV file, write a CSV file\n"
    "  bench  time one algorithm on random states, print one benchmark CSV row\n"
    "  rollout  simulate a scene file for N steps, write the trajectory (CSV or .npy)\n"
    "\n"
    "M, a model, is a URDF file or a generator spec: chain:N, rope:N, ballrope:N, tree:N:SEED,\n"
    "curtain:K:N; --floating-base gives its root link a free joint (6 DoF, first in q and qd).\n"
    "'scandyn <command> --help' lists a command's flags; docs/cli.md is the reference.\n";

const char* const kInfoUsage =
    "usage: scandyn info --model M [--floating-base] [--allow-nonphysical-inertia] [--print-loops]\n"
    "\n"
    "Prints the model's name, source, nv, nq, base (fixed or floating), root link and\n"
    "gravity, the CUDA devices (or why there are none), then one line per body in DoF\n"
    "order: index, joint, type, parent index (-1 = base), child link, axis (with\n"
    "multi-DoF joints also q and v, where the joint's entries start in q and in qd);\n"
    "then one line per frame (every URDF link, fixed links included: the names eval\n"
    "--frames takes): index, name, the body carrying it (-1 = base), its origin in that\n"
    "body's frame.\n"
    "  --floating-base  give the root link a free joint: q = [p; quaternion x y z w;\n"
    "                   joints] (nq = nv + 1), qd = [base twist in the base frame (w, v);\n"
    "                   joints]\n"
    "  --print-loops    print the loops a generator carries (fivebar, fourbar, cloth:K:N)\n"
    "                   as a loop file instead.\n";

const char* const kEvalUsage =
    "usage: scandyn eval --model M --states IN.csv --out OUT.csv [--algo LIST]\n"
    "                    [--fd auto|aba|jsi|hybrid|parallel] [--fallback aba|double]\n"
    "                    [--fd-check on|off|auto] [--fd-check-tol X]\n"
    "                    [--backend serial|openmp|cuda] [--strategy S] [--threads N]\n"
    "                    [--devices all|current|0,1,...]\n"
    "                    [--precision double|float] [--frames NAMES] [--reference world|local]\n"
    "\n"
    "  --states IN.csv   header row, one state per row; columns q_<i>, qd_<i>, qdd_<i>,\n"
    "                    tau_<i> (i = DoF index) in any order\n"
    "  --out OUT.csv     tau_id_<i>, qdd_fd_<i>, M_<i>_<j>, h_<i> of the selected algorithms,\n"
    "                    one row per input row, 17 significant digits\n"
    "  --algo LIST       comma-separated subset of id (needs q, qd, qdd), fd (q, qd, tau),\n"
    "                    mass (q), bias (q, qd), did / dfd (first-order derivatives, as\n"
    "                    id / fd), d2id (second-order derivatives of id: columns\n"
    "                    d2tau_dq2_<i>_<j>_<k>, d2tau_dqd2_.., d2tau_dqdqd_..), fk\n"
    "                    (q: frame poses, columns fk_<frame>_px..pz, _qx.._qw) and jac\n"
    "                    (q: frame Jacobians, 6 x nv, rows [angular; linear], columns\n"
    "                    J_<frame>_<row>_<dof>); default:\n"
    "                    each of id, fd, bias whose columns are all present\n"
    "  --frames NAMES    fk and jac: comma-separated frame (URDF link) names, fixed links\n"
    "                    included; default: every frame, as `scandyn info` lists them\n"
    "  --reference R     jac: world (default; world axes at the frame's origin, Pinocchio's\n"
    "                    LOCAL_WORLD_ALIGNED) or local (the frame's axes, LOCAL)\n"
    "  --backend NAME    serial (default), openmp (threads over instances, or scans\n"
    "                    over links for fewer instances than threads on long chains)\n"
    "                    or cuda (id, fd and bias, one GPU thread per instance,\n"
    "                    or scans over links for long chains)\n"
    "  --fd METHOD       forward dynamics by aba (articulated bodies), jsi (CRBA +\n"
    "                    Cholesky), parallel (chains from the base: scans over links,\n"
    "                    O(log n) depth) or hybrid (chains, cuda only: articulated\n"
    "                    inertias on the CPU, the rest as GPU scans); default auto:\n"
    "                    serial aba; openmp parallel for chains of 4096+ links, else\n"
    "                    aba; cuda aba up to 64 DoF, parallel for longer chains, else jsi\n"
    "  --fallback aba    with --fd jsi: an instance whose mass matrix factorisation\n"
    "                    fails (a pivot that is not positive) is computed by aba\n"
    "                    instead, and a warning on stderr counts them (cuda: up to\n"
    "                    64 DoF, by the ABA kernel over just those instances); with\n"
    "                    the check on, also an instance the check flags\n"
    "  --fallback double with --precision float: an instance the check flags is\n"
    "                    computed again by aba in double (aba,double: both, in order);\n"
    "                    a warning on stderr counts them\n"
    "  --fd-check MODE   check every forward dynamics result: the residual\n"
    "                    ID(q, qd, qdd) - tau in double, turned into an estimate of\n"
    "                    qdd's relative error; a row above the threshold fails (exit\n"
    "                    1, naming the row) unless a fallback fixes it. Default on\n"
    "                    (eval); auto: only where it costs under 10% (jsi, 200+ DoF,\n"
    "                    CPU); off: the unchecked, bit-identical result\n"
    "  --fd-check-tol X  the check's threshold (default 1e-4 float, 1e-10 double)\n"
    "  --strategy S      inverse dynamics by recursion, scan-local or scan-world;\n"
    "                    default auto (chosen by shape, see docs/cli.md)\n"
    "  --threads N       OpenMP threads (default: all)\n"
    "  --devices D       cuda: the GPUs the batch is split across, contiguous ranges\n"
    "                    of rows, one engine per device, all at once: all, current\n"
    "                    (default) or ordinals such as 0,1 (docs/scaling.md)\n"
    "  --simd M          serial/openmp recursions (id, bias, mass, aba) W instances\n"
    "                    per vector register: auto (default), on or off\n"
    "  --precision P     double (default) or float\n"
    "  --floating-base   the model on a free joint at its root (as for info): q_0..q_{nq-1}\n"
    "                    (the base quaternion q_3..q_6 normalised, a data error when its\n"
    "                    norm is off from 1 by more than 1e-6), qd, qdd, tau nv each\n"
    "  --allow-nonphysical-inertia  load links whose inertia no rigid body can have\n"
    "                    (not positive definite, or breaking the triangle inequality),\n"
    "                    with a warning, instead of refusing the model\n"
    "\n"
    "       scandyn eval --model M --states IN.csv --out OUT.csv --algo hybrid\n"
    "                    --prescribed LIST [--backend ...] [--threads N] [--precision P]\n"
    "Hybrid dynamics: LIST names the DoFs whose accelerations are given (DoF indices or\n"
    "joint names, comma-separated); reads q_<i>, qd_<i>, qdd_<i> of those DoFs and\n"
    "tau_<i> of the others; writes qdd_hd_<i> and tau_hd_<i> of every DoF.\n"
    "\n"
    "       scandyn eval --model M --states IN.csv --out OUT.csv [--loops FILE]\n"
    "                    [--algo fd [--loop-solver S] | --algo id --actuated LIST]\n"
    "Closed loops (a loop file, or the loops of fivebar, fourbar, cloth:K:N): fd writes\n"
    "qdd_fd_<i> and lambda_<k> (M qdd + h = tau + J^T lambda, J qdd + Jdot qd = 0);\n"
    "id with the actuated DoFs writes tau_id_<i> (minimum norm) and lambda_<k>. A state\n"
    "violating its loops by more than 1e-6 is an error. Serial, double.\n"
    "  --loop-solver S  fd's solver: dense (rank-revealing, lambda of minimum norm),\n"
    "                   sparse (CHOLMOD, when built with it), iterative (matrix-free\n"
    "                   conjugate gradients, relative residual 1e-10), or auto\n"
    "                   (default: dense below 200 DoF, else sparse, else iterative)\n"
    "  --loop-solver iterative --backend cuda [--precision double|float]: the iterative\n"
    "                   solver on the GPU (trees of unbranched chains from the base,\n"
    "                   e.g. cloth:K:N; block-Jacobi preconditioner; float: 1e-5)\n";

const char* const kRolloutUsage =
    "usage: scandyn rollout --scene S.json --steps N --out TRAJ.csv|TRAJ.npy [--every K]\n"
    "                       [--backend serial|openmp|cuda] [--devices all|current|0,1,...]\n"
    "                       [--tau TAU.npy] [--contacts]\n"
    "\n"
    "Simulates the scene (docs/scenes.md) for N steps from its initial state, with zero\n"
    "joint torques or those of --tau, and writes the state of every instance at steps\n"
    "0, K, 2K, ... and N:\n"
    "  .csv  columns step,time,instance,q_<i>...,qd_<i>..., 17 significant digits\n"
    "  .npy  a NumPy array of shape (records, instances, 1 + nq + nv): [time, q, qd],\n"
    "        float64 (or float32 for a float scene)\n"
    "  q has nq entries (nq = nv, or more with a floating base, \"base\": \"floating\",\n"
    "  and ball joints: [px, py, pz, qx, qy, qz, qw, joints...]), qd nv\n"
    "  --tau TAU.npy  joint torques (float32 or float64 .npy, numpy.save): shape (N, B, nv),\n"
    "        row t acting during the step from t to t + 1; (B, nv), constant per instance;\n"
    "        or (nv,), one row for every instance and step (B: the scene's instances)\n"
    "  --contacts  (a scene with effects.contacts) adds per contact point k the contact\n"
    "        force of the step that ended there (world frame, N) and whether it touched:\n"
    "        .csv  columns cf_<k>_x,cf_<k>_y,cf_<k>_z,contact_<k> after qd_<i>\n"
    "        .npy  4 more values per point: [fx, fy, fz, in_contact]\n"
    "  --devices D  cuda: the GPUs the instances are split across, contiguous ranges,\n"
    "        one simulator shard per device stepping at once: all, current or ordinals\n"
    "        such as 0,1 (overrides the scene's \"devices\"; the trajectory is the same)\n"
    "A progress bar goes to stderr when it is a terminal. --backend overrides the scene's\n"
    "(and, other than cuda, drops the scene's devices).\n";

const char* const kBenchUsage =
    "usage: scandyn bench --model M --algo id|fd|mass|bias|did|dfd|d2id|fk|jac|hybrid --instances B [--fd METHOD]\n"
    "                     [--fallback aba|double] [--fd-check on|off|auto] [--fd-check-tol X]\n"
    "                     [--frames NAMES] [--reference world|local]\n"
    "                     [--backend serial|openmp|cuda] [--strategy S] [--threads N]\n"
    "                     [--devices all|current|0,1,...]\n"
    "                     [--precision double|float] [--min-time SECONDS] [--csv FILE]\n"
    "\n"
    "Times the algorithm on B random states (fixed seed) and prints one CSV row:\n"
    "algo,strategy,backend,precision,model,links,instances,seconds_per_call,\n"
    "evals_per_second,max_rel_err (with the header when stdout is a terminal). With\n"
    "--backend cuda two rows for id and bias: strategy thread (the batch resident in\n"
    "device memory) and thread-host (host buffers, copies to and from the device\n"
    "included); one row, <strategy>-host (e.g. jsi_thread-host, parallel-host), for fd.\n"
    "  --fd METHOD       auto (default), aba, jsi, hybrid or parallel, as for eval\n"
    "  --frames, --reference  fk (frame poses) and jac (frame Jacobians), as for eval\n"
    "                    (default every frame); cuda: rows thread (resident) and thread-host\n"
    "  --fallback aba    as for eval (strategy column jsi+aba; cuda: jsi_thread+aba-host,\n"
    "                    no device-resident row)\n"
    "  --fd-check MODE   as for eval, default auto; flagged instances are a warning\n"
    "                    (strategy column <method>+check where it runs)\n"
    "  --fd-check-tol X, --fallback double   as for eval\n"
    "  --backend, --strategy, --threads, --devices   as for eval; with several devices\n"
    "                    the strategy column ends in -x<devices> (thread-x2: the resident\n"
    "                    batch split across two devices, each shard's launch queued at once)\n"
    "  --min-time S      keep timing whole passes until S seconds passed (default 0.5)\n"
    "  --csv FILE        also append the row to FILE (created with the header)\n"
    "  --allow-nonphysical-inertia, --floating-base  as for eval\n"
    "\n"
    "       scandyn bench --algo step --scene S.json [--instances B] [--backend ...]\n"
    "                     [--devices ...] [--precision ...] [--min-time SECONDS] [--csv FILE]\n"
    "Times whole simulator steps of the scene (instances, backend and precision from the\n"
    "scene unless given); evals_per_second is instance-steps per second, strategy\n"
    "<engine>:<integrator>:<effects>, max_rel_err the state after 10 steps against the\n"
    "double serial simulator (at most 1000 instances compared). --devices as for rollout\n"
    "(strategy <engine>-x<devices>:...).\n"
    "\n"
    "       scandyn bench --model M --algo hybrid --prescribed LIST --instances B ...\n"
    "Times the hybrid dynamics (LIST as for eval); max_rel_err of qdd and tau against\n"
    "the double serial hybrid dynamics.\n";

// One subcommand: its name, usage text, accepted flags and body.
struct Command {
  const char* name;
  const char* usage;
  std::vector<std::string> flags;
  int (*run)(const Args&);
};

const Command kCommands[] = {
    {"info", kInfoUsage, {"model", "allow-nonphysical-inertia", "floating-base", "print-loops"}, &run_info},
    {"eval",
     kEvalUsage,
     {"model", "states", "out", "algo", "fd", "fallback", "backend", "strategy", "threads", "precision",
      "allow-nonphysical-inertia", "frames", "reference", "floating-base", "fd-check", "fd-check-tol", "prescribed", "loops",
      "actuated", "loop-solver", "simd", "devices"},
     &run_eval},
    {"bench",
     kBenchUsage,
     {"model", "algo", "fd", "fallback", "instances", "backend", "strategy", "threads", "precision", "min-time",
      "csv", "allow-nonphysical-inertia", "scene", "frames", "reference", "floating-base", "fd-check", "fd-check-tol", "prescribed",
      "simd", "devices"},
     &run_bench},
    {"rollout", kRolloutUsage, {"scene", "steps", "out", "every", "backend", "devices", "tau", "contacts"}, &run_rollout},
};

int fail(int code, const std::string& message) {
  std::string line = message;
  for (char& c : line)
    if (c == '\n' || c == '\r') c = ' ';  // always exactly one line
  // other control characters (a NUL included: it would cut the line short) as \xNN
  line = "scandyn: " + scandyn::printable(line) + "\n";
  std::fwrite(line.data(), 1, line.size(), stderr);
  return code;
}

// OMP_NUM_THREADS is capped like --threads: the OpenMP runtime crashes when asked
// for 10^5 threads. Each entry of the (comma-separated) list is checked.
void check_omp_environment() {
  const char* env = std::getenv("OMP_NUM_THREADS");
  if (!env) return;
  const std::string value = env;
  std::size_t start = 0;
  for (;;) {
    const std::size_t comma = value.find(',', start);
    const std::string item = value.substr(start, comma == std::string::npos ? std::string::npos : comma - start);
    std::size_t digits = 0;
    while (digits < item.size() && item[digits] == ' ') ++digits;
    const std::string trimmed = item.substr(digits);
    bool numeric = !trimmed.empty();
    for (char c : trimmed) numeric = numeric && ((c >= '0' && c <= '9') || c == ' ');
    if (numeric && (trimmed.size() > 4 || std::atoi(trimmed.c_str()) > 4096))
      throw UsageError("OMP_NUM_THREADS=" + value + ": at most 4096 threads (the limit of --threads); unset it "
                       "or lower it", false);
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
}

int dispatch(int argc, char** argv) {
  install_signal_handlers();
  check_omp_environment();
  if (argc < 2) return fail(kExitUsage, "missing command (try 'scandyn --help')");
  const std::string cmd = argv[1];
  if (cmd == "--help" || cmd == "-h" || cmd == "help") {
    std::fputs(kUsage, stdout);
    return kExitOk;
  }
  if (cmd == "--version") {
    std::printf("scandyn %s\n", SCANDYN_VERSION);
    return kExitOk;
  }
  for (const Command& c : kCommands) {
    if (cmd != c.name) continue;
    const Args args(c.name, argc, argv, 2, c.flags);
    if (args.help()) {
      std::fputs(c.usage, stdout);
      return kExitOk;
    }
    return c.run(args);
  }
  return fail(kExitUsage, "unknown command '" + cmd + "' (try 'scandyn --help')");
}

}  // namespace

int main(int argc, char** argv) {
#if SCANDYN_CLI_SPARSE_LOOPS
  // scenes with closed loops may step through the factor graph's sparse solver
  // (CHOLMOD; "loop_solver": "sparse", or "auto" from 200 DoF on: docs/loops.md)
  scandyn::factor_graph::register_sparse_loop_solver();
#endif
  try {
    return dispatch(argc, argv);
  } catch (const UsageError& e) {
    const std::string cmd = argc >= 2 ? argv[1] : "";
    if (!e.hint_help) return fail(kExitUsage, e.what());
    return fail(kExitUsage, std::string(e.what()) + " (try 'scandyn " + cmd + " --help')");
  } catch (const scandyn::ModelError& e) {
    return fail(kExitData, e.what());
  } catch (const DataError& e) {
    return fail(kExitData, e.what());
  } catch (const CsvError& e) {
    return fail(kExitData, e.what());
  } catch (const scandyn::InputError& e) {
    return fail(kExitData, e.what());
  } catch (const scandyn::ResourceError& e) {
    return fail(kExitData, e.what());
  } catch (const scandyn::sim::SceneError& e) {
    return fail(kExitData, e.what());
  } catch (const std::bad_alloc&) {
    const std::string cmd = argc >= 2 ? argv[1] : "";
    return fail(kExitData, "out of memory in '" + cmd + "' (host memory available: " +
                               scandyn::format_bytes(double(scandyn::host_memory_available())) +
                               "); try fewer instances, rows or links");
  } catch (const std::exception& e) {
    return fail(kExitData, std::string("error: ") + e.what());
  }
}
