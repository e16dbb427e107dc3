// kernels/device_batch.cu: DeviceBatch (scandyn/cuda/device_batch.hpp).
#include "scandyn/cuda/device_batch.hpp"

#include <cuda_runtime.h>

#include <string>

#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;

template <class S>
DeviceBatch<S>::DeviceBatch(Index nv, Index B, const std::vector<const S*>& inputs, std::size_t out_width,
                            bool failures, std::size_t other_bytes, Index nq)
    : nv_(nv), B_(B), nq_(nq > 0 ? nq : nv), width_(out_width) {
  if (inputs.size() > 3) throw BackendError("DeviceBatch: more than three inputs");
  const std::size_t count = static_cast<std::size_t>(B);
  std::size_t scalars = width_ * count;
  for (std::size_t k = 0; k < inputs.size(); ++k) scalars += static_cast<std::size_t>(width(int(k))) * count;
  bytes_ = scalars * sizeof(S) + (failures ? count * sizeof(int) : 0);
  buffer_ = detail::device_malloc(bytes_, [&](std::size_t free_bytes, std::size_t) {
    return "backend 'cuda': the device-resident batch of " + std::to_string(count) + " instances needs " +
           std::to_string(bytes_) + " bytes of device memory besides the " + std::to_string(other_bytes) +
           " bytes of the engine's buffers; " + std::to_string(free_bytes) + " bytes are free";
  });
  try {
    check(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking), "cudaStreamCreateWithFlags");
    // inputs transposed to the engines' fast layout. Everything on the stream, which
    // does not synchronise with the legacy default stream, and waited for before soa
    // is refilled.
    std::vector<S> soa(static_cast<std::size_t>(nq_ > nv ? nq_ : nv) * count);
    S* dev = static_cast<S*>(buffer_);
    for (std::size_t k = 0; k < inputs.size(); ++k) {
      const S* rows = inputs[k];
      const Index w = width(int(k));
      const std::size_t n = static_cast<std::size_t>(w) * count;  // values of this input
      for (std::size_t b = 0; b < count; ++b)
        for (Index i = 0; i < w; ++i) soa[static_cast<std::size_t>(i) * count + b] = rows[b * w + i];
      check(cudaMemcpyAsync(dev, soa.data(), n * sizeof(S), cudaMemcpyHostToDevice, stream_),
            "copying the batch to the device");
      check(cudaStreamSynchronize(stream_), "copying the batch to the device");
      in_[k] = dev;
      dev += n;
    }
    out_ = dev;
    check(cudaMemsetAsync(out_, 0xff, width_ * count * sizeof(S), stream_), "cudaMemsetAsync");  // NaN
    if (failures) {
      failed_ = reinterpret_cast<int*>(out_ + width_ * count);
      check(cudaMemsetAsync(failed_, 0xff, count * sizeof(int), stream_), "cudaMemsetAsync");  // -1
    }
    check(cudaStreamSynchronize(stream_), "cudaMemsetAsync");
  } catch (...) {
    release();
    throw;
  }
}

template <class S>
DeviceBatch<S>::~DeviceBatch() {
  release();
}

template <class S>
void DeviceBatch<S>::release() noexcept {
  if (stream_) {
    cudaStreamSynchronize(stream_);
    cudaStreamDestroy(stream_);
  }
  if (buffer_) cudaFree(buffer_);
  stream_ = nullptr;
  buffer_ = nullptr;
}

template <class S>
void DeviceBatch<S>::synchronize(const char* what) {
  check(cudaStreamSynchronize(stream_), (std::string("running ") + what).c_str());
}

template <class S>
void DeviceBatch<S>::read_output(S* rows) {
  const std::size_t B = static_cast<std::size_t>(B_);
  std::vector<S> soa(width_ * B);
  check(cudaMemcpyAsync(soa.data(), out_, soa.size() * sizeof(S), cudaMemcpyDeviceToHost, stream_),
        "copying the results to the host");
  check(cudaStreamSynchronize(stream_), "copying the results to the host");
  for (std::size_t b = 0; b < B; ++b)
    for (std::size_t e = 0; e < width_; ++e) rows[b * width_ + e] = soa[e * B + b];
}

template <class S>
void DeviceBatch<S>::read_failed(int* failed) {
  check(cudaMemcpyAsync(failed, failed_, static_cast<std::size_t>(B_) * sizeof(int), cudaMemcpyDeviceToHost, stream_),
        "copying the failed DoFs to the host");
  check(cudaStreamSynchronize(stream_), "copying the failed DoFs to the host");
}

template class DeviceBatch<float>;
template class DeviceBatch<double>;

}  // namespace cuda
}  // namespace scandyn
