// The GPU's sparse Cholesky of the factor graph (factor_graph::GpuSparseCholesky:
// cuSOLVER's csrchol on the explicit normal matrix, permuted by CHOLMOD's elimination
// order) against independent truths and against CHOLMOD on the same system:
// - trees (chain:20, iiwa, tree:12:1): forward dynamics against the serial ABA,
//   inverse dynamics against the serial RNEA, under CHOLMOD's nested dissection and
//   the tree order: 1e-12 relative (max |x - ref| <= 1e-12 (1 + max |ref|)), double;
// - loops (fivebar, cloth:4:4, cloth:10:10 with their generators' point loops, random
//   closed states, beta = kLoopBeta and kLoopRefine refinement steps as
//   bench_factor_graph solves them): J qdd + gamma = 0 (J, gamma from loop_kinematics)
//   to 1e-10 of the terms' scale (max_r sum_j |J_rj qdd_j|, max |gamma|); qdd against
//   the dense reference constrained_forward_dynamics (rank-revealing Eigen solve) and
//   against CHOLMOD's to 1e-8 of max |qdd| (the CPU's test_factor_graph holds
//   CHOLMOD to the dense reference at 1e-8 on the same systems);
// - errors: a matrix that is not positive definite, an order that is not a
//   permutation, no device: one exception each, naming what is wrong.
// Skipped, with the reason, without a usable device or without CHOLMOD.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <string>

#include "cuda_test_util.hpp"
#include "scandyn/factor_graph/factor_graph_config.hpp"

#if SCANDYN_HAS_CHOLMOD && SCANDYN_HAS_FACTOR_GRAPH_GPU
#include "loop_cases.hpp"
#include "scandyn/algorithm/loops.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/factor_graph/dynamics_graph.hpp"
#include "scandyn/factor_graph/gpu_sparse_cholesky.hpp"
#include "scandyn/factor_graph/normal_equations.hpp"
#include "scandyn/factor_graph/sparse_cholesky.hpp"
#include "test_util.hpp"

using namespace scandyn;
using factor_graph::DynamicsGraph;
using factor_graph::GpuSparseCholesky;
using factor_graph::Ordering;
using factor_graph::SparseCholesky;

