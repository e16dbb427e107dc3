// Random models on a floating base for the tests of multi-DoF joints: a random tree
// on a free root with spherical joints, and a random free chain (a floating base
// followed by 1-DoF links, each the previous one's child).
#pragma once

#include <random>

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

}  // namespace scandyn::test
