// tests/prescribed_masks.hpp: which DoFs a hybrid-dynamics test prescribes (nonzero: the
// DoF's acceleration is given), for the chain hybrid's host and device tests.
#pragma once

#include <random>
#include <vector>

#include "scandyn/config.hpp"

namespace scandyn::test {

using PrescribedMask = std::vector<unsigned char>;

// each of the n DoFs prescribed with probability p
inline PrescribedMask random_prescribed_mask(Index n, double p, std::mt19937_64& g) {
  std::bernoulli_distribution coin(p);
  PrescribedMask m(n);
  for (auto& x : m) x = coin(g);
  return m;
}

// Masks that exercise every case: none, all, random 50 / 10 / 90 %, a run at the base,
// a run at the tip, alternating, one long run in the middle.
inline std::vector<PrescribedMask> prescribed_masks(Index n, std::mt19937_64& g) {
  std::vector<PrescribedMask> v;
  v.push_back(PrescribedMask(n, 0));
  v.push_back(PrescribedMask(n, 1));
  v.push_back(random_prescribed_mask(n, 0.5, g));
  v.push_back(random_prescribed_mask(n, 0.1, g));
  v.push_back(random_prescribed_mask(n, 0.9, g));
  PrescribedMask base(n, 0), tip(n, 0), alt(n, 0), mid(n, 0);
  for (Index i = 0; i < n; ++i) {
    base[i] = i < n / 3;
    tip[i] = i >= n - n / 3;
    alt[i] = i % 2;
    mid[i] = i > n / 4 && i < 3 * n / 4;
  }
  for (auto* m : {&base, &tip, &alt, &mid}) v.push_back(*m);
  return v;
}

}  // namespace scandyn::test
