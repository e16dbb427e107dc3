// src/cli/backend_cuda.cpp: the CUDA backend of `scandyn eval` and `scandyn bench`.
//
// Each algorithm runs through one of the library's CUDA engines:
//   id, bias  CudaInverseDynamics (scandyn/cuda/inverse_dynamics.hpp), bias as id
//             with qdd = 0: one GPU thread per instance up to 64 DoF, scans across
//             links beyond (or as --strategy says);
//   fd        CudaForwardDynamics (scandyn/cuda/forward_dynamics.hpp) by the --fd
//             method (one engine per method): jsi (one GPU thread per instance up
//             to 64 DoF, CRBA per block and cuSOLVER's batched Cholesky beyond), aba
//             (one thread per instance, up to 64 DoF), parallel and hybrid
//             (unbranched chains from the base, link scans), auto (the engine's choice);
//   mass      CudaMassMatrix (scandyn/cuda/mass_matrix.hpp): the CRBA, one thread
//             per instance up to 64 DoF, one thread block per instance beyond.
// and each in two ways:
//   run()       eval's chunks and bench's "<strategy>-host" row: host buffers, the
//               engine's compute() (copies in, kernel, copy out, sync). For fd its
//               FdBatchStatus's first failed instance becomes the BatchStatus that
//               eval and bench report as for the CPU backends;
//   resident()  bench's "<strategy>" row: the batch copied once to device memory in
//               the engines' fast layout (instance innermost), the engine's
//               compute_async() on a stream (CudaResidentBatch, one class for every
//               algorithm); fd's failed DoFs stay on the device until status()
//               reads them, after the timing. Every algorithm and method has one
//               except --fd hybrid (its articulated inertias are computed on the
//               host from q in host memory: compute() only).
// Each engine is made when the evaluator is, if its algorithm is among
// EvalOptions::algos, or on first use.
// Which algorithms this backend computes is its AlgoSet in the table of backend.cpp.
#include "backend.hpp"

#if SCANDYN_HAS_CUDA

#include <cuda_runtime_api.h>

#include <functional>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "cli.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/cuda/mass_matrix.hpp"

namespace scandyn::cli {

std::string cuda_unusable() {
  const cuda::Result<int> count = cuda::device_count();
  if (!count) return count.error;
  if (count.value == 0) return "no usable CUDA device: the CUDA runtime reports 0 devices";
  return "";
}

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

// The inputs of id (qdd as given) or bias (qdd = 0: one zero read by every entry).
template <class S>
IdBatchIn<S> id_inputs(Algo algo, BatchView<const S> q, BatchView<const S> qd, BatchView<const S> qdd,
                       const S* zero) {
  if (algo == Algo::Bias) qdd = BatchView<const S>{zero, q.batch, 0, 0};
  return IdBatchIn<S>{q, qd, qdd, nullptr};
}

void require_id_or_bias(Algo algo) {
  // what is left once fd and mass are handled; anything else is a bug
  if (algo != Algo::Id && algo != Algo::Bias)
    throw std::logic_error(std::string("backend 'cuda' was asked for --algo ") + algo_name(algo));
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
                    std::size_t engine_bytes, Queue queue)
      : strategy_(std::move(strategy)), what_(std::move(what)), nv_(nv), B_(static_cast<Index>(count)),
        width_(out_width), queue_(std::move(queue)) {
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
    std::vector<int> failed(static_cast<std::size_t>(B_));
    check(cudaMemcpyAsync(failed.data(), device_.failed, failed.size() * sizeof(int), cudaMemcpyDeviceToHost,
                          device_.stream),
          "copying the failed DoFs to the host");
    check(cudaStreamSynchronize(device_.stream), "copying the failed DoFs to the host");
    for (std::size_t b = 0; b < failed.size(); ++b) {
      if (failed[b] < 0) continue;
      st.instance = b;
      st.status = Status{failed[b]};
      break;
    }
    return st;
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
  S* buffer_ = nullptr;  // the inputs (nv x B each), the output (width x B), the zero; the failed DoFs (B ints)
  Device device_;
};

template <class S>
class CudaEvaluator final : public Evaluator<S> {
 public:
  // Makes the engines of o.algos (the inverse dynamics' when o.algos is 0), others
  // on first use, so that an eval of id alone runs on a model that fd cannot take.
  CudaEvaluator(const ModelTpl<S>& model, const EvalOptions& o)
      : model_(model), nv_(model.nv()), fallback_(o.fallback_aba) {
    bo_.backend = BackendKind::Cuda;
    bo_.strategy = o.strategy;
    bo_.max_batch = static_cast<Index>(o.max_batch);
    const AlgoSet algos = o.algos ? o.algos : algo_bit(Algo::Id);
    if (algos & algo_bit(Algo::Fd)) fd_engine(o.fd);
    if (algos & algo_bit(Algo::Mass)) mass_engine();
    if (algos & (algo_bit(Algo::Id) | algo_bit(Algo::Bias))) id_engine();
  }

