// kernels/inverse_dynamics.cu: batched inverse dynamics, one thread per instance.
//
// The layers of scandyn/cuda/inverse_dynamics.hpp: rnea_instance (the header) ->
// id_instances_kernel -> launch_id_instances -> CudaInverseDynamics (host staging
// for compute(): the pinned chunked pipeline of host_pipeline.hpp for the thread
// strategy, or the pageable copies of staging.hpp; the plain launch for
// compute_async()).
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdlib>
#include <memory>
#include <stdexcept>
#include <string>
#include <type_traits>

#include "scandyn/cuda/device.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "host_pipeline.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {

using detail::check;
using detail::copy;
using detail::plan;
using detail::Staging;

// ---- the model as kernel parameter --------------------------------------------

namespace {

// Body i of the parameter block: the model's (user frames), or its z-axis body
// (zm: z_axis_model(model)), with its frame's rotation and kTurned.
template <class S, int C>
void set_body(ThreadModelParams<S, C, Body<S>>& p, const ModelTpl<S>& model, const ZAxisModel<S>*, Index i) {
  p.body[i] = model.bodies[i];
}
template <class S, int C>
void set_body(ThreadModelParams<S, C, ZJointBody<S>>& p, const ModelTpl<S>& model, const ZAxisModel<S>* zm, Index i) {
  const JointType t = model.bodies[i].type;
  if (t != JointType::Revolute && t != JointType::Prismatic)
    throw BackendError("backend 'cuda': joint '" +
                       (i < Index(model.joint_names.size()) ? model.joint_names[i] : "of body " + std::to_string(i)) +
                       "' is neither revolute nor prismatic; the z-axis thread-per-instance kernels take 1-DoF joints only");
  p.body[i] = z_joint_body(zm->model.bodies[i]);
  p.frame_Q[i] = zm->frame_Q[i];
  if (zm->turned[i]) p.flags[i] |= kTurned;
}

// The model's parameter block; slots_out receives ThreadModel::branch_slots().
template <int C, class Bd, class S>
ThreadModelParams<S, C, Bd> make_params(const ModelTpl<S>& model, Index& slots_out) {
  ThreadModelParams<S, C, Bd> p{};  // zero-filled, unused bodies included
  const Index n = model.nv();
  p.nv = n;
  p.a0 = base_acceleration(model.gravity);
  std::unique_ptr<ZAxisModel<S>> zm;  // z-axis bodies: the re-expressed model
  if constexpr (ThreadModelParams<S, C, Bd>::z_axes) {
    try {
      zm = std::make_unique<ZAxisModel<S>>(z_axis_model(model));
    } catch (const std::invalid_argument& e) {
      throw BackendError(std::string("backend 'cuda': ") + e.what());
    }
  }
  Index last_branch_child[C];  // (nv) highest-numbered branch child of each body, -1 if none
  for (Index i = 0; i < n; ++i) {
    const Index parent = model.bodies[i].parent;
    if (parent >= i || parent < -1)
      throw BackendError("backend 'cuda': body " + std::to_string(i) + " has parent " + std::to_string(parent) +
                         " (bodies must come after their parent)");
    set_body(p, model, zm.get(), i);
    last_branch_child[i] = -1;
    if (parent >= 0) p.ancestors[i] = p.ancestors[parent] | (1ull << parent);
    if (parent < 0) p.flags[i] |= kParentIsBase;
    else if (parent == i - 1) p.flags[i] |= kParentIsPrev;
    else p.flags[parent] |= kStacked, last_branch_child[parent] = i;  // a child that is not the next body
  }
  // branch slots: branch points in increasing order, each to the lowest slot whose
  // last range ended at or before it (interval colouring: as many slots as ranges overlap)
  Index slot_end[C];  // (slots) the last range's end, h(p), of each slot in use
  Index slots = 0;
  for (Index i = 0; i < n; ++i) {
    const Index h = last_branch_child[i];
    if (h < 0) continue;
    p.flags[h] |= kOpensSlot;
    Index s = 0;
    while (s < slots && slot_end[s] > i) ++s;
    if (s == slots) ++slots;
    slot_end[s] = h;
    p.flags[i] |= static_cast<int>(s) << kSlotShift;
  }
  slots_out = slots;
  return p;
}

// The bodies past a floating base as a fixed-base model, the world standing in for
// the base: what the kernels walk (ThreadModelParams::floating). Throws BackendError
// for a multi-DoF joint past the base (a spherical joint), which the kernels do not take.
template <class S>
ModelTpl<S> bodies_past_floating_base(const ModelTpl<S>& model) {
  ModelTpl<S> m;
  m.name = model.name;
  m.gravity = model.gravity;
  for (Index i = 1; i < model.nbodies(); ++i) {
    Body<S> b = model.bodies[i];
    const std::string joint = i < Index(model.joint_names.size()) ? model.joint_names[i] : "of body " + std::to_string(i);
    if (joint_nv(b.type) != 1)
      throw BackendError("backend 'cuda': model '" + model.name + "' has the spherical joint '" + joint +
                         "'; the thread-per-instance kernels take a floating base and revolute or prismatic "
                         "joints past it (use the serial or openmp backend)");
    b.parent -= 1;  // the base (body 0) becomes -1
    m.bodies.push_back(b);
    m.joint_names.push_back(joint);
  }
  set_joint_offsets(m);
  return m;
}

// The parameter block of a model with or without a floating base.
template <int C, class Bd, class S>
ThreadModelParams<S, C, Bd> make_model_params(const ModelTpl<S>& model, Index& slots_out) {
  if (!model.floating_base()) return make_params<C, Bd>(model, slots_out);
  ThreadModelParams<S, C, Bd> p = make_params<C, Bd>(bodies_past_floating_base(model), slots_out);
  p.floating = 1;
  p.base = model.bodies[0];
  return p;
}

}  // namespace

