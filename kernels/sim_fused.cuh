// kernels/sim_fused.cuh (internal): the simulator's fused step kernel, one thread
// per instance: load the instance's q, qd, tau, run step_instance (the scene's
// integrator and effects, scandyn/sim/integrators.hpp) over the articulated-body
// algorithm (aba_instance, with the implicit integrator's armature on its pivots),
// store q, qd. The state never leaves the device.
//
// The ABA, not the joint-space inertia: it is the serial backend's algorithm (so
// the backends differ by rounding only), faster on the GPU (bench_cuda_fd: iiwa
// 10^7 float 3.3 ms against 4.5), and it stays accurate in float where the
// joint-space inertia's Cholesky does not (a 40-link chain's float rollout drifts
// 5e-2 from the double one in 100 steps with the JSI).
//
// Instantiated per (precision, integrator) in kernels/sim_fused_<S>_<integrator>.cu
// (six translation units, so a parallel build compiles them side by side). Each
// kernel takes about 5 s of nvcc time (sm_90), so not all 2 x 4 x 32 x 3 x 2 are
// compiled; the documented subset (compiled_kernel):
//   - the gravity bit never changes the code: gravity is the base acceleration a0,
//     a value in the kernel parameter (zero when absent), the same arithmetic
//     either way, so a scene's set maps to set & ~kGravity;
//   - float, capacity 8 (the RL robots: iiwa, and anything of up to 8 DoF), models
//     without branch children (ThreadModel::branch_slots() == 0: chains, and
//     chains hanging from the base): every one of the 16 remaining sets for euler
//     and rk4, and the 12 with damping or springs for implicit (implicit without
//     them is euler: effective_integrator), over the chain ABA (kSlots 0): an
//     absent effect costs nothing here, and bench_cuda_sim's effects table
//     measures exactly this case;
//   - everything else (double; float beyond 8 DoF; float branched models of up to
//     8): one kernel per integrator with every joint effect and external wrenches
//     compiled in, over the any-tree ABA (kSlots = C); undeclared effects run with
//     neutral coefficients (d = k = kl = dl = 0, limits -inf / +inf, zero
//     wrenches), which gives the same numbers as the absent effect (test_sim's
//     ZeroCoefficientsEqualAbsentEffects checks that identity on the host) at the
//     cost of a few per-DoF operations.
//   - scenes with contacts: one kernel per (precision, capacity, integrator) with
//     every effect and the contact pass compiled in (kContactKernelSet), over the
//     any-tree ABA; its per-thread scratch (the bodies' poses, twists, wrenches)
//     is C transforms, twists and wrenches in local memory.
// 44 + 3 + 3 x 3 (float) + 4 x 3 (double) = 68 kernels, and 24 with contacts.
// Floating bases (sim_fused_floating_kernel): per (precision, capacity, integrator)
// one kernel without the contact pass and one with it (rk4 with contacts, and
// points that do not walk their paths), plus sim_floating_contacts_kernel per
// (precision, capacity): the contacts of euler and implicit steps, run before the
// step kernel without the pass. With
// SCANDYN_SIM_EFFECT_SETS=0 (CMake option SCANDYN_SIM_EFFECT_SETS=OFF, what
// scripts/test.sh uses on machines without a GPU) only the all-effects any-tree
// kernels: 24 + 24.
#pragma once

#include <cuda_runtime.h>

#include <climits>
#include <type_traits>
#include <utility>

#include "scandyn/cuda/forward_dynamics.hpp"
#include "scandyn/sim/contacts.hpp"
#include "scandyn/sim/integrators.hpp"

#if !defined(SCANDYN_SIM_EFFECT_SETS)
#define SCANDYN_SIM_EFFECT_SETS 1
#endif

