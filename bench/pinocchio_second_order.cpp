// bench/pinocchio_second_order.cpp: scandyn's second-order derivatives of inverse
// dynamics (rnea_second_derivatives, scandyn/algorithm/second_derivatives.hpp)
// against Pinocchio's ComputeRNEASecondOrderDerivatives
// (pinocchio/algorithm/rnea-second-order-derivatives.hpp, the analytical recursion of
// Singh, Russell and Wensing; Pinocchio 3 and 4 name it with a capital C), in C++,
// on iiwa, hyq, atlas and random URDF trees of revolute, continuous, prismatic and
// fixed joints. Fixed base, double, one thread.
//
// Built only when a Pinocchio C++ prefix is found (cmake/pinocchio_prefix.cmake: the
// `pin` wheel's cmeel.prefix in .venv, or SCANDYN_PINOCCHIO_PREFIX); header-only use
// of Pinocchio (no Pinocchio library is linked).
//
// Models. scandyn loads each URDF with its own loader (parse_urdf + build_model).
// Pinocchio's model is built here from the same parsed URDF description (the RawTree
// of scandyn's parse_urdf: the file's numbers, before scandyn's builder merges fixed
// links, normalises axes or orders bodies) through Pinocchio's own model API, the way
// Pinocchio's URDF parser does it: a joint's placement is the URDF origin composed
// with the placements of the fixed joints above it; revolute -> JointModelRevoluteUnaligned,
// continuous -> JointModelRevoluteUnboundedUnaligned (q = (cos, sin)), prismatic ->
// JointModelPrismaticUnaligned (axis normalised); a link's inertia is
// Inertia(mass, com, R I R^T) appended to the joint it moves with (fixed links at
// their placement). Pinocchio's URDF parser itself (libpinocchio_parsers) is not
// used: it links the wheel's urdfdom 6, which would put a second urdfdom, defining
// the same symbols as the system's urdfdom 3 that scandyn links, into the process. scripts/check_pinocchio.py checks scandyn's models against
// Pinocchio's parser (first order, ctest pinocchio_crosscheck); here tau = RNEA is
// compared too (column tau_err on stderr), so a model mismatch shows.
//
// Joint order. The Pinocchio model is built depth-first with siblings in reverse
// name order (scandyn: name order), so on branched trees the DoF order differs; the
// map is by joint name: perm[pinocchio DoF] = scandyn DoF, checked to be a bijection.
// q: Pinocchio's configuration is scandyn's angle for revolute and prismatic joints
// and (cos, sin) of it for continuous ones; v, a are permuted. The derivatives are
// with respect to v (the tangent), the same for every joint type here.
//
// Tensor layouts (read from rnea-second-order-derivatives.hxx and checked here).
// Pinocchio's tensors are Data::Tensor3x, indexed T(a, b, c) (storage order does not
// matter: entries are read through operator()). scandyn's are flat nv^3 arrays,
// entry (i, j, k) at (i * nv + j) * nv + k. With P = perm:
//   d2tau_dqdq(a, b, c) = d^2 tau_a / dq_b dq_c   = scandyn d2tau_dq2  (P a, P b, P c)
//   d2tau_dvdv(a, b, c) = d^2 tau_a / dv_b dv_c   = scandyn d2tau_dqd2 (P a, P b, P c)
//   d2tau_dqdv(a, b, c) = d^2 tau_a / dq_b dv_c   = scandyn d2tau_dqdqd(P a, P b, P c)
//   d2tau_dadq(a, b, c) = d M_ab / dq_c           = scandyn dM_dq      (P a, P b, P c)
// i.e. the same (torque, first variable, second variable) order and the same signs.
// (The header's prose on d2tau_dqdv contradicts itself: "config along 2nd, velocity
// along the third" for Tensor3 and "v vary along the columns and q along the pages"
// in the remarks; the numbers agree with the first reading (the mixed partial
// d/dv_c (dtau_a/dq_b)), and this program also prints the error of the transposed
// reading (b <-> c) on stderr, which is 0.09-1.) Pinocchio accumulates into its
// tensors, so they are zeroed before each call (its 5-argument overload does that,
// and that overload is what is timed). Pinocchio has no external forces in this
// function; none are passed to scandyn either. Gravity: both (0, 0, -9.81).
//
// Error: per tensor, max |pinocchio - scandyn| / max(1, max |pinocchio|), over the
// four tensors and every state; max_rel_err is the largest. Exit 1 when it (or the
// RNEA torque error) exceeds --tol (default 1e-9).
//
// Timing: one call of each (scandyn with dM_dq, the four tensors as Pinocchio), one
// thread, double, the mean over a run of at least --min-seconds (default 0.5);
// three runs alternating scandyn and Pinocchio, the fastest run's mean of each kept.
//
// Usage: pinocchio_second_order [--min-seconds S] [--states N] [--random N] [--tol T]
//   CSV on stdout: model,nv,scandyn_us,pinocchio_us,ratio,max_rel_err
//   (ratio = scandyn_us / pinocchio_us); per-tensor errors on stderr.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <map>
#include <random>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include <pinocchio/math.hpp>
#include <pinocchio/multibody.hpp>
#include <pinocchio/algorithm/rnea.hpp>
#include <pinocchio/algorithm/rnea-second-order-derivatives.hpp>