// The model travels as a kernel parameter: sm_70+ with CUDA >= 12.1 take 32764 bytes
// of parameters per launch (the views and pointers after it need < 256).
static_assert(sizeof(ThreadModelParams<double, kMaxThreadDofs>) + 256 <= 32764,
              "ThreadModelParams no longer fits in a kernel parameter block");
static_assert(sizeof(ThreadModelParams<double, kMaxThreadDofs, ZJointBody<double>>) + 256 <= 32764,
              "ThreadModelParams (z-axis) no longer fits in a kernel parameter block");

template <class S, class Bd>
ThreadModel<S, Bd>::ThreadModel(const ModelTpl<S>& model)
    : nv_(model.nv()), nq_(model.nq()), floating_(model.floating_base()) {
  if (model.multi_dof() && !floating_)
    throw BackendError("backend 'cuda': model '" + model.name + "' has the spherical joint '" +
                       first_multi_dof_joint(model) +
                       "'; the thread-per-instance kernels take a floating base and revolute or prismatic "
                       "joints (use the serial or openmp backend)");
  if (floating_ && !kFloatingKernels<S, Bd>)
    throw BackendError("backend 'cuda': model '" + model.name +
                       "' has a floating base, which the thread-per-instance kernels take in z-axis joint "
                       "frames only (ZThreadModel)");
  const Index bodies = floating_ ? model.nbodies() - 1 : nv_;  // the kernels' bodies (past the base)
  if (bodies > kMaxThreadDofs)
    throw BackendError("backend 'cuda': model '" + model.name + "' has " + std::to_string(bodies) +
                       (floating_ ? " joints past its floating base" : " DoF") +
                       "; the thread-per-instance kernels take at most " + std::to_string(kMaxThreadDofs) +
                       " (per-thread state is sized at compile time)");
  if (bodies <= 8) capacity_ = 8, params_ = make_model_params<8, Bd>(model, branch_slots_);
  else if (bodies <= 16) capacity_ = 16, params_ = make_model_params<16, Bd>(model, branch_slots_);
  else if (bodies <= 32) capacity_ = 32, params_ = make_model_params<32, Bd>(model, branch_slots_);
  else capacity_ = 64, params_ = make_model_params<64, Bd>(model, branch_slots_);
}

// ---- kernel and launch ---------------------------------------------------------

// One thread per instance b < B: the RNEA of instance b.
// kFloating: the model has a floating base (rnea_instance's kFloating).
template <class S, int C, class Bd, bool kFloating>
__global__ void __launch_bounds__(kIdInstancesBlock)
    id_instances_kernel(const __grid_constant__ ThreadModelParams<S, C, Bd> model, const IdBatchIn<S> batch_in,
                        const BatchView<S> tau_out) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= batch_in.q.batch) return;
  const Force<S>* fext = batch_in.fext ? batch_in.fext + b * (kFloating ? model_nbodies(model) : model.nv) : nullptr;
  // double keeps the forward pass's transforms for iiwa-sized models (H100: 4.1e9
  // against 3.4e9 evaluations/s recomputing them; float gains nothing from it)
  constexpr bool kKeepXup = sizeof(S) == 8 && C <= 8;
  rnea_instance<S, C, kKeepXup, (C * sizeof(S) <= 64), kThreadTrig<S>, Bd, kFloating>(
      model, instance_column(batch_in.q, b), instance_column(batch_in.qd, b), instance_column(batch_in.qdd, b), fext,
      instance_column(tau_out, b));
}