  BatchStatus run(Algo algo, FdMethod fd_method, const BatchIn<S>& in, S* out) override {
    const Index B = static_cast<Index>(in.count);
    using V = BatchView<const S>;
    if (algo == Algo::Fd) {
      cuda::CudaForwardDynamics<S>& engine = fd_engine(fd_method);
      const FdBatchIn<S> fd{V::aos(in.q, nv_, B), V::aos(in.qd, nv_, B), V::aos(in.tau, nv_, B), nullptr};
      cuda::FdBatchStatus st;
      try {
        st = engine.compute(fd, BatchView<S>::aos(out, nv_, B));
      } catch (const BackendError& e) {
        throw DataError(e.what());
      }
      fallbacks_ = static_cast<std::size_t>(st.fell_back);
      BatchStatus status;
      if (!st.ok()) {
        status.instance = static_cast<std::size_t>(st.first_instance);
        status.status = Status{st.first_dof};
      }
      return status;
    }
    if (algo == Algo::Mass) {
      // out: each instance's nv x nv matrix, row-major (nv^2 entries, instance-major)
      try {
        mass_engine().compute(V::aos(in.q, nv_, B), BatchView<S>::aos(out, nv_ * nv_, B));
      } catch (const BackendError& e) {
        throw DataError(e.what());
      }
      return {};
    }
    require_id_or_bias(algo);
    cuda::CudaInverseDynamics<S>& engine = id_engine();
    const IdBatchIn<S> id =
        id_inputs<S>(algo, V::aos(in.q, nv_, B), V::aos(in.qd, nv_, B), V::aos(in.qdd, nv_, B), &zero_);
    try {
      engine.compute(id, BatchView<S>::aos(out, nv_, B));
    } catch (const BackendError& e) {
      throw DataError(e.what());
    }
    return {};
  }

  // the engine's algorithm (Auto: its choice by shape)
  FdMethod fd_method(FdMethod requested) const override {
    switch (fd_engine(requested).algorithm()) {
      case cuda::FdAlgorithm::Aba: return FdMethod::Aba;
      case cuda::FdAlgorithm::Parallel: return FdMethod::Parallel;
      case cuda::FdAlgorithm::Hybrid: return FdMethod::Hybrid;
      default: return FdMethod::Jsi;
    }
  }

  // the engine's strategy with "-host": thread-host, aba_thread-host, crba_thread-host, ...
  std::size_t fallbacks() const override { return fallbacks_; }

  std::string strategy(Algo algo, FdMethod fd) const override {
    if (algo == Algo::Fd && fd_engine(fd).fallback_aba()) return "jsi_thread+aba-host";
    const std::string s = algo == Algo::Fd     ? fd_engine(fd).strategy()
                          : algo == Algo::Mass ? mass_engine().strategy()
                                               : id_engine().strategy();
    return s + "-host";
  }
  bool exact(Algo, FdMethod) const override { return false; }  // other compiler, FMA contraction

  // The batch on the device, the engine's compute_async() per call; the row's
  // strategy is the engine's without "-host". Null for --fd hybrid and for the
  // fallback to the ABA (compute() only: it must see which instances failed).
  std::unique_ptr<ResidentBatch<S>> resident(Algo algo, FdMethod fd, const BatchIn<S>& in) override {
    using Device = typename CudaResidentBatch<S>::Device;
    const std::size_t width = output_width(algo, nv_);
    if (algo == Algo::Fd) {
      cuda::CudaForwardDynamics<S>& e = fd_engine(fd);
      if (e.algorithm() == cuda::FdAlgorithm::Hybrid) return nullptr;  // compute_async: cudaErrorNotSupported
      if (e.fallback_aba()) return nullptr;
      return std::make_unique<CudaResidentBatch<S>>(
          e.strategy(), "the forward dynamics", nv_, in.count, std::vector<const S*>{in.q, in.qd, in.tau},
          width, true, e.device_bytes(), [&e](const Device& d) {
            return e.compute_async(FdBatchIn<S>{d.in[0], d.in[1], d.in[2], nullptr}, d.out, d.failed, d.stream);
          });
    }
    if (algo == Algo::Mass) {
      cuda::CudaMassMatrix<S>& e = mass_engine();
      return std::make_unique<CudaResidentBatch<S>>(
          e.strategy(), "the mass matrix", nv_, in.count, std::vector<const S*>{in.q}, width, false,
          e.device_bytes(), [&e](const Device& d) { return e.compute_async(d.in[0], d.out, d.stream); });
    }
    require_id_or_bias(algo);
    cuda::CudaInverseDynamics<S>& e = id_engine();
    std::vector<const S*> inputs{in.q, in.qd};  // (id: and qdd; bias: qdd = 0, the zero)
    if (algo == Algo::Id) inputs.push_back(in.qdd);
    return std::make_unique<CudaResidentBatch<S>>(
        e.strategy(), "the inverse dynamics", nv_, in.count, inputs, width, false, e.device_bytes(),
        [&e, algo](const Device& d) {
          return e.compute_async(id_inputs<S>(algo, d.in[0], d.in[1], d.in[2], d.zero), d.out, d.stream);
        });
  }

