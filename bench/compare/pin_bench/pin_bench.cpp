// pin_bench: the Pinocchio side of bench/compare (docs/benchmarks.md, "Side by side").
//
//   pin_bench info  --urdf F                       DoF order: one line per DoF, "index joint nq"
//   pin_bench eval  --urdf F --states IN.csv --out OUT.csv
//   pin_bench bench --urdf F --name NAME --algo id|fd|mass|bias|did|dfd --instances B
//                   [--threads N] [--min-time S] [--root free]
//   pin_bench version
//
// eval reads scandyn's state columns (q_i, qd_i, qdd_i, tau_i; DoF index i in Pinocchio's
// order, which `info` prints) and writes scandyn's output columns (tau_id_i, qdd_fd_i,
// M_i_j, h_i) with 17 significant digits, so that bench/compare/check.py compares the two
// files column by column. A continuous joint (nq = 2 in Pinocchio) takes q_i as an angle
// and is given (cos q_i, sin q_i).
//
// bench times one algorithm on B instances the way `scandyn bench` does: states from
// std::mt19937_64 seeded 42, uniform in [-1, 1] (all of q, then qd, then the third input),
// one warm-up call, then whole calls (each over all B instances) in rounds until --min-time
// seconds have passed; seconds_per_call = elapsed / calls. Without --threads the calls are
// a serial loop over the instances with one pinocchio::Data. With --threads N: id and fd by
// Pinocchio's own OpenMP batch functions (rneaInParallel, abaInParallel over a ModelPool,
// strategy `pool`), mass and bias (which have no such function) by an OpenMP loop over the
// instances with one Data per thread (strategy `omp-loop`).
// Algorithms: id = rnea, fd = aba, mass = crba (upper triangle, LOCAL convention, both
// Pinocchio's defaults; copied out whole as scandyn's batch copies its nv x nv output),
// bias = nonLinearEffects, did = computeRNEADerivatives and dfd = computeABADerivatives
// (their three nv x nv matrices copied out per instance, as scandyn's engines write
// theirs; no --threads). Everything in double, spatial conventions irrelevant here
// (only joint-space quantities cross the interface).
// --root free (bench only): the model on a free flyer (buildModel(urdf,
// JointModelFreeFlyer()), scandyn's --floating-base); its states are drawn like scandyn
// bench's: all q (B x nq, scandyn's layout: an angle per 1-DoF joint, the base's
// position and quaternion, normalised), then qd, then the third input.
// Prints one CSV row: algo,strategy,backend,precision,model,links,instances,seconds_per_call,evals_per_second
#include <pinocchio/algorithm/aba.hpp>
#include <pinocchio/algorithm/crba.hpp>
#include <pinocchio/algorithm/rnea.hpp>
#include <pinocchio/algorithm/aba-derivatives.hpp>
#include <pinocchio/algorithm/rnea-derivatives.hpp>
#include <pinocchio/algorithm/parallel/aba.hpp>
#include <pinocchio/algorithm/parallel/rnea.hpp>
#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/model.hpp>
#include <pinocchio/multibody/pool.hpp>
#include <pinocchio/parsers/urdf.hpp>

#include <omp.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <iostream>
#include <map>
#include <random>
#include <sstream>
#include <string>
#include <vector>

