// src/model/builder.cpp: the one builder and validator behind every model
// (URDF files, generators, raw trees).
//
// Order of work: validate names and numbers link by link and joint by joint (first
// error in RawTree order wins), connect joints to links, find the one root, then walk
// the tree depth-first in preorder with an explicit stack (no recursion: generated
// ropes have 10^6 links), children of a link in byte-wise joint-name order, fixed
// joints transparent. Each moving joint opens a body; each link's inertia is added
// to the body it belongs to.
#include <Eigen/Eigenvalues>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>
#include <string_view>
#include <cstdint>
#include <functional>
#include <vector>

#include "scandyn/model/load.hpp"

namespace scandyn {
namespace {

// Relative tolerances of the inertia checks (docs/models.md).
constexpr double kPositiveDefiniteTol = 1e-12;  // lambda_min > tol * lambda_max
constexpr double kTriangleTol = 1e-9;           // lambda_max <= lambda_1 + lambda_2 + tol * trace
constexpr double kMinAxisNorm = 1e-12;          // a moving joint's axis must be longer than this

std::string fmt(double x) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.6g", x);
  return buf;
}

[[noreturn]] void fail(const RawTree& t, const char* kind, const std::string& name,
                       const std::string& what) {
  throw ModelError(t.source + ": " + kind + " '" + name + "': " + what);
}

bool finite(double x) { return std::isfinite(x); }
bool finite(const Vec3<double>& v) { return finite(v.x) && finite(v.y) && finite(v.z); }
bool finite(const Sym3<double>& s) {
  return finite(s.xx) && finite(s.yy) && finite(s.zz) && finite(s.xy) && finite(s.xz) &&
         finite(s.yz);
}
bool finite(const RawQuat& q) { return finite(q.x) && finite(q.y) && finite(q.z) && finite(q.w); }
bool is_zero(const Vec3<double>& v) { return v.x == 0 && v.y == 0 && v.z == 0; }
bool finite(const Mat3<double>& m) {
  for (double x : m.m)
    if (!finite(x)) return false;
  return true;
}
bool finite(const Transform<double>& X) { return finite(X.E) && finite(X.r); }
bool finite(const Inertia<double>& I) { return finite(I.m) && finite(I.h) && finite(I.I); }

// Euclidean norm of (a, b, c, d) without overflow or underflow in the squares: scaled
// by the largest magnitude (sqrt(x^2 + ...) of 1e155 overflows to Inf, and 1/Inf
// turns an axis into 0 0 0).
double safe_norm(double a, double b, double c, double d = 0) {
  const double m = std::max({std::fabs(a), std::fabs(b), std::fabs(c), std::fabs(d)});
  if (m == 0 || !finite(m)) return m;
  a /= m, b /= m, c /= m, d /= m;
  return m * std::sqrt(a * a + b * b + c * c + d * d);
}

// The unit vector along v (v finite and not zero).
Vec3<double> unit(const Vec3<double>& v) {
  const double m = std::max({std::fabs(v.x), std::fabs(v.y), std::fabs(v.z)});
  const Vec3<double> s{v.x / m, v.y / m, v.z / m};  // largest component +-1: no overflow
  const double n = std::sqrt(dot(s, s));
  return (1.0 / n) * s;
}

// Rotation matrix (child coordinates -> parent coordinates) of a unit quaternion.
Mat3<double> quat_matrix(const RawQuat& q) {
  const double n = safe_norm(q.x, q.y, q.z, q.w);
  const double x = q.x / n, y = q.y / n, z = q.z / n, w = q.w / n;
  return {{1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
           2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
           2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)}};
}

Mat3<double> rotation(bool has_quat, const RawQuat& q, const Vec3<double>& rpy) {
  if (has_quat) return quat_matrix(q);
  if (is_zero(rpy)) return Mat3<double>::identity();
  return rpy_matrix(rpy.x, rpy.y, rpy.z);
}

// Quaternion given but unusable (zero).
bool bad_quat(bool has_quat, const RawQuat& q) {
  return has_quat && q.x == 0 && q.y == 0 && q.z == 0 && q.w == 0;
}

// --- per-link and per-joint checks -------------------------------------------

