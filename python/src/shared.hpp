// python/src/shared.hpp: what the extension module's source files (module.cpp,
// kinematics.cpp, simulator.cpp) share: the loaded model, the error types that module.cpp's
// translator turns into scandyn.errors classes (ShapeError, DTypeError,
// DeviceError), the names used in their messages, and enter_device (a CUDA device
// current for a scope).
#pragma once

#include <nanobind/nanobind.h>

#include <memory>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <type_traits>

#include "scandyn/cuda/device.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/model.hpp"

namespace scandyn::py {

struct ShapeError : std::runtime_error {
  using std::runtime_error::runtime_error;
};
struct DTypeError : std::runtime_error {
  using std::runtime_error::runtime_error;
};
struct DeviceError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// A loaded model in double, and its float copy made on first use (engines in float
// need a ModelTpl<float> that outlives them). Engines hold a shared_ptr to it.
struct PyModel {
  Model md;
  std::once_flag float_once;
  std::unique_ptr<ModelTpl<float>> mf;

  template <class S>
  const ModelTpl<S>& get() {
    if constexpr (std::is_same_v<S, double>) {
      return md;
    } else {
      std::call_once(float_once, [this] { mf = std::make_unique<ModelTpl<float>>(md.template cast<float>()); });
      return *mf;
    }
  }
};

// Makes `device` current for a scope (cuda::DeviceScope: engines and simulators are made
// on, and launch to, the current device; the caller's is restored on exit); -1 keeps the
// current one. BackendError naming the device when it cannot be made current.
inline void enter_device(std::optional<cuda::DeviceScope>& scope, int device) {
  if (device < 0) return;
  scope.emplace(device);
  if (!scope->ok())
    throw BackendError("backend 'cuda': cannot use CUDA device " + std::to_string(device) + ": " + scope->error());
}

// "float32" or "float64", the dtype name of S.
template <class S>
const char* scalar_name() {
  return std::is_same_v<S, float> ? "float32" : "float64";
}

// An array's shape as Python prints it: "(3,)", "(2, 7)".
template <class A>
std::string shape_str(const A& a) {
  std::string s = "(";
  for (size_t i = 0; i < a.ndim(); ++i) s += (i ? ", " : "") + std::to_string(a.shape(i));
  return s + (a.ndim() == 1 ? ",)" : ")");
}

// Registers the Kinematics engine class (python/src/kinematics.cpp).
void bind_kinematics(nanobind::module_& m);

// Registers the derivatives (python/src/derivatives.cpp).
void bind_derivatives(nanobind::module_& m);

}  // namespace scandyn::py