namespace scandyn {
namespace sim {
namespace detail {

inline constexpr int kSimBlock = 128;

// The kernel parameter of capacity C: the model as fd_instances_kernel reads it
// (z-axis frames: ZThreadModel), plus the joint coefficients and the implicit
// armature (__grid_constant__: read from the constant bank; about 21 KB at C = 64 in double).
// Bd: the body type of the model view (ZJointBody: the fused step's z-axis frames;
// Body: user frames, for kernels that also run the user-frame derivative routines).
template <class S, int C, class Bd = ZJointBody<S>>
struct SimParams {
  static constexpr int capacity = C;
  cuda::ThreadModelParams<S, C, Bd> model;  // a0 = -g, or zero without gravity
  JointCoefficients<S> coef[C];         // (nv) joint coefficients
  S armature[C];                        // (nv) dt d + dt^2 k (implicit), else unused
  S dt;                                 // time step
  Index branch_slots;                   // ThreadModel::branch_slots(): 0 lets the chain kernels run
};

// The forward dynamics of one instance as the fused step runs it: aba_instance with
// kSlots branch slots (0: models without branch children; C: any model), rolled
// loops (FdKernelChoice's choice for the ABA), the armature on the pivots. Also a
// host function, so that tests run the fused composition without a device.
template <class S, int C, int kSlots, class Bd>
__host__ __device__ __forceinline__ Index fused_forward_dynamics(const cuda::ThreadModelParams<S, C, Bd>& model,
                                                                 const Force<S>* fext, const S* q, const S* qd,
                                                                 const S* tau, const S* armature, S* qdd) {
  return cuda::aba_instance<S, C, false, false, cuda::kThreadTrig<S>, kSlots>(
      model, cuda::DofColumn<const S>{q, 1}, cuda::DofColumn<const S>{qd, 1}, cuda::DofColumn<const S>{tau, 1}, fext,
      cuda::DofColumn<S>{qdd, 1}, armature);
}

// One thread's scratch for the contact pass (capacity C).
template <class S, int C>
struct FusedContactScratch {
  Transform<S> X[C];  // body <- world
  Motion<S> v[C];     // body twists
  Force<S> f[C];      // external + contact wrenches
  S armature[C];      // implicit: the armature + the contacts' diagonal
};

// The forward dynamics of the fused step with contacts: the contact pass
// (contacts.hpp) at (q, qd), its wrenches added to fext (null: none), its
// diagonal to the implicit armature (arm, null for explicit integrators: then no
// look-ahead), then fused_forward_dynamics. readings (P, or null) gets the
// points' contacts and is set to null (rk4: the first stage's). Host and device.
// The contact points' positions are in the model's body frames (z-axis frames for
// a ZJointBody model); fext in the user's, as everywhere: the contact wrenches are
// turned back to the user's frames before they join it (cuda::user_wrench).
template <class S, int C, int kSlots, int CC, class Bd>
__host__ __device__ __forceinline__ Index fused_contact_forward_dynamics(
    const cuda::ThreadModelParams<S, C, Bd>& model, S dt, const ContactSet<S>& cs, const Force<S>* fext,
    FusedContactScratch<S, CC>& w, ContactReading<S>*& readings, const S* q, const S* qd, const S* tau, const S* arm,
    S* qdd) {
  static_assert(CC == C, "the contact scratch has the kernel's capacity");
  const Index n = model.nv;
  for (Index i = 0; i < n; ++i) {
    w.f[i] = Force<S>::zero();
    w.armature[i] = arm ? arm[i] : S(0);
  }
  contact_pass_any(cs, model.body, n, q, qd, 1, arm ? dt : S(0), w.X, w.v, w.f, arm ? w.armature : nullptr, readings);
  for (Index i = 0; i < n; ++i) {
    w.f[i] = cuda::user_wrench(model, i, w.f[i]);
    if (fext) w.f[i] += fext[i];
  }
  readings = nullptr;
  return fused_forward_dynamics<S, C, kSlots>(model, w.f, q, qd, tau, arm ? w.armature : nullptr, qdd);
}

// The steps' failures on the device: failed instance-steps, and the lowest failed
// instance with the DoF at which its forward dynamics stopped, as one key
// (instance << 32 | DoF) so that one atomicMin keeps both. The host reads it into a
// BatchStatus (kernels/simulator_step.cu).
struct StepStatus {
  unsigned long long failed;  // failed instance-steps
  unsigned long long first;   // instance << 32 | DoF of the lowest failed instance; kStepStatusClear.first: none
};
inline constexpr StepStatus kStepStatusClear = {0ull, ~0ull};

__device__ __forceinline__ void record_step_failure(StepStatus* status, Index b, Index dof) {
  atomicAdd(&status->failed, 1ull);
  atomicMin(&status->first, (static_cast<unsigned long long>(b) << 32) | static_cast<unsigned>(dof));
}

// A recorded DoF with this bit set: the state at that DoF is not finite after the
// step (Failure::NonFinite), rather than a failed pivot there.
inline constexpr Index kNonFiniteDof = Index(1) << 30;

// Arguments of one launch (device pointers).
template <class S>
struct FusedArgs {
  S* q;                      // (nv x B) SoA, q[i * B + b]
  S* qd;                     // (nv x B)
  BatchView<const S> tau;    // (nv x B) any strides; data null: zero torques
  const Force<S>* wrenches;  // external wrenches of instance b at wrenches + b * wrench_stride, or null
  long long wrench_stride;   // nv (per-step buffer) or 0 (the constant ones)
  Index batch;               // B
  StepStatus* status;        // the failures (record_step_failure)
  ContactSet<S> contacts;    // contacts (kContacts): points and obstacles in device memory
  ContactReading<S>* readings;  // (B x P) the step's contacts, or null without contacts
  // The floating-base step's contacts from sim_floating_contacts_kernel (launch_fused_floating), or null:
  S* contact_tau;            // (nv x B) the contacts' generalized forces, added to tau
  S* contact_armature;       // (B x nv) implicit: the armature with the contacts' diagonal, instance b's at b * nv
};

template <class S, int C, unsigned E, Integrator I, int kSlots>
__global__ void __launch_bounds__(kSimBlock, sizeof(S) == 4 ? 4 : 1)
    sim_fused_kernel(const __grid_constant__ SimParams<S, C> p, const FusedArgs<S> a) {
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= a.batch) return;
  const Index n = p.model.nv;
  const long long B = a.batch;
  S q[C], qd[C], tau[C];                        // the instance's state and torques
  S tw[C], qdd[C];                              // StepScratch: tau + effects, FD's result
  S qs[I == Integrator::Rk4 ? C : 1], qds[I == Integrator::Rk4 ? C : 1];  // rk4 stages
  S aq[I == Integrator::Rk4 ? C : 1], aqd[I == Integrator::Rk4 ? C : 1];
SCANDYN_SIM_UNROLL
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;
    q[i] = a.q[i * B + b];
    qd[i] = a.qd[i * B + b];
    tau[i] = a.tau.data ? a.tau.at(i, b) : S(0);
  }
  const Force<S>* fext = (E & kExternal) ? a.wrenches + b * a.wrench_stride : nullptr;
  FusedContactScratch<S, (E & kContacts) ? C : 1> cw;
  ContactReading<S>* readings = (E & kContacts) ? a.readings + b * a.contacts.npoints : nullptr;
  auto fd = [&](const S* qa, const S* qda, const S* t, const S* arm, S* out) -> Index {
    if constexpr ((E & kContacts) != 0) {
      return fused_contact_forward_dynamics<S, C, kSlots>(p.model, p.dt, a.contacts, fext, cw, readings, qa, qda, t,
                                                           arm, out);
    } else {
      return fused_forward_dynamics<S, C, kSlots>(p.model, fext, qa, qda, t, arm, out);
    }
  };
  const StepScratch<S> w{tw, qdd, qs, qds, aq, aqd};
  const Index failed = step_instance<E, I, C>(n, p.dt, p.coef, p.armature, q, qd, tau, w, fd);
  if (failed >= 0) {
    record_step_failure(a.status, static_cast<Index>(b), failed);
    return;
  }
  Index nonfinite = -1;  // the first DoF whose new state is not finite
SCANDYN_SIM_UNROLL
  for (Index i = 0; i < C; ++i) {
    if (i >= n) continue;
    a.q[i * B + b] = q[i];
    a.qd[i * B + b] = qd[i];
    if (nonfinite < 0 && !(isfinite(q[i]) && isfinite(qd[i]))) nonfinite = i;
  }
  if (nonfinite >= 0) record_step_failure(a.status, static_cast<Index>(b), nonfinite | kNonFiniteDof);
}

// ---- a floating base ------------------------------------------------------------
// The fused step of a model with a floating base and revolute / prismatic joints
// past it (cuda::ThreadModelParams::floating): step_instance_at (integrators.hpp:
// euler, implicit or rk4 on the configuration manifold, the base's quaternion
// advanced through the exponential map, as on the CPU) over aba_instance's
// floating-base kernel (kFloating, any tree: kSlots = C), one thread per instance.
// Every joint effect and external wrenches are compiled in (neutral coefficients
// and zero wrenches where the scene has none); the contact pass runs on the
// kernel's own model (FloatingThreadPath: z-axis frames past the base, the points
// turned into them at setup), for euler and implicit steps of points that walk their
// paths in sim_floating_contacts_kernel before the step (generalized forces and the
// implicit diagonal per instance), otherwise in the step kernel (kContacts:
// floating_contacts, generalized forces, or wrenches turned back to the user's
// frames where they join fext, which aba_instance turns again: external_wrench).

// The floating-base kernel's arguments beside FusedArgs (device memory).
template <class S>
struct FloatingArgs {
  const Body<S>* bodies;             // (nbodies) the model's bodies: joint types, q / qd offsets, user frames
  const JointCoefficients<S>* coef;  // (nv) joint coefficients (the base's neutral)
  const S* armature;                 // (nv) implicit: dt d + dt^2 k, else null
};

// One thread's scratch for the floating-base contact pass (capacity C: C + 1 bodies, C + 6 DoFs).
template <class S, int C>
struct FloatingContactScratch {
  Transform<S> X[C + 1];  // body <- world
  Motion<S> v[C + 1];     // body twists
  Force<S> f[C + 1];      // external + contact wrenches (user frames; ContactSet::walk_paths off)
  S armature[C + 6];      // implicit: the armature + the contacts' diagonal
  S tau[C + 6];           // the joint forces + the contacts' generalized forces (walk_paths on)
};

// The floating-base thread model as the contact pass walks it (the path interface
// of ContactBodyPath, scandyn/sim/contacts.hpp), in the kernels' frames: path body 0
// is the base (model.base, its free joint; its transform computed once per pass),
// path body k >= 1 the kernels' body k - 1 (model.body: a z-axis frame, its sine and
// cosine by kThreadTrig, as the ABA's), read from the kernel parameter. Path bodies
// are numbered as the model's (a contact point's body), the DoFs as the step's (the
// base's 6 first); q and qd with the base's entries first.
template <class S, int C>
struct FloatingThreadPath {
  const cuda::ThreadModelParams<S, C, ZJointBody<S>>& model;
  const S* q;
  const S* qd;
  Transform<S> X0;  // the base's Xup (base <- world)
  __host__ __device__ FloatingThreadPath(const cuda::ThreadModelParams<S, C, ZJointBody<S>>& m, const S* q_,
                                         const S* qd_)
      : model(m), q(q_), qd(qd_), X0(joint_transform_at(m.base, q_)) {}
  __host__ __device__ Index parent(Index j) const { return j == 0 ? Index(-1) : model.body[j - 1].parent + 1; }
  __host__ __device__ Transform<S> xup(Index j) const {
    return j == 0 ? X0 : joint_transform<cuda::kThreadTrig<S>>(model.body[j - 1], q[6 + j]);
  }
  __host__ __device__ Motion<S> motion(Index j) const {
    if (j == 0) return joint_motion_at(model.base, qd);
    return joint_motion(model.body[j - 1], qd[5 + j]);
  }
  template <class Turn, class F>
  __host__ __device__ void for_each_column(Index j, Turn&& turn, const Vec3<S>& lever, F&& f) const {
    if (j == 0) {
      for (int c = 0; c < 6; ++c) f(Index(c), contact_column(model.base, c, turn, lever));
    } else {
      f(Index(5 + j), contact_column(model.body[j - 1], 0, turn, lever));
    }
  }
};

// The contacts of one floating-base forward dynamics, a function of its own
// (__noinline__: inlined, its code made nvcc stop inlining the step's whole forward
// dynamics into the kernel, a call with 768 bytes of spills around the ABA; called,
// it keeps its registers to itself). The contact pass on FloatingThreadPath (the
// points in the kernels' frames). With cs.walk_paths (a few points: feet) the
// contacts become generalized forces added to tau (nv) into w.tau, and fext is left
// as it is: no per-body wrench array in the thread's memory, whose traffic made the
// step 2.5x slower than without contacts; otherwise body wrenches, turned to the
// user's frames and added to fext (nb, null: none) into w.f. arm (nv, null for
// explicit integrators) plus the contacts' diagonal into w.armature (h = dt when arm
// is given). tau, fext, arm then point at what the ABA reads. readings as
// add_contact_wrenches.
template <class S, int C>
__host__ __device__ __noinline__ void floating_contacts(const cuda::ThreadModelParams<S, C, ZJointBody<S>>& model,
                                                        const ContactSet<S>& cs, S dt, const S* q, const S* qd,
                                                        const S*& tau, const Force<S>*& fext, const S*& arm,
                                                        FloatingContactScratch<S, C>& w, ContactReading<S>*& readings) {
  const Index nb = model.nv + 1, nv = model.nv + 6;
  if (arm)
    for (Index i = 0; i < nv; ++i) w.armature[i] = arm[i];
  const FloatingThreadPath<S, C> path(model, q, qd);
  const S h = arm ? dt : S(0);
  S* const armature = arm ? w.armature : nullptr;
  if (cs.walk_paths) {
    for (Index i = 0; i < nv; ++i) w.tau[i] = tau[i];
    contact_pass_on_any(path, cs, nb, h, w.X, w.v, static_cast<Force<S>*>(nullptr), armature, readings, w.tau);
    tau = w.tau;
  } else {
    for (Index i = 0; i < nb; ++i) w.f[i] = Force<S>::zero();
    contact_pass_on_any(path, cs, nb, h, w.X, w.v, w.f, armature, readings);
    for (Index i = 0; i < nb; ++i) {
      if (i > 0) w.f[i] = cuda::user_wrench(model, i - 1, w.f[i]);
      if (fext) w.f[i] += fext[i];
    }
    fext = w.f;
  }
  readings = nullptr;
  if (arm) arm = w.armature;
}

// The forward dynamics of the floating-base fused step: the contact pass at (q, qd)
// when the scene has contact points (its wrenches added to fext, null: none; its
// diagonal to the implicit armature arm, null for explicit integrators), then
// aba_instance with kFloating. readings as for fused_contact_forward_dynamics. Host
// and device.
template <class S, int C, bool kContacts = true>
__host__ __device__ __forceinline__ Index fused_floating_forward_dynamics(
    const cuda::ThreadModelParams<S, C, ZJointBody<S>>& model, const FloatingArgs<S>& fa, S dt,
    const ContactSet<S>& cs, const Force<S>* fext, FloatingContactScratch<S, C>& w, ContactReading<S>*& readings,
    const S* q, const S* qd, const S* tau, const S* arm, S* qdd) {
  if (kContacts && cs.npoints > 0)
    floating_contacts(model, cs, dt, q, qd, tau, fext, arm, w, readings);
  return cuda::aba_instance<S, C, false, false, cuda::kThreadTrig<S>, C, false, ZJointBody<S>, true>(
      model, cuda::DofColumn<const S>{q, 1}, cuda::DofColumn<const S>{qd, 1}, cuda::DofColumn<const S>{tau, 1}, fext,
      cuda::DofColumn<S>{qdd, 1}, arm);
}

// The per-set chain kernels: float, capacity 8, with SCANDYN_SIM_EFFECT_SETS.
template <class S, int C>
constexpr bool kPerSetKernels = SCANDYN_SIM_EFFECT_SETS && std::is_same<S, float>::value && C == 8;

// The one kernel per (S, C, I) that runs scenes with contacts: every effect
// compiled in, over the any-tree ABA (undeclared effects with neutral
// coefficients, as the all-effects kernel).
inline constexpr unsigned kContactKernelSet = kJointEffects | kExternal | kContacts;

// Does the kernel of effect set e with kSlots branch slots exist for (S, C, I)?
// (the header comment's subset)
template <class S, int C, Integrator I>
constexpr bool compiled_kernel(unsigned e, int slots) {
  if (e & kGravity) return false;
  if (e & kContacts) return e == kContactKernelSet && slots == C;
  const bool all_effects_tree = e == (kJointEffects | kExternal) && slots == C;
  if (kPerSetKernels<S, C> && slots == 0)
    return I == Integrator::Implicit ? (e & kImplicitEffects) != 0 : true;
  return all_effects_tree;
}

// The kernel a scene's effect set runs on (S, C, I), for a model with
// branch_slots branch slots: its own set without gravity over the chain ABA, or
// the all-effects kernel over the any-tree ABA (then the wrenches must point at nv
// zero wrenches when the scene has none). Returns the set; slots gets kSlots.
template <class S, int C, Integrator I>
constexpr unsigned kernel_set(unsigned effects, Index branch_slots, int& slots) {
  if (effects & kContacts) {
    slots = C;
    return kContactKernelSet;
  }
  if (kPerSetKernels<S, C> && branch_slots == 0) {
    slots = 0;
    return effects & ~unsigned(kGravity);
  }
  slots = C;
  return kJointEffects | kExternal;
}

template <class F, unsigned... K>
void for_each_set(F& f, std::integer_sequence<unsigned, K...>) {
  (f(std::integral_constant<unsigned, K>{}), ...);
}

// Launches the fused step for effect set `effects` (a scene's, any of 32) with
// integrator I on `stream`. params: the SimParams of the model's capacity.
template <class S, Integrator I, class Params>
cudaError_t launch_fused_with(const Params& params, unsigned effects, const FusedArgs<S>& args, cudaStream_t stream) {
  constexpr int C = Params::capacity;
  int slots = C;
  const unsigned e = kernel_set<S, C, I>(effects, params.branch_slots, slots);
  const unsigned blocks = static_cast<unsigned>((static_cast<long long>(args.batch) + kSimBlock - 1) / kSimBlock);
  cudaError_t err = cudaErrorInvalidValue;  // a set not compiled for I (never: the front end maps them)
  auto one = [&](auto set) {
    constexpr unsigned E = decltype(set)::value;
    if constexpr (compiled_kernel<S, C, I>(E, 0)) {
      if (e == E && slots == 0) {
        sim_fused_kernel<S, C, E, I, 0><<<blocks, kSimBlock, 0, stream>>>(params, args);
        err = cudaGetLastError();
      }
    }
    if constexpr (compiled_kernel<S, C, I>(E, C)) {
      if (e == E && slots == C) {
        sim_fused_kernel<S, C, E, I, C><<<blocks, kSimBlock, 0, stream>>>(params, args);
        err = cudaGetLastError();
      }
    }
  };
  for_each_set(one, std::make_integer_sequence<unsigned, kEffectSets>{});
  return err;
}

// Instance b's state (q: nq entries, qd: nv) and torques (tau: nv, zeros without
// them) from the SoA state.
template <class S>
__device__ __forceinline__ void load_state_at(const FusedArgs<S>& a, long long b, S* q, S* qd, S* tau, Index nq,
                                              Index nv) {
  const long long B = a.batch;
  for (Index i = 0; i < nq; ++i) q[i] = a.q[i * B + b];
  for (Index i = 0; i < nv; ++i) {
    qd[i] = a.qd[i * B + b];
    tau[i] = a.tau.data ? a.tau.at(i, static_cast<Index>(b)) : S(0);
  }
}

// Instance b's new state (q: nq entries, qd: nv) into the SoA state; a non-finite
// entry recorded as the CPU backends do: the first i < nv with q_i or qd_i not
// finite, then q's last entries.
template <class S>
__device__ __forceinline__ void store_state_at(const FusedArgs<S>& a, long long b, const S* q, const S* qd, Index nq,
                                               Index nv) {
  const long long B = a.batch;
  Index nonfinite = -1;
  for (Index i = 0; i < nv; ++i) {
    a.q[i * B + b] = q[i];
    a.qd[i * B + b] = qd[i];
    if (nonfinite < 0 && !(isfinite(q[i]) && isfinite(qd[i]))) nonfinite = i;
  }
  for (Index i = nv; i < nq; ++i) {
    a.q[i * B + b] = q[i];
    if (nonfinite < 0 && !isfinite(q[i])) nonfinite = i;
  }
  if (nonfinite >= 0) record_step_failure(a.status, static_cast<Index>(b), nonfinite | kNonFiniteDof);
}

// One thread per instance b < B: a step of a floating-base model (the section
// above). State: q (nq = C + 7 at most), qd, tau and the scratch (C + 6) per thread.
// kContacts: the contact pass compiled in (scenes with contact points); without it
// the kernel has no contact code at all, which keeps its registers for the ABA.
template <class S, int C, Integrator I, bool kContacts>
__global__ void __launch_bounds__(kSimBlock, sizeof(S) == 4 ? 4 : 1)
    sim_fused_floating_kernel(const __grid_constant__ SimParams<S, C> p, const FusedArgs<S> a,
                              const FloatingArgs<S> fa) {
  constexpr unsigned E = kJointEffects | kExternal;  // (contacts: fused_floating_forward_dynamics)
  constexpr int V = C + 6, Q = C + 7;
  constexpr bool kRk4 = I == Integrator::Rk4;
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= a.batch) return;
  const Index n = p.model.nv, nv = n + 6, nq = n + 7, nb = n + 1;
  S q[Q], qd[V], tau[V];  // the instance's state and torques
  S tw[V], qdd[V];        // StepScratchAt: tau + effects, FD's result
  S qs[kRk4 ? Q : 1], qds[kRk4 ? V : 1], aq[kRk4 ? V : 1], aqd[kRk4 ? V : 1], theta[kRk4 ? V : 1];  // rk4 stages
  load_state_at(a, b, q, qd, tau, nq, nv);
  const S* armature = fa.armature;
  if (!kContacts && a.contact_tau) {  // the contacts, computed by sim_floating_contacts_kernel
    for (Index i = 0; i < nv; ++i) tau[i] += a.contact_tau[i * a.batch + b];
    if (a.contact_armature) armature = a.contact_armature + b * nv;
  }
  const Force<S>* fext = a.wrenches + b * a.wrench_stride;
  FloatingContactScratch<S, C> cw;
  ContactReading<S>* readings = a.readings ? a.readings + b * a.contacts.npoints : nullptr;
  auto fd = [&](const S* qa, const S* qda, const S* t, const S* arm, S* out) -> Index {
    return fused_floating_forward_dynamics<S, C, kContacts>(p.model, fa, p.dt, a.contacts, fext, cw, readings, qa, qda,
                                                            t, arm, out);
  };
  const StepScratchAt<S> w{tw, qdd, qs, qds, aq, aqd, theta};
  const Index failed =
      step_instance_at<E, I>(fa.bodies, nb, nq, nv, p.dt, fa.coef, armature, q, qd, tau, w, fd);
  if (failed >= 0) {
    record_step_failure(a.status, static_cast<Index>(b), failed);
    return;
  }
  store_state_at(a, b, q, qd, nq, nv);
}

