// src/model/generators.cpp: built-in model generators (chain:N, rope:N, ballrope:N,
// tree:N:SEED, curtain:K:N, cloth:K:N (the curtain's tree), fivebar, fourbar). Each one writes a RawTree, exactly as a URDF file would describe
// it, and goes through build_model like any file. Geometry: docs/models.md.
//
// Names are zero-padded to the width of the largest index, so byte-wise name order
// is index order and the DoF order is predictable; they stay within std::string's
// small buffer (no heap allocation per name) up to 10^7 links.
#include <cmath>
#include <cstdint>
#include <cstring>
#include <random>
#include <string>
#include <vector>

#include "scandyn/model/load.hpp"

namespace scandyn {
namespace {

constexpr double kPi = 3.14159265358979323846;

[[noreturn]] void bad_spec(const std::string& spec, const std::string& what) {
  throw ModelError(spec + ": " + what);
}

std::vector<std::string> split(const std::string& s, char sep) {
  std::vector<std::string> out(1);
  for (char c : s) {
    if (c == sep) out.emplace_back();
    else out.back() += c;
  }
  return out;
}

bool all_digits(const std::string& s) {
  if (s.empty()) return false;
  for (char c : s)
    if (c < '0' || c > '9') return false;
  return true;
}

// A count in [1, kMaxGeneratedBodies].
long long parse_count(const std::string& spec, const std::string& s, const char* what) {
  if (!all_digits(s))
    bad_spec(spec, std::string(what) + " must be a positive integer, got '" + s + "'");
  if (s.size() > 12) bad_spec(spec, std::string(what) + " is too large (at most " +
                                        std::to_string(kMaxGeneratedBodies) + ")");
  const long long v = std::stoll(s);
  if (v < 1) bad_spec(spec, std::string(what) + " must be >= 1");
  if (v > kMaxGeneratedBodies)
    bad_spec(spec, std::string(what) + " is too large (at most " + std::to_string(kMaxGeneratedBodies) + ")");
  return v;
}

std::uint64_t parse_seed(const std::string& spec, const std::string& s) {
  if (!all_digits(s)) bad_spec(spec, "SEED must be a non-negative integer, got '" + s + "'");
  std::uint64_t v = 0;
  for (char c : s) {
    const std::uint64_t d = static_cast<std::uint64_t>(c - '0');
    if (v > (UINT64_MAX - d) / 10) bad_spec(spec, "SEED does not fit in 64 bits");
    v = v * 10 + d;
  }
  return v;
}

// Decimal digits of n - 1 (at least 1): the width that zero-pads indices 0..n-1.
int index_width(long long n) {
  int w = 1;
  for (long long x = n - 1; x >= 10; x /= 10) ++w;
  return w;
}

// Appends i zero-padded to width w at p; returns the end.
char* put_index(char* p, long long i, int w) {
  for (int k = w - 1; k >= 0; --k, i /= 10) p[k] = static_cast<char>('0' + i % 10);
  return p + w;
}

// prefix + index (+ "_" + index2 when w2 > 0) + suffix, built in place.
std::string make_name(const char* prefix, long long i, int w, long long i2 = 0, int w2 = 0,
                      const char* suffix = "") {
  char buf[96];
  const std::size_t pl = std::strlen(prefix), sl = std::strlen(suffix);
  std::memcpy(buf, prefix, pl);
  char* p = put_index(buf + pl, i, w);
  if (w2 > 0) {
    *p++ = '_';
    p = put_index(p, i2, w2);
  }
  std::memcpy(p, suffix, sl);
  return std::string(buf, static_cast<std::size_t>(p - buf) + sl);
}

RawLink& add_link(RawTree& t, std::string name, double mass, const Vec3<double>& com,
                  const Sym3<double>& Ic) {
  t.links.emplace_back();
  RawLink& l = t.links.back();
  l.name = std::move(name);
  l.has_inertial = true;
  l.mass = mass;
  l.com_xyz = com;
  l.inertia = Ic;
  return l;
}

RawLink& add_frame(RawTree& t, std::string name) {  // massless link
  t.links.emplace_back();
  t.links.back().name = std::move(name);
  return t.links.back();
}

RawJoint& add_joint(RawTree& t, std::string name, RawJointType type, const std::string& parent,
                    const std::string& child, const Vec3<double>& xyz, const Vec3<double>& axis) {
  t.joints.emplace_back();
  RawJoint& j = t.joints.back();
  j.name = std::move(name);
  j.type = type;
  j.type_name = type == RawJointType::Prismatic   ? "prismatic"
                : type == RawJointType::Fixed     ? "fixed"
                : type == RawJointType::Spherical ? "spherical"
                                                  : "revolute";
  j.parent = parent;
  j.child = child;
  j.xyz = xyz;
  j.axis = axis;
  return j;
}

// --- chain:N -------------------------------------------------------------------
// Uniform rods of 1 kg, 0.3 m along +z; axes z, y, z, y, ...
RawTree chain(long long n) {
  constexpr double m = 1.0, L = 0.3;
  const Sym3<double> Ic{m * L * L / 12, m * L * L / 12, 1e-3, 0, 0, 0};
  RawTree t;
  t.links.reserve(static_cast<std::size_t>(n) + 1);
  t.joints.reserve(static_cast<std::size_t>(n));
  add_frame(t, "base");
  const int w = index_width(n);
  for (long long i = 0; i < n; ++i) {
    add_link(t, make_name("link_", i, w), m, {0, 0, L / 2}, Ic);
    add_joint(t, make_name("joint_", i, w), RawJointType::Revolute, t.links[i].name,
              t.links[i + 1].name, i == 0 ? Vec3<double>{0, 0, 0} : Vec3<double>{0, 0, L},
              i % 2 == 0 ? Vec3<double>{0, 0, 1} : Vec3<double>{0, 1, 0});
  }
  return t;
}

// --- rope:N and curtain:K:N ----------------------------------------------------
// Solid cylinders 1 cm long, radius 2 mm, 10 g, hanging along -z; axes x, y, x, ...
constexpr double kRopeMass = 0.01, kRopeLength = 0.01, kRopeRadius = 0.002;

Sym3<double> rope_inertia() {
  const double m = kRopeMass, L = kRopeLength, r = kRopeRadius;
  const double side = m * (3 * r * r + L * L) / 12;
  return {side, side, m * r * r / 2, 0, 0, 0};
}

// Appends one rope of n links hanging from link `parent_index` of t, its first
// joint at `origin`. Names: joint_i / link_i, or joint_k_i / link_k_i when wk > 0
// (k padded to width wk, i to the width of n - 1).
void add_rope(RawTree& t, std::size_t parent_index, const Vec3<double>& origin, long long n,
              long long k, int wk, RawJointType type = RawJointType::Revolute) {
  const Sym3<double> Ic = rope_inertia();
  const int wi = index_width(n);
  for (long long i = 0; i < n; ++i) {
    const std::size_t parent = i == 0 ? parent_index : t.links.size() - 1;
    const std::size_t child = t.links.size();
    if (wk > 0) add_link(t, make_name("link_", k, wk, i, wi), kRopeMass, {0, 0, -kRopeLength / 2}, Ic);
    else add_link(t, make_name("link_", i, wi), kRopeMass, {0, 0, -kRopeLength / 2}, Ic);
    add_joint(t, wk > 0 ? make_name("joint_", k, wk, i, wi) : make_name("joint_", i, wi),
              type, t.links[parent].name, t.links[child].name,
              i == 0 ? origin : Vec3<double>{0, 0, -kRopeLength},
              i % 2 == 0 ? Vec3<double>{1, 0, 0} : Vec3<double>{0, 1, 0});
  }
}

// rope:N (revolute joints) and ballrope:N (spherical joints).
RawTree rope(long long n, RawJointType type = RawJointType::Revolute) {
  RawTree t;
  t.links.reserve(static_cast<std::size_t>(n) + 1);
  t.joints.reserve(static_cast<std::size_t>(n));
  add_frame(t, "base");
  add_rope(t, 0, {0, 0, 0}, n, 0, 0, type);
  return t;
}

RawTree curtain(long long ropes, long long n) {
  RawTree t;
  t.links.reserve(static_cast<std::size_t>(ropes * n) + 1);
  t.joints.reserve(static_cast<std::size_t>(ropes * n));
  add_frame(t, "rod");
  const int wk = index_width(ropes);
  for (long long k = 0; k < ropes; ++k) add_rope(t, 0, {0.02 * static_cast<double>(k), 0, 0}, n, k, wk);
  return t;
}

// --- tree:N:SEED -----------------------------------------------------------------
// Random numbers from std::mt19937_64 through our own mappings (the standard
// distributions differ between library implementations).
struct Random {
  explicit Random(std::uint64_t seed) : g(seed) {}
  std::mt19937_64 g;
  double u01() { return static_cast<double>(g() >> 11) * 0x1.0p-53; }          // [0, 1)
  double uniform(double a, double b) { return a + (b - a) * u01(); }           // [a, b)
  long long index(long long n) {                                               // [0, n)
    const long long k = static_cast<long long>(u01() * static_cast<double>(n));
    return k < n ? k : n - 1;
  }
  Vec3<double> box(double a, double b) { const double x = uniform(a, b), y = uniform(a, b); return {x, y, uniform(a, b)}; }
};

// Mass, centre of mass, inertial-frame rotation and principal moments of a solid
// box (so the triangle inequality holds) for one random link.
RawLink& add_random_link(RawTree& t, std::string name, Random& rng) {
  const double m = rng.uniform(0.5, 2.0);
  const Vec3<double> c = rng.box(-0.1, 0.1);
  const Vec3<double> rpy = rng.box(-kPi, kPi);
  const Vec3<double> s = rng.box(0.05, 0.4);  // box edge lengths
  const Sym3<double> Ic{m * (s.y * s.y + s.z * s.z) / 12, m * (s.x * s.x + s.z * s.z) / 12,
                        m * (s.x * s.x + s.y * s.y) / 12, 0, 0, 0};
  RawLink& l = add_link(t, std::move(name), m, c, Ic);
  l.com_rpy = rpy;
  return l;
}

RawTree random_tree(long long n, std::uint64_t seed) {
  Random rng(seed);
  RawTree t;
  const int w = index_width(n);
  t.links.reserve(static_cast<std::size_t>(n + n / 5) + 1);
  t.joints.reserve(static_cast<std::size_t>(n + n / 5));
  add_frame(t, "base");
  std::vector<std::size_t> link_of(static_cast<std::size_t>(n)), fixed_of(static_cast<std::size_t>(n), 0);
  for (long long i = 0; i < n; ++i) {
    // parent: the base or one of bodies 0..i-1, uniformly; for a body that carries
    // a fixed link, the fixed link or the body's own link with probability 1/2 each
    const long long p = rng.index(i + 1) - 1;
    std::size_t parent = 0;
    if (p >= 0) {
      parent = link_of[p];
      if (p % 5 == 4 && rng.u01() < 0.5) parent = fixed_of[p];
    }
    const RawJointType type = rng.u01() < 0.2 ? RawJointType::Prismatic : RawJointType::Revolute;
    Vec3<double> axis;
    do {  // uniform on the sphere, no component below 0.1 in magnitude
      const double z = rng.uniform(-1, 1), phi = rng.uniform(0, 2 * kPi);
      const double rho = std::sqrt(1 - z * z);
      axis = {rho * std::cos(phi), rho * std::sin(phi), z};
    } while (std::fabs(axis.x) < 0.1 || std::fabs(axis.y) < 0.1 || std::fabs(axis.z) < 0.1);
    const Vec3<double> xyz = rng.box(-0.3, 0.3);
    const Vec3<double> rpy = rng.box(-kPi, kPi);
    link_of[i] = t.links.size();
    add_random_link(t, make_name("link_", i, w), rng);
    RawJoint& j = add_joint(t, make_name("joint_", i, w), type, t.links[parent].name,
                            t.links[link_of[i]].name, xyz, axis);
    j.rpy = rpy;
    if (i % 5 == 4) {  // a massive link fixed to body i
      const Vec3<double> fxyz = rng.box(-0.3, 0.3);
      const Vec3<double> frpy = rng.box(-kPi, kPi);
      fixed_of[i] = t.links.size();
      add_random_link(t, make_name("link_", i, w, 0, 0, "_fixed"), rng);
      RawJoint& f = add_joint(t, make_name("joint_", i, w, 0, 0, "_fixed"), RawJointType::Fixed,
                              t.links[link_of[i]].name, t.links[fixed_of[i]].name, fxyz, {1, 0, 0});
      f.rpy = frpy;
    }
  }
  return t;
}

// --- fourbar and fivebar: planar closed linkages, all joints about z -------------
// Slender rods of 1 kg per m along their link vector (a link frame at the joint, the
// rod from it to the next joint or the closing point), in the xy-plane; the loop
// that closes them is generator_loops's (scandyn/algorithm/loops.hpp). The
// configuration q = 0 is closed and away from singularities.

// A rod link from the joint to `tip` (link frame): mass 1 kg/m, centre at tip / 2,
// inertia about the centre m L^2 / 12 across the rod plus 1e-5 kg m^2 on all axes
// (so that it is a physical inertia).
RawLink& add_rod(RawTree& t, std::string name, const Vec3<double>& tip) {
  const double L = std::sqrt(tip.x * tip.x + tip.y * tip.y + tip.z * tip.z), m = L;
  const Vec3<double> u{tip.x / L, tip.y / L, tip.z / L};
  const double k = m * L * L / 12, e = 1e-5;
  // k (I - u u^T) + e I
  const Sym3<double> Ic{k * (1 - u.x * u.x) + e, k * (1 - u.y * u.y) + e, k * (1 - u.z * u.z) + e,
                        -k * u.x * u.y, -k * u.x * u.z, -k * u.y * u.z};
  return add_link(t, std::move(name), m, {tip.x / 2, tip.y / 2, tip.z / 2}, Ic);
}

// fourbar: ground pivots A = (0, 0) and D = (0.5, 0); crank A-B (0, 0.2), coupler
// B-C (0.4, 0), rocker D-C (-0.1, 0.2) at q = 0; the loop joins the coupler's tip C
// to the rocker's tip.
RawTree fourbar() {
  RawTree t;
  const Vec3<double> z{0, 0, 1};
  add_frame(t, "ground");
  add_rod(t, "crank", {0, 0.2, 0});
  add_rod(t, "coupler", {0.4, 0, 0});
  add_rod(t, "rocker", {-0.1, 0.2, 0});
  add_joint(t, "joint_a", RawJointType::Revolute, "ground", "crank", {0, 0, 0}, z);
  add_joint(t, "joint_b", RawJointType::Revolute, "crank", "coupler", {0, 0.2, 0}, z);
  add_joint(t, "joint_d", RawJointType::Revolute, "ground", "rocker", {0.5, 0, 0}, z);
  return t;
}

// fivebar: ground pivots A = (0, 0) and E = (0.3, 0); left proximal A-B (0, 0.25),
// left distal B-P (0.15, 0.15), right proximal E-D (0, 0.25), right distal D-P
// (-0.15, 0.15) at q = 0; the loop joins the two distal tips at P = (0.15, 0.4).
RawTree fivebar() {
  RawTree t;
  const Vec3<double> z{0, 0, 1};
  add_frame(t, "ground");
  add_rod(t, "left_proximal", {0, 0.25, 0});
  add_rod(t, "left_distal", {0.15, 0.15, 0});
  add_rod(t, "right_proximal", {0, 0.25, 0});
  add_rod(t, "right_distal", {-0.15, 0.15, 0});
  add_joint(t, "joint_l0", RawJointType::Revolute, "ground", "left_proximal", {0, 0, 0}, z);
  add_joint(t, "joint_l1", RawJointType::Revolute, "left_proximal", "left_distal", {0, 0.25, 0}, z);
  add_joint(t, "joint_r0", RawJointType::Revolute, "ground", "right_proximal", {0.3, 0, 0}, z);
  add_joint(t, "joint_r1", RawJointType::Revolute, "right_proximal", "right_distal", {0, 0.25, 0}, z);
  return t;
}

bool starts_with(const std::string& s, const char* p) { return s.rfind(p, 0) == 0; }

}  // namespace

bool is_generator_spec(const std::string& s) {
  return starts_with(s, "chain:") || starts_with(s, "rope:") || starts_with(s, "tree:") ||
         starts_with(s, "curtain:") || starts_with(s, "cloth:") || s == "fivebar" || s == "fourbar" ||
         starts_with(s, "ballrope:");
}

RawTree generate_tree(const std::string& spec) { return generate_tree(spec, false); }

RawTree generate_tree(const std::string& spec, bool floating_base) {
  const std::vector<std::string> parts = split(spec, ':');
  const std::string& kind = parts[0];
  RawTree t;
  if (kind == "chain" || kind == "rope" || kind == "ballrope") {
    if (parts.size() != 2) bad_spec(spec, "expected " + kind + ":N");
    const long long n = parse_count(spec, parts[1], "N");
    t = kind == "chain" ? chain(n) : rope(n, kind == "rope" ? RawJointType::Revolute : RawJointType::Spherical);
    if (floating_base) {
      // free chain: the first link is the root (the floating base), its joint and the
      // massless base frame are dropped
      t.links.erase(t.links.begin());
      t.joints.erase(t.joints.begin());
    }
  } else if (kind == "tree") {
    if (parts.size() != 3) bad_spec(spec, "expected tree:N:SEED");
    const long long n = parse_count(spec, parts[1], "N");
    const std::uint64_t seed = parse_seed(spec, parts[2]);
    t = random_tree(n, seed);
    if (floating_base) {
      // the base frame gets a random link's mass and inertia (drawn after the tree's)
      Random rng(seed ^ 0x9e3779b97f4a7c15ull);
      RawTree base;
      add_random_link(base, "base", rng);
      t.links[0] = base.links[0];
    }
  } else if (kind == "fivebar" || kind == "fourbar") {
    if (parts.size() != 1) bad_spec(spec, "expected " + kind + " (no parameters)");
    t = kind == "fivebar" ? fivebar() : fourbar();
  } else if (kind == "curtain" || kind == "cloth") {
    // cloth:K:N is curtain:K:N's tree; its point loops are generator_loops's
    if (parts.size() != 3) bad_spec(spec, "expected " + kind + ":K:N");
    const long long k = parse_count(spec, parts[1], "K");
    const long long n = parse_count(spec, parts[2], "N");
    if (k * n > kMaxGeneratedBodies)
      bad_spec(spec, "K*N is too large (at most " + std::to_string(kMaxGeneratedBodies) + ")");
    t = curtain(k, n);
  } else {
    bad_spec(spec, "unknown generator (expected chain:N, rope:N, ballrope:N, tree:N:SEED, curtain:K:N, cloth:K:N, "
                   "fivebar or fourbar)");
  }
  t.name = spec;
  t.source = spec;
  return t;
}

Model make_generated(const std::string& spec, const BuildOptions& options) {
  return build_model(generate_tree(spec, options.floating_base), options);
}

}  // namespace scandyn