namespace {

using Clock = std::chrono::steady_clock;
using Mat = Eigen::MatrixXd;
using Vec = Eigen::VectorXd;

[[noreturn]] void die(const std::string &msg) {
  std::cerr << "pin_bench: " << msg << "\n";
  std::exit(2);
}

std::map<std::string, std::string> parse_flags(int argc, char **argv, int first) {
  std::map<std::string, std::string> f;
  for (int i = first; i < argc; ++i) {
    std::string a = argv[i];
    if (a.rfind("--", 0) != 0 || i + 1 >= argc) die("bad argument '" + a + "'");
    f[a.substr(2)] = argv[++i];
  }
  return f;
}

std::string need(const std::map<std::string, std::string> &f, const std::string &k) {
  auto it = f.find(k);
  if (it == f.end()) die("missing --" + k);
  return it->second;
}

pinocchio::Model load(const std::string &urdf, bool free_root = false) {
  pinocchio::Model model;
  if (free_root) pinocchio::urdf::buildModel(urdf, pinocchio::JointModelFreeFlyer(), model);
  else pinocchio::urdf::buildModel(urdf, model);
  return model;
}

// scandyn's q of a floating-base model (nq = nv + 1: the base's 7 entries, then an
// angle per joint) -> Pinocchio's configuration (cos, sin for a continuous joint).
void to_config_free(const pinocchio::Model &model, const double *sq, Eigen::Ref<Vec> q) {
  int k = 0;
  for (pinocchio::JointIndex j = 1; j < (pinocchio::JointIndex)model.njoints; ++j) {
    const int iq = model.idx_qs[j], nq = model.nqs[j], nv = model.nvs[j];
    if (nq == 2 && nv == 1) {
      q[iq] = std::cos(sq[k]);
      q[iq + 1] = std::sin(sq[k]);
      k += 1;
    } else {
      for (int i = 0; i < nq; ++i) q[iq + i] = sq[k + i];
      k += nq;
    }
  }
}

// angle per DoF -> Pinocchio configuration (cos, sin for a continuous joint)
void to_config(const pinocchio::Model &model, const double *angles, Eigen::Ref<Vec> q) {
  for (pinocchio::JointIndex j = 1; j < (pinocchio::JointIndex)model.njoints; ++j) {
    const int iq = model.idx_qs[j], iv = model.idx_vs[j], nq = model.nqs[j], nv = model.nvs[j];
    if (nq == nv) {
      for (int k = 0; k < nq; ++k) q[iq + k] = angles[iv + k];
    } else if (nq == 2 && nv == 1) {
      q[iq] = std::cos(angles[iv]);
      q[iq + 1] = std::sin(angles[iv]);
    } else {
      die("joint " + model.names[j] + ": nq " + std::to_string(nq) + ", nv " + std::to_string(nv) +
          " is not supported");
    }
  }
}

int cmd_info(const pinocchio::Model &model) {
  std::printf("nq %d nv %d\n", model.nq, model.nv);
  for (pinocchio::JointIndex j = 1; j < (pinocchio::JointIndex)model.njoints; ++j)
    for (int k = 0; k < model.nvs[j]; ++k)
      std::printf("%d %s %d\n", model.idx_vs[j] + k, model.names[j].c_str(), model.nqs[j]);
  return 0;
}

std::vector<std::string> split(const std::string &line) {
  std::vector<std::string> out;
  std::stringstream ss(line);
  std::string cell;
  while (std::getline(ss, cell, ',')) {
    while (!cell.empty() && (cell.back() == '\r' || cell.back() == ' ')) cell.pop_back();
    out.push_back(cell);
  }
  return out;
}

int cmd_eval(const pinocchio::Model &model, const std::string &in_path, const std::string &out_path) {
  const int nv = model.nv;
  std::ifstream in(in_path);
  if (!in) die(in_path + ": cannot open");
  std::string line;
  std::getline(in, line);
  const std::vector<std::string> header = split(line);
  std::map<std::string, int> col;
  for (size_t c = 0; c < header.size(); ++c) col[header[c]] = (int)c;
  auto idx = [&](const std::string &fam, int i) {
    auto it = col.find(fam + "_" + std::to_string(i));
    if (it == col.end()) die(in_path + ": missing column " + fam + "_" + std::to_string(i));
    return it->second;
  };
  std::ofstream out(out_path);
  if (!out) die(out_path + ": cannot write");
  {
    std::string h;
    for (int i = 0; i < nv; ++i) h += "tau_id_" + std::to_string(i) + ",";
    for (int i = 0; i < nv; ++i) h += "qdd_fd_" + std::to_string(i) + ",";
    for (int i = 0; i < nv; ++i)
      for (int j = 0; j < nv; ++j) h += "M_" + std::to_string(i) + "_" + std::to_string(j) + ",";
    for (int i = 0; i < nv; ++i) h += "h_" + std::to_string(i) + (i + 1 < nv ? "," : "");
    out << h << "\n";
  }
  pinocchio::Data data(model);
  std::vector<double> ang(nv);
  Vec q(model.nq), qd(nv), qdd(nv), tau(nv);
  char buf[64];
  auto put = [&](double x, bool last) {
    std::snprintf(buf, sizeof buf, "%.17g", x);
    out << buf << (last ? "\n" : ",");
  };
  while (std::getline(in, line)) {
    if (line.find_first_not_of(" \t\r") == std::string::npos) continue;
    const std::vector<std::string> cells = split(line);
    for (int i = 0; i < nv; ++i) {
      ang[i] = std::stod(cells[idx("q", i)]);
      qd[i] = std::stod(cells[idx("qd", i)]);
      qdd[i] = std::stod(cells[idx("qdd", i)]);
      tau[i] = std::stod(cells[idx("tau", i)]);
    }
    to_config(model, ang.data(), q);
    const Vec t_id = pinocchio::rnea(model, data, q, qd, qdd);
    const Vec a_fd = pinocchio::aba(model, data, q, qd, tau);
    Mat M = pinocchio::crba(model, data, q);
    M.triangularView<Eigen::StrictlyLower>() = M.transpose().triangularView<Eigen::StrictlyLower>();
    const Vec h = pinocchio::nonLinearEffects(model, data, q, qd);
    for (int i = 0; i < nv; ++i) put(t_id[i], false);
    for (int i = 0; i < nv; ++i) put(a_fd[i], false);
    for (int i = 0; i < nv; ++i)
      for (int j = 0; j < nv; ++j) put(M(i, j), false);
    for (int i = 0; i < nv; ++i) put(h[i], i + 1 == nv);
  }
  return 0;
}

int cmd_bench(const pinocchio::Model &model, const std::map<std::string, std::string> &f) {
  const std::string algo = need(f, "algo"), name = need(f, "name");
  const long B = std::atol(need(f, "instances").c_str());
  if (B < 1) die("--instances must be >= 1");
  const int threads = f.count("threads") ? std::atoi(f.at("threads").c_str()) : 0;
  const double min_time = f.count("min-time") ? std::atof(f.at("min-time").c_str()) : 0.5;
  const bool derivatives = algo == "did" || algo == "dfd";
  if (algo != "id" && algo != "fd" && algo != "mass" && algo != "bias" && !derivatives)
    die("unknown --algo " + algo);
  if (derivatives && threads > 0) die("--algo " + algo + " runs serially (no --threads)");
  const int nv = model.nv;
  const bool need_M_out = algo == "mass" || derivatives;
  const int blocks = derivatives ? 3 : 1;  // nv x nv outputs per instance
  const double bytes = 8.0 * B * (model.nq + 3.0 * nv + (need_M_out ? blocks * double(nv) * nv : nv));
  if (bytes > 4.0 * (1u << 30)) die("batch needs more than 4 GiB");

  // states as `scandyn bench` draws them: all q (B x nv), then qd, then the third input
  std::mt19937_64 gen(42);
  std::uniform_real_distribution<double> U(-1.0, 1.0);
  const bool free_root = f.count("root") && f.at("root") == "free";
  const int snq = free_root ? nv + 1 : nv;  // scandyn's q entries per instance
  std::vector<double> ang((size_t)B * snq);
  Mat Q(model.nq, B), V(nv, B), X(nv, B), Out(nv, need_M_out ? 0 : B);
  for (auto &a : ang) a = U(gen);
  for (long b = 0; b < B; ++b) {
    double *a = ang.data() + (size_t)b * snq;
    if (!free_root) {
      to_config(model, a, Q.col(b));
      continue;
    }
    const double n = std::sqrt(a[3] * a[3] + a[4] * a[4] + a[5] * a[5] + a[6] * a[6]);
    for (int k = 3; k < 7; ++k) a[k] /= n;
    to_config_free(model, a, Q.col(b));
  }
  for (long b = 0; b < B; ++b)
    for (int i = 0; i < nv; ++i) V(i, b) = U(gen);
  for (long b = 0; b < B; ++b)
    for (int i = 0; i < nv; ++i) X(i, b) = U(gen);
  std::vector<double> Mout(need_M_out ? (size_t)B * blocks * nv * nv : 0);

  std::string strategy, backend = threads > 0 ? "openmp" : "serial";
  std::unique_ptr<pinocchio::ModelPool> pool;
  std::vector<pinocchio::Data> datas;
  const int nthreads = threads > 0 ? threads : 1;
  for (int t = 0; t < nthreads; ++t) datas.emplace_back(model);
  if (threads > 0 && (algo == "id" || algo == "fd")) {
    pool.reset(new pinocchio::ModelPool(model, (size_t)threads));
    strategy = "pool";
  } else {
    strategy = threads > 0 ? "omp-loop" : "loop";
  }
  if (threads > 0) omp_set_num_threads(threads);

  auto one = [&](pinocchio::Data &data, long b) {
    if (algo == "id") {
      Out.col(b) = pinocchio::rnea(model, data, Q.col(b), V.col(b), X.col(b));
    } else if (algo == "fd") {
      Out.col(b) = pinocchio::aba(model, data, Q.col(b), V.col(b), X.col(b));
    } else if (derivatives) {
      const auto out = [&](int k) { return Eigen::Map<Mat>(Mout.data() + ((size_t)b * 3 + k) * nv * nv, nv, nv); };
      if (algo == "did") {
        pinocchio::computeRNEADerivatives(model, data, Q.col(b), V.col(b), X.col(b));
        out(0) = data.dtau_dq;
        out(1) = data.dtau_dv;
        out(2) = data.M;
      } else {
        pinocchio::computeABADerivatives(model, data, Q.col(b), V.col(b), X.col(b));
        out(0) = data.ddq_dq;
        out(1) = data.ddq_dv;
        out(2) = data.Minv;
      }
    } else if (algo == "bias") {
      Out.col(b) = pinocchio::nonLinearEffects(model, data, Q.col(b), V.col(b));
    } else {
      pinocchio::crba(model, data, Q.col(b));
      Eigen::Map<Mat>(Mout.data() + (size_t)b * nv * nv, nv, nv) = data.M;
    }
  };
  auto call = [&]() {
    if (pool) {
      if (algo == "id")
        pinocchio::rneaInParallel((size_t)threads, *pool, Q, V, X, Out);
      else
        pinocchio::abaInParallel((size_t)threads, *pool, Q, V, X, Out);
    } else if (threads > 0) {
#pragma omp parallel for schedule(static) num_threads(threads)
      for (long b = 0; b < B; ++b) one(datas[(size_t)omp_get_thread_num()], b);
    } else {
      for (long b = 0; b < B; ++b) one(datas[0], b);
    }
  };

  call();  // warm-up
  long calls = 0;
  const auto t0 = Clock::now();
  double elapsed = 0;
  long round = 1;
  do {
    for (long r = 0; r < round; ++r) call();
    calls += round;
    elapsed = std::chrono::duration<double>(Clock::now() - t0).count();
    const double per = elapsed / calls, left = min_time - elapsed;
    round = left > 0 ? std::max(1L, std::min(calls, (long)(left / per) + 1)) : 1;  // at most doubling
  } while (elapsed < min_time);
  const double spc = elapsed / calls;
  std::printf("%s,%s,%s,double,%s,%d,%ld,%.6g,%.6g\n", algo.c_str(), strategy.c_str(), backend.c_str(),
              name.c_str(), nv, B, spc, B / spc);
  // keep the results alive
  volatile double sink = need_M_out ? Mout[0] : Out(0, 0);
  (void)sink;
  return 0;
}

}  // namespace

int main(int argc, char **argv) {
  if (argc < 2) die("usage: pin_bench info|eval|bench|version ...");
  const std::string cmd = argv[1];
  if (cmd == "version") {
    std::printf("pinocchio %d.%d.%d, Eigen %d.%d.%d\n", PINOCCHIO_MAJOR_VERSION, PINOCCHIO_MINOR_VERSION,
                PINOCCHIO_PATCH_VERSION, EIGEN_WORLD_VERSION, EIGEN_MAJOR_VERSION, EIGEN_MINOR_VERSION);
    return 0;
  }
  const auto f = parse_flags(argc, argv, 2);
  try {
    if (f.count("root") && f.at("root") != "free") die("--root takes 'free'");
    const pinocchio::Model model = load(need(f, "urdf"), cmd == "bench" && f.count("root"));
    if (cmd == "info") return cmd_info(model);
    if (cmd == "eval") return cmd_eval(model, need(f, "states"), need(f, "out"));
    if (cmd == "bench") return cmd_bench(model, f);
  } catch (const std::exception &e) {
    die(e.what());
  }
  die("unknown command " + cmd);
}