void check_link(const RawTree& t, const RawLink& l, const BuildOptions& opt) {
  const char* L = "link";
  if (!finite(l.mass)) fail(t, L, l.name, "mass is not finite (" + fmt(l.mass) + ")");
  if (!finite(l.com_xyz) || !finite(l.com_rpy) || (l.com_has_quat && !finite(l.com_quat)))
    fail(t, L, l.name, "<inertial><origin> has a non-finite number");
  if (bad_quat(l.com_has_quat, l.com_quat)) fail(t, L, l.name, "<inertial><origin> quaternion is zero");
  if (!finite(l.inertia)) fail(t, L, l.name, "<inertia> has a non-finite number");
  if (!l.has_inertial) return;  // massless frame
  if (!(l.mass > 0)) fail(t, L, l.name, "mass " + fmt(l.mass) + " is not positive");

  // principal moments; exact for a diagonal tensor (every generated link)
  const Sym3<double>& I = l.inertia;
  double e[3];
  if (I.xy == 0 && I.xz == 0 && I.yz == 0) {
    e[0] = I.xx, e[1] = I.yy, e[2] = I.zz;
    std::sort(e, e + 3);
  } else {
    Eigen::Matrix3d A;
    A << I.xx, I.xy, I.xz, I.xy, I.yy, I.yz, I.xz, I.yz, I.zz;
    const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(A, Eigen::EigenvaluesOnly);
    for (int k = 0; k < 3; ++k) e[k] = es.eigenvalues()[k];  // ascending
  }
  const bool definite = e[0] > kPositiveDefiniteTol * std::fabs(e[2]);
  if (definite && e[2] - (e[0] + e[1]) <= kTriangleTol * (e[0] + e[1] + e[2])) return;
  const std::string moments = fmt(e[0]) + ", " + fmt(e[1]) + ", " + fmt(e[2]);
  const std::string what =
      !definite ? "rotational inertia about the centre of mass is not positive definite "
                  "(principal moments " + moments + ")"
                : "principal moments " + moments +
                      " violate the triangle inequality (the largest exceeds the sum of the other two)";
  if (opt.require_physical_inertia)
    fail(t, L, l.name, what + "; no rigid body has this inertia (load it anyway with "
                                   "--allow-nonphysical-inertia, or BuildOptions::require_physical_inertia = false)");
  if (opt.warnings) opt.warnings->push_back(t.source + ": link '" + l.name + "': " + what);
}

// Joint type and numbers (links are checked after all names are known).
void check_joint(const RawTree& t, const RawJoint& j) {
  const char* J = "joint";
  switch (j.type) {
    case RawJointType::Revolute:
    case RawJointType::Continuous:
    case RawJointType::Prismatic:
    case RawJointType::Fixed:
    case RawJointType::Spherical:
      break;
    case RawJointType::Floating:
    case RawJointType::Planar:
      fail(t, J, j.name, "joint type '" + j.type_name + "' is not supported (fixed-base trees of "
                         "revolute, continuous, prismatic and fixed joints only)");
    default:
      fail(t, J, j.name, "unknown joint type '" + j.type_name + "'");
  }
  if (!finite(j.xyz) || !finite(j.rpy) || (j.has_quat && !finite(j.quat)))
    fail(t, J, j.name, "<origin> has a non-finite number");
  if (bad_quat(j.has_quat, j.quat)) fail(t, J, j.name, "<origin> quaternion is zero");
  if (!finite(j.axis)) fail(t, J, j.name, "<axis> has a non-finite number");
  if (j.type != RawJointType::Fixed && j.type != RawJointType::Spherical) {
    const double n = safe_norm(j.axis.x, j.axis.y, j.axis.z);
    if (!(n > kMinAxisNorm)) fail(t, J, j.name, "<axis> is zero");
    const Vec3<double> u = unit(j.axis);
    if (!finite(u) || std::fabs(std::sqrt(dot(u, u)) - 1) > 1e-9)
      fail(t, J, j.name, "<axis> " + fmt(j.axis.x) + " " + fmt(j.axis.y) + " " + fmt(j.axis.z) +
                         " cannot be normalised");
  }
}

