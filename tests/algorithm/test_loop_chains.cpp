// The host side of the CUDA iterative loop solver (scandyn/cuda/loop_iterative.hpp),
// which runs without a device: loop_chain_layout (the chains and every body's loop
// sides) and its refusals, and the per-chain *_range passes of loop_iterative.hpp
// composed over the chains against the whole-tree passes the CPU solver runs, bit for
// bit (the same arithmetic per body, in the same order), with loop_body_wrench's gather
// against loop_point_wrenches' scatter.
#include <gtest/gtest.h>

#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "scandyn/algorithm/loop_chains.hpp"
#include "scandyn/algorithm/loop_iterative.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

template <class T>
bool same_bits(const std::vector<T>& a, const std::vector<T>& b) {
  return a.size() == b.size() && std::memcmp(a.data(), b.data(), sizeof(T) * a.size()) == 0;
}

TEST(LoopChains, ClothLayout) {
  const Model model = load_model("cloth:5:7");
  const LoopSet loops = generator_loops("cloth:5:7", model);
  const auto rows = loop_rows_of<double>(loops);
  const LoopChainLayout lay = loop_chain_layout(model, rows);
  ASSERT_EQ(lay.chain_start.size(), 6u);
  for (Index c = 0; c <= 5; ++c) EXPECT_EQ(lay.chain_start[c], 7 * c);
  EXPECT_EQ(lay.longest, 7);
  EXPECT_EQ(lay.row_of.back(), loops.rows());
  // every loop side appears once, at its body, in increasing (loop, side) order
  std::vector<int> seen(2 * rows.size(), 0);
  for (Index i = 0; i < model.nv(); ++i)
    for (Index e = lay.side_start[i]; e < lay.side_start[i + 1]; ++e) {
      const Index k = lay.side[e] >> 1;
      const int s = lay.side[e] & 1;
      EXPECT_EQ(s == 0 ? rows[k].body_a : rows[k].body_b, i);
      if (e > lay.side_start[i]) {
        EXPECT_LT(lay.side[e - 1], lay.side[e]);
      }
      ++seen[lay.side[e]];
    }
  for (std::size_t k = 0; k < rows.size(); ++k)
    for (int s = 0; s < 2; ++s) EXPECT_EQ(seen[2 * k + s], (s == 0 ? rows[k].body_a : rows[k].body_b) >= 0 ? 1 : 0);
}

TEST(LoopChains, RefusesOtherTrees) {
  for (const std::string spec : {"tree:12:1", "ballrope:3"}) {
    SCOPED_TRACE(spec);
    const Model model = load_model(spec);
    try {
      loop_chain_layout(model, std::vector<LoopRow<double>>{});
      FAIL() << "no error";
    } catch (const LoopError& e) {
      const std::string what = e.what();
      EXPECT_NE(what.find("unbranched chains"), std::string::npos) << what;
      EXPECT_NE(what.find(spec == "ballrope:3" ? "multi-DoF" : "branches"), std::string::npos) << what;
    }
  }
  // chains from the base: accepted (rope, curtain, and the five-bar's two arms)
  for (const std::string spec : {"rope:5", "curtain:3:4", "fivebar", "fourbar"})
    EXPECT_NO_THROW(loop_chain_layout(load_model(spec), std::vector<LoopRow<double>>{})) << spec;
}

