// src/cli/rollout_torques.hpp: `scandyn rollout --tau FILE.npy`, the joint torques of
// every step read from a NumPy array (scandyn/io/npy.hpp) and handed to the
// simulator in its own memory (host, or the device for a cuda simulator).
//
// Shapes (B instances, nv DoF, N = --steps): (N, B, nv) a torque per step, instance
// and DoF, row t acting during the step from t to t + 1; (B, nv) one torque per
// instance for every step; (nv,) one row for every instance and step. float32 or
// float64, converted to the scene's precision. Every torque must be finite.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "scandyn/batch.hpp"
#include "scandyn/io/npy.hpp"

namespace scandyn::cli {

template <class S>
class RolloutTorques {
 public:
  // Opens `path` and checks it against the rollout (steps, B, nv): shape, dtype,
  // size; the constant shapes are read (and checked finite) here. stream: the
  // cuda simulator's stream (its cudaStream_t) when on_device, else ignored.
  // Throws DataError or InputError (exit 1) naming the file and what is wrong.
  RolloutTorques(const std::string& path, long long steps, Index B, Index nv, bool on_device, void* stream);
  ~RolloutTorques();
  RolloutTorques(const RolloutTorques&) = delete;
  RolloutTorques& operator=(const RolloutTorques&) = delete;

  // The torques of step s (1..N: the step from state s - 1 to s) as an (nv x B) view
  // in the simulator's memory, valid until the next call (on cuda, copied on the
  // simulator's stream, so the step queued after it reads them in order).
  BatchView<const S> for_step(long long s);

  // Host bytes these torques take (one block of B x nv).
  static double host_bytes(Index B, Index nv) { return double(B) * double(nv) * sizeof(S); }

 private:
  enum class Shape { Row, PerInstance, PerStep };
  void read_block(std::size_t first, std::size_t count, long long row);  // into host_, checked finite
  BatchView<const S> view(const S* data) const;
  void to_device();

  io::NpyReader file_;
  Shape shape_ = Shape::Row;
  Index B_ = 0, nv_ = 0;
  bool on_device_ = false;
  void* stream_ = nullptr;
  std::vector<S> host_;  // the current block: (B x nv) rows, or one (nv) row
  S* device_ = nullptr;  // its device copy (cuda)
};

}  // namespace scandyn::cli
