// Shared helpers for the test programs: model paths, random states, tolerances.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <random>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "scandyn/accuracy.hpp"
#include "scandyn/batch.hpp"
#include "scandyn/model/load.hpp"

namespace scandyn::test {

// Directory holding iiwa.urdf, hyq.urdf, atlas.urdf: $SCANDYN_MODELS_DIR, else the
// build-time default (the shipped models/ of the source tree).
inline std::string models_dir() {
  const char* env = std::getenv("SCANDYN_MODELS_DIR");
  return env && *env ? std::string(env) : std::string(SCANDYN_DEFAULT_MODELS_DIR);
}
inline std::string model_path(const std::string& file) { return models_dir() + "/" + file; }

// The shipped robots (iiwa.urdf, hyq.urdf, atlas.urdf). GRiD's atlas.urdf has four
// links whose inertia no rigid body can have, so the physical-inertia check is waived.
inline Model load_robot(const std::string& file) {
  BuildOptions o;
  o.require_physical_inertia = false;
  return load_urdf(model_path(file), o);
}

// The models every CPU engine test runs: the three robots, a random tree with
// revolute and prismatic joints and a rope.
inline std::vector<std::pair<std::string, Model>> engine_test_models() {
  return {{"iiwa", load_robot("iiwa.urdf")},
          {"hyq", load_robot("hyq.urdf")},
          {"atlas", load_robot("atlas.urdf")},
          {"tree:30:7", load_model("tree:30:7")},
          {"rope:40", load_model("rope:40")}};
}

// The scandyn executable built alongside the tests.
inline std::string cli_path() { return SCANDYN_CLI_PATH; }

// Tolerance by precision: Tol<S>(for_double, for_float).
template <class S>
constexpr S Tol(double for_double, double for_float) {
  return std::is_same<S, float>::value ? S(for_float) : S(for_double);
}

// max_i |x_i|
inline double max_abs(const std::vector<double>& x) {
  double m = 0;
  for (double v : x) m = std::max(m, std::abs(v));
  return m;
}

// max_i |x_i - y_i| over x's entries (y at least as long)
inline double max_diff(const std::vector<double>& x, const std::vector<double>& y) {
  double m = 0;
  for (std::size_t k = 0; k < x.size(); ++k) m = std::max(m, std::abs(x[k] - y[k]));
  return m;
}

// Uniform random vector in [lo, hi].
inline std::vector<double> random_vector(std::mt19937_64& rng, int n, double lo, double hi) {
  std::uniform_real_distribution<double> d(lo, hi);
  std::vector<double> v(static_cast<std::size_t>(n));
  for (auto& x : v) x = d(rng);
  return v;
}

// n random body wrenches, each component uniform in [-a, a].
template <class S>
std::vector<Force<S>> random_wrenches(std::mt19937_64& rng, int n, double a) {
  std::vector<Force<S>> out(static_cast<std::size_t>(n));
  for (auto& f : out) {
    const auto r = random_vector(rng, 6, -a, a);
    f = Force<S>{{S(r[0]), S(r[1]), S(r[2])}, {S(r[3]), S(r[4]), S(r[5])}};
  }
  return out;
}

// A batch of B random states of an nv-DoF model, every value a double exactly
// representable in S (so S and double runs see the same inputs): q in [-3.1, 3.1],
// qd and u (qdd or tau) in [-2, 2], each (nv x B) with entry (i, b) at i * B + b;
// fext (B x nv) body wrenches with components in [-1, 1].
template <class S>
void random_exact_batch(Index nv, Index B, unsigned seed, std::vector<double>& q, std::vector<double>& qd,
                        std::vector<double>& u, std::vector<Force<double>>& fext) {
  std::mt19937_64 g(seed);
  auto fill = [&](std::vector<double>& v, double a) {
    v = random_vector(g, static_cast<int>(nv * B), -a, a);
    for (double& x : v) x = double(S(x));
  };
  fill(q, 3.1);
  fill(qd, 2.0);
  fill(u, 2.0);
  fext = random_wrenches<double>(g, static_cast<int>(nv * B), 1.0);
  for (auto& f : fext) f = f.template cast<S>().template cast<double>();
}

template <class T>
std::vector<T> cast_vector(const std::vector<double>& v) {
  return std::vector<T>(v.begin(), v.end());
}

// Body wrenches in precision T.
template <class T>
std::vector<Force<T>> cast_wrenches(const std::vector<Force<double>>& f) {
  std::vector<Force<T>> out(f.size());
  for (std::size_t k = 0; k < f.size(); ++k) out[k] = f[k].template cast<T>();
  return out;
}

// scandyn::rel_err over two vectors; NaN if their sizes differ.
template <class A, class B>
double max_rel_err(const std::vector<A>& a, const std::vector<B>& b) {
  if (a.size() != b.size()) return std::numeric_limits<double>::quiet_NaN();
  return rel_err(a.data(), b.data(), b.size());
}

// A random tree built directly from Body structs (independent of the loader):
// arbitrary unit axes, ~25% prismatic, rotated inertias with offset centres of mass.
inline Model random_model(int n, unsigned seed) {
  std::mt19937_64 g(seed);
  auto uni = [&](double lo, double hi) { return std::uniform_real_distribution<double>(lo, hi)(g); };
  auto vec = [&](double s) { return Vec3<double>{uni(-s, s), uni(-s, s), uni(-s, s)}; };
  Model m;
  m.name = m.source = "random:" + std::to_string(n);
  for (int i = 0; i < n; ++i) {
    Body<double> b;
    b.parent = i == 0 ? -1 : static_cast<Index>(std::uniform_int_distribution<int>(-1, i - 1)(g));
    b.type = uni(0, 1) < 0.25 ? JointType::Prismatic : JointType::Revolute;
    Vec3<double> ax = vec(1);
    const double nrm = std::sqrt(dot(ax, ax));
    b.axis = (1.0 / nrm) * ax;
    b.Xtree = Transform<double>::from_pose(rpy_matrix(uni(-3, 3), uni(-1.5, 1.5), uni(-3, 3)), vec(0.3));
    const double p1 = uni(0.02, 0.2), p2 = uni(0.02, 0.2), p3 = uni(std::fabs(p1 - p2) + 0.01, p1 + p2);
    const Mat3<double> R = rpy_matrix(uni(-3, 3), uni(-1.5, 1.5), uni(-3, 3));
    // Ic = R diag(p) R^T
    Mat3<double> D = Mat3<double>::zero();
    D(0, 0) = p1; D(1, 1) = p2; D(2, 2) = p3;
    const Sym3<double> Ic = Sym3<double>::from(R * D * transpose(R));
    b.I = Inertia<double>::from_com(uni(0.5, 2.0), vec(0.1), Ic);
    m.bodies.push_back(b);
    m.joint_names.push_back("j" + std::to_string(i));
    m.link_names.push_back("l" + std::to_string(i));
  }
  return m;
}

// A random configuration (nq entries) of m: uniform in [lo, hi], then each quaternion
// (spherical joints, the floating base's q_3..q_6) normalised. For a model of 1-DoF
// joints the same draws as random_vector(rng, nv, lo, hi).
inline std::vector<double> random_q(const Model& m, std::mt19937_64& rng, double lo = -2, double hi = 2) {
  std::vector<double> q = random_vector(rng, static_cast<int>(m.nq()), lo, hi);
  if (!m.multi_dof()) return q;
  for (const Body<double>& b : m.bodies) {
    if (b.type != JointType::Free && b.type != JointType::Spherical) continue;
    double* x = q.data() + b.idx_q + (b.type == JointType::Free ? 3 : 0);
    const double n = std::sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2] + x[3] * x[3]);
    for (int k = 0; k < 4; ++k) x[k] /= n;
  }
  return q;
}