namespace {

using test::max_abs;
using test::max_diff;

#define SKIP_WITHOUT_DEVICE()                                      \
  do {                                                             \
    const std::string why = scandyn::test::no_device_reason();     \
    if (!why.empty()) GTEST_SKIP() << "no CUDA device: " << why;   \
  } while (0)

// The graph's solution by CHOLMOD under `ordering` (Given: the tree order) and by
// the GPU under CHOLMOD's elimination order.
struct Solutions {
  std::vector<double> cholmod, gpu;
};
Solutions solve_both(const DynamicsGraph& g, Ordering ordering, double beta, int refine) {
  SparseCholesky chol(g.At(), ordering, ordering == Ordering::Given ? g.tree_order() : std::vector<Index>{}, beta);
  chol.factorize(g.At());
  Solutions s;
  chol.solve(g.At(), g.b(), s.cholmod, refine);
  GpuSparseCholesky gpu(g.At(), chol.elimination_order(), beta);
  gpu.factorize(g.At());
  gpu.solve(g.At(), g.b(), s.gpu, refine);
  EXPECT_EQ(gpu.stats().n, g.unknowns());
  EXPECT_GT(gpu.stats().internal_bytes, 0u);
  return s;
}

// Trees: forward dynamics = ABA, inverse dynamics = RNEA, GPU = CHOLMOD.
TEST(CudaSparseCholesky, TreesReproduceAbaAndRnea) {
  SKIP_WITHOUT_DEVICE();
  std::mt19937_64 rng(31);
  std::vector<Model> models;
  models.push_back(make_generated("chain:20"));
  models.push_back(test::load_robot("iiwa.urdf"));
  models.push_back(make_generated("tree:12:1"));
  for (const Model& model : models) {
    const int nv = model.nv();
    Data data(model);
    const auto q = test::random_vector(rng, nv, -3, 3), qd = test::random_vector(rng, nv, -2, 2),
               tau = test::random_vector(rng, nv, -10, 10), qdd_in = test::random_vector(rng, nv, -5, 5);
    std::vector<double> qdd(static_cast<std::size_t>(nv)), tau_id(static_cast<std::size_t>(nv));
    ASSERT_TRUE(aba(model, data, q.data(), qd.data(), tau.data(), qdd.data()).ok());
    rnea(model, data, q.data(), qd.data(), qdd_in.data(), tau_id.data());
    DynamicsGraph fd(model, {}, {});
    fd.assemble(q.data(), qd.data(), nullptr, tau.data());
    DynamicsGraph id(model, {}, std::vector<char>(static_cast<std::size_t>(nv), 1));
    id.assemble(q.data(), qd.data(), qdd_in.data(), nullptr);
    for (Ordering o : {Ordering::NESDIS, Ordering::Given}) {
      SCOPED_TRACE(model.name + " " + factor_graph::ordering_name(o));
      const Solutions f = solve_both(fd, o, 0.0, 2);
      std::vector<double> qdd_gpu(static_cast<std::size_t>(nv));
      fd.extract(f.gpu.data(), qdd_gpu.data(), nullptr, nullptr);
      EXPECT_LE(max_diff(qdd_gpu, qdd), 1e-12 * (1 + max_abs(qdd)));
      EXPECT_LE(max_diff(f.gpu, f.cholmod), 1e-12 * (1 + max_abs(f.cholmod)));
      const Solutions i = solve_both(id, o, 0.0, 2);
      std::vector<double> tau_gpu(static_cast<std::size_t>(nv));
      id.extract(i.gpu.data(), nullptr, tau_gpu.data(), nullptr);
      EXPECT_LE(max_diff(tau_gpu, tau_id), 1e-12 * (1 + max_abs(tau_id)));
      EXPECT_LE(max_diff(i.gpu, i.cholmod), 1e-12 * (1 + max_abs(i.cholmod)));
    }
  }
}

// Loops (the factor graph's loop systems: redundant, kLoopBeta, kLoopRefine
// refinement steps as bench_factor_graph solves them): the constraints hold at the
// acceleration level; qdd is CHOLMOD's and the dense reference's to qdd_tol of max |qdd|.
void check_loops(const std::string& spec, double tau_scale, double qdd_tol) {
  SCOPED_TRACE(spec);
  const test::LoopCase c = test::loop_cases({spec})[0];
  const Index nv = c.model.nv(), m = c.loops.rows();
  std::mt19937_64 rng(32);
  std::vector<double> q, qd;
  ASSERT_LE(test::closed_state(c, rng, q, qd), 1e-12);
  const auto tau = test::random_vector(rng, nv, -tau_scale, tau_scale);
  DynamicsGraph g(c.model, factor_graph::graph_loops(c.loops), {});
  g.assemble(q.data(), qd.data(), nullptr, tau.data());
  const Solutions s = solve_both(g, Ordering::NESDIS, factor_graph::kLoopBeta, factor_graph::kLoopRefine);
  std::vector<double> qdd_gpu(static_cast<std::size_t>(nv)), qdd_chol(static_cast<std::size_t>(nv));
  g.extract(s.gpu.data(), qdd_gpu.data(), nullptr, nullptr);
  g.extract(s.cholmod.data(), qdd_chol.data(), nullptr, nullptr);
  // J qdd + gamma = 0
  std::vector<double> J(static_cast<std::size_t>(m) * nv), gamma(static_cast<std::size_t>(m));
  loop_kinematics(c.model, c.loops, q.data(), qd.data(), nullptr, J.data(), gamma.data());
  double worst = 0, scale = max_abs(gamma);
  for (Index r = 0; r < m; ++r) {
    double v = gamma[r], terms = 0;
    for (Index j = 0; j < nv; ++j) {
      v += J[r * nv + j] * qdd_gpu[j];
      terms += std::abs(J[r * nv + j] * qdd_gpu[j]);
    }
    worst = std::max(worst, std::abs(v));
    scale = std::max(scale, terms);
  }
  EXPECT_LE(worst, 1e-10 * scale) << "J qdd + gamma, scale " << scale;
  EXPECT_LE(max_diff(qdd_gpu, qdd_chol), qdd_tol * max_abs(qdd_chol)) << "against CHOLMOD";
  std::vector<double> qdd_ref(static_cast<std::size_t>(nv)), lambda_ref(static_cast<std::size_t>(m));
  constrained_forward_dynamics(c.model, c.loops, q.data(), qd.data(), tau.data(), qdd_ref.data(), lambda_ref.data());
  EXPECT_LE(max_diff(qdd_gpu, qdd_ref), qdd_tol * max_abs(qdd_ref)) << "against constrained_forward_dynamics";
}

TEST(CudaSparseCholesky, FiveBar) {
  SKIP_WITHOUT_DEVICE();
  check_loops("fivebar", 1.0, 1e-10);
}

TEST(CudaSparseCholesky, Cloth4x4) {
  SKIP_WITHOUT_DEVICE();
  check_loops("cloth:4:4", 1e-3, 1e-8);  // 10 g links of 1 cm
}

TEST(CudaSparseCholesky, Cloth10x10) {
  SKIP_WITHOUT_DEVICE();
  check_loops("cloth:10:10", 1e-3, 1e-8);
}

// A normal matrix with a zero pivot (an unknown in no equation, beta = 0): one
// runtime_error saying it is not positive definite.
TEST(CudaSparseCholesky, NotPositiveDefiniteIsOneClearError) {
  SKIP_WITHOUT_DEVICE();
  factor_graph::SparseMatrix At;  // 2 unknowns x 2 equations: unknown 1 in neither
  At.rows = At.cols = 2;
  At.col_ptr = {0, 1, 2};
  At.row_idx = {0, 0};
  At.val = {1.0, 2.0};
  GpuSparseCholesky gpu(At, {}, 0.0);
  try {
    gpu.factorize(At);
    ADD_FAILURE() << "factorize accepted a singular normal matrix";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("not positive definite"), std::string::npos) << e.what();
  }
}

