// Random models on a floating base for the tests of multi-DoF joints: a random tree
// on a free root with spherical joints, and a random free chain (a floating base
// followed by 1-DoF links, each the previous one's child).
#pragma once

#include <random>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "test_util.hpp"

namespace scandyn::test {

// A random tree on a free root: random_model's bodies (revolute and prismatic,
// arbitrary axes, rotated inertias) with body 0 a free joint and about a fraction
// `spherical` of the others spherical.
inline Model random_floating_model(int n, unsigned seed, double spherical = 0.35) {
  Model m = random_model(n, seed);
  std::mt19937_64 g(seed * 7 + 1);
  m.bodies[0].type = JointType::Free;
  m.bodies[0].parent = -1;
  m.bodies[0].Xtree = Transform<double>::identity();
  for (int i = 1; i < n; ++i) {
    Body<double>& b = m.bodies[static_cast<std::size_t>(i)];
    if (b.parent < 0) b.parent = 0;  // one root: the free body
    if (std::uniform_real_distribution<double>(0, 1)(g) < spherical) b.type = JointType::Spherical;
  }
  set_joint_offsets(m);
  return m;
}

// random_chain's bodies with body 0 a free joint: a free rope of random links.
inline Model random_free_chain(int n, unsigned seed) {
  Model m = random_chain(n, seed);
  m.name = m.source = "random-free-chain:" + std::to_string(n);
  m.bodies[0].type = JointType::Free;
  m.bodies[0].Xtree = Transform<double>::identity();
  m.joint_names[0] = "root_joint";
  set_joint_offsets(m);
  return m;
}

// B random states of a model (any joints), structure of arrays: entry (i, b) at
// i * B + b; q (nq x B) by random_q in [-3, 3], qd (nv x B) in [-1, 1], u (nv x B:
// qdd or tau) in [-2, 2], and body wrenches (B x nbodies, empty without).
struct SoaStates {
  Index nq = 0, nv = 0, nb = 0, B = 0;
  std::vector<double> q, qd, u;
  std::vector<Force<double>> fext;
};

inline SoaStates random_soa_states(const Model& m, Index B, unsigned seed, bool with_fext) {
  std::mt19937_64 g(seed);
  SoaStates x;
  x.nq = m.nq(), x.nv = m.nv(), x.nb = m.nbodies(), x.B = B;
  x.q.resize(static_cast<std::size_t>(x.nq * B));
  for (Index b = 0; b < B; ++b) {
    const auto qb = random_q(m, g, -3, 3);
    for (Index i = 0; i < x.nq; ++i) x.q[static_cast<std::size_t>(i * B + b)] = qb[static_cast<std::size_t>(i)];
  }
  x.qd = random_vector(g, static_cast<int>(x.nv * B), -1, 1);
  x.u = random_vector(g, static_cast<int>(x.nv * B), -2, 2);
  if (with_fext) x.fext = random_wrenches<double>(g, static_cast<int>(x.nb * B), 1.0);
  return x;
}

// The serial double reference of every instance, SoA (nv x B): forward dynamics
// (aba, u = tau; every instance must succeed) or inverse dynamics (rnea, u = qdd).
inline std::vector<double> soa_reference(const Model& m, const SoaStates& x, bool forward) {
  Data data(m, false);
  std::vector<double> out(x.qd.size()), qi(x.nq), qdi(x.nv), ui(x.nv), oi(x.nv);
  for (Index b = 0; b < x.B; ++b) {
    for (Index i = 0; i < x.nq; ++i) qi[i] = x.q[i * x.B + b];
    for (Index i = 0; i < x.nv; ++i) qdi[i] = x.qd[i * x.B + b], ui[i] = x.u[i * x.B + b];
    const Force<double>* f = x.fext.empty() ? nullptr : x.fext.data() + b * x.nb;
    if (forward) EXPECT_TRUE(aba(m, data, qi.data(), qdi.data(), ui.data(), oi.data(), f).ok());
    else rnea(m, data, qi.data(), qdi.data(), ui.data(), oi.data(), f);
    for (Index i = 0; i < x.nv; ++i) out[i * x.B + b] = oi[i];
  }
  return out;
}

}  // namespace scandyn::test
