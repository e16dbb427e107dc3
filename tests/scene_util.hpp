// Scenes from JSON text, for the simulator tests.
#pragma once

#include <string>

#include "scandyn/sim/scene.hpp"

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

}  // namespace scandyn::test
