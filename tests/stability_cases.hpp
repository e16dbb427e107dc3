// The stability suite's cases, shared by its CPU (tests/algorithm/test_stability.cpp) and GPU
// (tests/cuda/test_cuda_stability.cu) variants: the hard models, the random states and
// their double serial references, what one run of a method measured, and how that
// measurement is recorded as a test property (scripts/accuracy_report reads the
// CPU suite's: key "<problem>.<method>.<precision>", value "%.3g" of the error or
// "reported pivot at DoF k").
#pragma once

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <limits>
#include <random>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "scandyn/accuracy.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn::stability {

template <class S>
const char* precision_name() { return std::is_same<S, float>::value ? "float" : "double"; }

// One instance of a model and its inputs: u is qdd for inverse dynamics and tau
// for forward dynamics.
struct Problem {
  std::string name;
  Model model;
  std::vector<double> q, qd, u;
  std::vector<double> ref_id, ref_fd;  // double rnea(q, qd, u), double aba(q, qd, u)
};

// What one run of a method on a Problem gave.
struct Outcome {
  double err = std::numeric_limits<double>::quiet_NaN();  // rel_err against the double reference
  bool finite = false;     // every output is finite
  Index failed_dof = -1;   // the pivot the method reported as not positive, -1 if none
  bool untouched = false;  // every output still holds the NaN it was filled with
  bool reported() const { return failed_dof >= 0; }
};

// Random inputs, uniform in [-1, 1] (qd in [-qd_max, qd_max]; q = 0 when
// stretched), and both double references.
inline Problem make_problem(std::string name, Model model, unsigned seed, double qd_max = 1.0,
                            bool stretched = false) {
  Problem p;
  p.name = std::move(name);
  p.model = std::move(model);
  const int n = static_cast<int>(p.model.nv());
  std::mt19937_64 rng(seed);
  p.q = stretched ? std::vector<double>(static_cast<std::size_t>(n), 0.0) : test::random_vector(rng, n, -1, 1);
  p.qd = test::random_vector(rng, n, -qd_max, qd_max);
  p.u = test::random_vector(rng, n, -1, 1);
  Data data(p.model, false);
  p.ref_id.resize(static_cast<std::size_t>(n));
  p.ref_fd.resize(static_cast<std::size_t>(n));
  rnea(p.model, data, p.q.data(), p.qd.data(), p.u.data(), p.ref_id.data());
  const Status st = aba(p.model, data, p.q.data(), p.qd.data(), p.u.data(), p.ref_fd.data());
  EXPECT_TRUE(st.ok()) << p.name << ": the double reference aba failed at DoF " << st.failed_dof;
  return p;
}

// Fills o.finite, o.untouched and o.err from a method's output (NaN-filled before
// the call) and the reference.
template <class S>
void measure(const std::vector<S>& out, const std::vector<double>& ref, Outcome& o) {
  o.finite = o.untouched = true;
  for (S x : out) {
    o.finite = o.finite && std::isfinite(x);
    o.untouched = o.untouched && std::isnan(x);
  }
  o.err = rel_err(out.data(), ref.data(), ref.size());
}

// Records the measurement as the test property "<problem>.<method>.<precision>".
template <class S>
void record(const Problem& p, const std::string& method, const Outcome& o) {
  const std::string key = p.name + "." + method + "." + precision_name<S>();
  char value[96];
  if (o.reported()) std::snprintf(value, sizeof value, "reported pivot at DoF %d", int(o.failed_dof));
  else std::snprintf(value, sizeof value, "%.3g", o.err);
  ::testing::Test::RecordProperty(key, value);
}

// ---- models ---------------------------------------------------------------------

inline Model rope(int n) { return load_model("rope:" + std::to_string(n)); }

// rope:n with every other link's inertia (mass, first moment, rotational inertia)
// multiplied by ratio: neighbouring links differ in mass by ratio and 1 / ratio.
inline Model mass_ratio_rope(int n, double ratio) {
  Model m = rope(n);
  for (int i = 1; i < n; i += 2) {
    Inertia<double>& I = m.bodies[static_cast<std::size_t>(i)].I;
    I.m *= ratio;
    I.h = ratio * I.h;
    for (double* x : {&I.I.xx, &I.I.yy, &I.I.zz, &I.I.xy, &I.I.xz, &I.I.yz}) *x *= ratio;
  }
  m.name = m.source = "rope-mass-ratio:" + std::to_string(n);
  return m;
}

// rope:n whose last link's inertia (mass, first moment, rotational inertia) is
// multiplied by ratio: a heavy weight on a light rope. In float the mass matrix's
// Cholesky fails where the ABA does not (host fd_jsi / aba, float, 64 links, 256
// states of test::random_exact_batch: ratio 1e4 fails 6, 3e4 103, 1e5 227, 1e6
// all; the ABA none, though its error grows with the ratio: 1.7e-3, 5e-3, 1.1e-2,
// 0.19).
inline Model heavy_tip_rope(int n, double ratio) {
  Model m = rope(n);
  Inertia<double>& I = m.bodies.back().I;
  I.m *= ratio;
  I.h = ratio * I.h;
  for (double* x : {&I.I.xx, &I.I.yy, &I.I.zz, &I.I.xy, &I.I.xz, &I.I.yz}) *x *= ratio;
  m.name = m.source = "rope-heavy-tip:" + std::to_string(n);
  return m;
}

// rope:n whose links are near point masses: 10 g at the link centre, rotational
// inertia 1e-9 kg m^2 about every axis through it.
inline Model tiny_inertia_rope(int n) {
  Model m = rope(n);
  for (auto& b : m.bodies) b.I = Inertia<double>::from_com(0.01, {0, 0, -0.005}, Sym3<double>{1e-9, 1e-9, 1e-9, 0, 0, 0});
  m.name = m.source = "rope-tiny-inertia:" + std::to_string(n);
  return m;
}

// rope:n with every joint axis along x: a planar chain whose axes are all parallel.
inline Model parallel_axes_rope(int n) {
  Model m = rope(n);
  for (auto& b : m.bodies) b.axis = {1, 0, 0};
  m.name = m.source = "rope-parallel-axes:" + std::to_string(n);
  return m;
}

}  // namespace scandyn::stability
