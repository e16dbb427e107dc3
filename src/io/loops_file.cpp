// src/io/loops_file.cpp: loop files (JSON, scandyn/algorithm/loops.hpp) and the loops
// the generators fivebar, fourbar and cloth:K:N carry.
#include <algorithm>
#include <cmath>
#include <iomanip>
#include <sstream>

#include <nlohmann/json.hpp>

#include "scandyn/algorithm/loops.hpp"
#include "scandyn/io/limits.hpp"

namespace scandyn {

namespace {

using json = nlohmann::json;

// The body of link `name`: a moving link's DoF index, -1 for the root link (the base).
Index link_body(const Model& model, const std::string& name, const std::string& where) {
  if (name == model.root_link) return -1;
  for (Index i = 0; i < model.nv(); ++i)
    if (model.link_names[i] == name) return i;
  throw LoopError(where + ": unknown link '" + printable(name) + "' (not a link of " + printable(model.source) + ")");
}

// Loops act on models of 1-DoF joints (nv positions): one clear error for the others.
void require_one_dof(const Model& model, const std::string& where) {
  if (model.multi_dof())
    throw LoopError(where + ": model '" + printable(model.name) + "' has the multi-DoF joint '" +
                    printable(first_multi_dof_joint(model)) +
                    "'; closed loops take models of revolute and prismatic joints only");
}

}  // namespace

LoopSet parse_loops(const std::string& json_text, const std::string& source, const Model& model) {
  require_one_dof(model, source);
  json doc;
  try {
    doc = json::parse(json_text);
  } catch (const json::parse_error& e) {
    throw LoopError(source + ": not valid JSON: " + e.what());
  }
  auto fail = [&](const std::string& key, const std::string& what) -> void {
    throw LoopError(source + ": " + key + ": " + what);
  };
  if (!doc.is_object() || !doc.contains("loops") || doc.size() != 1)
    fail("loops", "expected an object with one key, \"loops\", an array of loops");
  const json& ls = doc["loops"];
  if (!ls.is_array()) fail("loops", "expected an array of loops");
  LoopSet out;
  for (std::size_t k = 0; k < ls.size(); ++k) {
    const std::string key = "loops[" + std::to_string(k) + "]";
    const json& l = ls[k];
    if (!l.is_object()) fail(key, "expected an object");
    for (auto it = l.begin(); it != l.end(); ++it)
      if (it.key() != "type" && it.key() != "link_a" && it.key() != "point_a" && it.key() != "link_b" &&
          it.key() != "point_b")
        fail(key + "." + printable(it.key()), "unknown key (expected type, link_a, point_a, link_b, point_b)");
    for (const char* req : {"type", "link_a", "point_a", "link_b", "point_b"})
      if (!l.contains(req)) fail(key + "." + req, "missing");
    LoopClosure c;
    if (l["type"] == "point") c.type = LoopType::Point;
    else if (l["type"] == "weld") c.type = LoopType::Weld;
    else fail(key + ".type", "expected \"point\" or \"weld\"");
    for (const char* name : {"link_a", "link_b"})
      if (!l[name].is_string()) fail(key + "." + name, "expected a link name");
    c.link_a = l["link_a"].get<std::string>();
    c.link_b = l["link_b"].get<std::string>();
    c.body_a = link_body(model, c.link_a, source + ": " + key + ".link_a");
    c.body_b = link_body(model, c.link_b, source + ": " + key + ".link_b");
    if (c.body_a == c.body_b) fail(key, "a loop between link '" + printable(c.link_a) + "' and itself");
    for (const char* name : {"point_a", "point_b"}) {
      const json& p = l[name];
      if (!p.is_array() || p.size() != 3 || !p[0].is_number() || !p[1].is_number() || !p[2].is_number())
        fail(key + "." + name, "expected [x, y, z], 3 numbers (m, in the link's frame)");
      const Vec3<double> v{p[0].get<double>(), p[1].get<double>(), p[2].get<double>()};
      if (!std::isfinite(v.x) || !std::isfinite(v.y) || !std::isfinite(v.z)) fail(key + "." + name, "not finite");
      (std::string(name) == "point_a" ? c.point_a : c.point_b) = v;
    }
    out.loops.push_back(c);
  }
  return out;
}

LoopSet load_loops(const std::string& path, const Model& model) {
  std::string text;
  try {
    text = read_regular_file(path, limits::kMaxSceneBytes, "loop file");
  } catch (const InputError& e) {
    throw LoopError(e.what());
  }
  return parse_loops(text, printable(path), model);
}

LoopSet generator_loops(const std::string& spec, const Model& model) {
  LoopSet out;
  // generators without loops (a free rope, a ballrope) give none, whatever their joints
  // (ia, ib: the links' bodies when known, else -2: looked up by name)
  auto add = [&](const std::string& a, const Vec3<double>& pa, const std::string& b, const Vec3<double>& pb,
                 Index ia = -2, Index ib = -2) {
    require_one_dof(model, spec);
    LoopClosure c;
    c.type = LoopType::Point;
    c.link_a = a, c.link_b = b;
    c.body_a = ia != -2 ? ia : link_body(model, a, spec), c.body_b = ib != -2 ? ib : link_body(model, b, spec);
    c.point_a = pa, c.point_b = pb;
    out.loops.push_back(c);
  };
  if (spec == "fourbar") {
    add("coupler", {0.4, 0, 0}, "rocker", {-0.1, 0.2, 0});
  } else if (spec == "fivebar") {
    add("left_distal", {0.15, 0.15, 0}, "right_distal", {-0.15, 0.15, 0});
  } else if (spec.rfind("cloth:", 0) == 0) {
    // link j of rope k to link j of rope k + 1, half-way between the ropes at the
    // link's lower end (ropes 0.02 m apart, links 0.01 m long: curtain:K:N)
    const std::size_t c1 = spec.find(':', 6);
    const long long K = std::stoll(spec.substr(6, c1 - 6)), N = std::stoll(spec.substr(c1 + 1));
    // rope k's link j is body k N + j (depth-first order, the ropes in joint-name order)
    auto name = [&](long long k, long long j) { return model.link_names[static_cast<std::size_t>(k * N + j)]; };
    // (the bodies by index: a lookup by name per loop is O(links) each, hours at 10^6 links)
    require_one_dof(model, spec);
    if (static_cast<long long>(model.link_names.size()) < K * N)
      throw LoopError(spec + ": the model has " + std::to_string(model.link_names.size()) + " links, not the " +
                      std::to_string(K * N) + " of its ropes");
    out.loops.reserve(static_cast<std::size_t>(std::max(0LL, (K - 1) * N)));
    for (long long k = 0; k + 1 < K; ++k)
      for (long long j = 0; j < N; ++j)
        add(name(k, j), {0.01, 0, -0.01}, name(k + 1, j), {-0.01, 0, -0.01}, static_cast<Index>(k * N + j),
            static_cast<Index>((k + 1) * N + j));
  }
  return out;
}

std::string loops_json(const LoopSet& loops) {
  std::ostringstream s;
  s << std::setprecision(17) << "{\"loops\": [";
  for (std::size_t k = 0; k < loops.loops.size(); ++k) {
    const LoopClosure& l = loops.loops[k];
    auto vec = [&](const Vec3<double>& v) { s << "[" << v.x << ", " << v.y << ", " << v.z << "]"; };
    s << (k ? ",\n  " : "\n  ") << "{\"type\": \"" << (l.type == LoopType::Point ? "point" : "weld")
      << "\", \"link_a\": " << json(l.link_a).dump() << ", \"point_a\": ";
    vec(l.point_a);
    s << ", \"link_b\": " << json(l.link_b).dump() << ", \"point_b\": ";
    vec(l.point_b);
    s << "}";
  }
  s << (loops.loops.empty() ? "]}\n" : "\n]}\n");
  return s.str();
}

}  // namespace scandyn