// The contacts of a floating-base step with one forward dynamics per step (euler,
// implicit) when the points walk their paths (ContactSet::walk_paths: a robot's
// feet), in a kernel of their own before the step (one thread per instance b): the
// contact pass at the state the step starts from, on FloatingThreadPath, as
// generalized forces into a.contact_tau (nv x B), and for implicit (h = dt) the
// scene's armature plus the contacts' diagonal into a.contact_armature (B x nv);
// the readings. The step kernel without the contact pass (kContacts false) then
// adds them. Split so, each kernel keeps its registers: the pass inside the step
// kernel cost it 1.5x the step (H200, floating hyq on four feet), mostly through the
// ABA's register allocation, not the pass's arithmetic.
template <class S, int C>
__global__ void __launch_bounds__(kSimBlock)
    sim_floating_contacts_kernel(const __grid_constant__ SimParams<S, C> p, const FusedArgs<S> a,
                                 const FloatingArgs<S> fa, S h) {
  constexpr int V = C + 6, Q = C + 7;
  const long long b = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (b >= a.batch) return;
  const Index n = p.model.nv, nv = n + 6, nq = n + 7, nb = n + 1;
  const long long B = a.batch;
  S q[Q], qd[V], force[V], arm[V];
  for (Index i = 0; i < nq; ++i) q[i] = a.q[i * B + b];
  for (Index i = 0; i < nv; ++i) {
    qd[i] = a.qd[i * B + b];
    force[i] = S(0);
    arm[i] = fa.armature ? fa.armature[i] : S(0);
  }
  ContactReading<S>* readings = a.readings ? a.readings + b * a.contacts.npoints : nullptr;
  contact_pass_on_any(FloatingThreadPath<S, C>(p.model, q, qd), a.contacts, nb, h, static_cast<Transform<S>*>(nullptr),
                      static_cast<Motion<S>*>(nullptr), static_cast<Force<S>*>(nullptr),
                      a.contact_armature ? arm : nullptr, readings, force);
  for (Index i = 0; i < nv; ++i) a.contact_tau[i * B + b] = force[i];
  if (a.contact_armature)
    for (Index i = 0; i < nv; ++i) a.contact_armature[b * nv + i] = arm[i];
}

