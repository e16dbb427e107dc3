// src/cli/kinematics_columns.cpp: the fk and jac columns of `scandyn eval`.
#include "kinematics_columns.hpp"

#include "cli.hpp"
#include "scandyn/model/frames.hpp"

namespace scandyn::cli {

KinematicsRequest parse_kinematics_request(const Args& args, const Model& model, bool fk, bool jac) {
  KinematicsRequest r;
  r.fk = fk;
  r.jac = jac;
  if (!r.any()) {
    for (const char* flag : {"frames", "reference"})
      if (args.has(flag))
        throw UsageError(std::string("--") + flag + " needs fk or jac in --algo");
    return r;
  }
  const std::string reference = args.get("reference", "world");
  if (reference == "local") r.options.reference = FrameReference::Local;
  else if (reference != "world")
    throw UsageError("unknown --reference value '" + reference + "' (expected world or local)");
  if (args.has("reference") && !jac) throw UsageError("--reference needs jac in --algo");
  r.options.pose = PoseFormat::PositionQuaternion;
  if (args.has("frames")) {
    r.options.frames = parse_frame_list(model, args.required("frames"));
  } else {
    for (std::size_t k = 0; k < model.frames.size(); ++k) r.options.frames.push_back(static_cast<Index>(k));
  }
  for (Index f : r.options.frames) r.frame_names.push_back(model.frame_names[static_cast<std::size_t>(f)]);
  return r;
}

template <class S>
KinematicsColumns<S>::KinematicsColumns(const ModelTpl<S>& model, const KinematicsRequest& request,
                                        const BackendOptions& options)
    : nv_(model.nv()), nq_(model.nq()), F_(static_cast<Index>(request.options.frames.size())), request_(request) {
  if (request.fk)
    for (const std::string& f : request.frame_names)
      for (const char* e : {"px", "py", "pz", "qx", "qy", "qz", "qw"}) names_.push_back("fk_" + f + "_" + e);
  if (request.jac)
    for (const std::string& f : request.frame_names)
      for (int r = 0; r < 6; ++r)
        for (Index j = 0; j < nv_; ++j) names_.push_back("J_" + f + "_" + std::to_string(r) + "_" + std::to_string(j));
  try {
    engine_ = make_kinematics(model, options, request.options);
  } catch (const BackendError& e) {
    throw UsageError(e.what(), false);
  }
}

template <class S>
KinematicsColumns<S>::~KinematicsColumns() = default;

template <class S>
void KinematicsColumns<S>::run(const S* q, std::size_t count, S* out, std::size_t row_stride) {
  const Index B = static_cast<Index>(count);
  const std::ptrdiff_t stride = static_cast<std::ptrdiff_t>(row_stride);
  // the fk block, then the jac block, of each row: strided views straight into out
  const BatchView<S> poses{request_.fk ? out : nullptr, B, 1, stride};
  const BatchView<S> J{request_.jac ? out + fk_width() : nullptr, B, 1, stride};
  try {
    engine_->compute(BatchView<const S>::aos(q, nq_, B), poses, J);
  } catch (const BackendError& e) {
    throw DataError(e.what());
  }
}

template <class S>
std::size_t KinematicsColumns<S>::fk_width() const {
  return request_.fk ? static_cast<std::size_t>(F_ * pose_width(request_.options.pose)) : 0;
}
template <class S>
std::size_t KinematicsColumns<S>::jac_width() const {
  return request_.jac ? static_cast<std::size_t>(F_ * 6 * nv_) : 0;
}

template class KinematicsColumns<float>;
template class KinematicsColumns<double>;

}  // namespace scandyn::cli
