// tests/prescribed_masks.hpp: which DoFs a hybrid-dynamics test prescribes (nonzero: the
// DoF's acceleration is given), for the chain hybrid's host and device tests.
#pragma once

#include <random>
#include <string>
#include <utility>
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

// Runs of prescribed DoFs much longer than a chunk, on an n-DoF rope (n >= 2000), each
// with its float bound: a run of DoFs n/20 .. n - n/20 - 1, every DoF, runs at the
// chain's start (the first 3/4) and end (the last 3/4), runs of 300 parted by single free
// links, alternating (runs of one). Free links that carry a long rigid run (the run's
// composite in their pivots) are ill-conditioned in float: on rope:2000 the serial float
// hybrid's own error there is 4e-4 / 6e-3, and the chain's varies from 3e-4 to 5e-2 with
// the seed and chunk, as the chain's walks before the run scan did (to 1e-1 over seeds
// 12..19; double stays within 1e-10): bound 1e-1 there, the float bound the device test
// takes for rope:10^5; 1e-2 elsewhere.
struct NamedMask {
  std::string name;
  PrescribedMask mask;
  double float_bound;
};
inline std::vector<NamedMask> long_run_masks(Index n) {
  std::vector<NamedMask> v;
  auto make = [&](std::string name, double float_bound, auto&& given) {
    PrescribedMask m(n);
    for (Index i = 0; i < n; ++i) m[i] = given(i);
    v.push_back({std::move(name), std::move(m), float_bound});
  };
  make("middle run", 1e-1, [&](Index i) { return i >= n / 20 && i < n - n / 20; });
  make("all", 1e-2, [](Index) { return true; });
  make("run at the start", 1e-2, [&](Index i) { return i < n - n / 4; });
  make("run at the end", 1e-1, [&](Index i) { return i >= n / 4; });
  make("runs of 300", 1e-2, [](Index i) { return i % 301 != 0; });
  make("alternating", 1e-2, [](Index i) { return i % 2 == 1; });
  return v;
}

}  // namespace scandyn::test
