// The simulator with closed loops (scene key "loops", generators fivebar, fourbar,
// cloth:K:N; docs/loops.md): 10^4 RK4 steps in double without damping conserve the
// mechanical energy (relative drift below 1e-6) with the loop-closure error bounded
// (below 1e-11 m after every projection); the scene's loop errors.
#include <gtest/gtest.h>

#include <cmath>

#include "scandyn/algorithm/loops.hpp"
#include "scandyn/sim/simulator.hpp"

using namespace scandyn;
using namespace scandyn::sim;

TEST(SimLoops, EnergyConservedAndClosureBounded) {
  struct Case {
    const char* model;
    int steps;
    double dt;
  } cases[] = {{"fivebar", 10000, 1e-3}, {"fourbar", 10000, 1e-3}, {"cloth:3:3", 2000, 2e-4}};
  for (const Case& c : cases) {
    SCOPED_TRACE(c.model);
    const Scene scene = parse_scene(std::string(R"({"model": ")") + c.model + R"(", "effects": {"gravity": true},
        "integrator": "rk4", "dt": )" + std::to_string(c.dt) + R"(, "initial": {"q": 0.3, "qd": 0.5}})", "test.json");
    ASSERT_FALSE(scene.loops.empty());
    Simulator<double> s(scene, BackendKind::Serial);
    const Index n = s.nv();
    std::vector<double> q(n), qd(n);
    const double e0 = s.energy()[0];
    double worst_closure = 0, worst_drift = 0;
    for (int k = 0; k < c.steps; ++k) {
      s.step();
      if (k % 100 == 99) {
        ASSERT_TRUE(s.status().ok()) << failure_message(s.status());
        s.read_state(q.data(), qd.data());
        worst_closure = std::max(worst_closure, loop_violation(scene.model, scene.loops, q.data(), qd.data()));
        worst_drift = std::max(worst_drift, std::fabs(s.energy()[0] - e0) / std::max(1e-3, std::fabs(e0)));
      }
    }
    EXPECT_LE(worst_closure, 1e-11);
    EXPECT_LE(worst_drift, 1e-6);
    // the mechanism moved
    EXPECT_GT(std::fabs(q[0] - 0.3), 1e-3);
  }
}

TEST(SimLoops, SceneErrors) {
  auto error_of = [](const std::string& json) -> std::string {
    try {
      Simulator<double> s(parse_scene(json, "test.json"), BackendKind::Serial);
    } catch (const std::exception& e) {
      return e.what();
    }
    return "";
  };
  EXPECT_NE(error_of(R"({"model": "chain:3", "dt": 0.001, "loops": [{"type": "point", "link_a": "nope", "point_a": [0,0,0],
                       "link_b": "link_1", "point_b": [0,0,0]}]})")
                .find("test.json: loops[0].link_a: unknown link 'nope'"),
            std::string::npos);
  EXPECT_NE(error_of(R"({"model": "chain:3", "dt": 0.001, "loops": 3})").find("test.json: loops: expected an array"),
            std::string::npos);
  EXPECT_NE(error_of(R"({"model": "fivebar", "dt": 0.001, "integrator": "implicit", "effects": {"damping": 0.1}})")
                .find("closed loops step with euler or rk4"),
            std::string::npos);
  // a start so far off the loops that the reset's Gauss-Newton projection does not
  // converge (one of these instances ends 7.5e-3 m off): refused, not stepped from
  EXPECT_NE(error_of(R"({"model": "cloth:6:6", "dt": 0.001, "instances": 4,
                         "initial": {"random": {"seed": 3, "q": 2.0}}})")
                .find("off its loops after projecting it onto them"),
            std::string::npos);
}
