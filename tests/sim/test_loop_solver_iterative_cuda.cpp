// The scene's "loop_solver": "iterative-cuda" (the iterative loop solver on a CUDA
// device, scandyn/cuda/loop_iterative.hpp; docs/scenes.md): parsed in every build; the
// simulator refuses it with a clear error in a build without CUDA, without a usable
// device, for a preconditioner the GPU solver lacks (SSOR and the other sweeps), a tree
// it refuses (branched, multi-DoF), and with contacts or external wrenches. Host only:
// no step runs (tests/cuda/test_cuda_loop_iterative.cu steps it on a device).
#include <gtest/gtest.h>

#include <cstdio>
#include <string>

#include "scandyn/build_config.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/loop_iterative.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scene_util.hpp"

namespace scandyn {
namespace {

const auto error_of = test::simulator_error;

bool has(const std::string& s, const std::string& part) { return s.find(part) != std::string::npos; }

// whether this build and machine have a usable device (else every iterative-cuda scene is refused)
bool device_usable() {
  const cuda::Result<int> c = cuda::device_count();
  return c.ok() && c.value > 0;
}

TEST(LoopSolverIterativeCuda, ParsedInEveryBuild) {
  const sim::Scene s = sim::parse_scene(R"({"model": "cloth:4:4", "dt": 0.001, "loop_solver": "iterative-cuda"})",
                                        "test.json");
  EXPECT_EQ(s.loop_solver, "iterative-cuda");
  try {
    (void)sim::parse_scene(R"({"model": "cloth:4:4", "dt": 0.001, "loop_solver": "iterative-gpu"})", "test.json");
    FAIL() << "an unknown loop solver accepted";
  } catch (const std::exception& e) {
    EXPECT_TRUE(has(e.what(), "\"iterative-cuda\"")) << e.what();
  }
}

TEST(LoopSolverIterativeCuda, AcceptedOrRefusedWithTheReason) {
  const std::string e = error_of(R"({"model": "cloth:4:4", "dt": 0.001, "loop_solver": "iterative-cuda"})");
  RecordProperty("cloth_4_4", e.empty() ? "accepted" : e);
  std::printf("cloth:4:4: %s\n", e.empty() ? "accepted" : e.c_str());
  if (!SCANDYN_HAS_CUDA) {
    EXPECT_TRUE(has(e, "this build has no CUDA")) << e;
  } else if (!device_usable()) {
    EXPECT_TRUE(has(e, "iterative-cuda")) << e;
    EXPECT_TRUE(has(e, "CUDA device")) << e;
  } else {
    EXPECT_EQ(e, "");
    EXPECT_EQ(error_of(R"({"model": "fivebar", "dt": 0.001, "loop_solver": "iterative-cuda",
                           "loop_preconditioner": "none"})"),
              "");
  }
}

TEST(LoopSolverIterativeCuda, RefusesWhatTheGpuSolverLacks) {
  // the preconditioner: the GPU solver's sweeps are block Jacobi's or none
  const std::string p = error_of(R"({"model": "cloth:4:4", "dt": 0.001, "loop_solver": "iterative-cuda",
                                     "loop_preconditioner": "ssor"})");
  EXPECT_TRUE(has(p, "iterative-cuda")) << p;
  if (SCANDYN_HAS_CUDA) {
    EXPECT_TRUE(has(p, "\"ssor\" is not on the GPU")) << p;
  }
  // contacts or external wrenches (in every build: checked first)
  const std::string w = error_of(R"({"model": "fivebar", "dt": 0.001, "loop_solver": "iterative-cuda",
      "effects": {"external": {"wrenches": [{"link": "left_distal", "wrench": [0, 0, 0, 1, 0, 0]}]}}})");
  EXPECT_TRUE(has(w, "iterative-cuda")) << w;
  EXPECT_TRUE(has(w, "external wrenches")) << w;
  // a branched tree: the refusal names the chains the GPU solver takes (before the device)
  const Model tree = load_model("tree:12:1");
  LoopSet loops;
  LoopClosure l;
  l.type = LoopType::Point;
  l.body_a = 1, l.body_b = tree.nv() - 1;
  loops.loops.push_back(l);
  const std::string t = cuda::cuda_iterative_loop_refusal(tree, loops, sim::LoopPreconditioner::BlockJacobi);
  EXPECT_TRUE(has(t, "iterative-cuda")) << t;
  if (SCANDYN_HAS_CUDA) {
    EXPECT_TRUE(has(t, "unbranched chains")) << t;
  }
  std::printf("refusals:\n  %s\n  %s\n  %s\n", p.c_str(), w.c_str(), t.c_str());
}

}  // namespace
}  // namespace scandyn
