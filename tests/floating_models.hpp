// Random models on a floating base for the tests of multi-DoF joints: a random tree
// on a free root with spherical joints, and a random free chain (a floating base
// followed by 1-DoF links, each the previous one's child).
#pragma once

#include <random>
#include <string>
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

// A model with the name the tests trace it by.
struct NamedModel {
  std::string name;
  Model m;
};

// The multi-DoF models the derivative tests run on: hyq and atlas on a floating base,
// the generator specs `floating_specs` on a floating base, the ball-joint rope of
// rope_links links on a fixed and on a floating root, a random free chain of
// chain_links links (chain_seed), and random floating trees of `trees` bodies (seed
// tree_seed + n, 40% spherical joints).
inline std::vector<NamedModel> multi_dof_models(const std::vector<std::string>& floating_specs, int rope_links,
                                                int chain_links, unsigned chain_seed, const std::vector<int>& trees,
                                                unsigned tree_seed) {
  std::vector<NamedModel> c;
  c.push_back({"hyq (floating)", load_floating(model_path("hyq.urdf"))});
  c.push_back({"atlas (floating)", load_floating(model_path("atlas.urdf"))});
  for (const std::string& spec : floating_specs) c.push_back({spec + " (floating)", load_floating(spec)});
  const std::string rope = "ballrope:" + std::to_string(rope_links);
  c.push_back({rope + " (fixed root)", load_model(rope)});
  c.push_back({rope + " (floating)", load_floating(rope)});
  c.push_back({"random free chain " + std::to_string(chain_links), random_free_chain(chain_links, chain_seed)});
  for (int n : trees)
    c.push_back({"random floating tree " + std::to_string(n), random_floating_model(n, tree_seed + n, 0.4)});
  return c;
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

// SoaStates in precision S, and the engines' soa input views of them (u: qdd for
// inverse dynamics, tau for forward dynamics).
template <class S>
struct SoaInputs {
  Index nq, nv, B;
  std::vector<S> q, qd, u;
  std::vector<Force<S>> fext;
  explicit SoaInputs(const SoaStates& x)
      : nq(x.nq), nv(x.nv), B(x.B), q(cast_vector<S>(x.q)), qd(cast_vector<S>(x.qd)), u(cast_vector<S>(x.u)),
        fext(cast_wrenches<S>(x.fext)) {}
  IdBatchIn<S> id() const {
    using V = BatchView<const S>;
    return {V::soa(q.data(), nq, B), V::soa(qd.data(), nv, B), V::soa(u.data(), nv, B), fext.data()};
  }
  FdBatchIn<S> fd() const {
    using V = BatchView<const S>;
    return {V::soa(q.data(), nq, B), V::soa(qd.data(), nv, B), V::soa(u.data(), nv, B), fext.data()};
  }
};

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