template <class S, class Bd>
cudaError_t launch_id_instances(const ThreadModel<S, Bd>& model, const IdBatchIn<S>& batch_in,
                                const BatchView<S>& tau_out, cudaStream_t stream) {
  const Index B = batch_in.q.batch;
  if (B < 0 || batch_in.qd.batch != B || batch_in.qdd.batch != B || tau_out.batch != B) return cudaErrorInvalidValue;
  if (B == 0 || model.nv() == 0) return cudaSuccess;
  if (!batch_in.q.data || !batch_in.qd.data || !batch_in.qdd.data || !tau_out.data) return cudaErrorInvalidValue;
  const unsigned blocks = static_cast<unsigned>((static_cast<long long>(B) + kIdInstancesBlock - 1) / kIdInstancesBlock);
  visit_compiled_capacity(model.params(), [&](const auto& params) {
    using P = std::decay_t<decltype(params)>;
    if (floating_kernels(model)) {
      if constexpr (kFloatingCapacity<P::capacity>)
        id_instances_kernel<S, P::capacity, Bd, kFloatingKernels<S, Bd>>
            <<<blocks, kIdInstancesBlock, 0, stream>>>(params, batch_in, tau_out);
    } else {
      id_instances_kernel<S, P::capacity, Bd, false>
          <<<blocks, kIdInstancesBlock, 0, stream>>>(params, batch_in, tau_out);
    }
  });
  return cudaGetLastError();
}

// ---- the engine -------------------------------------------------------------------

template <class S>
CudaInverseDynamics<S>::CudaInverseDynamics(const ModelTpl<S>& model, const BackendOptions& options)
    : nv_(model.nv()), nq_(model.nq()), nb_(model.nbodies()), max_batch_(options.max_batch) {
  if (options.strategy == IdStrategy::ScanWorld)
    throw BackendError(
        "backend 'cuda': strategy 'scan-world' is not available on this backend "
        "(use auto, recursion or scan-local)");
  if (max_batch_ < 0) throw BackendError("backend 'cuda': max_batch " + std::to_string(max_batch_) + " is negative");
  // a spherical joint: the link scans (the thread kernels take a floating base only)
  const bool threads_take = model.one_dof_past_base();
  const IdStrategy strategy = options.strategy != IdStrategy::Auto ? options.strategy
                              : threads_take ? choose_id_strategy(BackendKind::Cuda, nv_, max_batch_, 1)
                                             : IdStrategy::ScanLocal;
  if (strategy == IdStrategy::Recursion && nv_ > kMaxThreadDofs)
    throw BackendError("backend 'cuda': model '" + model.name + "' has " + std::to_string(nv_) +
                       " DoF; strategy 'recursion' (a thread per instance) takes at most " +
                       std::to_string(kMaxThreadDofs) + " (use auto or scan-local)");
  // q, qd, qdd, tau (nq scalars each, detail::stage_inputs) and fext (6 nq) for max_batch instances
  staging_ = std::make_unique<detail::StagingBuffer>(max_batch_, nv_, sizeof(S) == 4 ? "float" : "double",
                                                     "q, qd, qdd, tau and fext",
                                                     10 * static_cast<std::size_t>(nq_) * sizeof(S));
  device_ = staging_->device();
  if (strategy == IdStrategy::ScanLocal) scan_ = std::make_unique<IdScanPlan<S>>(model, max_batch_);
  else thread_ = std::make_unique<ZThreadModel<S>>(model), require_floating_capacity(*thread_, model.name);
  bytes_ = staging_->bytes() + (scan_ ? scan_->device_bytes() : 0);
  // the pinned host path: the thread kernels, one per instance, take a chunk as a sub-batch
  if (thread_ && detail::host_staging_from_env() == host_staging::Mode::Pinned) {
    pipeline_ = std::make_unique<detail::HostPipeline>();
  }
}

template <class S>
CudaInverseDynamics<S>::~CudaInverseDynamics() = default;

template <class S>
std::size_t CudaInverseDynamics<S>::host_ring_bytes() const {
  return pipeline_ ? pipeline_->ring_bytes() : 0;
}

template <class S>
int CudaInverseDynamics<S>::host_ring_allocations() const {
  return pipeline_ ? pipeline_->allocations() : 0;
}

template <class S>
cudaError_t CudaInverseDynamics<S>::compute_async(const IdBatchIn<S>& in, const BatchView<S>& tau,
                                                  cudaStream_t stream) {
  return scan_ ? scan_->launch(in, tau, stream) : launch_id_instances(*thread_, in, tau, stream);
}