// The per-chain composition of every pass the CUDA solver runs equals the whole-tree pass.
TEST(LoopChains, PerChainPassesEqualTheWholeTreeBitForBit) {
  std::mt19937_64 rng(11);
  for (const std::string spec : {"cloth:5:7", "cloth:3:4", "fivebar"}) {
    SCOPED_TRACE(spec);
    const Model model = load_model(spec);
    const LoopSet loops = generator_loops(spec, model);
    const auto rows = loop_rows_of<double>(loops);
    const LoopChainLayout lay = loop_chain_layout(model, rows);
    const Index n = model.nv(), m = loops.rows(), nl = static_cast<Index>(rows.size());
    const Body<double>* bodies = model.bodies.data();
    const Index nc = static_cast<Index>(lay.chain_start.size()) - 1;
    const std::vector<double> q = test::random_vector(rng, n, -0.5, 0.5), qd = test::random_vector(rng, n, -1, 1),
                              tau = test::random_vector(rng, n, -1, 1), lam = test::random_vector(rng, m, -1, 1),
                              xv = test::random_vector(rng, n, -1, 1);
    struct Arrays {
      std::vector<Transform<double>> X0, Xup;
      std::vector<Motion<double>> v, c, a, acc, acc2;
      std::vector<Force<double>> U, pA, f;
      std::vector<ABInertia<double>> IA;
      std::vector<double> D, u, qdd0, s, s2;
      std::vector<Mat6<double>> Om, Om2;
      explicit Arrays(Index n)
          : X0(n), Xup(n), v(n), c(n), a(n), acc(n), acc2(n), U(n), pA(n), f(n), IA(n), D(n), u(n), qdd0(n), s(n),
            s2(n), Om(n), Om2(n) {}
    } w(n), h(n);
    // whole tree
    loop_body_motion(bodies, n, q.data(), qd.data(), w.X0.data(), w.v.data(), w.a.data());
    ASSERT_LT(loop_aba_factor(bodies, n, model.gravity, q.data(), qd.data(), tau.data(), w.Xup.data(), w.U.data(),
                              w.D.data(), w.qdd0.data(), w.v.data(), w.c.data(), w.a.data(), w.IA.data(), w.pA.data(),
                              w.u.data()),
              0);
    loop_point_wrenches(rows.data(), nl, n, w.X0.data(), lam.data(), w.f.data());
    loop_tree_response(bodies, n, w.Xup.data(), w.U.data(), w.D.data(), w.f.data(), w.pA.data(), w.s.data(),
                       w.acc.data());
    loop_tree_response(bodies, n, w.Xup.data(), static_cast<const Force<double>*>(nullptr),
                       static_cast<const double*>(nullptr), w.f.data(), w.pA.data(), w.s2.data(), w.acc2.data());
    loop_joint_motion(bodies, n, w.Xup.data(), xv.data(), w.c.data());
    loop_response_blocks(bodies, n, w.Xup.data(), w.U.data(), w.D.data(), w.Om.data());
    loop_response_blocks(bodies, n, w.Xup.data(), static_cast<const Force<double>*>(nullptr),
                         static_cast<const double*>(nullptr), w.Om2.data());
    // per chain (h.c: first the ABA's scratch, then J x's motions, as above)
    std::vector<Motion<double>> v1(n), a1(n);
    for (Index ch = 0; ch < nc; ++ch) {
      const Index b = lay.chain_start[ch], e = lay.chain_start[ch + 1];
      loop_body_motion_range(bodies, b, e, q.data(), qd.data(), h.X0.data(), h.v.data(), h.a.data());
    }
    EXPECT_TRUE(same_bits(h.X0, w.X0));
    v1 = h.v, a1 = h.a;
    for (Index ch = 0; ch < nc; ++ch) {
      const Index b = lay.chain_start[ch], e = lay.chain_start[ch + 1];
      ASSERT_LT(loop_aba_factor_range(bodies, b, e, model.gravity, q.data(), qd.data(), tau.data(), h.Xup.data(),
                                      h.U.data(), h.D.data(), h.qdd0.data(), h.v.data(), h.c.data(), h.a.data(),
                                      h.IA.data(), h.pA.data(), h.u.data()),
                0);
    }
    for (Index i = 0; i < n; ++i) h.f[i] = loop_body_wrench(rows.data(), lay.row_of.data(), lay.side_start.data(),
                                                             lay.side.data(), i, h.X0.data(), lam.data());
    for (Index ch = 0; ch < nc; ++ch) {
      const Index b = lay.chain_start[ch], e = lay.chain_start[ch + 1];
      loop_tree_response_range(bodies, b, e, h.Xup.data(), h.U.data(), h.D.data(), h.f.data(), h.pA.data(),
                               h.s.data(), h.acc.data());
      loop_tree_response_range(bodies, b, e, h.Xup.data(), static_cast<const Force<double>*>(nullptr),
                               static_cast<const double*>(nullptr), h.f.data(), h.pA.data(), h.s2.data(),
                               h.acc2.data());
      loop_joint_motion_range(bodies, b, e, h.Xup.data(), xv.data(), h.c.data());
      loop_response_blocks_range(bodies, b, e, h.Xup.data(), h.U.data(), h.D.data(), h.Om.data());
      loop_response_blocks_range(bodies, b, e, h.Xup.data(), static_cast<const Force<double>*>(nullptr),
                                 static_cast<const double*>(nullptr), h.Om2.data());
    }
    EXPECT_TRUE(same_bits(h.Xup, w.Xup));
    EXPECT_TRUE(same_bits(h.U, w.U));
    EXPECT_TRUE(same_bits(h.D, w.D));
    EXPECT_TRUE(same_bits(h.qdd0, w.qdd0));
    EXPECT_TRUE(same_bits(h.IA, w.IA));
    EXPECT_TRUE(same_bits(h.f, w.f));
    EXPECT_TRUE(same_bits(h.s, w.s));
    EXPECT_TRUE(same_bits(h.acc, w.acc));
    EXPECT_TRUE(same_bits(h.s2, w.s2));
    EXPECT_TRUE(same_bits(h.acc2, w.acc2));
    EXPECT_TRUE(same_bits(h.c, w.c));
    EXPECT_TRUE(same_bits(h.Om, w.Om));
    EXPECT_TRUE(same_bits(h.Om2, w.Om2));
    // per-loop rows (gamma, J x) one loop at a time against all loops at once
    std::vector<double> g_all(m), g_one(m), jx_all(m), jx_one(m);
    loop_rows(bodies, n, rows.data(), nl, w.X0.data(), v1.data(), a1.data(), static_cast<double*>(nullptr),
              static_cast<double*>(nullptr), g_all.data());
    loop_rows_apply(rows.data(), nl, w.X0.data(), w.c.data(), jx_all.data());
    for (Index k = 0; k < nl; ++k) {
      loop_rows(bodies, n, rows.data() + k, Index(1), w.X0.data(), v1.data(), a1.data(), static_cast<double*>(nullptr),
                static_cast<double*>(nullptr), g_one.data() + lay.row_of[k]);
      loop_rows_apply(rows.data() + k, Index(1), w.X0.data(), w.c.data(), jx_one.data() + lay.row_of[k]);
    }
    EXPECT_TRUE(same_bits(g_one, g_all));
    EXPECT_TRUE(same_bits(jx_one, jx_all));
  }
}

}  // namespace
}  // namespace scandyn
