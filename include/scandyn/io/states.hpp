// scandyn/io/states.hpp: the states files of `scandyn eval` (DESIGN.md, docs/cli.md):
// input columns q_<i>, qd_<i>, qdd_<i>, tau_<i> matched by name, and the output
// columns of each algorithm (tau_id_<i>, qdd_fd_<i>, M_<i>_<j>, h_<i>).
#pragma once

#include <array>
#include <cstddef>
#include <string>
#include <vector>

#include "scandyn/model/model.hpp"

namespace scandyn::io {

// DId, DFd: the first-order derivatives of inverse and forward dynamics; D2Id: the
// second-order derivatives of inverse dynamics.
enum class Algo { Id, Fd, Mass, Bias, DId, DFd, D2Id };
const char* algo_name(Algo algo);  // "id", "fd", "mass", "bias", "did", "dfd", "d2id"
bool parse_algo(const std::string& name, Algo& algo);  // false if unknown

// A set of algorithms: bit (1 << algo) for each member.
using AlgoSet = unsigned;
constexpr AlgoSet algo_bit(Algo algo) { return 1u << static_cast<unsigned>(algo); }
// The members' names joined by sep, in the order id, fd, mass, bias, did, dfd, d2id.
std::string algo_list(AlgoSet algos, const char* sep);

// Values per instance that algo writes: nv, nv * nv for Mass, 3 * nv * nv for DId
// and DFd, 3 * nv^3 for D2Id.
std::size_t output_width(Algo algo, Index nv);
// Output column names: tau_id_<i>, qdd_fd_<i>, M_<i>_<j> (row-major) or h_<i>;
// did: dtau_dq_<i>_<j>, dtau_dqd_<i>_<j>, dtau_dqdd_<i>_<j> (= M); dfd:
// dqdd_dq_<i>_<j>, dqdd_dqd_<i>_<j>, dqdd_dtau_<i>_<j> (= M^-1); each block
// row-major, (i, j) = d output_i / d input_j; d2id: d2tau_dq2_<i>_<j>_<k>,
// d2tau_dqd2_<i>_<j>_<k>, d2tau_dqdqd_<i>_<j>_<k> (d^2 tau_i / dx_j dy_k, k fastest).
std::vector<std::string> output_columns(Algo algo, Index nv);

// The four input families of a states file, by column-name prefix.
enum class Family { Q = 0, Qd = 1, Qdd = 2, Tau = 3 };
constexpr int kFamilies = 4;

const char* family_prefix(Family f);  // "q_", "qd_", "qdd_", "tau_"
// The families algo reads: id q, qd, qdd; fd q, qd, tau; mass q; bias q, qd; did as
// id, dfd as fd, d2id as id.
std::vector<Family> algo_inputs(Algo algo);

// Where each state entry sits in a CSV row.
struct StateColumns {
  Index nv = 0;
  Index nq = 0;  // entries of q (= nv unless the model has quaternions: floating base, ball joints)
  std::array<std::vector<int>, kFamilies> column;  // [family][i]: CSV column, -1 if absent
                                                   // (nq entries for q, nv for the others)

  const std::vector<int>& of(Family f) const { return column[static_cast<int>(f)]; }
  bool any(Family f) const;             // at least one column of f present
  Index first_missing(Family f) const;  // lowest absent index of f, -1 if complete
  bool complete(Family f) const { return first_missing(f) < 0; }
  // True when every family algo reads is complete.
  bool supports(Algo algo) const;
};

// Matches column names to state entries. Throws CsvError naming source for a
// name that is not <family>_<i> with i a decimal index without leading zeros, or
// an index >= nv. (Duplicate names are already rejected by CsvReader.)
StateColumns map_state_columns(const std::vector<std::string>& names, Index nv,
                               const std::string& source);
// The same for a model of nq positions (q_0..q_{nq-1}) and nv velocities.
StateColumns map_state_columns(const std::vector<std::string>& names, Index nq, Index nv,
                               const std::string& source);

// Relative tolerance on a quaternion's norm in a states file: |‖q‖ - 1| above it is
// a data error, within it the quaternion is normalised.
inline constexpr double kQuaternionNormTol = 1e-6;

// The positions in q of the model's unit quaternions (the x of each (x, y, z, w)):
// idx_q + 3 of a free joint, idx_q of a spherical one. Empty for 1-DoF models.
template <class S>
std::vector<Index> quaternion_offsets(const ModelTpl<S>& model) {
  std::vector<Index> out;
  if (!model.multi_dof()) return out;
  for (const auto& b : model.bodies) {
    if (b.type == JointType::Free) out.push_back(b.idx_q + 3);
    else if (b.type == JointType::Spherical) out.push_back(b.idx_q);
  }
  return out;
}

// Normalises the quaternions (at offsets, from quaternion_offsets) of one CSV row's
// q family in place. Throws CsvError naming where (the file and row) and the
// columns of a quaternion whose norm is not finite or is off from 1 by more than
// kQuaternionNormTol relative.
void normalize_quaternions(const StateColumns& cols, const std::vector<Index>& offsets, double* row,
                           const std::string& where);

// Checks that every family an algo reads is complete, and that no family is
// present only in part. Throws CsvError naming source and the first missing column.
void check_state_columns(const StateColumns& cols, const std::vector<Algo>& algos,
                         const std::string& source);

// Copies family f of one CSV row into dst[0..nv) (converting to S).
template <class S>
void gather_family(const StateColumns& cols, Family f, const double* row, S* dst) {
  const std::vector<int>& c = cols.of(f);
  for (std::size_t i = 0; i < c.size(); ++i) dst[i] = static_cast<S>(row[c[i]]);
}

}  // namespace scandyn::io
