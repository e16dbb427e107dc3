// src/cli/engines_cuda.cpp: bench's device-resident batch for the CUDA engines:
// the batch copied once to device memory in the engines' fast layout (instance
// innermost), the engine's compute_async() on a stream per call; fd's failed DoFs
// stay on the device until status() reads them, after the timing. Every engine has
// one except fd by the hybrid method and jsi with the aba fallback (compute() only:
// the host must see q, or which instances failed).
#include "engines.hpp"

#if SCANDYN_HAS_CUDA

#include <cuda_runtime_api.h>

#include <functional>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "cli.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/cuda/mass_matrix.hpp"

namespace scandyn::cli {

namespace {

std::string cuda_error_text(cudaError_t err) {
  (void)cudaGetLastError();  // clear a non-sticky error
  const char* s = cudaGetErrorString(err);
  return std::string(s ? s : "unknown CUDA error") + " (" + std::to_string(static_cast<int>(err)) + ")";
}

// A CUDA call during a computation: a failure is a failed computation (exit 1).
void check(cudaError_t err, const char* what) {
  if (err != cudaSuccess) throw DataError(std::string("backend 'cuda': ") + what + ": " + cuda_error_text(err));
}

// The batch in device memory, structure of arrays (entry (e, b) at [e * B + b]):
// the inputs an algorithm reads, its output (out_width values per instance, NaN
// until a call writes them), one zero (bias's qdd) and, for fd, each instance's
// failed DoF. One class for every algorithm: `queue` is the engine's
// compute_async() on the views.
template <class S>
class CudaResidentBatch final : public ResidentBatch<S> {
 public:
  // What a call of the engine gets: device views of the inputs (in the order given
  // to the constructor; the rest empty), of the output, the zero, the failed DoFs
  // (B ints; null unless the algorithm reports failures) and the stream.
  struct Device {
    BatchView<const S> in[3];
    BatchView<S> out;
    const S* zero = nullptr;
    int* failed = nullptr;
    cudaStream_t stream = nullptr;
  };
  using Queue = std::function<cudaError_t(const Device&)>;

  // strategy: the benchmark's strategy column; what: the computation, for error
  // messages ("the forward dynamics"); inputs: host arrays of `count` instances x nv
  // values, instance-major (BatchIn's), at most three; failures: whether a call
  // writes a failed DoF per instance (fd); engine_bytes: the engine's own device
  // memory, named when this batch does not fit.
  CudaResidentBatch(std::string strategy, std::string what, Index nv, std::size_t count,
                    const std::vector<const S*>& inputs, std::size_t out_width, bool failures,
                    std::size_t engine_bytes, Queue queue, Failure failure = Failure::None)
      : strategy_(std::move(strategy)), what_(std::move(what)), nv_(nv), B_(static_cast<Index>(count)),
        width_(out_width), queue_(std::move(queue)), failure_(failure) {
    if (inputs.size() > 3) throw std::logic_error("CudaResidentBatch: more than three inputs");
    const std::size_t n = static_cast<std::size_t>(nv_) * count;  // values of one input
    const std::size_t scalars = inputs.size() * n + width_ * count + 1;
    const std::size_t bytes = scalars * sizeof(S) + (failures ? count * sizeof(int) : 0);
    cudaError_t err = cudaMalloc(reinterpret_cast<void**>(&buffer_), bytes);
    if (err != cudaSuccess) {
      const std::string why = cuda_error_text(err);
      buffer_ = nullptr;
      std::size_t free_bytes = 0, total_bytes = 0;
      (void)cudaMemGetInfo(&free_bytes, &total_bytes);
      (void)cudaGetLastError();
      throw UsageError("backend 'cuda': the device-resident batch of " + std::to_string(count) +
                           " instances needs " + std::to_string(bytes) + " bytes of device memory besides the " +
                           std::to_string(engine_bytes) + " bytes of the engine's buffers; " +
                           std::to_string(free_bytes) + " bytes are free (cudaMalloc: " + why + ")",
                       false);
    }
    try {
      fill(inputs, n, scalars, failures);
    } catch (...) {
      release();
      throw;
    }
  }

  ~CudaResidentBatch() override { release(); }
  CudaResidentBatch(const CudaResidentBatch&) = delete;
  CudaResidentBatch& operator=(const CudaResidentBatch&) = delete;

  void launch() override { check(queue_(device_), ("launching " + what_).c_str()); }
  void wait() override { check(cudaStreamSynchronize(device_.stream), ("running " + what_).c_str()); }

  void read(S* out) override {
    wait();
    const std::size_t B = static_cast<std::size_t>(B_);
    std::vector<S> soa(width_ * B);
    check(cudaMemcpyAsync(soa.data(), device_.out.data, soa.size() * sizeof(S), cudaMemcpyDeviceToHost,
                          device_.stream),
          "copying the results to the host");
    check(cudaStreamSynchronize(device_.stream), "copying the results to the host");
    for (std::size_t b = 0; b < B; ++b)
      for (std::size_t e = 0; e < width_; ++e) out[b * width_ + e] = soa[e * B + b];
  }

  // fd: the lowest instance whose failed DoF is set, as run() reports it
  BatchStatus status() override {
    wait();
    BatchStatus st;
    if (!device_.failed) return st;
    failed_.resize(static_cast<std::size_t>(B_));
    check(cudaMemcpyAsync(failed_.data(), device_.failed, failed_.size() * sizeof(int), cudaMemcpyDeviceToHost,
                          device_.stream),
          "copying the failed DoFs to the host");
    check(cudaStreamSynchronize(device_.stream), "copying the failed DoFs to the host");
    return summarize_failures(failed_.data(), B_, failure_);
  }

  std::string strategy() const override { return strategy_; }