// A model on a free joint at its root (--floating-base), nonphysical inertias allowed
// (GRiD's atlas.urdf).
inline Model load_floating(const std::string& spec) {
  BuildOptions o;
  o.floating_base = true;
  o.require_physical_inertia = false;
  return load_model(spec, o);
}

// One free rigid body (a floating base alone, no gravity): mass, centre of mass and
// principal moments along the body axes.
inline Model free_body_model(double mass, const Vec3<double>& com, const Vec3<double>& moments) {
  Model m;
  m.name = m.source = "free body";
  Body<double> b;
  b.parent = -1;
  b.type = JointType::Free;
  b.axis = {1, 0, 0};
  b.Xtree = Transform<double>::identity();
  b.I = Inertia<double>::from_com(mass, com, Sym3<double>{moments.x, moments.y, moments.z, 0, 0, 0});
  m.bodies = {b};
  m.joint_names = {"root_joint"};
  m.link_names = {"body"};
  m.q_lower = {-HUGE_VAL};
  m.q_upper = {HUGE_VAL};
  m.gravity = {0, 0, 0};
  set_joint_offsets(m);
  return m;
}

// random_model's bodies as an unbranched chain (body i's parent is body i - 1).
inline Model random_chain(int n, unsigned seed) {
  Model m = random_model(n, seed);
  m.name = m.source = "random-chain:" + std::to_string(n);
  for (int i = 0; i < n; ++i) m.bodies[static_cast<std::size_t>(i)].parent = i - 1;
  return m;
}