 private:
  // (const: made on first use, kept in mutable members)
  cuda::CudaInverseDynamics<S>& id_engine() const {
    if (!id_) {
      try {
        id_ = std::make_unique<cuda::CudaInverseDynamics<S>>(model_, bo_);
      } catch (const BackendError& e) {
        // no device, recursion beyond 64 DoF, scan-world, buffers beyond device memory
        throw UsageError(e.what(), false);
      }
    }
    return *id_;
  }

  cuda::CudaMassMatrix<S>& mass_engine() const {
    if (!mass_) {
      BackendOptions bo = bo_;
      bo.strategy = IdStrategy::Auto;  // --strategy is inverse dynamics' (as on the CPU backends)
      try {
        mass_ = std::make_unique<cuda::CudaMassMatrix<S>>(model_, bo);
      } catch (const BackendError& e) {
        // no device, buffers beyond device memory
        throw UsageError(e.what(), false);
      }
    }
    return *mass_;
  }

  // the engine of one --fd method (made on first use)
  cuda::CudaForwardDynamics<S>& fd_engine(FdMethod method) const {
    auto& fd = fd_[static_cast<int>(method)];
    if (!fd) {
      BackendOptions bo = bo_;
      bo.strategy = IdStrategy::Auto;  // --strategy is inverse dynamics' (as on the CPU backends)
      cuda::FdAlgorithm algo = cuda::FdAlgorithm::Auto;
      switch (method) {
        case FdMethod::Auto: algo = cuda::FdAlgorithm::Auto; break;
        case FdMethod::Aba: algo = cuda::FdAlgorithm::Aba; break;
        case FdMethod::Jsi: algo = cuda::FdAlgorithm::Jsi; break;
        case FdMethod::Hybrid: algo = cuda::FdAlgorithm::Hybrid; break;
        case FdMethod::Parallel: algo = cuda::FdAlgorithm::Parallel; break;
      }
      try {
        fd = std::make_unique<cuda::CudaForwardDynamics<S>>(model_, bo, algo);
        if (fallback_ && method == FdMethod::Jsi) fd->set_fallback_aba(true);
      } catch (const BackendError& e) {
        // no device, buffers beyond device memory, a method the model cannot take
        throw UsageError(std::string("--fd ") + fd_method_name(method) + ": " + e.what(), false);
      }
    }
    return *fd;
  }

  const ModelTpl<S>& model_;
  Index nv_;
  BackendOptions bo_;
  S zero_ = 0;  // qdd of bias
  mutable std::unique_ptr<cuda::CudaInverseDynamics<S>> id_;
  mutable std::unique_ptr<cuda::CudaMassMatrix<S>> mass_;
  mutable std::unique_ptr<cuda::CudaForwardDynamics<S>> fd_[5];  // by FdMethod
  bool fallback_ = false;        // --fallback aba: the Jsi engine's set_fallback_aba
  std::size_t fallbacks_ = 0;    // instances the last fd run() computed by the ABA instead
};

}  // namespace

template <class S>
std::unique_ptr<Evaluator<S>> make_cuda_evaluator(const ModelTpl<S>& model, const EvalOptions& options) {
  return std::make_unique<CudaEvaluator<S>>(model, options);
}
template std::unique_ptr<Evaluator<double>> make_cuda_evaluator(const ModelTpl<double>&, const EvalOptions&);
template std::unique_ptr<Evaluator<float>> make_cuda_evaluator(const ModelTpl<float>&, const EvalOptions&);

}  // namespace scandyn::cli

#endif  // SCANDYN_HAS_CUDA
