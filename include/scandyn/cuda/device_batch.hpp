// scandyn/cuda/device_batch.hpp: a batch of host rows held in device memory, in the
// engines' fast layout, for calling their compute_async() without transfers (the
// benchmarks' device-resident rows, tests).
//
//   cuda::DeviceBatch<float> d(nv, B, {q_rows, qd_rows, tau_rows}, nv, /*failures=*/true);
//   fd.compute_async({d.input(0), d.input(1), d.input(2)}, d.output(), d.failed_dof(), d.stream());
//   d.read_output(qdd_rows);                  // waits; B x nv, instance-major
#pragma once

#include <cuda_runtime_api.h>

#include <cstddef>
#include <vector>

#include "scandyn/batch.hpp"

namespace scandyn {
namespace cuda {

template <class S>
class DeviceBatch {
 public:
  // Copies up to three host arrays of B rows of nv values (instance-major, b * nv + i)
  // to the current device, each as an (nv x B) structure of arrays (entry (i, b) at
  // i * B + b); allocates the output, out_width values per instance in the same
  // layout, set to NaN until a call writes it (so an entry never written shows), and
  // with failures B ints set to -1, on a non-blocking stream of its own. Throws
  // BackendError naming the bytes needed (besides other_bytes already held on the
  // device, named in the message) and the bytes free. nq: the first input's row
  // length when it is q with a quaternion (nq > nv: a floating base or ball joints);
  // 0: nv.
  DeviceBatch(Index nv, Index B, const std::vector<const S*>& inputs, std::size_t out_width, bool failures,
              std::size_t other_bytes = 0, Index nq = 0);
  ~DeviceBatch();
  DeviceBatch(const DeviceBatch&) = delete;
  DeviceBatch& operator=(const DeviceBatch&) = delete;

  BatchView<const S> input(int k) const { return BatchView<const S>::soa(in_[k], width(k), B_); }  // (width x B)
  Index width(int k) const { return k == 0 ? nq_ : nv_; }  // input k's row length
  BatchView<S> output() const { return BatchView<S>::soa(out_, static_cast<Index>(width_), B_); }  // (width x B)
  int* failed_dof() const { return failed_; }  // (B) device ints, or null without failures
  cudaStream_t stream() const { return stream_; }
  std::size_t bytes() const { return bytes_; }

  // Waits for the stream; throws BackendError("backend 'cuda': running <what>: ...").
  void synchronize(const char* what);
  // Copies the output to rows (B x width, instance-major); waits.
  void read_output(S* rows);
  // Copies the failed DoFs to failed (B ints); waits.
  void read_failed(int* failed);

 private:
  void release() noexcept;
  Index nv_, B_;
  Index nq_;  // input 0's row length
  std::size_t width_;
  std::size_t bytes_ = 0;
  void* buffer_ = nullptr;   // the inputs (width(k) x B each), the output (width x B), the failed DoFs (B ints)
  const S* in_[3] = {nullptr, nullptr, nullptr};
  S* out_ = nullptr;
  int* failed_ = nullptr;
  cudaStream_t stream_ = nullptr;
};

}  // namespace cuda
}  // namespace scandyn
