// src/factor_graph/dynamics_graph.cpp: assembly of the dynamics factor graph's
// linear system (scandyn/factor_graph/dynamics_graph.hpp).
#include "scandyn/factor_graph/dynamics_graph.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "scandyn/algorithm/steps.hpp"

namespace scandyn::factor_graph {
namespace {

Vec3<double> unit3(int k) { return {k == 0 ? 1.0 : 0.0, k == 1 ? 1.0 : 0.0, k == 2 ? 1.0 : 0.0}; }

// e_k of motion space: k < 3 angular, else linear.
Motion<double> unit_motion(int k) {
  return k < 3 ? Motion<double>{unit3(k), Vec3<double>::zero()} : Motion<double>{Vec3<double>::zero(), unit3(k - 3)};
}

}  // namespace

ModelUnits model_units(const Model& model) {
  double log_m = 0, log_l = 0;
  int count = 0;
  for (const Body<double>& b : model.bodies) {
    if (!(b.I.m > 0)) continue;
    const double gyration2 = (b.I.I.xx + b.I.I.yy + b.I.I.zz) / (2 * b.I.m);
    if (!(gyration2 > 0)) continue;
    log_m += std::log2(b.I.m);
    log_l += 0.5 * std::log2(gyration2);
    ++count;
  }
  ModelUnits u;
  if (count > 0) {
    u.mass = std::exp2(std::round(log_m / count));
    u.length = std::exp2(std::round(log_l / count));
  }
  return u;
}

std::vector<LoopClosure> graph_loops(const scandyn::LoopSet& loops) {
  std::vector<LoopClosure> out;
  out.reserve(loops.loops.size());
  for (const scandyn::LoopClosure& l : loops.loops) {
    LoopClosure g;
    g.type = l.type == LoopType::Weld ? LoopClosure::Type::Weld : LoopClosure::Type::Point;
    g.body_a = l.body_a;
    g.point_a = l.point_a;
    g.body_b = l.body_b;
    g.point_b = l.point_b;
    out.push_back(g);
  }
  return out;
}

DynamicsGraph::DynamicsGraph(const Model& model, std::vector<LoopClosure> loops,
                             std::vector<char> known_qdd, std::vector<double> armature,
                             const ModelUnits* units, bool loop_compliance)
    : model_(model), loops_(std::move(loops)), known_qdd_(std::move(known_qdd)), armature_(std::move(armature)),
      has_compliance_(loop_compliance) {
  if (model.multi_dof())
    throw std::invalid_argument("factor graph: model '" + model.name + "' has the multi-DoF joint '" +
                                first_multi_dof_joint(model) + "'; the factor graph takes revolute and prismatic "
                                "joints only");
  const Index nv = model.nv();
  if (known_qdd_.empty()) known_qdd_.assign(static_cast<std::size_t>(nv), 0);
  if (static_cast<Index>(known_qdd_.size()) != nv)
    throw std::invalid_argument("factor graph: known_qdd has " + std::to_string(known_qdd_.size()) +
                                " entries, the model has " + std::to_string(nv) + " DoFs");
  if (!armature_.empty() && static_cast<Index>(armature_.size()) != nv)
    throw std::invalid_argument("factor graph: armature has " + std::to_string(armature_.size()) +
                                " entries, the model has " + std::to_string(nv) + " DoFs");
  Index off = 14 * nv;
  for (std::size_t k = 0; k < loops_.size(); ++k) {
    const LoopClosure& L = loops_[k];
    for (Index body : {L.body_a, L.body_b})
      if (body < -1 || body >= nv)
        throw std::invalid_argument("factor graph: loop " + std::to_string(k) + " names body " +
                                    std::to_string(body) + ", the model has bodies -1.." +
                                    std::to_string(nv - 1));
    if (L.body_a == L.body_b)
      throw std::invalid_argument("factor graph: loop " + std::to_string(k) + " joins body " +
                                  std::to_string(L.body_a) + " to itself");
    lambda_offset_.push_back(off);
    off += L.dim();
  }
  At_.rows = At_.cols = off;
  b_.assign(static_cast<std::size_t>(off), 0.0);
  // Units of the unknowns and of the equations (time unit 1 s): angular
  // acceleration 1, linear acceleration L, moment M L^2, force M L; a joint's qdd and
  // tau by its type; equation 14 i + 12 (S^T f - tau) and the prior are in tau's
  // unit (a given qdd's prior in qdd's); loop rows: linear accelerations (point) and
  // angular ones (weld); multipliers: forces and moments.
  units_ = units ? *units : model_units(model);
  const double L = units_.length, M = units_.mass;
  unknown_unit_.assign(static_cast<std::size_t>(off), 1.0);
  equation_unit_.assign(static_cast<std::size_t>(off), 1.0);
  for (Index i = 0; i < nv; ++i) {
    const bool prismatic = model.bodies[i].type == JointType::Prismatic;
    for (int k = 0; k < 3; ++k) {
      unknown_unit_[var_a(i) + 3 + k] = equation_unit_[14 * i + 3 + k] = L;
      unknown_unit_[var_f(i) + k] = equation_unit_[14 * i + 6 + k] = M * L * L;
      unknown_unit_[var_f(i) + 3 + k] = equation_unit_[14 * i + 9 + k] = M * L;
    }
    unknown_unit_[var_qdd(i)] = prismatic ? L : 1.0;
    unknown_unit_[var_tau(i)] = equation_unit_[14 * i + 12] = prismatic ? M * L : M * L * L;
    equation_unit_[14 * i + 13] = known_qdd_[static_cast<std::size_t>(i)] ? unknown_unit_[var_qdd(i)]
                                                                          : unknown_unit_[var_tau(i)];
  }
  for (std::size_t k = 0; k < loops_.size(); ++k) {
    const Index e0 = lambda_offset_[k];
    const int lin = loops_[k].type == LoopClosure::Type::Weld ? 3 : 0;
    for (int r = 0; r < lin; ++r) unknown_unit_[e0 + r] = M * L * L;  // moment; angular acceleration rows: 1
    for (int r = 0; r < 3; ++r) {
      unknown_unit_[e0 + lin + r] = M * L;
      equation_unit_[e0 + lin + r] = L;
    }
  }
  // Pattern pass at q = qd = 0 with unit inputs: the structure does not depend on
  // the values (every block is written whole, zeros included).
  std::vector<double> zero(static_cast<std::size_t>(nv), 0.0);
  write(true, zero.data(), zero.data(), zero.data(), zero.data());
  // Compress: At(col = equation, row = unknown).
  const std::size_t nt = trip_row_.size();
  At_.col_ptr.assign(static_cast<std::size_t>(off) + 1, 0);
  for (std::size_t k = 0; k < nt; ++k) ++At_.col_ptr[static_cast<std::size_t>(trip_row_[k]) + 1];
  for (Index j = 0; j < off; ++j) At_.col_ptr[j + 1] += At_.col_ptr[j];
  std::vector<Index> order(nt);
  for (std::size_t k = 0; k < nt; ++k) order[k] = static_cast<Index>(k);
  std::stable_sort(order.begin(), order.end(), [&](Index x, Index y) {
    return trip_row_[x] != trip_row_[y] ? trip_row_[x] < trip_row_[y] : trip_col_[x] < trip_col_[y];
  });
  // Merge duplicates (an unknown written twice in one equation) into one slot.
  slot_.assign(nt, 0);
  std::vector<Index> col_ptr(static_cast<std::size_t>(off) + 1, 0);
  for (std::size_t p = 0; p < nt; ++p) {
    const Index k = order[p];
    const bool dup = p > 0 && trip_row_[order[p - 1]] == trip_row_[k] &&
                     trip_col_[order[p - 1]] == trip_col_[k];
    if (!dup) {
      At_.row_idx.push_back(trip_col_[k]);
      ++col_ptr[static_cast<std::size_t>(trip_row_[k]) + 1];
    }
    slot_[static_cast<std::size_t>(k)] = static_cast<Index>(At_.row_idx.size()) - 1;
  }
  for (Index j = 0; j < off; ++j) col_ptr[j + 1] += col_ptr[j];
  At_.col_ptr = col_ptr;
  At_.val.assign(At_.row_idx.size(), 0.0);
  trip_row_.clear();
  trip_row_.shrink_to_fit();
  trip_col_.clear();
  trip_col_.shrink_to_fit();
}

void DynamicsGraph::assemble(const double* q, const double* qd, const double* qdd_in,
                             const double* tau_in) {
  write(false, q, qd, qdd_in, tau_in);
  std::fill(At_.val.begin(), At_.val.end(), 0.0);
  for (std::size_t k = 0; k < trip_val_.size(); ++k) At_.val[static_cast<std::size_t>(slot_[k])] += trip_val_[k];
  // to the model's units: A = W A_SI S, b = W b_SI (powers of two: exact)
  for (Index e = 0; e < At_.cols; ++e) {
    const double w = 1.0 / equation_unit_[static_cast<std::size_t>(e)];
    b_[static_cast<std::size_t>(e)] *= w;
    for (Index t = At_.col_ptr[e]; t < At_.col_ptr[e + 1]; ++t)
      At_.val[static_cast<std::size_t>(t)] *= w * unknown_unit_[static_cast<std::size_t>(At_.row_idx[t])];
  }
}

// One pass over the factors in a fixed order. pattern: record (equation, unknown)
// of every entry; otherwise record its value (same order) and the right-hand side.
void DynamicsGraph::write(bool pattern, const double* q, const double* qd, const double* qdd_in,
                          const double* tau_in) {
  const Index nv = model_.nv();
  std::size_t t = 0;
  if (!pattern) trip_val_.resize(slot_.size());
  auto put = [&](Index eq, Index var, double value) {
    if (pattern) {
      trip_row_.push_back(eq);
      trip_col_.push_back(var);
    } else {
      trip_val_[t++] = value;
    }
  };
  std::fill(b_.begin(), b_.end(), 0.0);
  // Kinematics ahead: Xup, world placement X0 (world -> body) and velocity v.
  std::vector<Transform<double>> Xup(static_cast<std::size_t>(nv)), X0(static_cast<std::size_t>(nv));
  std::vector<Motion<double>> v(static_cast<std::size_t>(nv));
  for (Index i = 0; i < nv; ++i) {
    const Body<double>& b = model_.bodies[i];
    const Index p = b.parent;
    Xup[i] = joint_transform(b, q[i]);
    X0[i] = p < 0 ? Xup[i] : Xup[i] * X0[p];
    v[i] = add_joint_motion(b, p < 0 ? Motion<double>::zero() : Xup[i].apply(v[p]), qd[i]);
  }
  const Motion<double> a0 = base_acceleration(model_.gravity);
  for (Index i = 0; i < nv; ++i) {
    const Body<double>& b = model_.bodies[i];
    const Index p = b.parent;
    const Index ea = 14 * i, ef = 14 * i + 6;
    // acceleration: a_i - Xup a_p - S qdd_i = v x S qd (+ Xup a0 at the root)
    const Motion<double> c = cross_joint_motion(b, v[i], qd[i]);
    const Motion<double> Xa0 = Xup[i].apply(a0);
    for (int r = 0; r < 6; ++r) {
      b_[static_cast<std::size_t>(ea + r)] = c[r] + (p < 0 ? Xa0[r] : 0.0);
      put(ea + r, var_a(i) + r, 1.0);
    }
    if (p >= 0)
      for (int k = 0; k < 6; ++k) {
        const Motion<double> col = Xup[i].apply(unit_motion(k));
        for (int r = 0; r < 6; ++r) put(ea + r, var_a(p) + k, -col[r]);
      }
    const Motion<double> S = joint_motion(b, 1.0);
    for (int r = 0; r < 6; ++r) put(ea + r, var_qdd(i), -S[r]);
    // force balance: f_i - Xup_c^T f_c (children) - I a_i = v x* I v
    const Force<double> bias = cross(v[i], b.I * v[i]);
    for (int r = 0; r < 6; ++r) {
      b_[static_cast<std::size_t>(ef + r)] = bias[r];
      put(ef + r, var_f(i) + r, 1.0);
    }
    for (int k = 0; k < 6; ++k) {
      const Force<double> col = b.I * unit_motion(k);
      for (int r = 0; r < 6; ++r) put(ef + r, var_a(i) + k, -col[r]);
    }
    if (p >= 0)  // this body's joint force, seen by the parent: -Xup^T f_i
      for (int k = 0; k < 6; ++k) {
        // row k of Xup^T is column k of Xup's motion matrix
        const Motion<double> colk = Xup[i].apply(unit_motion(k));
        for (int r = 0; r < 6; ++r) put(14 * p + 6 + k, var_f(i) + r, -colk[r]);
      }
    // joint force: S^T f_i + armature_i qdd_i - tau_i = 0
    for (int r = 0; r < 6; ++r) put(14 * i + 12, var_f(i) + r, S[r]);
    if (!armature_.empty()) put(14 * i + 12, var_qdd(i), armature_[static_cast<std::size_t>(i)]);
    put(14 * i + 12, var_tau(i), -1.0);
    // prior: qdd_i or tau_i given
    if (known_qdd_[static_cast<std::size_t>(i)]) {
      put(14 * i + 13, var_qdd(i), 1.0);
      b_[static_cast<std::size_t>(14 * i + 13)] = qdd_in ? qdd_in[i] : 0.0;
    } else {
      put(14 * i + 13, var_tau(i), 1.0);
      b_[static_cast<std::size_t>(14 * i + 13)] = tau_in ? tau_in[i] : 0.0;
    }
  }
  // Loop closures. For side s (sign +1 for a, -1 for b) on body j at point p, with E
  // the world -> body rotation and lambda = [moment (weld only); force] in world axes:
  //   force on body j:  s G lambda,  G lambda = [E mu + p x E l; E l]
  //   constraint rows:  s G^T a_j = s [E^T a.w (weld); E^T (a.v + a.w x p)]
  // and the velocity products E^T w x (v + w x p) go to the right-hand side.
  for (std::size_t k = 0; k < loops_.size(); ++k) {
    const LoopClosure& L = loops_[k];
    const Index e0 = lambda_offset_[k];
    const bool weld = L.type == LoopClosure::Type::Weld;
    const int lin = weld ? 3 : 0;  // first row / multiplier of the point part
    for (int side = 0; side < 2; ++side) {
      const double s = side == 0 ? 1.0 : -1.0;
      const Index j = side == 0 ? L.body_a : L.body_b;
      const Vec3<double>& pt = side == 0 ? L.point_a : L.point_b;
      if (j < 0) {  // the base: a = a0, no unknowns; its rows' terms go to b
        const Vec3<double> acc = a0.v + cross(a0.w, pt);
        for (int r = 0; r < 3; ++r) b_[static_cast<std::size_t>(e0 + lin + r)] -= s * acc[r];
        continue;
      }
      const Mat3<double>& E = X0[j].E;
      for (int r = 0; r < 3; ++r) {
        const Vec3<double> u = E * unit3(r);  // world axis r in body coordinates
        // point rows: u . (a.v + a.w x p) = u . a.v + (p x u) . a.w
        const Vec3<double> pu = cross(pt, u);
        for (int c = 0; c < 3; ++c) put(e0 + lin + r, var_a(j) + c, s * pu[c]);
        for (int c = 0; c < 3; ++c) put(e0 + lin + r, var_a(j) + 3 + c, s * u[c]);
        // forces: s [p x u; u] lambda_r on the body's balance (sign: + applied force)
        for (int c = 0; c < 3; ++c) put(14 * j + 6 + c, e0 + lin + r, s * pu[c]);
        for (int c = 0; c < 3; ++c) put(14 * j + 9 + c, e0 + lin + r, s * u[c]);
        if (weld) {
          for (int c = 0; c < 3; ++c) put(e0 + r, var_a(j) + c, s * u[c]);
          for (int c = 0; c < 3; ++c) put(14 * j + 6 + c, e0 + r, s * u[c]);
        }
      }
      const Vec3<double> vp = v[j].v + cross(v[j].w, pt);
      const Vec3<double> wv = mul_transpose(E, cross(v[j].w, vp));  // world axes
      for (int r = 0; r < 3; ++r) b_[static_cast<std::size_t>(e0 + lin + r)] -= s * wv[r];
    }
    // the compliance w lambda (w in the model's units: its SI value here, scaled by assemble)
    if (has_compliance_)
      for (Index e = e0; e < e0 + L.dim(); ++e)
        put(e, e, compliance_ * equation_unit_[static_cast<std::size_t>(e)] / unknown_unit_[static_cast<std::size_t>(e)]);
  }
}

// Appends body i's unknowns in the order the articulated-body elimination removes
// them: tau_i, f_i (leaving f_i = IA_i a_i + pA_i), a_i, qdd_i.
void DynamicsGraph::push_body_block(Index i, std::vector<Index>& order) const {
  order.push_back(var_tau(i));
  for (int r = 0; r < 6; ++r) order.push_back(var_f(i) + r);
  for (int r = 0; r < 6; ++r) order.push_back(var_a(i) + r);
  order.push_back(var_qdd(i));
}

std::vector<Index> DynamicsGraph::tree_order() const {
  const Index nv = model_.nv();
  std::vector<Index> order;
  order.reserve(static_cast<std::size_t>(At_.rows));
  const bool inverse = std::all_of(known_qdd_.begin(), known_qdd_.end(), [](char c) { return c != 0; });
  if (inverse && nv > 0) {
    for (Index i = 0; i < nv; ++i) order.push_back(var_qdd(i));
    for (Index i = nv - 1; i >= 0; --i) order.push_back(var_tau(i));
    for (Index i = 0; i < nv; ++i)
      for (int r = 0; r < 6; ++r) order.push_back(var_f(i) + r);
    for (Index i = nv - 1; i >= 0; --i)
      for (int r = 0; r < 6; ++r) order.push_back(var_a(i) + r);
  } else {
    for (Index i = nv - 1; i >= 0; --i) push_body_block(i, order);
  }
  for (Index k = 14 * nv; k < At_.rows; ++k) order.push_back(k);
  return order;
}

std::vector<Index> DynamicsGraph::cyclic_reduction_order() const {
  const Index nv = model_.nv();
  for (Index i = 0; i < nv; ++i)
    if (model_.parent(i) != i - 1)
      throw std::invalid_argument("factor graph: cyclic_reduction_order needs one unbranched chain (body " +
                                  std::to_string(i) + " has parent " + std::to_string(model_.parent(i)) + ")");
  // Level of body i: the number of trailing zeros of i + 1 (odd positions: level 0).
  std::vector<Index> bodies(static_cast<std::size_t>(nv));
  for (Index i = 0; i < nv; ++i) bodies[i] = i;
  auto level = [](Index i) { int l = 0; for (unsigned x = static_cast<unsigned>(i) + 1; (x & 1u) == 0; x >>= 1) ++l; return l; };
  std::stable_sort(bodies.begin(), bodies.end(), [&](Index x, Index y) { return level(x) < level(y); });
  std::vector<Index> order;
  order.reserve(static_cast<std::size_t>(At_.rows));
  for (Index i : bodies) push_body_block(i, order);
  for (Index k = 14 * nv; k < At_.rows; ++k) order.push_back(k);
  return order;
}

void DynamicsGraph::extract(const double* x, double* qdd, double* tau, double* lambda) const {
  const Index nv = model_.nv();
  for (Index i = 0; i < nv; ++i) {
    if (qdd) qdd[i] = x[var_qdd(i)] * unknown_unit_[static_cast<std::size_t>(var_qdd(i))];
    if (tau) tau[i] = x[var_tau(i)] * unknown_unit_[static_cast<std::size_t>(var_tau(i))];
  }
  if (lambda)
    for (Index k = 14 * nv; k < At_.rows; ++k) lambda[k - 14 * nv] = x[k] * unknown_unit_[static_cast<std::size_t>(k)];
}

}  // namespace scandyn::factor_graph
