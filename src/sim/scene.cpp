// src/sim/scene.cpp: scene files (JSON, nlohmann-json) -> Scene, with every error
// naming the file and the key. Format: docs/scenes.md.
#include "scandyn/sim/scene.hpp"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <sys/stat.h>

#include <nlohmann/json.hpp>

#include "scandyn/algorithm/configuration.hpp"
#include "scandyn/io/limits.hpp"
#include "scandyn/io/states.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/sharded.hpp"
#include "scandyn/sim/iterative_loops.hpp"

namespace scandyn {
namespace sim {

using json = nlohmann::json;

std::string effect_names(unsigned effects) {
  static const char* const names[] = {"gravity", "damping", "springs", "limits", "external", "contacts"};
  std::string s;
  for (int k = 0; k < 6; ++k) {
    if (!(effects & (1u << k))) continue;
    if (!s.empty()) s += "+";
    s += names[k];
  }
  return s.empty() ? "none" : s;
}

const char* to_string(Integrator integrator) {
  switch (integrator) {
    case Integrator::Euler: return "euler";
    case Integrator::Rk4: return "rk4";
    case Integrator::Implicit: return "implicit";
    case Integrator::Variational: return "variational";
  }
  return "?";
}

bool parse_integrator(const std::string& name, Integrator& integrator) {
  if (name == "euler") integrator = Integrator::Euler;
  else if (name == "rk4") integrator = Integrator::Rk4;
  else if (name == "implicit") integrator = Integrator::Implicit;
  else if (name == "variational") integrator = Integrator::Variational;
  else return false;
  return true;
}


namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

// Reads one JSON document; every error names source and the key path.
class Reader {
 public:
  explicit Reader(std::string source) : source_(std::move(source)) {}

  [[noreturn]] void fail(const std::string& key, const std::string& what) const {
    std::string k = printable(key);
    if (k.size() > 200) k = k.substr(0, 197) + "...";
    throw SceneError(source_ + ": " + (k.empty() ? "" : k + ": ") + what);
  }

  // A value as written, shortened for messages.
  static std::string shown(const json& v) {
    std::string s = printable(v.dump(-1, ' ', false, json::error_handler_t::replace));
    if (s.size() > 60) s = s.substr(0, 57) + "...";
    return s;
  }

  [[noreturn]] void expected(const std::string& key, const std::string& what, const json& got) const {
    fail(key, "expected " + what + ", got " + shown(got));
  }

  // Object at key with only the allowed member names.
  void check_object(const std::string& key, const json& v, const std::set<std::string>& allowed) const {
    if (!v.is_object()) expected(key, "an object", v);
    for (auto it = v.begin(); it != v.end(); ++it) {
      if (allowed.count(it.key())) continue;
      std::string list;
      for (const auto& a : allowed) list += (list.empty() ? "" : ", ") + a;
      fail(join(key, it.key()), "unknown key (expected one of: " + list + ")");
    }
  }

  static std::string join(const std::string& key, const std::string& member) {
    return key.empty() ? member : key + "." + member;
  }

  double number(const std::string& key, const json& v, const char* what = "a number") const {
    if (!v.is_number()) expected(key, what, v);
    const double x = v.get<double>();
    if (!std::isfinite(x)) expected(key, what, v);
    return x;
  }

  double positive(const std::string& key, const json& v) const {
    const double x = number(key, v, "a positive number");
    if (!(x > 0)) expected(key, "a positive number", v);
    return x;
  }

  long long integer(const std::string& key, const json& v, long long lo, long long hi) const {
    const std::string what = "an integer from " + std::to_string(lo) + " to " + std::to_string(hi);
    if (!v.is_number_integer()) expected(key, what, v);
    if (v.is_number_unsigned()) {
      const auto u = v.get<unsigned long long>();
      if (u > static_cast<unsigned long long>(hi) || static_cast<long long>(u) < lo) expected(key, what, v);
      return static_cast<long long>(u);
    }
    const long long x = v.get<long long>();
    if (x < lo || x > hi) expected(key, what, v);
    return x;
  }

  std::string string(const std::string& key, const json& v) const {
    if (!v.is_string()) expected(key, "a string", v);
    return v.get<std::string>();
  }

  bool boolean(const std::string& key, const json& v) const {
    if (!v.is_boolean()) expected(key, "true or false", v);
    return v.get<bool>();
  }