// The derived quantities of a built body (its unit axis, joint transform and spatial
// inertia, merged fixed links included) must be finite: inputs that are each finite
// can still overflow in a product (a mass of 1e200 at 1e200 m: m c^2 = Inf).
void check_body(const RawTree& t, const Model& m, std::size_t b) {
  const Body<double>& body = m.bodies[b];
  const std::string& joint = m.joint_names[b];
  const auto overflow = [&](const std::string& what) {
    fail(t, "joint", joint, what + " of its body (link '" + m.link_names[b] +
                                "', fixed-joint children merged) overflows: a number in the model is too large");
  };
  if (!finite(body.axis) || std::fabs(dot(body.axis, body.axis) - 1) > 1e-6) overflow("the unit axis");
  if (!finite(body.Xtree)) overflow("the joint transform");
  if (!finite(body.I)) overflow("the spatial inertia");
}

// Spatial inertia of a link about its own origin, link axes.
Inertia<double> link_inertia(const RawLink& l) {
  if (!l.has_inertial) return Inertia<double>::zero();
  Sym3<double> Ic = l.inertia;
  if (l.com_has_quat || !is_zero(l.com_rpy)) {
    // Ic_link = R Ic R^T: congruence_transpose(E, A) = E^T A E with E = R^T
    const Mat3<double> R = rotation(l.com_has_quat, l.com_quat, l.com_rpy);
    Ic = congruence_transpose(transpose(R), Ic);
  }
  return Inertia<double>::from_com(l.mass, l.com_xyz, Ic);
}

// child_X_parent of a joint at q = 0.
Transform<double> joint_transform(const RawJoint& j) {
  return Transform<double>::from_pose(rotation(j.has_quat, j.quat, j.rpy), j.xyz);
}

// Name -> index, open addressing over (hash tag, index) slots. With 10^6 names the
// cost is cache misses, so callers hash ahead and prefetch (several times faster than
// std::unordered_map here).
class NameIndex {
 public:
  explicit NameIndex(std::size_t n) {
    std::size_t cap = 16;
    while (cap < 2 * n) cap <<= 1;
    slots_.assign(cap, Slot{0, -1});
    mask_ = cap - 1;
  }
  static std::size_t hash(std::string_view key) { return std::hash<std::string_view>()(key); }
  void prefetch(std::size_t h) const { __builtin_prefetch(&slots_[h & mask_]); }
  // Inserts (key, i) unless key is present; returns the index already there, or -1.
  // names(j) is the j-th name.
  template <class Names>
  int insert(std::string_view key, std::size_t h, int i, const Names& names) {
    const auto tag = static_cast<std::uint32_t>(h >> 32);
    for (std::size_t s = h & mask_;; s = (s + 1) & mask_) {
      Slot& slot = slots_[s];
      if (slot.index < 0) {
        slot = {tag, i};
        return -1;
      }
      if (slot.tag == tag && names(slot.index) == key) return slot.index;
    }
  }
  // Index of key, or -1.
  template <class Names>
  int find(std::string_view key, std::size_t h, const Names& names) const {
    const auto tag = static_cast<std::uint32_t>(h >> 32);
    for (std::size_t s = h & mask_;; s = (s + 1) & mask_) {
      const Slot& slot = slots_[s];
      if (slot.index < 0) return -1;
      if (slot.tag == tag && names(slot.index) == key) return slot.index;
    }
  }

 private:
  struct Slot {
    std::uint32_t tag;
    int index;
  };
  std::vector<Slot> slots_;
  std::size_t mask_;
};

// Inserts names(0..n-1) into index; returns the first i whose name repeats an
// earlier one (not inserted), or -1.
template <class Names>
int insert_all(NameIndex& index, int n, const Names& names) {
  constexpr int kAhead = 16;  // prefetch distance
  std::vector<std::size_t> h(static_cast<std::size_t>(n));
  for (int i = 0; i < n; ++i) h[i] = NameIndex::hash(names(i));
  for (int i = 0; i < n; ++i) {
    if (i + kAhead < n) index.prefetch(h[i + kAhead]);
    if (index.insert(names(i), h[i], i, names) >= 0) return i;
  }
  return -1;
}

}  // namespace