// ---- joints of any type -----------------------------------------------------------
// The step of a model the thread kernels do not take (spherical joints; a floating
// base with more than kMaxThreadDofs bodies past it): step_instance_at over the
// general path's ABA (aba_general, scandyn/instance/general_instance.hpp), one thread
// per instance, its state and scratch in the GeneralPlan's buffer (thread t
// takes instances t, t + slots, ...). Effects and contacts as the floating-base
// kernel. The GeneralPlan's scratch arrays (GeneralWorkOf) are interleaved across
// the threads (kScalars: every scalar, else by the plan's strides); the step's own
// state and scratch scalars lie contiguous per thread in the plan's extra area
// (GeneralSimScalars: q, qs, then qd, tau and StepScratchAt's arrays and the contacts'
// armature, then the contact pass's nb transforms, twists and wrenches), as
// step_instance_at takes plain pointers.
template <class S>
struct GeneralSimScalars {
  // 2 nq + 9 nv scalars (q, qs; qd tau tw qdd qds aq aqd theta arm) and the contact arrays
  static std::size_t extra_bytes(Index nb, Index nq, Index nv) {
    return static_cast<std::size_t>(2 * nq + 9 * nv) * sizeof(S) +
           static_cast<std::size_t>(nb) * (sizeof(Transform<S>) + sizeof(Motion<S>) + sizeof(Force<S>));
  }
};