#include "plain_bench_util.hpp"
#include "scandyn/algorithm/reference.hpp"
#include "scandyn/algorithm/second_derivatives.hpp"
#include "scandyn/model/load.hpp"

namespace {

using scandyn::Index;
using scandyn::RawJoint;
using scandyn::RawJointType;
using scandyn::RawLink;
using scandyn::RawTree;

Eigen::Matrix3d rotation(bool has_quat, const scandyn::RawQuat& quat, const scandyn::Vec3<double>& rpy) {
  if (has_quat) return Eigen::Quaterniond(quat.w, quat.x, quat.y, quat.z).normalized().toRotationMatrix();
  return pinocchio::rpy::rpyToMatrix(rpy.x, rpy.y, rpy.z);
}

Eigen::Vector3d vec(const scandyn::Vec3<double>& v) { return {v.x, v.y, v.z}; }

pinocchio::SE3 joint_origin(const RawJoint& j) {
  return pinocchio::SE3(rotation(j.has_quat, j.quat, j.rpy), vec(j.xyz));
}

// The link's spatial inertia in the link frame, as Pinocchio's URDF parser makes it.
pinocchio::Inertia link_inertia(const RawLink& l) {
  if (!l.has_inertial) return pinocchio::Inertia::Zero();
  const Eigen::Matrix3d R = rotation(l.com_has_quat, l.com_quat, l.com_rpy);
  Eigen::Matrix3d I;
  I << l.inertia.xx, l.inertia.xy, l.inertia.xz, l.inertia.xy, l.inertia.yy, l.inertia.yz, l.inertia.xz,
      l.inertia.yz, l.inertia.zz;
  return pinocchio::Inertia(l.mass, vec(l.com_xyz), R * I * R.transpose());
}

// Pinocchio's model of the tree (fixed base): depth-first from the root link,
// siblings in reverse name order.
pinocchio::Model pinocchio_model(const RawTree& tree) {
  std::map<std::string, const RawLink*> links;
  for (const RawLink& l : tree.links) links[l.name] = &l;
  std::map<std::string, std::vector<const RawJoint*>> children;
  std::map<std::string, bool> is_child;
  for (const RawJoint& j : tree.joints) {
    children[j.parent].push_back(&j);
    is_child[j.child] = true;
  }
  std::string root;
  for (const RawLink& l : tree.links)
    if (!is_child[l.name]) {
      if (!root.empty()) throw std::runtime_error(tree.source + ": more than one root link");
      root = l.name;
    }
  pinocchio::Model model;
  model.name = tree.name;
  std::function<void(const std::string&, pinocchio::JointIndex, const pinocchio::SE3&)> visit =
      [&](const std::string& link, pinocchio::JointIndex parent, const pinocchio::SE3& placement) {
        std::vector<const RawJoint*> kids = children[link];
        std::sort(kids.begin(), kids.end(), [](const RawJoint* a, const RawJoint* b) { return a->name > b->name; });
        for (const RawJoint* j : kids) {
          const pinocchio::SE3 X = placement * joint_origin(*j);
          const RawLink& child = *links.at(j->child);
          if (j->type == RawJointType::Fixed) {
            if (child.has_inertial) model.appendBodyToJoint(parent, link_inertia(child), X);
            visit(child.name, parent, X);
            continue;
          }
          const Eigen::Vector3d axis = vec(j->axis).normalized();
          pinocchio::JointIndex id;
          if (j->type == RawJointType::Revolute)
            id = model.addJoint(parent, pinocchio::JointModelRevoluteUnaligned(axis), X, j->name);
          else if (j->type == RawJointType::Continuous)
            id = model.addJoint(parent, pinocchio::JointModelRevoluteUnboundedUnaligned(axis), X, j->name);
          else if (j->type == RawJointType::Prismatic)
            id = model.addJoint(parent, pinocchio::JointModelPrismaticUnaligned(axis), X, j->name);
          else
            throw std::runtime_error(tree.source + ": joint " + j->name + " of type " + j->type_name +
                                     " (revolute, continuous, prismatic and fixed only)");
          model.appendBodyToJoint(id, link_inertia(child), pinocchio::SE3::Identity());
          visit(child.name, id, pinocchio::SE3::Identity());
        }
      };
  visit(root, 0, pinocchio::SE3::Identity());
  return model;
}

// A random tree of n links below a massless base (scripts/check_pinocchio.py's
// random_urdf): random parents, revolute / continuous / prismatic / fixed joints
// (weights 5 / 2 / 2 / 2), random origins, axes and rotated inertial frames, half the
// fixed links massless; joint names j<random>_link_<i>, so sibling order is not
// creation order.
std::string random_urdf(int n, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> u01(0, 1);
  auto uni = [&](double a, double b) { return a + (b - a) * u01(rng); };
  auto num = [](double x) {
    char buf[40];
    std::snprintf(buf, sizeof buf, "%.17g", x);
    return std::string(buf);
  };
  auto vec3 = [&](double s) {
    const double a = uni(-s, s), b = uni(-s, s), c = uni(-s, s);
    return num(a) + " " + num(b) + " " + num(c);
  };
  auto inertial_link = [&](const std::string& name) {
    const double m = uni(0.2, 3.0), a = uni(0.01, 0.3), b = uni(0.01, 0.3);
    const double c = uni(std::abs(a - b) + 1e-3, a + b);
    const Eigen::Matrix3d R = pinocchio::rpy::rpyToMatrix(uni(-3, 3), uni(-3, 3), uni(-3, 3));
    const Eigen::Matrix3d Ic = R * Eigen::Vector3d(a, b, c).asDiagonal() * R.transpose();
    std::ostringstream s;
    s << "<link name=\"" << name << "\"><inertial><origin xyz=\"" << vec3(0.2) << "\" rpy=\"" << vec3(3)
      << "\"/><mass value=\"" << num(m) << "\"/><inertia ixx=\"" << num(Ic(0, 0)) << "\" ixy=\"" << num(Ic(0, 1))
      << "\" ixz=\"" << num(Ic(0, 2)) << "\" iyy=\"" << num(Ic(1, 1)) << "\" iyz=\"" << num(Ic(1, 2))
      << "\" izz=\"" << num(Ic(2, 2)) << "\"/></inertial></link>";
    return s.str();
  };
  std::vector<std::string> names{"base"};
  std::ostringstream links, joints;
  links << "<link name=\"base\"/>\n";
  const char* kinds[] = {"revolute", "continuous", "prismatic", "fixed"};
  std::discrete_distribution<int> kind_of({5, 2, 2, 2});
  for (int i = 0; i < n; ++i) {
    const std::string name = "link_" + std::to_string(i);
    const std::string parent = names[std::uniform_int_distribution<std::size_t>(0, names.size() - 1)(rng)];
    const std::string kind = kinds[kind_of(rng)];
    const std::string body = inertial_link(name);
    if (kind == "fixed" && u01(rng) < 0.5)
      links << "<link name=\"" << name << "\"/>\n";
    else
      links << body << "\n";
    Eigen::Vector3d axis(uni(-1, 1), uni(-1, 1), uni(-1, 1));
    axis.normalize();
    const std::string jname =
        "j" + std::to_string(1000 + std::uniform_int_distribution<int>(0, 999)(rng)).substr(1) + "_" + name;
    const std::string limit = (kind == "revolute" || kind == "prismatic")
                                  ? "<limit lower=\"-3\" upper=\"3\" effort=\"100\" velocity=\"10\"/>"
                                  : "";
    joints << "<joint name=\"" << jname << "\" type=\"" << kind << "\"><parent link=\"" << parent
           << "\"/><child link=\"" << name << "\"/><origin xyz=\"" << vec3(0.4) << "\" rpy=\"" << vec3(3)
           << "\"/><axis xyz=\"" << num(axis.x()) << " " << num(axis.y()) << " " << num(axis.z()) << "\"/>"
           << limit << "</joint>\n";
    names.push_back(name);
  }
  return "<?xml version=\"1.0\"?>\n<robot name=\"random\">\n" + links.str() + joints.str() + "</robot>\n";
}

std::string read_file(const std::string& path) {
  FILE* f = std::fopen(path.c_str(), "rb");
  if (!f) throw std::runtime_error("cannot open " + path);
  std::string text;
  char buf[65536];
  std::size_t n;
  while ((n = std::fread(buf, 1, sizeof buf, f)) > 0) text.append(buf, n);
  std::fclose(f);
  return text;
}

// Mean seconds per call over a run of at least min_time seconds.
template <class F>
double mean_seconds(double min_time, F&& call) {
  using Clock = std::chrono::steady_clock;
  std::size_t calls = 0;
  const auto t0 = Clock::now();
  double el = 0;
  do {
    call();
    ++calls;
    el = std::chrono::duration<double>(Clock::now() - t0).count();
  } while (el < min_time);
  return el / double(calls);
}

struct Options {
  double min_seconds = 0.5;
  int states = 5;
  int random = 8;
  double tol = 1e-9;
};

struct Errors {
  double dqdq = 0, dvdv = 0, dqdv = 0, dadq = 0, dqdv_transposed = 0, tau = 0;
  double max() const { return std::max({dqdq, dvdv, dqdv, dadq, tau}); }
};

// Compares and times one model; prints its CSV row, returns its largest error.
double run_model(const std::string& label, const RawTree& tree, const Options& opt, std::mt19937_64& rng) {
  scandyn::BuildOptions bo;
  bo.require_physical_inertia = false;  // GRiD's atlas breaks the triangle inequality on 4 links
  const scandyn::Model sm = scandyn::build_model(tree, bo);
  const pinocchio::Model pm = pinocchio_model(tree);
  pinocchio::Data pd(pm);
  const Index n = sm.nv();
  if (pm.nv != n || sm.multi_dof()) throw std::runtime_error(label + ": nv differs or multi-DoF joints");

  // perm[pinocchio DoF] = scandyn DoF, by joint name
  std::vector<Index> perm(n, -1);
  std::vector<bool> taken(n, false);
  for (pinocchio::JointIndex j = 1; j < static_cast<pinocchio::JointIndex>(pm.njoints); ++j) {
    const auto it = std::find(sm.joint_names.begin(), sm.joint_names.end(), pm.names[j]);
    if (it == sm.joint_names.end()) throw std::runtime_error(label + ": no scandyn joint " + pm.names[j]);
    const Index b = Index(it - sm.joint_names.begin());
    if (pm.nvs[j] != 1 || taken[b]) throw std::runtime_error(label + ": joint map is not a bijection");
    perm[pm.idx_vs[j]] = b;
    taken[b] = true;
  }
  bool identity = true;
  for (Index a = 0; a < n; ++a) identity = identity && perm[a] == a;

  const std::size_t n3 = std::size_t(n) * n * n;
  std::vector<double> q(n), qd(n), qdd(n), tau(n), H1(n3), H2(n3), H3(n3), dM(n3);
  Eigen::VectorXd pq(pm.nq), pv(n), pa(n);
  scandyn::SecondDerivativeData<double> sd(sm);
  scandyn::Data rd(sm);
  std::uniform_real_distribution<double> u(-2, 2);
  auto at = [n](const std::vector<double>& T, Index i, Index j, Index k) { return T[(std::size_t(i) * n + j) * n + k]; };
  auto set_state = [&] {
    for (Index i = 0; i < n; ++i) q[i] = u(rng), qd[i] = u(rng), qdd[i] = u(rng);
    for (pinocchio::JointIndex j = 1; j < static_cast<pinocchio::JointIndex>(pm.njoints); ++j) {
      const Index b = perm[pm.idx_vs[j]];
      if (pm.nqs[j] == 2) {
        pq[pm.idx_qs[j]] = std::cos(q[b]);
        pq[pm.idx_qs[j] + 1] = std::sin(q[b]);
      } else {
        pq[pm.idx_qs[j]] = q[b];
      }
      pv[pm.idx_vs[j]] = qd[b];
      pa[pm.idx_vs[j]] = qdd[b];
    }
  };

  Errors e;
  for (int s = 0; s < opt.states; ++s) {
    set_state();
    scandyn::rnea_second_derivatives(sm, sd, q.data(), qd.data(), qdd.data(),
                                     static_cast<const scandyn::Force<double>*>(nullptr), H1.data(), H2.data(),
                                     H3.data(), dM.data());
    pinocchio::ComputeRNEASecondOrderDerivatives(pm, pd, pq, pv, pa);
    scandyn::rnea(sm, rd, q.data(), qd.data(), qdd.data(), tau.data());
    const Eigen::VectorXd ptau = pinocchio::rnea(pm, pd, pq, pv, pa);
    double scale[5] = {1, 1, 1, 1, 1};
    double diff[5] = {0, 0, 0, 0, 0};
    for (Index a = 0; a < n; ++a)
      for (Index b = 0; b < n; ++b)
        for (Index c = 0; c < n; ++c) {
          const Index i = perm[a], j = perm[b], k = perm[c];
          const double ref[4] = {pd.d2tau_dqdq(a, b, c), pd.d2tau_dvdv(a, b, c), pd.d2tau_dqdv(a, b, c),
                                 pd.d2tau_dadq(a, b, c)};
          const double got[5] = {at(H1, i, j, k), at(H2, i, j, k), at(H3, i, j, k), at(dM, i, j, k),
                                 at(H3, i, k, j)};
          for (int t = 0; t < 4; ++t) {
            scale[t] = std::max(scale[t], std::abs(ref[t]));
            diff[t] = std::max(diff[t], std::abs(ref[t] - got[t]));
          }
          diff[4] = std::max(diff[4], std::abs(ref[2] - got[4]));
        }
    scale[4] = scale[2];
    double tscale = 1, tdiff = 0;
    for (Index a = 0; a < n; ++a) {
      tscale = std::max(tscale, std::abs(ptau[a]));
      tdiff = std::max(tdiff, std::abs(ptau[a] - tau[perm[a]]));
    }
    e.dqdq = std::max(e.dqdq, diff[0] / scale[0]);
    e.dvdv = std::max(e.dvdv, diff[1] / scale[1]);
    e.dqdv = std::max(e.dqdv, diff[2] / scale[2]);
    e.dadq = std::max(e.dadq, diff[3] / scale[3]);
    e.dqdv_transposed = std::max(e.dqdv_transposed, diff[4] / scale[4]);
    e.tau = std::max(e.tau, tdiff / tscale);
  }
  std::fprintf(stderr,
               "%s: nv %d, joint map %s; rel err d2tau_dq2 %.2e d2tau_dv2 %.2e d2tau_dqdv %.2e dM_dq %.2e "
               "tau %.2e (d2tau_dqdv read transposed: %.2e)\n",
               label.c_str(), int(n), identity ? "identity" : "permuted", e.dqdq, e.dvdv, e.dqdv, e.dadq, e.tau,
               e.dqdv_transposed);

  // timing at one more random state
  set_state();
  double ts = 1e300, tp = 1e300;
  for (int rep = 0; rep < 3; ++rep) {
    ts = std::min(ts, mean_seconds(opt.min_seconds, [&] {
                    scandyn::rnea_second_derivatives(sm, sd, q.data(), qd.data(), qdd.data(),
                                                     static_cast<const scandyn::Force<double>*>(nullptr), H1.data(),
                                                     H2.data(), H3.data(), dM.data());
                  }));
    tp = std::min(tp, mean_seconds(opt.min_seconds, [&] { pinocchio::ComputeRNEASecondOrderDerivatives(pm, pd, pq, pv, pa); }));
  }
  std::printf("%s,%d,%.2f,%.2f,%.2f,%.1e\n", label.c_str(), int(n), ts * 1e6, tp * 1e6, ts / tp, e.max());
  std::fflush(stdout);
  return e.max();
}

}  // namespace