// Checked on the host before any CUDA call: runs without a device too.
TEST(CudaSparseCholesky, RefusesAnOrderThatIsNotAPermutation) {
  const Model model = make_generated("chain:3");
  DynamicsGraph g(model, {}, {});
  std::vector<Index> order(static_cast<std::size_t>(g.unknowns()), 0);
  try {
    GpuSparseCholesky gpu(g.At(), order, 0.0);
    ADD_FAILURE() << "an order of zeros was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("not a permutation"), std::string::npos) << e.what();
  }
}

// Without a device the constructor names the failing call.
TEST(CudaSparseCholesky, NoDeviceIsOneClearError) {
  if (scandyn::test::no_device_reason().empty()) GTEST_SKIP() << "a CUDA device is usable here";
  const Model model = make_generated("chain:3");
  DynamicsGraph g(model, {}, {});
  try {
    GpuSparseCholesky gpu(g.At(), {}, 0.0);
    ADD_FAILURE() << "constructed without a device";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("GpuSparseCholesky: cudaGetDeviceCount"), std::string::npos) << e.what();
  }
}

}  // namespace
#else
TEST(CudaSparseCholesky, NeedsCholmodAndCusolver) {
  GTEST_SKIP() << "built without SuiteSparse CHOLMOD or without cuSOLVER: the GPU's sparse Cholesky is compared "
                  "with CHOLMOD (apt-get install libsuitesparse-dev libmetis-dev)";
}
#endif