 private:
  // the stream, the inputs transposed into the buffer, the output set to NaN, the
  // zero, the failed DoFs, the views
  void fill(const std::vector<const S*>& inputs, std::size_t n, std::size_t scalars, bool failures) {
    check(cudaStreamCreateWithFlags(&device_.stream, cudaStreamNonBlocking), "cudaStreamCreateWithFlags");
    const cudaStream_t stream = device_.stream;
    // inputs transposed to the engines' fast layout. Everything on the stream,
    // which does not synchronise with the legacy default stream, and waited for
    // before soa is refilled.
    std::vector<S> soa(n);
    S* dev = buffer_;
    int k = 0;
    for (const S* aos : inputs) {
      for (Index b = 0; b < B_; ++b)
        for (Index i = 0; i < nv_; ++i)
          soa[static_cast<std::size_t>(i) * B_ + b] = aos[static_cast<std::size_t>(b) * nv_ + i];
      check(cudaMemcpyAsync(dev, soa.data(), n * sizeof(S), cudaMemcpyHostToDevice, stream),
            "copying the batch to the device");
      check(cudaStreamSynchronize(stream), "copying the batch to the device");
      device_.in[k++] = BatchView<const S>::soa(dev, nv_, B_);
      dev += n;
    }
    // the output: NaN (all bits set) until a call writes it, so an entry never
    // written shows in the error
    const std::size_t out = width_ * static_cast<std::size_t>(B_);
    check(cudaMemsetAsync(dev, 0xff, out * sizeof(S), stream), "cudaMemsetAsync");
    device_.out = BatchView<S>::soa(dev, static_cast<Index>(width_), B_);
    S* const zero = buffer_ + scalars - 1;
    check(cudaMemsetAsync(zero, 0, sizeof(S), stream), "cudaMemsetAsync");
    device_.zero = zero;
    if (failures) {
      device_.failed = reinterpret_cast<int*>(buffer_ + scalars);
      check(cudaMemsetAsync(device_.failed, 0xff, static_cast<std::size_t>(B_) * sizeof(int), stream),
            "cudaMemsetAsync");  // -1: none (every call writes each instance's)
    }
    check(cudaStreamSynchronize(stream), "cudaMemsetAsync");
  }

  void release() noexcept {
    if (device_.stream) {
      cudaStreamSynchronize(device_.stream);
      cudaStreamDestroy(device_.stream);
    }
    if (buffer_) cudaFree(buffer_);
    device_.stream = nullptr;
    buffer_ = nullptr;
  }

  std::string strategy_, what_;
  Index nv_, B_;
  std::size_t width_;    // output values per instance
  Queue queue_;
  Failure failure_ = Failure::None;  // what a failed DoF means (fd: the method's pivot)
  std::vector<int> failed_;          // (B) the failed DoFs on the host, after status()
  S* buffer_ = nullptr;  // the inputs (nv x B each), the output (width x B), the zero; the failed DoFs (B ints)
  Device device_;
};

}  // namespace

template <class S>
std::unique_ptr<ResidentBatch<S>> make_resident_batch(Algo algo, Engine& engine, Index nv, const BatchIn<S>& in) {
  using Device = typename CudaResidentBatch<S>::Device;
  const std::size_t width = output_width(algo, nv);
  if (algo == Algo::Fd) {
    auto& e = dynamic_cast<cuda::CudaForwardDynamics<S>&>(engine);
    if (e.method() == FdMethod::Hybrid || e.fallback_aba()) return nullptr;
    return std::make_unique<CudaResidentBatch<S>>(
        e.strategy(), "the forward dynamics", nv, in.count, std::vector<const S*>{in.q, in.qd, in.tau}, width, true,
        e.device_bytes(), [&e](const Device& d) {
          return e.compute_async(FdBatchIn<S>{d.in[0], d.in[1], d.in[2], nullptr}, d.out, d.failed, d.stream);
        },
        pivot_failure(e.method()));
  }
  if (algo == Algo::Mass) {
    auto& e = dynamic_cast<cuda::CudaMassMatrix<S>&>(engine);
    return std::make_unique<CudaResidentBatch<S>>(
        e.strategy(), "the mass matrix", nv, in.count, std::vector<const S*>{in.q}, width, false, e.device_bytes(),
        [&e](const Device& d) { return e.compute_async(d.in[0], d.out, d.stream); });
  }
  if (algo == Algo::Bias) {
    auto& e = dynamic_cast<cuda::CudaBiasForces<S>&>(engine);
    return std::make_unique<CudaResidentBatch<S>>(
        e.strategy(), "the bias forces", nv, in.count, std::vector<const S*>{in.q, in.qd}, width, false,
        e.device_bytes(), [&e](const Device& d) {
          return e.compute_async(BiasBatchIn<S>{d.in[0], d.in[1], nullptr}, d.out, d.stream);
        });
  }
  auto& e = dynamic_cast<cuda::CudaInverseDynamics<S>&>(engine);
  return std::make_unique<CudaResidentBatch<S>>(
      e.strategy(), "the inverse dynamics", nv, in.count, std::vector<const S*>{in.q, in.qd, in.qdd}, width, false,
      e.device_bytes(), [&e](const Device& d) {
        return e.compute_async(IdBatchIn<S>{d.in[0], d.in[1], d.in[2], nullptr}, d.out, d.stream);
      });
}
template std::unique_ptr<ResidentBatch<float>> make_resident_batch(Algo, Engine&, Index, const BatchIn<float>&);
template std::unique_ptr<ResidentBatch<double>> make_resident_batch(Algo, Engine&, Index, const BatchIn<double>&);

}  // namespace scandyn::cli

#endif  // SCANDYN_HAS_CUDA
