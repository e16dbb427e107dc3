// Shared plumbing of bench_sim (CPU) and bench_cuda_sim (GPU): scenes built from
// JSON text, the models directory, and max_rel_err against the double serial
// simulator.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <string>
#include <vector>

#include "scandyn/accuracy.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sim/simulator.hpp"

namespace scandyn::bench {

// $SCANDYN_MODELS_DIR, else the shipped models (model_search_dirs)
inline std::string models_dir() {
  const std::vector<std::string> dirs = model_search_dirs();
  return dirs.empty() ? "models" : dirs.front();
}

// A model spec usable in a scene: generators as they are, robots by their file.
inline std::string model_for_scene(const std::string& model) {
  return model.find(':') != std::string::npos ? model : models_dir() + "/" + model + ".urdf";
}

// The effect sets of the benchmarks: "gravity+damping" (the RL row), "gravity"
// (only gravity declared) and "all-zero" (every effect declared, zero coefficients:
// the same trajectory as "gravity", computed by the all-effects instantiation).
inline std::string effects_json(const std::string& set) {
  if (set == "gravity") return R"({"gravity": true})";
  if (set == "gravity+damping") return R"({"gravity": true, "damping": 0.5})";
  if (set == "all-zero")
    return R"({"gravity": true, "damping": 0, "springs": {"stiffness": 0}, "limits": {"stiffness": 0, "damping": 0},
               "external": {"wrenches": []}})";
  return "{}";
}

// The contacts of the "+contacts" effect sets: a point at every link origin
// (radius 2 mm), k = 1e3, c = 1, mu = 0.5, against a plane 1 m (robots) or 1% of
// the rope's length (rope:N, hanging along -z: 0.01 N m long) below its lowest
// point at rest, and, for ropes, a sphere of radius 0.2 L beside it at mid-length.
// Planes only for robots (the RL case), a plane and a sphere for ropes.
inline std::string contacts_json(const std::string& model) {
  std::string obstacles = R"("planes": [{"normal": [0, 0, 1], "offset": -1}])";
  if (model.rfind("rope:", 0) == 0) {
    const double L = 0.01 * std::atof(model.c_str() + 5);
    obstacles = R"("planes": [{"normal": [0, 0, 1], "offset": )" + std::to_string(-1.01 * L) +
                R"(}], "spheres": [{"center": [)" + std::to_string(0.3 * L) + ", 0, " + std::to_string(-0.5 * L) +
                R"(], "radius": )" + std::to_string(0.2 * L) + "}]";
  }
  return R"("contacts": {)" + obstacles +
         R"(, "all_links": {"radius": 0.002}, "stiffness": 1e3, "damping": 1, "friction": 0.5})";
}

// effects_json of `set`, or of set without a "+contacts" suffix with contacts_json added
inline std::string effects_json_for(const std::string& set, const std::string& model) {
  const std::string suffix = "+contacts";
  if (set.size() <= suffix.size() || set.compare(set.size() - suffix.size(), suffix.size(), suffix) != 0)
    return effects_json(set);
  std::string base = effects_json(set.substr(0, set.size() - suffix.size()));
  base.pop_back();  // the closing brace
  return base + ", " + contacts_json(model) + "}";
}

inline sim::Scene make_scene(const std::string& model, const std::string& effects, const std::string& integrator,
                             const char* precision, const char* backend, long long instances, double dt) {
  const std::string json = R"({"model": ")" + model_for_scene(model) + R"(", "effects": )" + effects_json_for(effects, model) +
                           R"(, "integrator": ")" + integrator + R"(", "dt": )" + std::to_string(dt) +
                           R"(, "precision": ")" + precision + R"(", "backend": ")" + backend +
                           R"(", "instances": )" + std::to_string(instances) +
                           R"(, "initial": {"random": {"seed": 1, "q": 0.3, "qd": 0.1}}})";
  return sim::parse_scene(json, "bench scene");
}

// max over the first `count` instances of max_i |x_i - ref_i| / max(1, max |ref_i|)
// over q and qd after `steps` steps, against Simulator<double> on the serial backend.
template <class S>
double max_rel_err_after(sim::Simulator<S>& s, const sim::Scene& scene, int steps, Index count) {
  sim::Scene rs = scene;
  rs.instances = count;
  sim::Simulator<double> ref(rs, BackendKind::Serial);
  for (int k = 0; k < steps; ++k) ref.step(), s.step();
  // q has nq rows (quaternion models), qd nv
  const std::size_t n = static_cast<std::size_t>(s.nv()), nq = static_cast<std::size_t>(s.nq());
  const std::size_t B = static_cast<std::size_t>(s.batch());
  std::vector<S> q(nq * B), qd(n * B);
  s.read_state(q.data(), qd.data());
  std::vector<double> rq(nq * count), rqd(n * count);
  ref.read_state(rq.data(), rqd.data());
  double worst = 0;
  std::vector<double> x(nq + n), r(nq + n);
  for (Index b = 0; b < count; ++b) {
    for (std::size_t i = 0; i < nq; ++i) x[i] = q[i * B + b], r[i] = rq[i * count + b];
    for (std::size_t i = 0; i < n; ++i) x[nq + i] = qd[i * B + b], r[nq + i] = rqd[i * count + b];
    const double e = rel_err(x.data(), r.data(), nq + n);
    if (std::isnan(e)) return e;
    worst = std::max(worst, e);
  }
  return worst;
}

}  // namespace scandyn::bench