// random_model's bodies as unbranched chains hanging from the base, numbered chain
// by chain: body i's parent is body i - 1, except at the chain starts `starts`
// (and body 0), whose parent is the base.
inline Model random_chains_from_base(int n, unsigned seed, const std::vector<int>& starts) {
  Model m = random_chain(n, seed);
  m.name = m.source = "random-chains:" + std::to_string(n);
  for (int s : starts) m.bodies[static_cast<std::size_t>(s)].parent = -1;
  return m;
}

// Models of up to 64 DoF at the shape edges of the thread-per-instance kernels: chains
// at the register capacities (8, 16, 32, 64) and one past them, trees, chains from the
// base, and random trees with arbitrary axes and ~25% prismatic joints whose parents
// are drawn at random (the numbering is not a preorder: subtrees are not contiguous).
inline std::vector<std::pair<std::string, Model>> thread_shape_models() {
  std::vector<std::pair<std::string, Model>> models;
  for (const char* spec : {"chain:1", "chain:8", "chain:9", "chain:16", "chain:17", "chain:33", "chain:64",
                           "tree:30:1", "tree:60:2", "curtain:3:5", "rope:40"})
    models.emplace_back(spec, load_model(spec));
  models.emplace_back("random_model(12)", random_model(12, 3));
  models.emplace_back("random_model(40)", random_model(40, 4));
  models.emplace_back("random_model(64)", random_model(64, 5));
  return models;
}

// Three nv x nv outputs of B instances in one buffer (the derivative engines'
// blocks), NaN-filled: instance-innermost (soa: block k's entry e of instance b at
// [(k nv^2 + e) B + b]) or each instance's three blocks side by side ([b 3 nv^2 + k
// nv^2 + e]).
template <class S>
struct DerivativeBlocks {
  std::vector<S> data;
  BatchView<S> v[3];
  DerivativeBlocks(Index nv, Index B, bool soa)
      : data(static_cast<std::size_t>(3) * nv * nv * B, std::numeric_limits<S>::quiet_NaN()) {
    const std::ptrdiff_t nn = static_cast<std::ptrdiff_t>(nv) * nv;
    for (int k = 0; k < 3; ++k)
      v[k] = soa ? BatchView<S>{data.data() + k * nn * B, B, B, 1} : BatchView<S>{data.data() + k * nn, B, 1, 3 * nn};
  }
  S at(int k, Index i, Index j, Index b, Index nv) const { return v[k].at(i * nv + j, b); }
};

// Largest |a - b| / max(1, max |b|) over instances, per block (blocks k0..k1 - 1);
// infinite when a has an entry that is not finite.
template <class S>
double block_err(const DerivativeBlocks<S>& a, const DerivativeBlocks<S>& b, Index nv, Index B, int k0 = 0,
                 int k1 = 3) {
  double worst = 0;
  for (int k = k0; k < k1; ++k)
    for (Index i = 0; i < B; ++i) {
      double scale = 1, err = 0;
      for (Index e = 0; e < nv * nv; ++e) {
        const double x = double(a.v[k].at(e, i)), y = double(b.v[k].at(e, i));
        if (!std::isfinite(x)) return INFINITY;
        scale = std::max(scale, std::fabs(y));
        err = std::max(err, std::fabs(x - y));
      }
      worst = std::max(worst, err / scale);
    }
  return worst;
}

}  // namespace scandyn::test
