// src/cli/states.hpp: the columns of a states file (q_<i>, qd_<i>, qdd_<i>,
// tau_<i>) and which algorithms they feed.
#pragma once

#include <array>
#include <string>
#include <vector>

#include "engines.hpp"

namespace scandyn::cli {

// The four input families of a states file, by column-name prefix.
enum class Family { Q = 0, Qd = 1, Qdd = 2, Tau = 3 };
constexpr int kFamilies = 4;

const char* family_prefix(Family f);  // "q_", "qd_", "qdd_", "tau_"
// The families algo reads: id q, qd, qdd; fd q, qd, tau; mass q; bias q, qd.
std::vector<Family> algo_inputs(Algo algo);

// Where each state entry sits in a CSV row.
struct StateColumns {
  Index nv = 0;
  std::array<std::vector<int>, kFamilies> column;  // [family][i]: CSV column, -1 if absent

  const std::vector<int>& of(Family f) const { return column[static_cast<int>(f)]; }
  bool any(Family f) const;             // at least one column of f present
  Index first_missing(Family f) const;  // lowest absent index of f, -1 if complete
  bool complete(Family f) const { return first_missing(f) < 0; }
  // True when every family algo reads is complete.
  bool supports(Algo algo) const;
};

// Matches column names to state entries. Throws DataError naming source for a
// name that is not <family>_<i> with i a decimal index without leading zeros, or
// an index >= nv. (Duplicate names are already rejected by CsvReader.)
StateColumns map_state_columns(const std::vector<std::string>& names, Index nv,
                               const std::string& source);

// Checks that every family an algo reads is complete, and that no family is
// present only in part. Throws DataError naming source and the first missing column.
void check_state_columns(const StateColumns& cols, const std::vector<Algo>& algos,
                         const std::string& source);

// Copies family f of one CSV row into dst[0..nv) (converting to S).
template <class S>
void gather_family(const StateColumns& cols, Family f, const double* row, S* dst) {
  const std::vector<int>& c = cols.of(f);
  for (std::size_t i = 0; i < c.size(); ++i) dst[i] = static_cast<S>(row[c[i]]);
}

}  // namespace scandyn::cli
