// tests/fuzz/fuzz_urdf.cpp: libFuzzer target for the URDF loader: the bytes are a
// URDF document, parsed (parse_urdf: size and nesting checks, urdfdom) and built
// (build_model: every validation). A ModelError is the expected outcome for bad
// input; anything else (a crash, a sanitizer report, another exception) is a bug.
#include <cstddef>
#include <cstdint>
#include <string>

#include "scandyn/model/load.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  try {
    const scandyn::RawTree tree = scandyn::parse_urdf(text, "fuzz.urdf");
    scandyn::BuildOptions strict;
    (void)scandyn::build_model(tree, strict);
  } catch (const scandyn::ModelError&) {
  }
  try {
    const scandyn::RawTree tree = scandyn::parse_urdf(text, "fuzz.urdf");
    scandyn::BuildOptions lenient;
    lenient.require_physical_inertia = false;
    const scandyn::Model m = scandyn::build_model(tree, lenient);
    (void)m.cast<float>();
  } catch (const scandyn::ModelError&) {
  }
  return 0;
}