int main(int argc, char** argv) {
  Options opt;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    const bool has = i + 1 < argc;
    if (a == "--min-seconds" && has) opt.min_seconds = std::atof(argv[++i]);
    else if (a == "--states" && has) opt.states = std::atoi(argv[++i]);
    else if (a == "--random" && has) opt.random = std::atoi(argv[++i]);
    else if (a == "--tol" && has) opt.tol = std::atof(argv[++i]);
    else {
      std::fprintf(stderr, "usage: %s [--min-seconds S] [--states N] [--random N] [--tol T]\n", argv[0]);
      return 2;
    }
  }
  double worst = 0;
  try {
    std::mt19937_64 rng(7);
    std::printf("model,nv,scandyn_us,pinocchio_us,ratio,max_rel_err\n");
    for (const std::string name : {"iiwa", "hyq", "atlas"}) {
      const std::string path = scandyn::bench::models_dir() + "/" + name + ".urdf";
      worst = std::max(worst, run_model(name, scandyn::parse_urdf(read_file(path), path), opt, rng));
    }
    const int sizes[] = {4, 8, 12, 16, 24, 32, 40, 48};
    for (int r = 0; r < opt.random; ++r) {
      std::mt19937_64 tree_rng(100 + r);
      const int links = sizes[r % 8];
      const std::string label = "random:" + std::to_string(links) + ":" + std::to_string(100 + r);
      worst = std::max(worst, run_model(label, scandyn::parse_urdf(random_urdf(links, tree_rng), label), opt, rng));
    }
  } catch (const std::exception& ex) {
    std::fprintf(stderr, "pinocchio_second_order: %s\n", ex.what());
    return 1;
  }
  std::fprintf(stderr, "pinocchio_second_order: max relative error %.2e (tolerance %.1e): %s\n", worst, opt.tol,
               worst <= opt.tol ? "ok" : "FAILED");
  return worst <= opt.tol ? 0 : 1;
}