template <class S, Integrator I, bool kScalars>
__global__ void __launch_bounds__(cuda::kGeneralBlock)
    sim_general_kernel(const cuda::GeneralArgs<S> g, const FusedArgs<S> a, const FloatingArgs<S> fa, S dt) {
  constexpr unsigned E = kJointEffects | kExternal;  // (contacts: add_contact_wrenches)
  const long long t = static_cast<long long>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= g.slots) return;
  const Index nb = g.nb, nv = g.nv, nq = g.nq;
  const long long B = a.batch;
  const auto gw = [&] {
    if constexpr (kScalars) return g.work_scalars(t);
    else return g.work_strided(t);
  }();
  char* const extra = g.extra_area(t);
  S* const q = reinterpret_cast<S*>(extra);
  S* const qs = q + nq;
  S* const qd = qs + nq;
  S* const tau = qd + nv;
  S* const tw = tau + nv;
  S* const qdd = tw + nv;
  S* const qds = qdd + nv;
  S* const aq = qds + nv;
  S* const aqd = aq + nv;
  S* const theta = aqd + nv;
  S* const carm = theta + nv;
  Transform<S>* const cX = reinterpret_cast<Transform<S>*>(carm + nv);
  Motion<S>* const cv = reinterpret_cast<Motion<S>*>(cX + nb);
  Force<S>* const cf = reinterpret_cast<Force<S>*>(cv + nb);
  const StepScratchAt<S> w{tw, qdd, qs, qds, aq, aqd, theta};
  for (long long b = t; b < B; b += g.slots) {
    load_state_at(a, b, q, qd, tau, nq, nv);
    const Force<S>* const fext = a.wrenches + b * a.wrench_stride;
    ContactReading<S>* readings = a.readings ? a.readings + b * a.contacts.npoints : nullptr;
    auto fd = [&](const S* qa, const S* qda, const S* tt, const S* arm, S* out) -> Index {
      const Force<S>* f = fext;
      if (a.contacts.npoints > 0)
        add_contact_wrenches<true>(a.contacts, g.bodies, nb, nv, dt, qa, qda, f, arm, cX, cv, cf, carm, readings);
      return aba_general(g.bodies, nb, g.a0, gw, qa, qda, tt, out, f, arm);
    };
    const Index failed = step_instance_at<E, I>(g.bodies, nb, nq, nv, dt, fa.coef, fa.armature, q, qd, tau, w, fd);
    if (failed >= 0) {
      record_step_failure(a.status, static_cast<Index>(b), failed);
      continue;
    }
    store_state_at(a, b, q, qd, nq, nv);
  }
}