  // A per-DoF quantity: one number for every DoF, or an array of nv numbers.
  // non_negative: values must be >= 0; nullable: null entries (or a null scalar)
  // mean `null_value` (+-inf for open limits).
  std::vector<double> per_dof(const std::string& key, const json& v, Index nv, bool non_negative,
                              bool nullable = false, double null_value = 0) const {
    const std::string what = std::string(non_negative ? "a non-negative number" : "a number") +
                             (nullable ? " or null" : "") + " or an array of " + std::to_string(nv) +
                             (non_negative ? " non-negative numbers" : " numbers");
    auto one = [&](const json& x, const std::string& k) -> double {
      if (nullable && x.is_null()) return null_value;
      if (!x.is_number()) expected(k, what, x);
      const double d = x.get<double>();
      if (!std::isfinite(d) || (non_negative && d < 0)) expected(k, what, x);
      return d;
    };
    std::vector<double> out(static_cast<std::size_t>(nv));
    if (v.is_array()) {
      if (v.size() != static_cast<std::size_t>(nv))
        fail(key, "expected " + std::to_string(nv) + " entries (one per DoF), got " + std::to_string(v.size()));
      for (Index i = 0; i < nv; ++i) {
        const json& x = v[static_cast<std::size_t>(i)];
        if (nullable && x.is_null()) { out[i] = null_value; continue; }
        if (!x.is_number()) expected(key, what, v);
        const double d = x.get<double>();
        if (!std::isfinite(d) || (non_negative && d < 0))
          fail(key + "[" + std::to_string(i) + "]", "expected " + std::string(non_negative ? "a non-negative number" : "a finite number") + ", got " + shown(x));
        out[i] = d;
      }
      return out;
    }
    const double d = one(v, key);
    for (double& x : out) x = d;
    return out;
  }

 private:
  std::string source_;
};

// [x, y, z] at key
Vec3<double> vec3(const Reader& r, const std::string& key, const json& v, const char* what) {
  if (!v.is_array() || v.size() != 3) r.expected(key, what, v);
  double x[3];
  for (int k = 0; k < 3; ++k) x[k] = r.number(key + "[" + std::to_string(k) + "]", v[static_cast<std::size_t>(k)]);
  return {x[0], x[1], x[2]};
}

double non_negative(const Reader& r, const std::string& key, const json& v) {
  const double x = r.number(key, v, "a non-negative number");
  if (x < 0) r.expected(key, "a non-negative number", v);
  return x;
}

// An array at key of objects with exactly the required members (and the optional ones).
const json& object_list(const Reader& r, const std::string& key, const json& v, const std::set<std::string>& required,
                        const std::set<std::string>& optional, const char* what) {
  if (!v.is_array()) r.expected(key, what, v);
  std::set<std::string> allowed = required;
  allowed.insert(optional.begin(), optional.end());
  for (std::size_t k = 0; k < v.size(); ++k) {
    const std::string item = key + "[" + std::to_string(k) + "]";
    r.check_object(item, v[k], allowed);
    for (const std::string& m : required)
      if (!v[k].contains(m)) r.fail(item + "." + m, "missing");
  }
  return v;
}

// effects.contacts -> c (docs/scenes.md, "contacts")
void parse_contacts(const Reader& r, const json& v, const Model& model, SceneContacts& c) {
  const std::string key = "effects.contacts";
  r.check_object(key, v, {"planes", "spheres", "points", "all_links", "stiffness", "damping", "friction", "creep_speed"});
  if (!v.contains("stiffness")) r.fail(key + ".stiffness", "missing (the normal stiffness k, N/m)");
  c.law.stiffness = non_negative(r, key + ".stiffness", v["stiffness"]);
  if (v.contains("damping")) c.law.damping = non_negative(r, key + ".damping", v["damping"]);
  if (v.contains("friction")) c.law.friction = non_negative(r, key + ".friction", v["friction"]);
  if (v.contains("creep_speed")) c.law.creep_speed = r.positive(key + ".creep_speed", v["creep_speed"]);
  if (v.contains("planes")) {
    const json& ps = object_list(r, key + ".planes", v["planes"], {"normal"}, {"offset"},
                                 "an array of {\"normal\": [nx, ny, nz], \"offset\": o}");
    for (std::size_t k = 0; k < ps.size(); ++k) {
      const std::string item = key + ".planes[" + std::to_string(k) + "]";
      const Vec3<double> n = vec3(r, item + ".normal", ps[k]["normal"], "[nx, ny, nz], a unit vector");
      const double len = std::sqrt(dot(n, n));
      if (!(std::abs(len - 1) <= 1e-6))
        r.fail(item + ".normal", "expected a unit vector, got " + Reader::shown(ps[k]["normal"]) + " (length " +
                                     std::to_string(len) + ")");
      const double o = ps[k].contains("offset") ? r.number(item + ".offset", ps[k]["offset"]) : 0.0;
      c.planes.push_back({(1 / len) * n, o});
    }
  }
  if (v.contains("spheres")) {
    const json& ss = object_list(r, key + ".spheres", v["spheres"], {"center", "radius"}, {},
                                 "an array of {\"center\": [x, y, z], \"radius\": R}");
    for (std::size_t k = 0; k < ss.size(); ++k) {
      const std::string item = key + ".spheres[" + std::to_string(k) + "]";
      c.spheres.push_back({vec3(r, item + ".center", ss[k]["center"], "[x, y, z] (m)"),
                           r.positive(item + ".radius", ss[k]["radius"])});
    }
  }
  if (v.contains("points")) {
    const json& ps = object_list(r, key + ".points", v["points"], {"link"}, {"position", "radius"},
                                 "an array of {\"link\": NAME, \"position\": [x, y, z], \"radius\": r}");
    std::map<std::string, Index> body_of;
    for (Index i = 0; i < model.nbodies(); ++i) body_of[model.link_names[i]] = i;
    for (std::size_t k = 0; k < ps.size(); ++k) {
      const std::string item = key + ".points[" + std::to_string(k) + "]";
      const std::string link = r.string(item + ".link", ps[k]["link"]);
      const auto it = body_of.find(link);
      if (it == body_of.end()) r.fail(item + ".link", "no moving link named '" + printable(link) + "' in the model");
      const Vec3<double> pos = ps[k].contains("position")
                                   ? vec3(r, item + ".position", ps[k]["position"], "[x, y, z] (m, link frame)")
                                   : Vec3<double>::zero();
      const double rho = ps[k].contains("radius") ? non_negative(r, item + ".radius", ps[k]["radius"]) : 0.0;
      c.points.push_back({it->second, pos, rho});
    }
  }
  if (v.contains("all_links")) {
    const json& a = v["all_links"];
    r.check_object(key + ".all_links", a, {"radius"});
    const double rho = a.contains("radius") ? non_negative(r, key + ".all_links.radius", a["radius"]) : 0.0;
    for (Index i = 0; i < model.nbodies(); ++i) c.points.push_back({i, Vec3<double>::zero(), rho});
  }
  if (c.points.empty()) r.fail(key, "no contact points (give \"points\" or \"all_links\")");
  if (c.planes.empty() && c.spheres.empty()) r.fail(key, "no obstacles (give \"planes\" or \"spheres\")");
}

// Per DoF (qd's order): which joint effects apply and the joint it belongs to.
struct DofDomains {
  std::vector<unsigned char> joint;    // (nv) 1 unless the floating base's: damping applies
  std::vector<unsigned char> one_dof;  // (nv) 1 on 1-DoF joints: springs and limits apply
  std::vector<Index> body;             // (nv) the body whose joint has the DoF
  std::vector<std::string> joint_name; // (nv) that joint's name
  bool restricted = false;             // some DoF is outside one_dof (multi-DoF joints)

