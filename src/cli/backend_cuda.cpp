// src/cli/backend_cuda.cpp: the CUDA backend of `scandyn eval` and `scandyn bench`.
//
// id and bias (= id with qdd = 0) run through the library's CUDA inverse-dynamics
// engine (scandyn/cuda/inverse_dynamics.hpp): one GPU thread per instance up to
// 64 DoF, scans across links beyond (or as --strategy says):
//   run()       eval's chunks and bench's "thread-host" row: host buffers,
//               CudaInverseDynamics::compute() (copies in, kernel, copy out, sync);
//   resident()  bench's "thread" row: the batch copied once to device memory in the
//               engine's fast layout (instance innermost), compute_async() on a stream.
// fd runs through the CUDA forward-dynamics engine (scandyn/cuda/forward_dynamics.hpp)
// by the --fd method (one engine per method): jsi (one GPU thread per instance up
// to 64 DoF, CRBA per block and cuSOLVER's batched Cholesky beyond), aba (one
// thread per instance, up to 64 DoF), parallel and hybrid (unbranched chains, link
// scans), auto (the engine's choice); run() only (bench's "<strategy>-host" row),
// CudaForwardDynamics::compute(), whose first failed factorisation becomes the
// BatchStatus that eval and bench report as for the CPU backends. Each engine is
// made when the evaluator is, if its algorithms are among EvalOptions::algos, or on
// first use.
// Which algorithms this backend computes is its AlgoSet in the table of backend.cpp.
#include "backend.hpp"

#if SCANDYN_HAS_CUDA

#include <cuda_runtime_api.h>

#include <stdexcept>
#include <vector>

#include "cli.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"

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
  // the table's AlgoSet keeps other algorithms away from this backend
  if (algo != Algo::Id && algo != Algo::Bias)
    throw std::logic_error(std::string("backend 'cuda' was asked for --algo ") + algo_name(algo));
}

// The batch in device memory, structure of arrays (entry (i, b) at [i * B + b]).
template <class S>
class CudaResidentBatch final : public ResidentBatch<S> {
 public:
  CudaResidentBatch(cuda::CudaInverseDynamics<S>& engine, Algo algo, const BatchIn<S>& in)
      : engine_(engine), nv_(engine.nv()), B_(static_cast<Index>(in.count)) {
    const std::size_t n = static_cast<std::size_t>(nv_) * in.count;
    const int arrays = algo == Algo::Id ? 4 : 3;  // q, qd, (qdd), tau
    const std::size_t bytes = (arrays * n + 1) * sizeof(S);
    cudaError_t err = cudaMalloc(reinterpret_cast<void**>(&buffer_), bytes);
    if (err != cudaSuccess) {
      const std::string why = cuda_error_text(err);
      buffer_ = nullptr;
      std::size_t free_bytes = 0, total_bytes = 0;
      (void)cudaMemGetInfo(&free_bytes, &total_bytes);
      (void)cudaGetLastError();
      throw UsageError("backend 'cuda': the device-resident batch of " + std::to_string(in.count) +
                           " instances needs " + std::to_string(bytes) + " bytes of device memory besides the " +
                           std::to_string(engine.device_bytes()) + " bytes of the engine's staging buffers; " +
                           std::to_string(free_bytes) + " bytes are free (cudaMalloc: " + why + ")",
                       false);
    }
    try {
      fill(algo, in, n, arrays);
    } catch (...) {
      release();
      throw;
    }
  }

  ~CudaResidentBatch() override { release(); }
  CudaResidentBatch(const CudaResidentBatch&) = delete;
  CudaResidentBatch& operator=(const CudaResidentBatch&) = delete;

  void launch() override { check(engine_.compute_async(in_, tau_, stream_), "launching the inverse dynamics"); }
  void wait() override { check(cudaStreamSynchronize(stream_), "running the inverse dynamics"); }

  void read(S* out) override {
    wait();
    const std::size_t n = static_cast<std::size_t>(nv_) * B_;
    std::vector<S> soa(n);
    check(cudaMemcpyAsync(soa.data(), tau_.data, n * sizeof(S), cudaMemcpyDeviceToHost, stream_),
          "copying tau to the host");
    check(cudaStreamSynchronize(stream_), "copying tau to the host");
    for (Index b = 0; b < B_; ++b)
      for (Index i = 0; i < nv_; ++i)
        out[static_cast<std::size_t>(b) * nv_ + i] = soa[static_cast<std::size_t>(i) * B_ + b];
  }