// The floating-base step of capacity C with integrator I (cudaErrorNotSupported for
// a capacity this build leaves out, cuda::kFloatingCapacity, which the backend
// refuses when it is made: cuda::require_floating_capacity); defined as launch_fused.
template <class S, Integrator I, int C>
cudaError_t launch_fused_floating(const SimParams<S, C>& params, const FusedArgs<S>& args, const FloatingArgs<S>& fa,
                                  cudaStream_t stream)
#if defined(SCANDYN_SIM_FUSED_DEFINE)
{
  if constexpr (cuda::kFloatingCapacity<C>) {
    const unsigned blocks = static_cast<unsigned>((static_cast<long long>(args.batch) + kSimBlock - 1) / kSimBlock);
    // the contacts of euler and implicit steps whose points walk their paths in a kernel
    // of their own, then the step without the pass; otherwise the pass in the step kernel
    const bool contacts = args.contacts.npoints > 0;
    const bool split = contacts && args.contact_tau && I != Integrator::Rk4 && args.contacts.walk_paths;
    FusedArgs<S> step = args;
    if (split) {
      sim_floating_contacts_kernel<S, C><<<blocks, kSimBlock, 0, stream>>>(
          params, args, fa, I == Integrator::Implicit ? params.dt : S(0));
      step.readings = nullptr;
      if (I != Integrator::Implicit) step.contact_armature = nullptr;
    } else {
      step.contact_tau = step.contact_armature = nullptr;
    }
    if (contacts && !split) sim_fused_floating_kernel<S, C, I, true><<<blocks, kSimBlock, 0, stream>>>(params, step, fa);
    else sim_fused_floating_kernel<S, C, I, false><<<blocks, kSimBlock, 0, stream>>>(params, step, fa);
    return cudaGetLastError();
  } else {
    return cudaErrorNotSupported;
  }
}
#else
    ;