Model build_model(const RawTree& t, const BuildOptions& opt) {
  const int nl = static_cast<int>(t.links.size());
  const int nj = static_cast<int>(t.joints.size());
  if (t.links.size() > 0x3fffffff || t.joints.size() > 0x3fffffff)
    throw ModelError(t.source + ": too many links or joints");
  if (nl == 0) throw ModelError(t.source + ": no links");

  // names: link name -> index, duplicates
  const auto link_name = [&](int i) { return std::string_view(t.links[i].name); };
  const auto joint_name = [&](int k) { return std::string_view(t.joints[k].name); };
  NameIndex link_index(t.links.size());
  if (const int i = insert_all(link_index, nl, link_name); i >= 0)
    fail(t, "link", t.links[i].name, "duplicate link name");
  {
    NameIndex joint_index(t.joints.size());
    if (const int k = insert_all(joint_index, nj, joint_name); k >= 0)
      fail(t, "joint", t.joints[k].name, "duplicate joint name");
  }
  // a link's index: the guess (the next link in file order, as writers and the
  // generators tend to put them) when it matches, else a hash lookup
  const auto find_link = [&](const std::string& name, int guess) {
    if (guess >= 0 && guess < nl && t.links[guess].name == name) return guess;
    return link_index.find(name, NameIndex::hash(name), link_name);
  };

  // numbers, link by link then joint by joint
  for (const RawLink& l : t.links) check_link(t, l, opt);
  for (const RawJoint& j : t.joints) check_joint(t, j);

  // connect: parent/child link of each joint, parent joint of each link
  std::vector<int> jparent(nj), jchild(nj), parent_joint(nl, -1), nchildren(nl + 1, 0);
  for (int k = 0, last = -1; k < nj; ++k) {
    const RawJoint& j = t.joints[k];
    const int p = find_link(j.parent, last);
    if (p < 0) fail(t, "joint", j.name, "parent link '" + j.parent + "' does not exist");
    const int c = find_link(j.child, last + 1);
    last = c;
    if (c < 0) fail(t, "joint", j.name, "child link '" + j.child + "' does not exist");
    if (p == c) fail(t, "joint", j.name, "connects link '" + j.child + "' to itself");
    jparent[k] = p;
    jchild[k] = c;
    int& pj = parent_joint[c];
    if (pj >= 0)
      fail(t, "link", j.child, "has two parent joints, '" + t.joints[pj].name + "' and '" + j.name + "'");
    pj = k;
    ++nchildren[p + 1];
  }

  // the one root
  int root = -1;
  for (int i = 0; i < nl; ++i) {
    if (parent_joint[i] >= 0) continue;
    if (root >= 0)
      fail(t, "link", t.links[i].name, "is a second root link (no parent joint) besides '" +
                                           t.links[root].name + "'; a model has one root");
    root = i;
  }
  if (root < 0)
    fail(t, "link", t.links[0].name, "has a parent joint like every other link: there is no root "
                                     "link (the joints form a cycle)");

  // children of each link (CSR), sorted by joint name, byte-wise
  for (int i = 0; i < nl; ++i) nchildren[i + 1] += nchildren[i];
  std::vector<int> child_joints(nj);
  {
    std::vector<int> fill(nchildren.begin(), nchildren.end() - 1);
    for (int k = 0; k < nj; ++k) child_joints[fill[jparent[k]]++] = k;
  }
  for (int i = 0; i < nl; ++i) {
    const auto b = child_joints.begin() + nchildren[i], e = child_joints.begin() + nchildren[i + 1];
    if (e - b > 1)
      std::sort(b, e, [&](int a, int c) { return t.joints[a].name < t.joints[c].name; });
  }

  // preorder walk. Each stack entry is a joint still to visit plus where its parent
  // link sits: the body it belongs to (-1: the base) and parent_X_body.
  struct Entry {
    int joint;
    int body;
    bool at_body_origin;   // X is the identity
    Transform<double> X;   // parent link frame <- body frame
  };
  Model m;
  m.name = t.name;
  m.source = t.source;
  m.root_link = t.links[root].name;
  int nv = opt.floating_base ? 1 : 0;  // moving bodies
  for (int k = 0; k < nj; ++k) nv += t.joints[k].type != RawJointType::Fixed;
  m.bodies.reserve(nv);
  m.joint_names.reserve(nv);
  m.link_names.reserve(nv);
  m.q_lower.reserve(nv);
  m.q_upper.reserve(nv);
  m.frames.reserve(static_cast<std::size_t>(nl));
  m.frame_names.reserve(static_cast<std::size_t>(nl));
  // the root link: the base frame, or body 0 with a floating base
  m.frames.push_back({opt.floating_base ? 0 : -1, Transform<double>::identity()});
  m.frame_names.push_back(t.links[root].name);

  std::vector<Entry> stack;
  std::vector<char> reached(nl, 0);
  reached[root] = 1;
  int visited = 1;
  auto push_children = [&](int link, int body, bool at_origin, const Transform<double>& X) {
    for (int c = nchildren[link + 1] - 1; c >= nchildren[link]; --c)
      stack.push_back({child_joints[c], body, at_origin, X});
  };
  if (opt.floating_base) {
    // body 0: the root link on a free joint
    if (t.links[root].name == "world")
      fail(t, "link", "world", "the root link is the world frame: the model is fixed to the world "
                               "through its child joints, so it has no floating base to free (remove "
                               "the world link to float the robot's own base)");
    Body<double> body;
    body.parent = -1;
    body.type = JointType::Free;
    body.axis = {1, 0, 0};  // unused by a free joint
    body.Xtree = Transform<double>::identity();
    body.I = link_inertia(t.links[root]);
    m.bodies.push_back(body);
    m.joint_names.push_back("root_joint");
    m.link_names.push_back(t.links[root].name);
    m.q_lower.push_back(-HUGE_VAL);
    m.q_upper.push_back(HUGE_VAL);
  }
  push_children(root, opt.floating_base ? 0 : -1, true, Transform<double>::identity());
  while (!stack.empty()) {
    const Entry e = stack.back();
    stack.pop_back();
    const RawJoint& j = t.joints[e.joint];
    const int link = jchild[e.joint];
    const RawLink& l = t.links[link];
    reached[link] = 1;
    ++visited;
    // link frame <- body frame, through this joint at q = 0
    const Transform<double> Xj = joint_transform(j);
    const Transform<double> X = e.at_body_origin ? Xj : Xj * e.X;
    if (j.type == RawJointType::Fixed) {
      // merged into the parent's body (dropped with the base)
      if (e.body >= 0 && l.has_inertial)
        m.bodies[e.body].I += link_inertia(l).transform_transpose(X);
      m.frames.push_back({e.body, X});  // the merged link keeps its frame
      m.frame_names.push_back(l.name);
      push_children(link, e.body, false, X);
    } else {
      const int b = static_cast<int>(m.bodies.size());
      Body<double> body;
      body.parent = e.body;
      body.type = j.type == RawJointType::Prismatic   ? JointType::Prismatic
                  : j.type == RawJointType::Spherical ? JointType::Spherical
                                                      : JointType::Revolute;
      body.axis = j.type == RawJointType::Spherical ? Vec3<double>{1, 0, 0} : unit(j.axis);  // unused by a ball
      body.Xtree = X;
      body.I = link_inertia(l);
      m.bodies.push_back(body);
      m.joint_names.push_back(j.name);
      m.link_names.push_back(l.name);
      m.q_lower.push_back(j.type == RawJointType::Continuous ? -HUGE_VAL : j.lower);
      m.q_upper.push_back(j.type == RawJointType::Continuous ? HUGE_VAL : j.upper);
      m.frames.push_back({b, Transform<double>::identity()});
      m.frame_names.push_back(l.name);
      push_children(link, b, true, Transform<double>::identity());
    }
  }

  // links the walk never reached hang in a cycle of their own
  if (visited < nl) {
    for (int i = 0; i < nl; ++i)
      if (!reached[i])
        fail(t, "link", t.links[i].name, "is not connected to the root link '" +
                                             t.links[root].name + "' (its joints form a cycle)");
  }
  for (std::size_t b = 0; b < m.bodies.size(); ++b) check_body(t, m, b);
  if (opt.floating_base && !(m.bodies[0].I.m > 0))
    fail(t, "link", m.root_link, "the floating base (the root link and the links fixed to it) has "
                                 "no mass: its forward dynamics would be singular");
  set_joint_offsets(m);
  return m;
}

}  // namespace scandyn
