// scandyn/algorithm/loop_chains.hpp: the layout the CUDA iterative loop solver
// (scandyn/cuda/loop_iterative.hpp) walks, host side and without CUDA: a tree that is a
// set of unbranched chains hanging from the fixed base, each contiguous in DoF order
// (curtain:K:N / cloth:K:N: rope k is bodies [k N, (k + 1) N); fivebar and fourbar too),
// and per body the loop sides acting on it (what loop_body_wrench gathers: J^T lambda's
// body wrenches without a scatter, since one body carries the sides of several loops,
// e.g. a cloth's link j of rope k those of loops (k - 1, j) and (k, j)).
#pragma once

#include <algorithm>
#include <string>
#include <vector>

#include "scandyn/algorithm/loops.hpp"

namespace scandyn {

struct LoopChainLayout {
  std::vector<Index> chain_start;  // (chains + 1): chain c is bodies [chain_start[c], chain_start[c + 1])
  std::vector<Index> side_start;   // (bodies + 1): body i's loop sides side[side_start[i] .. side_start[i + 1])
  std::vector<Index> side;         // 2 k + s: loop k's side s (0: a, 1: b), per body by increasing k, s
  std::vector<Index> row_of;       // (loops + 1): loop k's first row; row_of[loops] = m
  Index longest = 0;               // the longest chain's bodies
};

// The layout of model's tree and the loops' rows. Throws LoopError naming why for a tree
// that is not a set of unbranched chains from the fixed base contiguous in DoF order (a
// multi-DoF joint, e.g. a floating base or a ball joint; a body whose parent is neither
// the base nor the body before it: a branch, or chains interleaved in DoF order).
template <class S>
LoopChainLayout loop_chain_layout(const ModelTpl<S>& model, const std::vector<LoopRow<S>>& rows) {
  const std::string who = "the CUDA iterative loop solver takes a tree of unbranched chains hanging from the fixed base "
                          "(curtain:K:N, cloth:K:N): ";
  if (model.multi_dof()) throw LoopError(who + "the model has multi-DoF joints (a floating base or ball joints)");
  const Index n = static_cast<Index>(model.bodies.size());
  LoopChainLayout out;
  for (Index i = 0; i < n; ++i) {
    const Index p = model.bodies[static_cast<std::size_t>(i)].parent;
    if (p < 0) {
      out.chain_start.push_back(i);
    } else if (p != i - 1) {
      throw LoopError(who + "body " + std::to_string(i) + " hangs from body " + std::to_string(p) +
                      ", not from the base or from body " + std::to_string(i - 1) +
                      " (the tree branches, or its chains are not contiguous in DoF order)");
    }
  }
  out.chain_start.push_back(n);
  for (std::size_t c = 0; c + 1 < out.chain_start.size(); ++c)
    out.longest = std::max(out.longest, out.chain_start[c + 1] - out.chain_start[c]);
  const Index nl = static_cast<Index>(rows.size());
  out.row_of.assign(static_cast<std::size_t>(nl) + 1, 0);
  for (Index k = 0; k < nl; ++k) out.row_of[k + 1] = out.row_of[k] + rows[k].rows();
  out.side_start.assign(static_cast<std::size_t>(n) + 1, 0);
  for (const LoopRow<S>& l : rows)
    for (int s = 0; s < 2; ++s) {
      const Index b = s == 0 ? l.body_a : l.body_b;
      if (b >= 0) ++out.side_start[static_cast<std::size_t>(b) + 1];
    }
  for (Index i = 0; i < n; ++i) out.side_start[i + 1] += out.side_start[i];
  out.side.resize(static_cast<std::size_t>(out.side_start[n]));
  std::vector<Index> fill(out.side_start.begin(), out.side_start.end() - 1);
  for (Index k = 0; k < nl; ++k)
    for (int s = 0; s < 2; ++s) {
      const Index b = s == 0 ? rows[k].body_a : rows[k].body_b;
      if (b >= 0) out.side[static_cast<std::size_t>(fill[b]++)] = 2 * k + s;
    }
  return out;
}

}  // namespace scandyn