  // A per-DoF quantity (values, read from v at key) kept to the DoFs in domain: a
  // single number applies there only (neutral elsewhere); an array entry other
  // than neutral outside it is an error naming the entry and the joint.
  std::vector<double> restrict(const Reader& r, const std::string& key, const json& v, std::vector<double> values,
                               const std::vector<unsigned char>& domain, double neutral, const char* effect) const {
    if (!restricted) return values;
    for (std::size_t i = 0; i < values.size(); ++i) {
      if (domain[i]) continue;
      if (v.is_array() && values[i] != neutral) {
        const bool base = !joint[i];
        r.fail(key + "[" + std::to_string(i) + "]",
               "DoF " + std::to_string(i) + " belongs to " +
                   (base ? std::string("the floating base ('") : std::string("the ball joint '")) +
                   printable(joint_name[i]) + (base ? "'), which takes no " : "', which takes no ") + effect +
                   " (expected " + (neutral == 0 ? std::string("0") : std::string("null")) + " there)");
      }
      values[i] = neutral;
    }
    return values;
  }

  // A per-body quantity (the model's joint limits) per DoF: the body's value on
  // 1-DoF joints, fill elsewhere.
  std::vector<double> per_body(const std::vector<double>& values, double fill) const {
    std::vector<double> out(body.size(), fill);
    for (std::size_t i = 0; i < body.size(); ++i)
      if (one_dof[i]) out[i] = values[static_cast<std::size_t>(body[i])];
    return out;
  }
};

DofDomains dof_domains(const Model& model) {
  DofDomains d;
  for (Index i = 0; i < model.nbodies(); ++i) {
    const Body<double>& b = model.bodies[i];
    for (int k = 0; k < joint_nv(b.type); ++k) {
      d.joint.push_back(b.type != JointType::Free);
      d.one_dof.push_back(joint_nv(b.type) == 1);
      d.body.push_back(i);
      d.joint_name.push_back(i < static_cast<Index>(model.joint_names.size()) ? model.joint_names[i] : std::to_string(i));
    }
  }
  d.restricted = model.multi_dof();
  return d;
}

// initial.q of a model with quaternion positions: an array of nq numbers; each
// quaternion's norm within io::kQuaternionNormTol of 1 (then normalised), else an
// error naming its entries and joint.
std::vector<double> initial_positions(const Reader& r, const json& v, const Model& model) {
  const Index nq = model.nq();
  if (!v.is_array())
    r.expected("initial.q", "an array of " + std::to_string(nq) + " numbers (nq: the model has quaternion positions)", v);
  if (v.size() != static_cast<std::size_t>(nq))
    r.fail("initial.q", "expected " + std::to_string(nq) + " entries (nq: positions with quaternions x, y, z, w; " +
                            std::to_string(model.nv()) + " is nv, the velocities' count), got " + std::to_string(v.size()));
  std::vector<double> q(static_cast<std::size_t>(nq));
  for (Index i = 0; i < nq; ++i)
    q[i] = r.number("initial.q[" + std::to_string(i) + "]", v[static_cast<std::size_t>(i)]);
  for (Index i = 0; i < model.nbodies(); ++i) {
    const Body<double>& b = model.bodies[i];
    if (joint_nq(b.type) == 1) continue;
    const Index at = b.idx_q + (b.type == JointType::Free ? 3 : 0);
    const double norm = std::sqrt(q[at] * q[at] + q[at + 1] * q[at + 1] + q[at + 2] * q[at + 2] + q[at + 3] * q[at + 3]);
    if (!(std::abs(norm - 1) <= io::kQuaternionNormTol)) {
      std::ostringstream m;
      m << "the quaternion (x, y, z, w) of joint '" << printable(model.joint_names[i]) << "' has norm " << norm
        << "; expected a unit quaternion (within " << io::kQuaternionNormTol << " relative)";
      r.fail("initial.q[" + std::to_string(at) + ".." + std::to_string(at + 3) + "]", m.str());
    }
    for (int k = 0; k < 4; ++k) q[at + k] /= norm;
  }
  return q;
}

bool file_exists(const std::string& p) {
  struct stat st;
  return ::stat(p.c_str(), &st) == 0 && S_ISREG(st.st_mode);
}

std::string dir_of(const std::string& path) {
  const std::size_t k = path.rfind('/');
  return k == std::string::npos ? "." : k == 0 ? "/" : path.substr(0, k);
}

// "devices" (after "backend"): "all", "current", "0,1" or [0, 1] (parse_devices): the
// cuda backend's devices; none where "auto" chose another backend; an error for a
// non-empty list on a backend named serial or openmp.
std::vector<int> scene_devices(const Reader& r, const json& v, const Scene& s) {
  const char* what = "\"all\", \"current\", a list of CUDA device ordinals such as [0, 1] or a string such as \"0,1\"";
  std::string text;
  if (v.is_string()) {
    text = v.get<std::string>();
  } else if (v.is_array()) {
    for (std::size_t k = 0; k < v.size(); ++k)
      text += (k ? "," : "") + std::to_string(r.integer("devices[" + std::to_string(k) + "]", v[k], 0, 999999));
  } else {
    r.expected("devices", what, v);
  }
  std::vector<int> devices;
  try {
    // "all" asks the CUDA runtime: only where the devices are used
    if (text != "all" || s.backend == BackendKind::Cuda) devices = parse_devices(text);
  } catch (const BackendError& e) {
    r.fail("devices", e.what());
  }
  if (s.backend == BackendKind::Cuda || (devices.empty() && text != "all")) return devices;
  if (s.backend_auto) return {};  // auto chose a CPU backend: the scene runs there
  r.fail("devices", "CUDA devices for the cuda backend; the scene's backend is '" + std::string(to_string(s.backend)) +
                        "' (remove \"devices\" or use \"backend\": \"cuda\")");
}

}  // namespace

Scene parse_scene(const std::string& text, const std::string& source, const std::string& base_dir) {
  const Reader r(source);
  // bounded before parsing: the size, the nesting depth (a value nested 10^5 deep
  // would overflow the stack where it is quoted or destroyed) and numbers beyond a
  // double (nlohmann reports those without a position or key)
  if (text.size() > limits::kMaxSceneBytes)
    r.fail("", "the scene has " + std::to_string(text.size()) + " bytes; at most " +
                   std::to_string(limits::kMaxSceneBytes) + " are read");
  try {
    check_json_text(text, limits::kMaxJsonDepth);
  } catch (const InputError& e) {
    r.fail("", e.what());
  }
  json doc;
  try {
    doc = json::parse(text);
  } catch (const json::exception& e) {
    std::string what = e.what();
    const std::size_t k = what.find("] ");
    if (k != std::string::npos) what = what.substr(k + 2);
    r.fail("", "not valid JSON: " + printable(what));
  }
  r.check_object("", doc, {"model", "allow_nonphysical_inertia", "effects", "integrator", "dt", "precision",
                           "backend", "devices", "threads", "instances", "initial", "prescribed", "loops", "loop_solver", "loop_preconditioner", "base"});
  if (!doc.contains("model")) r.fail("model", "missing (a URDF path or a generator spec such as rope:1000)");
  if (!doc.contains("dt")) r.fail("dt", "missing (the time step in seconds)");

  Scene s;
  s.path = source;
  // ---- model
  s.model_spec = r.string("model", doc["model"]);
  if (s.model_spec.empty()) r.expected("model", "a URDF path or a generator spec", doc["model"]);
  if (s.model_spec.find('\0') != std::string::npos)
    r.fail("model", "'" + printable(s.model_spec) + "' contains a NUL character");
  BuildOptions options;
  if (doc.contains("base")) {  // "fixed" (the default) or "floating" (a free joint at the root)
    const std::string base = r.string("base", doc["base"]);
    if (base == "floating") options.floating_base = true;
    else if (base != "fixed") r.expected("base", "\"fixed\" or \"floating\"", doc["base"]);
  }
  if (doc.contains("allow_nonphysical_inertia"))
    options.require_physical_inertia = !r.boolean("allow_nonphysical_inertia", doc["allow_nonphysical_inertia"]);
  if (is_generator_spec(s.model_spec) || s.model_spec[0] == '/') {
    s.model_path = s.model_spec;
  } else {
    const std::string found = find_model_file(s.model_spec, {base_dir});
    if (file_exists(found)) s.model_path = found;
    if (s.model_path.empty()) {
      std::string list = base_dir;
      for (const auto& d : model_search_dirs()) list += ", " + d;
      r.fail("model", "'" + printable(s.model_spec) + "' not found (looked in " + printable(list) + ")");
    }
  }
  try {
    s.model = load_model(s.model_path, options);
  } catch (const ModelError& e) {
    r.fail("model", e.what());
  }
  const Index nv = s.model.nv(), nq = s.model.nq();
  if (nv == 0) r.fail("model", "'" + s.model_spec + "' has no degrees of freedom");
  // Where the per-DoF joint effects apply (docs/scenes.md, "Floating base and ball
  // joints"): damping on every DoF of a joint (not the floating base's six),
  // springs and limits on 1-DoF joints only (a quaternion has no q - q0).
  const DofDomains domains = dof_domains(s.model);
  const Vec3<double> default_gravity = s.model.gravity;
  s.model.gravity = Vec3<double>::zero();

  // ---- effects
  s.joints.assign(static_cast<std::size_t>(nv), JointCoefficients<double>{0, 0, 0, -kInf, kInf, 0, 0});
  if (doc.contains("effects")) {
    const json& e = doc["effects"];
    r.check_object("effects", e, {"gravity", "damping", "springs", "limits", "external", "contacts"});
    if (e.contains("gravity")) {
      const json& g = e["gravity"];
      if (g.is_boolean()) {
        if (g.get<bool>()) s.effects |= kGravity, s.model.gravity = default_gravity;
      } else if (g.is_array() && g.size() == 3) {
        double v[3];
        for (int k = 0; k < 3; ++k) v[k] = r.number("effects.gravity[" + std::to_string(k) + "]", g[k]);
        s.model.gravity = {v[0], v[1], v[2]};
        s.effects |= kGravity;
      } else {
        r.expected("effects.gravity", "true, false or [gx, gy, gz] (m/s^2)", g);
      }
    }
    if (e.contains("damping")) {
      const std::vector<double> d =
          domains.restrict(r, "effects.damping", e["damping"], r.per_dof("effects.damping", e["damping"], nv, true),
                           domains.joint, 0.0, "joint damping");
      for (Index i = 0; i < nv; ++i) s.joints[i].damping = d[i];
      s.effects |= kDamping;
    }
    if (e.contains("springs")) {
      const json& sp = e["springs"];
      r.check_object("effects.springs", sp, {"stiffness", "rest"});
      if (!sp.contains("stiffness")) r.fail("effects.springs.stiffness", "missing");
      const std::vector<double> k =
          domains.restrict(r, "effects.springs.stiffness", sp["stiffness"],
                           r.per_dof("effects.springs.stiffness", sp["stiffness"], nv, true), domains.one_dof, 0.0,
                           "joint springs");
      const std::vector<double> q0 =
          sp.contains("rest") ? domains.restrict(r, "effects.springs.rest", sp["rest"],
                                                 r.per_dof("effects.springs.rest", sp["rest"], nv, false),
                                                 domains.one_dof, 0.0, "joint springs")
                              : std::vector<double>(nv, 0.0);
      for (Index i = 0; i < nv; ++i) s.joints[i].stiffness = k[i], s.joints[i].rest = q0[i];
      s.effects |= kSprings;
    }
    if (e.contains("limits")) {
      const json& l = e["limits"];
      r.check_object("effects.limits", l, {"stiffness", "damping", "lower", "upper"});
      if (!l.contains("stiffness")) r.fail("effects.limits.stiffness", "missing");
      const std::vector<double> k =
          domains.restrict(r, "effects.limits.stiffness", l["stiffness"],
                           r.per_dof("effects.limits.stiffness", l["stiffness"], nv, true), domains.one_dof, 0.0,
                           "joint limits");
      const std::vector<double> d =
          l.contains("damping") ? domains.restrict(r, "effects.limits.damping", l["damping"],
                                                   r.per_dof("effects.limits.damping", l["damping"], nv, true),
                                                   domains.one_dof, 0.0, "joint limits")
                                : std::vector<double>(nv, 0.0);
      const std::vector<double> lo =
          l.contains("lower") ? domains.restrict(r, "effects.limits.lower", l["lower"],
                                                 r.per_dof("effects.limits.lower", l["lower"], nv, false, true, -kInf),
                                                 domains.one_dof, -kInf, "joint limits")
                              : domains.per_body(s.model.q_lower, -kInf);
      const std::vector<double> hi =
          l.contains("upper") ? domains.restrict(r, "effects.limits.upper", l["upper"],
                                                 r.per_dof("effects.limits.upper", l["upper"], nv, false, true, kInf),
                                                 domains.one_dof, kInf, "joint limits")
                              : domains.per_body(s.model.q_upper, kInf);
      for (Index i = 0; i < nv; ++i) {
        if (lo[i] > hi[i]) {
          std::ostringstream m;
          m << "DoF " << i << " (joint '" << domains.joint_name[i] << "'): lower limit " << lo[i]
            << " is above upper limit " << hi[i];
          r.fail("effects.limits", m.str());
        }
        s.joints[i].limit_stiffness = k[i];
        s.joints[i].limit_damping = d[i];
        s.joints[i].lower = lo[i];
        s.joints[i].upper = hi[i];
      }
      s.effects |= kLimits;
    }
    if (e.contains("external")) {
      const json& x = e["external"];
      r.check_object("effects.external", x, {"wrenches", "per_step"});
      if (x.contains("per_step")) s.wrenches_per_step = r.boolean("effects.external.per_step", x["per_step"]);
      if (x.contains("wrenches")) {
        const json& ws = x["wrenches"];
        if (!ws.is_array()) r.expected("effects.external.wrenches", "an array of {\"link\": NAME, \"wrench\": [6 numbers]}", ws);
        std::map<std::string, Index> body_of;
        for (Index i = 0; i < s.model.nbodies(); ++i) body_of[s.model.link_names[i]] = i;
        for (std::size_t k = 0; k < ws.size(); ++k) {
          const std::string key = "effects.external.wrenches[" + std::to_string(k) + "]";
          r.check_object(key, ws[k], {"link", "wrench"});
          if (!ws[k].contains("link")) r.fail(key + ".link", "missing");
          if (!ws[k].contains("wrench")) r.fail(key + ".wrench", "missing");
          const std::string link = r.string(key + ".link", ws[k]["link"]);
          const auto it = body_of.find(link);
          if (it == body_of.end()) r.fail(key + ".link", "no moving link named '" + link + "' in the model");
          const json& w = ws[k]["wrench"];
          if (!w.is_array() || w.size() != 6)
            r.expected(key + ".wrench", "[nx, ny, nz, fx, fy, fz] (moment N m, force N; body frame)", w);
          double v[6];
          for (int c = 0; c < 6; ++c) v[c] = r.number(key + ".wrench[" + std::to_string(c) + "]", w[c]);
          s.wrenches.push_back({it->second, Force<double>{{v[0], v[1], v[2]}, {v[3], v[4], v[5]}}});
        }
      }
      s.effects |= kExternal;
    }
    if (e.contains("contacts")) {
      parse_contacts(r, e["contacts"], s.model, s.contacts);
      s.effects |= kContacts;
    }
  }

  // ---- integration and execution
  if (doc.contains("loop_solver")) {  // closed loops: dense, sparse, iterative(-cuda) or auto (docs/loops.md)
    s.loop_solver = r.string("loop_solver", doc["loop_solver"]);
    if (s.loop_solver != "auto" && s.loop_solver != "dense" && s.loop_solver != "sparse" &&
        s.loop_solver != "iterative" && s.loop_solver != "iterative-cuda")
      r.expected("loop_solver", "\"auto\", \"dense\", \"sparse\", \"iterative\" or \"iterative-cuda\"",
                 doc["loop_solver"]);
  }
  if (doc.contains("loop_preconditioner")) {  // the iterative loop solver's (docs/loops.md)
    s.loop_preconditioner = r.string("loop_preconditioner", doc["loop_preconditioner"]);
    try {
      (void)parse_loop_preconditioner(s.loop_preconditioner);
    } catch (const LoopError&) {
      r.expected("loop_preconditioner",
                 "\"block-jacobi\", \"symmetric-gauss-seidel\", \"ssor\", \"block-tridiagonal\", \"block-dilu\" or \"none\"",
                 doc["loop_preconditioner"]);
    }
  }
  if (doc.contains("integrator")) {
    const std::string name = r.string("integrator", doc["integrator"]);
    if (!parse_integrator(name, s.integrator)) r.expected("integrator", "\"euler\", \"rk4\", \"implicit\" or \"variational\"", doc["integrator"]);
  }
  s.dt = r.positive("dt", doc["dt"]);
  if (doc.contains("precision")) {
    const std::string p = r.string("precision", doc["precision"]);
    if (p == "double") s.precision = Precision::Double;
    else if (p == "float") s.precision = Precision::Float;
    else r.expected("precision", "\"double\" or \"float\"", doc["precision"]);
  }
  if (doc.contains("backend")) {
    const std::string b = r.string("backend", doc["backend"]);
    if (b == "serial") s.backend = BackendKind::Serial;
    else if (b == "openmp") s.backend = BackendKind::OpenMP;
    else if (b == "cuda") s.backend = BackendKind::Cuda;
    else if (b == "auto") s.backend = auto_backend(&s.backend_note), s.backend_auto = true;
    else r.expected("backend", "\"auto\", \"serial\", \"openmp\" or \"cuda\"", doc["backend"]);
  }
  if (doc.contains("devices")) s.devices = scene_devices(r, doc["devices"], s);
  if (doc.contains("threads")) s.threads = static_cast<int>(r.integer("threads", doc["threads"], 0, 4096));
  if (doc.contains("instances"))
    s.instances = static_cast<Index>(r.integer("instances", doc["instances"], 1, 1000000000));

  // ---- initial state
  InitialState& in = s.initial;
  in.q.assign(static_cast<std::size_t>(nq), 0.0);  // the neutral configuration (identity quaternions)
  neutral_bodies(s.model.bodies.data(), s.model.nbodies(), in.q.data());
  in.qd.assign(static_cast<std::size_t>(nv), 0.0);
  if (doc.contains("initial")) {
    const json& i = doc["initial"];
    r.check_object("initial", i, {"q", "qd", "random"});
    if (i.contains("q")) in.q = s.model.multi_dof() ? initial_positions(r, i["q"], s.model) : r.per_dof("initial.q", i["q"], nv, false);
    if (i.contains("qd")) in.qd = r.per_dof("initial.qd", i["qd"], nv, false);
    if (i.contains("random")) {
      const json& rd = i["random"];
      r.check_object("initial.random", rd, {"seed", "q", "qd"});
      if (!rd.contains("seed")) r.fail("initial.random.seed", "missing (a non-negative integer)");
      const json& seed = rd["seed"];
      if (!seed.is_number_integer() || (!seed.is_number_unsigned() && seed.get<long long>() < 0))
        r.expected("initial.random.seed", "a non-negative integer", seed);
      in.random = true;
      in.seed = seed.get<std::uint64_t>();
      in.q_spread = rd.contains("q") ? r.per_dof("initial.random.q", rd["q"], nv, true) : std::vector<double>(nv, 0.0);
      in.qd_spread = rd.contains("qd") ? r.per_dof("initial.random.qd", rd["qd"], nv, true) : std::vector<double>(nv, 0.0);
    }
  }

  // ---- closed loops: the generator's, then the scene's (an array of loops, or a loop file)
  try {
    s.loops = generator_loops(s.model_spec, s.model);
    if (doc.contains("loops")) {
      const json& l = doc["loops"];
      LoopSet more;
      if (l.is_string()) {
        const std::string p = l.get<std::string>();
        more = load_loops(!p.empty() && p[0] == '/' ? p : base_dir + "/" + p, s.model);
      } else if (l.is_array()) {
        more = parse_loops(json{{"loops", l}}.dump(), source, s.model);
      } else {
        r.expected("loops", "an array of loops or a loop file's path", l);
      }
      for (const LoopClosure& c : more.loops) s.loops.loops.push_back(c);
    }
  } catch (const LoopError& e) {
    throw SceneError(e.what());
  }

  // ---- prescribed joint motion
  if (doc.contains("prescribed")) {
    const json& p = doc["prescribed"];
    if (s.model.multi_dof())
      r.fail("prescribed", "the model has the multi-DoF joint '" + printable(first_multi_dof_joint(s.model)) +
                               "': prescribed joint motion (the hybrid dynamics) takes models of 1-DoF joints only");
    r.check_object("prescribed", p, {"joints", "trajectory"});
    if (!p.contains("joints")) r.fail("prescribed.joints", "missing (an array of joint names or DoF indices)");
    if (!p.contains("trajectory")) r.fail("prescribed.trajectory", "missing (an array, one trajectory per joint)");
    const json& js = p["joints"];
    const json& ts = p["trajectory"];
    if (!js.is_array() || js.empty()) r.expected("prescribed.joints", "a non-empty array of joint names or DoF indices", js);
    if (!ts.is_array() || ts.size() != js.size())
      r.expected("prescribed.trajectory", "an array of " + std::to_string(js.size()) + " trajectories (one per joint)", ts);
    std::vector<unsigned char> seen(static_cast<std::size_t>(nv), 0);
    for (std::size_t k = 0; k < js.size(); ++k) {
      const std::string key = "prescribed.joints[" + std::to_string(k) + "]";
      Index dof = -1;
      if (js[k].is_string()) {
        const std::string name = js[k].get<std::string>();
        const auto it = std::find(s.model.joint_names.begin(), s.model.joint_names.end(), name);
        if (it == s.model.joint_names.end()) r.fail(key, "unknown joint '" + name + "' (scandyn info lists the joints)");
        dof = static_cast<Index>(it - s.model.joint_names.begin());
      } else {
        dof = static_cast<Index>(r.integer(key, js[k], 0, nv - 1));
      }
      if (seen[static_cast<std::size_t>(dof)]) r.fail(key, "DoF " + std::to_string(dof) + " is listed twice");
      seen[static_cast<std::size_t>(dof)] = 1;
      s.prescribed.dofs.push_back(dof);
      const std::string tkey = "prescribed.trajectory[" + std::to_string(k) + "]";
      const json& t = ts[k];
      r.check_object(tkey, t, {"sine", "table"});
      if (t.size() != 1) r.expected(tkey, "an object with one key, \"sine\" or \"table\"", t);
      if (t.contains("sine")) {
        const json& sn = t["sine"];
        const std::string skey = tkey + ".sine";
        r.check_object(skey, sn, {"amplitude", "frequency", "phase", "offset"});
        auto get = [&](const char* name) { return sn.contains(name) ? r.number(skey + "." + name, sn[name]) : 0.0; };
        const double f = get("frequency");
        if (f < 0) r.expected(skey + ".frequency", "a non-negative number (Hz)", sn["frequency"]);
        s.prescribed.trajectory.push_back(sine_trajectory(get("amplitude"), f, get("phase"), get("offset")));
      } else {
        const json& tb = t["table"];
        const std::string bkey = tkey + ".table";
        if (!tb.is_array() || tb.size() < 2) r.expected(bkey, "an array of at least 2 [t, q] pairs", tb);
        std::vector<double> tt, qq;
        for (std::size_t j = 0; j < tb.size(); ++j) {
          const std::string pkey = bkey + "[" + std::to_string(j) + "]";
          if (!tb[j].is_array() || tb[j].size() != 2) r.expected(pkey, "a [t, q] pair", tb[j]);
          tt.push_back(r.number(pkey + "[0]", tb[j][0]));
          qq.push_back(r.number(pkey + "[1]", tb[j][1]));
          if (j > 0 && !(tt[j] > tt[j - 1])) r.fail(pkey, "times must increase strictly");
        }
        s.prescribed.trajectory.push_back(table_trajectory(std::move(tt), std::move(qq)));
      }
    }
  }
  return s;
}

BackendKind auto_backend(std::string* why) {
  const std::string cuda = backend_unusable(BackendKind::Cuda);
  if (cuda.empty()) {
    if (why) *why = "";
    return BackendKind::Cuda;
  }
  const std::string openmp = backend_unusable(BackendKind::OpenMP);
  if (why) *why = "cuda: " + cuda + (openmp.empty() ? "" : "; openmp: " + openmp);
  return openmp.empty() ? BackendKind::OpenMP : BackendKind::Serial;
}

std::string backend_choice(const Scene& scene) {
  if (!scene.backend_auto) return "";
  return std::string("scene backend auto: ") + to_string(scene.backend) +
         (scene.backend_note.empty() ? "" : " (" + scene.backend_note + ")");
}

Scene load_scene(const std::string& path) {
  std::string text;
  try {
    text = read_regular_file(path, limits::kMaxSceneBytes, "scene file");
  } catch (const InputError& e) {
    throw SceneError(e.what());
  }
  return parse_scene(text, printable(path), dir_of(path));
}

}  // namespace sim
}  // namespace scandyn