template <class S>
void CudaInverseDynamics<S>::compute(const IdBatchIn<S>& in, const BatchView<S>& tau) {
  check_batch(in, tau, max_batch_);
  const Index B = in.q.batch;
  const Index nv = nv_;
  if (B == 0 || nv == 0) return;
  // staging buffers: nq x max_batch scalars each, then the wrenches
  const std::size_t cap = static_cast<std::size_t>(nq_) * max_batch_;
  // (both paths: a tau view whose entries overlap is refused here)
  const Staging stau = plan(tau, nv, cap, true, "tau");
  if (pipeline_) return compute_pinned(in, tau);
  S* const buffer = static_cast<S*>(staging_->data());
  const cudaStream_t stream = staging_->stream();
  S* const dtau = buffer + 3 * cap;

  // copy in, in whatever layout keeps the copies few
  const detail::StagedInputs<S> d = detail::stage_inputs<S>({in.q, in.qd, in.qdd}, {"q", "qd", "qdd"}, in.fext,
                                                            {nq_, nv, nv}, nb_, cap, buffer, stream);
  // run
  const IdBatchIn<S> din{d.in[0], d.in[1], d.in[2], d.fext};
  const BatchView<S> dtau_view = stau.device_view(dtau, B);
  check(compute_async(din, dtau_view, stream), scan_ ? "launching the link scans" : "launching id_instances_kernel");
  // copy out: tau's entries only
  check(copy(stau, tau, nv, dtau, cudaMemcpyDeviceToHost, stream), "copying tau to the host");
  check(cudaStreamSynchronize(stream), scan_ ? "running the link scans" : "running id_instances_kernel");
}

// The pinned path (host_pipeline.hpp): per chunk, q, qd, qdd packed in the layout
// their host views suggest (host_staging::choose_layout), fext verbatim, and tau.
template <class S>
void CudaInverseDynamics<S>::compute_pinned(const IdBatchIn<S>& in, const BatchView<S>& tau) {
  namespace hs = host_staging;
  const Index B = in.q.batch, nv = nv_;
  const detail::PackedBatchInputs<S, IdBatchIn<S>> inputs(in, nq_, nv, nb_);
  const hs::Layout ltau = hs::choose_layout(tau, nv, true);
  const auto layout = [&](Index n) {
    detail::SlotLayout L;
    inputs.add_to(L, n);                                 // arrays 0-3
    L.add(hs::packed_entries(ltau, nv, n) * sizeof(S));  // 4: tau
    return L;
  };
  const std::size_t per_instance = inputs.bytes_per_instance() + static_cast<std::size_t>(nv) * sizeof(S);
  const auto pack = [&](const detail::HostChunk& c) { inputs.pack(c); };
  const auto launch = [&](const detail::HostChunk& c, cudaStream_t stream) {
    return launch_id_instances(*thread_, inputs.device_batch(c),
                               hs::packed_view(c.device_array<S>(4), ltau, nv, c.range.count), stream);
  };
  const auto unpack = [&](const detail::HostChunk& c) {
    hs::unpack(c.host_array<const S>(4), ltau, tau, nv, c.range, 0);
  };
  pipeline_->run(B, per_instance, max_batch_, layout, pack, launch, unpack,
                 "launching id_instances_kernel", "running id_instances_kernel");
}

// ---- the bias forces ----------------------------------------------------------------

template <class S>
CudaBiasForces<S>::CudaBiasForces(const ModelTpl<S>& model, const BackendOptions& options) : id_(model, options) {
  zero_device_ = static_cast<S*>(detail::device_malloc(sizeof(S), [](std::size_t free_bytes, std::size_t) {
    return "backend 'cuda': the bias forces' zero qdd needs " + std::to_string(sizeof(S)) + " bytes; " +
           std::to_string(free_bytes) + " are free";
  }));
  check(cudaMemset(zero_device_, 0, sizeof(S)), "cudaMemset");
}

template <class S>
CudaBiasForces<S>::~CudaBiasForces() {
  if (zero_device_) cudaFree(zero_device_);
}

template <class S>
void CudaBiasForces<S>::compute(const BiasBatchIn<S>& in, const BatchView<S>& h) {
  id_.compute(IdBatchIn<S>{in.q, in.qd, BatchView<const S>{&zero_host_, in.q.batch, 0, 0}, in.fext}, h);
}

template <class S>
cudaError_t CudaBiasForces<S>::compute_async(const BiasBatchIn<S>& in, const BatchView<S>& h, cudaStream_t stream) {
  return id_.compute_async(IdBatchIn<S>{in.q, in.qd, BatchView<const S>{zero_device_, in.q.batch, 0, 0}, in.fext}, h,
                           stream);
}

#define SCANDYN_INSTANTIATE(S)                                                                           \
  template class ThreadModel<S>;                                                                         \
  template class ThreadModel<S, ZJointBody<S>>;                                                          \
  template class CudaInverseDynamics<S>;                                                                 \
  template class CudaBiasForces<S>;                                                                      \
  template cudaError_t launch_id_instances(const ThreadModel<S>&, const IdBatchIn<S>&, const BatchView<S>&, \
                                           cudaStream_t);                                                 \
  template cudaError_t launch_id_instances(const ZThreadModel<S>&, const IdBatchIn<S>&, const BatchView<S>&, \
                                           cudaStream_t);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace cuda
}  // namespace scandyn