#endif

// The fused step of capacity C with integrator I: defined and explicitly
// instantiated in kernels/sim_fused_<S>_<integrator>.cu (which define
// SCANDYN_SIM_FUSED_DEFINE); elsewhere a declaration only, so no other unit
// compiles the kernels again.
template <class S, Integrator I, int C>
cudaError_t launch_fused(const SimParams<S, C>& params, unsigned effects, const FusedArgs<S>& args, cudaStream_t stream)
#if defined(SCANDYN_SIM_FUSED_DEFINE)
{
  return launch_fused_with<S, I>(params, effects, args, stream);
}
#else
    ;
#endif

#define SCANDYN_SIM_FUSED_INSTANTIATE_C(S, I, C)                                                                \
  template cudaError_t launch_fused<S, I, C>(const SimParams<S, C>&, unsigned, const FusedArgs<S>&, cudaStream_t); \
  template cudaError_t launch_fused_floating<S, I, C>(const SimParams<S, C>&, const FusedArgs<S>&,                \
                                                      const FloatingArgs<S>&, cudaStream_t);
// (every capacity, or with SCANDYN_CUDA_ALL_CAPACITIES 0 capacity 8 only:
// cuda::kCompiledCapacity; the launches go through visit_compiled_capacity)
#if SCANDYN_CUDA_ALL_CAPACITIES
#define SCANDYN_SIM_FUSED_INSTANTIATE(S, I)   \
  SCANDYN_SIM_FUSED_INSTANTIATE_C(S, I, 8)    \
  SCANDYN_SIM_FUSED_INSTANTIATE_C(S, I, 16)   \
  SCANDYN_SIM_FUSED_INSTANTIATE_C(S, I, 32)   \
  SCANDYN_SIM_FUSED_INSTANTIATE_C(S, I, 64)
#else
#define SCANDYN_SIM_FUSED_INSTANTIATE(S, I) SCANDYN_SIM_FUSED_INSTANTIATE_C(S, I, 8)
#endif

}  // namespace detail
}  // namespace sim
}  // namespace scandyn
