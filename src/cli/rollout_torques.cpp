// src/cli/rollout_torques.cpp: rollout --tau (rollout_torques.hpp).
#include "rollout_torques.hpp"

#include <cmath>

#include "cli.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/io/limits.hpp"

#if SCANDYN_HAS_CUDA
#include <cuda_runtime_api.h>
#endif

namespace scandyn::cli {

template <class S>
RolloutTorques<S>::RolloutTorques(const std::string& path, long long steps, Index B, Index nv, bool on_device,
                                  void* stream) try
    : file_(path), B_(B), nv_(nv), on_device_(on_device), stream_(stream) {
  const std::vector<std::int64_t>& sh = file_.shape();
  const std::string expected = "expected (steps, instances, nv) = (" + std::to_string(steps) + ", " +
                               std::to_string(B) + ", " + std::to_string(nv) + "), (instances, nv) = (" +
                               std::to_string(B) + ", " + std::to_string(nv) + ") or (nv,) = (" + std::to_string(nv) +
                               ",)";
  const auto bad = [&](const std::string& why) {
    return DataError("--tau " + path + ": shape " + file_.shape_string() + ": " + why + "; " + expected);
  };
  if (sh.empty() || sh.size() > 3) throw bad("not 1, 2 or 3 dimensions");
  if (sh.back() != nv) throw bad("the last dimension is not the model's nv = " + std::to_string(nv));
  if (sh.size() >= 2 && sh[sh.size() - 2] != B)
    throw bad("the instance dimension is not the scene's " + std::to_string(B) + " instances");
  if (sh.size() == 3 && sh[0] != steps)
    throw bad("torques for " + std::to_string(sh[0]) + " steps, the rollout takes " + std::to_string(steps) +
              " (--steps)");
  shape_ = sh.size() == 1 ? Shape::Row : sh.size() == 2 ? Shape::PerInstance : Shape::PerStep;
  const std::size_t block = shape_ == Shape::Row ? std::size_t(nv) : std::size_t(B) * std::size_t(nv);
  host_.resize(block);
#if SCANDYN_HAS_CUDA
  if (on_device_ && block > 0) {
    if (const cudaError_t err = cudaMalloc(reinterpret_cast<void**>(&device_), block * sizeof(S)); err != cudaSuccess)
      throw DataError("--tau " + path + ": cannot allocate " + std::to_string(block * sizeof(S)) +
                      " bytes of device memory for the torques: " + cudaGetErrorString(err));
  }
#else
  if (on_device_) throw DataError("--tau: a device simulator in a build without CUDA");
#endif
  if (shape_ != Shape::PerStep) {
    read_block(0, block, 0);
    to_device();
  }
} catch (const InputError& e) {  // the file as a file (npy.hpp): said as --tau's
  throw DataError(std::string("--tau ") + e.what());
}

template <class S>
RolloutTorques<S>::~RolloutTorques() {
#if SCANDYN_HAS_CUDA
  if (device_) {
    cudaStreamSynchronize(static_cast<cudaStream_t>(stream_));  // the last step has read them
    cudaFree(device_);
  }
#endif
}

template <class S>
void RolloutTorques<S>::read_block(std::size_t first, std::size_t count, long long step) {
  try {
    file_.read<S>(first, count, host_.data());
  } catch (const InputError& e) {
    throw DataError(std::string("--tau ") + e.what());
  }
  for (std::size_t k = 0; k < count; ++k) {
    if (std::isfinite(static_cast<double>(host_[k]))) continue;
    const std::size_t b = k / std::size_t(nv_), i = k % std::size_t(nv_);
    const double x = static_cast<double>(host_[k]);
    // the entry as NumPy indexes it, and what it is
    std::string index = "[", what;
    if (shape_ == Shape::PerStep) index += std::to_string(step) + ", ", what = "step " + std::to_string(step + 1) + ", ";
    if (shape_ != Shape::Row) index += std::to_string(b) + ", ", what += "instance " + std::to_string(b) + ", ";
    index += std::to_string(i) + "]";
    throw DataError("--tau " + file_.path() + ": tau" + index + " (" + what + "DoF " + std::to_string(i) + ") is " +
                    (std::isnan(x) ? "nan" : x > 0 ? "inf" : "-inf") +
                    (sizeof(S) == 4 && file_.item_size() == 8 ? " in float (the scene's precision)" : "") +
                    "; torques must be finite");
  }
}

template <class S>
void RolloutTorques<S>::to_device() {
#if SCANDYN_HAS_CUDA
  if (!device_) return;
  // pageable host memory: the call returns once host_ is staged, so host_ may be
  // refilled at once; the copy runs on the simulator's stream, after the steps before it
  const cudaError_t err = cudaMemcpyAsync(device_, host_.data(), host_.size() * sizeof(S), cudaMemcpyHostToDevice,
                                          static_cast<cudaStream_t>(stream_));
  if (err != cudaSuccess)
    throw DataError("--tau " + file_.path() + ": copying the torques to the device: " + cudaGetErrorString(err));
#endif
}

template <class S>
BatchView<const S> RolloutTorques<S>::view(const S* data) const {
  // (B x nv) rows: entry (i, b) at b * nv + i; one row: the same nv entries for every b
  return {data, B_, 1, shape_ == Shape::Row ? 0 : std::ptrdiff_t(nv_)};
}

template <class S>
BatchView<const S> RolloutTorques<S>::for_step(long long s) {
  if (shape_ == Shape::PerStep) {
    const std::size_t block = host_.size();
    read_block(static_cast<std::size_t>(s - 1) * block, block, s - 1);
    to_device();
  }
  return view(device_ ? device_ : host_.data());
}

template class RolloutTorques<float>;
template class RolloutTorques<double>;

}  // namespace scandyn::cli
