// tests/loop_cases.hpp: the closed-loop models the loop engines' tests run on (the
// generators' loops, and the five-bar closed by a weld instead of a point), and random
// closed states (projected onto the loops).
#pragma once

#include <random>
#include <string>
#include <vector>

#include "scandyn/algorithm/loops.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn::test {

struct LoopCase {
  std::string spec;
  Model model;
  LoopSet loops;
};

// specs: generators with loops; "fivebar+weld": the five-bar's loop as a weld (6 rows on 4 DoF).
inline std::vector<LoopCase> loop_cases(const std::vector<std::string>& specs) {
  std::vector<LoopCase> v;
  for (const std::string& s : specs) {
    const bool weld = s == "fivebar+weld";
    const std::string gen = weld ? "fivebar" : s;
    LoopCase c{s, load_model(gen), {}};
    c.loops = generator_loops(gen, c.model);
    if (weld) {
      c.loops.loops[0].type = LoopType::Weld;
      c.loops.loops[0].point_b = c.loops.loops[0].point_a;
    }
    v.push_back(std::move(c));
  }
  return v;
}

// A random closed state: q near 0 (|q_i| <= 0.2) and qd in [-1, 1] projected onto the
// loops, drawn again until the projection converges (the weld-closed five-bar is a
// rigid structure: some draws lead elsewhere). Returns the final |phi| (<= 1e-12 on success).
inline double closed_state(const LoopCase& c, std::mt19937_64& g, std::vector<double>& q, std::vector<double>& qd) {
  const Index n = c.model.nv();
  double r = 1;
  for (int attempt = 0; attempt < 50 && r > 1e-12; ++attempt) {
    q = random_vector(g, n, -0.2, 0.2), qd = random_vector(g, n, -1, 1);
    r = project_to_loops(c.model, c.loops, q.data(), qd.data());
  }
  return r;
}

}  // namespace scandyn::test
