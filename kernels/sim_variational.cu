// kernels/sim_variational.cu: the simulator's variational step on the GPU
// (kernels/sim_variational.cuh): one thread per instance runs variational_dense_step
// of scandyn/sim/variational_instance.hpp, the routine the serial and OpenMP steps
// run for models of up to kVariationalExactMaxDofs DoFs.
#include "sim_variational.cuh"

#include <algorithm>
#include <string>
#include <vector>

#include "scandyn/engine.hpp"
#include "staging.hpp"

namespace scandyn {
namespace sim {
namespace detail {
namespace {

using cuda::detail::check;

constexpr int kVariationalBlock = 64;

// One thread per instance b: its q, qd, tau into local arrays, one variational
// step (every effect the step takes compiled in: undeclared effects have neutral
// coefficients, gravity is a0's value, wrenches are read only when declared, which
// gives the numbers of the absent effects), q, qd back; a failure is recorded (the
// DoF, with kNotConvergedDof for Newton's) and the instance keeps its state.
template <class S, int C>
__global__ void __launch_bounds__(kVariationalBlock)
    sim_variational_kernel(const VariationalArgs<S> v, const FusedArgs<S> a) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= a.batch) return;
  const Index n = v.model.nv;
  const long long B = a.batch;
  S q[C], qd[C], tau[C];  // the instance's state and torques
  for (Index i = 0; i < n; ++i) {
    q[i] = a.q[i * B + b];
    qd[i] = a.qd[i * B + b];
    tau[i] = a.tau.data ? a.tau.at(i, b) : S(0);
  }
  VariationalThreadScratch<S, C> scratch;  // local memory
  const VariationalScratch<S> w = scratch.view(n, v.matrices, b, B);
  const Force<S>* fx = v.external ? a.wrenches + b * a.wrench_stride : nullptr;
  const VariationalResult res = variational_dense_step<kVariationalEffects>(v.model, w, v.dt, v.coef, q, qd, tau, fx);
  if (res.failed_dof >= 0) {
    record_step_failure(a.status, static_cast<Index>(b),
                        res.failed_dof | (res.failure == Failure::NotConverged ? kNotConvergedDof : Index(0)));
    return;
  }
  Index nonfinite = -1;  // the first DoF whose new state is not finite
  for (Index i = 0; i < n; ++i) {
    a.q[i * B + b] = q[i];
    a.qd[i * B + b] = qd[i];
    if (nonfinite < 0 && !(isfinite(q[i]) && isfinite(qd[i]))) nonfinite = i;
  }
  if (nonfinite >= 0) record_step_failure(a.status, static_cast<Index>(b), nonfinite | kNonFiniteDof);
}

template <class S, int C>
cudaError_t launch_variational(const VariationalArgs<S>& v, const FusedArgs<S>& a, cudaStream_t stream) {
  const unsigned blocks = static_cast<unsigned>((a.batch + kVariationalBlock - 1) / kVariationalBlock);
  if constexpr (cuda::kCompiledCapacity<C>) {
    sim_variational_kernel<S, C><<<blocks, kVariationalBlock, 0, stream>>>(v, a);
    return cudaGetLastError();
  } else {
    return cudaErrorNotSupported;  // (refused at construction, require_compiled_capacity)
  }
}

}  // namespace

static_assert(kVariationalCudaMaxDofs <= cuda::kMaxThreadDofs && kVariationalCudaMaxDofs <= kVariationalExactMaxDofs,
              "the CUDA variational step: capacities up to 64, the exact Jacobian");

template <class S>
void VariationalSimPlan<S>::require_capacity(const SimSetup<S>& setup) {
  if (setup.model.nv() > kVariationalCudaMaxDofs)
    throw BackendError(variational_cuda_refusal(setup.model.name, setup.model.nv()));
}

template <class S>
VariationalSimPlan<S>::VariationalSimPlan(const SimSetup<S>& setup) {
  require_capacity(setup);
  const Index n = setup.model.nv();
  capacity_ = n <= 8 ? 8 : n <= 16 ? 16 : n <= 32 ? 32 : 64;
  cuda::require_compiled_capacity(capacity_, "the variational step", setup.model.name);
  const std::size_t nn = static_cast<std::size_t>(n);
  const std::size_t body_bytes = nn * sizeof(Body<S>);
  const std::size_t coef_bytes = nn * sizeof(JointCoefficients<S>);
  const std::size_t matrix_bytes = 6 * nn * nn * static_cast<std::size_t>(setup.batch) * sizeof(S);
  auto up = [](std::size_t x) { return (x + 255) / 256 * 256; };
  const std::size_t bytes = up(body_bytes) + up(coef_bytes) + matrix_bytes;
  raw_ = cuda::detail::device_malloc(bytes, [&](std::size_t free_bytes, std::size_t) {
    return "backend 'cuda': the variational step of " + std::to_string(setup.batch) + " instances of a " +
           std::to_string(n) + "-DoF model needs " + std::to_string(bytes) +
           " bytes of device memory (six nv x nv Newton matrices per instance); " + std::to_string(free_bytes) +
           " are free";
  });
  char* p = static_cast<char*>(raw_);
  auto* bodies = reinterpret_cast<Body<S>*>(p);
  auto* coef = reinterpret_cast<JointCoefficients<S>*>(p + up(body_bytes));
  S* matrices = reinterpret_cast<S*>(p + up(body_bytes) + up(coef_bytes));
  check(cudaMemcpy(bodies, setup.model.bodies.data(), body_bytes, cudaMemcpyHostToDevice), "copying the bodies");
  check(cudaMemcpy(coef, setup.coef.data(), coef_bytes, cudaMemcpyHostToDevice), "copying the joint coefficients");
  const Motion<S> a0 = base_acceleration(setup.model.gravity);
  const Motion<S> a0_rest = base_acceleration(Vec3<S>{S(0), S(0), S(0)});
  args_ = {VariationalModel<S>{bodies, n, a0, a0_rest, true}, coef, matrices, setup.dt,
           (setup.effects & kExternal) != 0};
}

template <class S>
VariationalSimPlan<S>::~VariationalSimPlan() {
  if (raw_) cudaFree(raw_);
}

template <class S>
cudaError_t VariationalSimPlan<S>::launch(const FusedArgs<S>& a, cudaStream_t stream) const {
  if (a.batch == 0) return cudaSuccess;
  switch (capacity_) {
    case 8: return launch_variational<S, 8>(args_, a, stream);
    case 16: return launch_variational<S, 16>(args_, a, stream);
    case 32: return launch_variational<S, 32>(args_, a, stream);
    default: return launch_variational<S, 64>(args_, a, stream);
  }
}

template class VariationalSimPlan<float>;
template class VariationalSimPlan<double>;

}  // namespace detail
}  // namespace sim
}  // namespace scandyn
