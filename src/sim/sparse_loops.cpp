// src/sim/sparse_loops.cpp: the registered sparse loop solver
// (scandyn/sim/sparse_loops.hpp).
#include "scandyn/sim/sparse_loops.hpp"

#include <atomic>

namespace scandyn::sim {

namespace {
std::atomic<LoopSolverFactory> g_sparse{nullptr};
}

void set_sparse_loop_solver(LoopSolverFactory factory) { g_sparse.store(factory); }
LoopSolverFactory sparse_loop_solver() { return g_sparse.load(); }

}  // namespace scandyn::sim
