// Scenes from JSON text, for the simulator tests, and the errors they raise.
#pragma once

#include <exception>
#include <string>

#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"

namespace scandyn::test {

// The scene of `json` (named "test.json" in errors; files it names found from base_dir).
inline sim::Scene scene_from(const std::string& json, const std::string& base_dir = ".") {
  return sim::parse_scene(json, "test.json", base_dir);
}

// The message of the SceneError parse_scene throws for json ("" when none).
inline std::string scene_error(const std::string& json, const std::string& base_dir = ".") {
  try {
    scene_from(json, base_dir);
  } catch (const sim::SceneError& e) {
    return e.what();
  }
  return "";
}

// The message of what making a serial double simulator of json's scene (named
// "test.json") throws, the scene's parse or the simulator's setup ("" when nothing).
inline std::string simulator_error(const std::string& json) {
  try {
    sim::Simulator<double> s(sim::parse_scene(json, "test.json"), BackendKind::Serial);
  } catch (const std::exception& e) {
    return e.what();
  }
  return "";
}

}  // namespace scandyn::test
