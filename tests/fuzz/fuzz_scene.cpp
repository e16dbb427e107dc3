// tests/fuzz/fuzz_scene.cpp: libFuzzer target for the scene parser: the bytes are a
// scene file (parse_scene: size, nesting and number checks, nlohmann-json, every
// key's validation, the model it names). Relative model paths resolve against the
// shipped models (SCANDYN_FUZZ_MODELS_DIR, set by CMake). A SceneError is the
// expected outcome for bad input; anything else is a bug.
//
// Generator specs naming more than 2000 bodies are skipped (the builder handles
// 10^6-link ropes, tested elsewhere; here they would only slow the fuzzer down),
// and so is any input that mentions a device or /proc path.
#include <cctype>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "scandyn/sim/scene.hpp"

namespace {

// True when text names a generator with more than `limit` bodies somewhere: any
// run of digits after "chain:", "rope:", "tree:" or "curtain:" (K x N multiplied).
bool names_big_generator(const std::string& text, double limit) {
  for (const char* prefix : {"chain:", "rope:", "tree:", "curtain:"}) {
    for (std::size_t k = text.find(prefix); k != std::string::npos; k = text.find(prefix, k + 1)) {
      std::size_t i = k + std::char_traits<char>::length(prefix);
      double product = 1;
      for (int part = 0; part < 2; ++part) {
        while (i < text.size() && (text[i] == ' ' || text[i] == '+' || text[i] == '0')) ++i;
        std::size_t j = i;
        while (j < text.size() && std::isdigit(static_cast<unsigned char>(text[j]))) ++j;
        if (j - i > 6) return true;
        if (j > i) product *= std::atof(text.substr(i, j - i).c_str());
        if (product > limit) return true;
        if (j >= text.size() || text[j] != ':') break;
        i = j + 1;
        if (std::string(prefix) == "tree:") break;  // tree:N:SEED
      }
    }
  }
  return false;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  // JSON \u escapes could spell a generator too: skip inputs that use them near "model"
  if (names_big_generator(text, 2000) || text.find("/dev") != std::string::npos ||
      text.find("/proc") != std::string::npos || text.find("/sys") != std::string::npos ||
      text.find("\\u") != std::string::npos)
    return 0;
  try {
    (void)scandyn::sim::parse_scene(text, "fuzz.json", SCANDYN_FUZZ_MODELS_DIR);
  } catch (const scandyn::sim::SceneError&) {
  }
  return 0;
}