  std::string strategy() const override { return engine_.strategy(); }  // "thread" or "scan-local"

 private:
  // the stream, the inputs transposed into the buffer, tau set to NaN, the views
  void fill(Algo algo, const BatchIn<S>& in, std::size_t n, int arrays) {
    check(cudaStreamCreateWithFlags(&stream_, cudaStreamNonBlocking), "cudaStreamCreateWithFlags");
    S* const q = buffer_;
    S* const qd = q + n;
    S* const tau = qd + n;
    S* const qdd = algo == Algo::Id ? tau + n : nullptr;
    S* const zero = buffer_ + arrays * n;
    // inputs transposed to the engine's fast layout; tau starts as NaN (all bits
    // set). Everything on stream_, which does not synchronise with the legacy
    // default stream, and waited for before soa is refilled.
    std::vector<S> soa(n);
    auto upload = [&](const S* aos, S* dev) {
      for (Index b = 0; b < B_; ++b)
        for (Index i = 0; i < nv_; ++i)
          soa[static_cast<std::size_t>(i) * B_ + b] = aos[static_cast<std::size_t>(b) * nv_ + i];
      check(cudaMemcpyAsync(dev, soa.data(), n * sizeof(S), cudaMemcpyHostToDevice, stream_),
            "copying the batch to the device");
      check(cudaStreamSynchronize(stream_), "copying the batch to the device");
    };
    upload(in.q, q);
    upload(in.qd, qd);
    if (qdd) upload(in.qdd, qdd);
    check(cudaMemsetAsync(zero, 0, sizeof(S), stream_), "cudaMemsetAsync");
    check(cudaMemsetAsync(tau, 0xff, n * sizeof(S), stream_), "cudaMemsetAsync");
    check(cudaStreamSynchronize(stream_), "cudaMemsetAsync");
    using V = BatchView<const S>;
    in_ = id_inputs<S>(algo, V::soa(q, nv_, B_), V::soa(qd, nv_, B_), V::soa(qdd, nv_, B_), zero);
    tau_ = BatchView<S>::soa(tau, nv_, B_);
  }

  void release() noexcept {
    if (stream_) {
      cudaStreamSynchronize(stream_);
      cudaStreamDestroy(stream_);
    }
    if (buffer_) cudaFree(buffer_);
    stream_ = nullptr;
    buffer_ = nullptr;
  }

  cuda::CudaInverseDynamics<S>& engine_;
  Index nv_, B_;
  S* buffer_ = nullptr;  // q, qd, tau, qdd (id only), each nv x B; then one zero
  cudaStream_t stream_ = nullptr;
  IdBatchIn<S> in_;
  BatchView<S> tau_;
};

template <class S>
class CudaEvaluator final : public Evaluator<S> {
 public:
  // Makes the engines of o.algos (the inverse dynamics' when o.algos is 0), others
  // on first use, so that an eval of id alone runs on a model that fd cannot take.
  CudaEvaluator(const ModelTpl<S>& model, const EvalOptions& o) : model_(model), nv_(model.nv()) {
    bo_.backend = BackendKind::Cuda;
    bo_.strategy = o.strategy;
    bo_.max_batch = static_cast<Index>(o.max_batch);
    const AlgoSet algos = o.algos ? o.algos : algo_bit(Algo::Id);
    if (algos & algo_bit(Algo::Fd)) fd_engine(o.fd);
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
      BatchStatus status;
      if (!st.ok()) {
        status.instance = static_cast<std::size_t>(st.first_instance);
        status.status = Status{st.first_dof};
      }
      return status;
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

  std::string strategy(Algo algo, FdMethod fd) const override {
    return (algo == Algo::Fd ? fd_engine(fd).strategy() : id_engine().strategy()) + "-host";
  }
  bool exact(Algo, FdMethod) const override { return false; }  // other compiler, FMA contraction

  // id and bias only: bench times fd through run() alone (its "jsi_thread-host" row)
  std::unique_ptr<ResidentBatch<S>> resident(Algo algo, FdMethod, const BatchIn<S>& in) override {
    if (algo == Algo::Fd) return nullptr;
    require_id_or_bias(algo);
    return std::make_unique<CudaResidentBatch<S>>(id_engine(), algo, in);
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
  mutable std::unique_ptr<cuda::CudaForwardDynamics<S>> fd_[5];  // by FdMethod
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
