// src/engine/batch_status.cpp: BatchStatus (scandyn/engine.hpp), what one batched call
// reports about its failed instances: merging shards' and stages' reports, the
// one-line messages, and the summaries of per-instance failed-DoF arrays.
#include <cmath>
#include <cstdio>
#include <string>

#include "scandyn/engine.hpp"

namespace scandyn {

void BatchStatus::merge(const BatchStatus& other) {
  if (other.first_instance >= 0 && (first_instance < 0 || other.first_instance < first_instance)) {
    first_instance = other.first_instance;
    first_dof = other.first_dof;
    failure = other.failure;
    estimate = other.estimate;
    threshold = other.threshold;
  }
  failed += other.failed;
  fell_back += other.fell_back;
  retried += other.retried;
}

std::string BatchStatus::reason() const {
  if (ok()) return "";
  const std::string pivot = " pivot at DoF " + std::to_string(first_dof) + " is not positive";
  switch (failure) {
    case Failure::MassMatrixPivot: return "mass matrix" + pivot;
    case Failure::BothPivots:
      return "mass matrix pivot not positive, and by the aba fallback the articulated inertia" + pivot;
    case Failure::NonFinite: return "the state at DoF " + std::to_string(first_dof) + " is not finite after the step";
    case Failure::ResidualTooLarge: {
      char b[256];
      std::snprintf(b, sizeof b,
                    "forward dynamics check: estimated error of qdd %.2g (M^-1 (ID(q, qd, qdd) - tau) relative to "
                    "max(1, |qdd|)) above the threshold %.2g (largest at DoF %lld)",
                    estimate, threshold, static_cast<long long>(first_dof));
      return b;
    }
    case Failure::NotConverged:
      return "the variational step's Newton iteration did not converge (largest correction at DoF " +
             std::to_string(first_dof) + ")";
    case Failure::LoopNotClosed: {
      if (std::isinf(estimate)) return "the projection onto the closed loops failed (its factorisation)";
      char b[256];
      std::snprintf(b, sizeof b,
                    "the projection onto the closed loops left loop %lld violated by %.2g (max |phi| m, |J qd| m/s; "
                    "tolerance %.2g)",
                    static_cast<long long>(first_dof), estimate, threshold);
      return b;
    }
    case Failure::ArticulatedPivot:
    case Failure::None: break;
  }
  return "articulated inertia" + pivot;
}

std::string BatchStatus::message() const {
  if (ok()) return "";
  std::string s = "instance " + std::to_string(first_instance) + ": " + reason();
  if (failed > 1) s += " (and " + std::to_string(failed - 1) + " more instance" + (failed > 2 ? "s" : "") + ")";
  return s;
}

BatchStatus summarize_failures(const int* failed_dof, Index B, Failure what, Index fell_back) {
  BatchStatus st;
  st.failed_dof = failed_dof;
  st.fell_back = fell_back;
  for (Index b = 0; b < B; ++b)
    if (failed_dof[b] >= 0) st.record(b, failed_dof[b], what);
  return st;
}

BatchStatus summarize_step_failures(int* failed_dof, Index B) {
  BatchStatus st;
  st.failed_dof = failed_dof;
  for (Index b = 0; b < B; ++b) {
    int& f = failed_dof[b];
    if (f >= 0) st.record(b, f, Failure::ArticulatedPivot);
    if (f <= -2) f = -2 - f, st.record(b, f, Failure::NonFinite);
  }
  return st;
}

BatchStatus summarize_checked(const int* failed_dof, const double* estimate, Index B, Failure pivot,
                              double threshold, Index fell_back, Index retried) {
  BatchStatus st;
  st.failed_dof = failed_dof;
  st.fell_back = fell_back;
  st.retried = retried;
  for (Index b = 0; b < B; ++b) {
    if (failed_dof[b] < 0) continue;
    const bool check = !(estimate[b] <= threshold);
    st.record(b, failed_dof[b], check ? Failure::ResidualTooLarge : pivot);
    if (check && st.first_instance == b) {
      st.estimate = estimate[b];
      st.threshold = threshold;
    }
  }
  return st;
}

}  // namespace scandyn
