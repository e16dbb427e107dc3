// src/cli/kinematics_columns.hpp: `scandyn eval --algo fk,jac`: the frames' poses and
// Jacobians of each state, as output columns, through the library's Kinematics
// engine (scandyn/engine.hpp) for the chosen backend.
//
// Columns, per selected frame F (--frames, in its order; default every frame of the
// model, the URDF links as `scandyn info` lists them):
//   fk   fk_<F>_px, fk_<F>_py, fk_<F>_pz   the frame's origin in the world (base) frame (m)
//        fk_<F>_qx, fk_<F>_qy, fk_<F>_qz, fk_<F>_qw
//                                          the unit quaternion of its orientation (w >= 0)
//   jac  J_<F>_<r>_<j>, r = 0..5, j = 0..nv-1: the 6 x nv frame Jacobian, row-major,
//        rows [angular; linear] (Pinocchio's rows 3-5, then 0-2), in world axes at the
//        frame's origin (--reference world, the default: Pinocchio's
//        LOCAL_WORLD_ALIGNED) or the frame's own axes (--reference local: LOCAL).
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "scandyn/engine.hpp"

namespace scandyn::cli {

class Args;

// What --algo fk,jac, --frames and --reference ask for.
struct KinematicsRequest {
  bool fk = false, jac = false;
  KinematicsOptions options;  // frames and reference; pose PositionQuaternion
  std::vector<std::string> frame_names;  // (F) the selected frames' names
  bool any() const { return fk || jac; }
};

// --frames (a comma list of frame names, default every frame) and --reference (world
// or local). Throws UsageError for --frames or --reference without fk or jac, an
// unknown reference; ModelError naming an unknown frame and listing the frames.
KinematicsRequest parse_kinematics_request(const Args& args, const Model& model, bool fk, bool jac);

// The fk and jac columns of one model and precision on one backend.
template <class S>
class KinematicsColumns {
 public:
  // max_batch rows per call; what the backend refuses is a UsageError (exit 2).
  KinematicsColumns(const ModelTpl<S>& model, const KinematicsRequest& request, const BackendOptions& options);
  ~KinematicsColumns();

  const std::vector<std::string>& names() const { return names_; }
  std::size_t width() const { return names_.size(); }
  // Writes count rows of width() values, row b at out[b * row_stride], from q (count
  // x nv, instance-major). A CUDA error is a DataError.
  void run(const S* q, std::size_t count, S* out, std::size_t row_stride);
  Kinematics<S>& engine() { return *engine_; }
  std::size_t fk_width() const;   // the fk columns per row (7 per frame, or 0)
  std::size_t jac_width() const;  // the jac columns per row (6 nv per frame, or 0)

 private:
  Index nv_, nq_, F_;  // DoFs (Jacobian columns), entries of q, frames
  KinematicsRequest request_;
  std::vector<std::string> names_;
  std::unique_ptr<Kinematics<S>> engine_;
};

}  // namespace scandyn::cli
