// scandyn/engine.hpp: one engine API for every algorithm on every backend.
//
//   scandyn::BackendOptions o;
//   o.backend = scandyn::BackendKind::OpenMP;     // Serial, OpenMP or Cuda
//   o.max_batch = B;
//   auto fd = scandyn::make_forward_dynamics<double>(model, o);   // o.fd_method: Auto, Aba, ...
//   scandyn::BatchStatus st = fd->compute(in, qdd);               // host memory
//   if (!st.ok()) std::cerr << st.message() << "\n";
//
// An engine is made once per model, backend and precision (the model must outlive
// it); it owns all scratch for up to max_batch instances and allocates nothing in
// compute(). Every engine computes from host memory with compute(); the CUDA
// engines (scandyn/cuda/*.hpp, the classes the factories return on Cuda) also have
// compute_async() on device memory and a stream. A backend that is not built, a
// device that cannot run, a model the chosen method cannot take and a batch that
// does not fit are a BackendError from the factory or from compute(); nothing falls
// back to another backend silently.
//
// Where each engine lives: the serial and OpenMP engines in cpu_fallback/, the CUDA
// engines in kernels/ (docs/architecture.md).
#pragma once

#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "scandyn/algorithm/fd_check.hpp"
#include "scandyn/batch.hpp"

namespace scandyn {

enum class BackendKind { Serial, OpenMP, Cuda };
enum class Precision { Double, Float };

// How inverse dynamics splits the work; Auto picks by shape (choose_id_strategy).
enum class IdStrategy {
  Auto,
  Recursion,  // one instance at a time per thread (CUDA: one GPU thread per instance)
  ScanLocal,  // scans over links, local-frame affine form
  ScanWorld,  // scans over links, world-frame form (CPU only)
};

// Whether forward dynamics checks its results at run time (scandyn/algorithm/fd_check.hpp):
// per instance, the residual r = ID(q, qd, qdd) - tau in double and the error estimate
// max|M^-1 r| / max(1, max|qdd|), compared with a threshold per precision.
//   Auto  on where the check costs under ~10% of the call (fd_check_enabled)
//   On    every instance of every call
//   Off   never (the result is bit-identical to an engine without the check)
enum class FdCheckMode { Auto, On, Off };

// The serial and OpenMP engines' SIMD path (cpu_fallback/simd_batch.hpp): the
// recursions (inverse dynamics and bias forces by the recursion, the mass matrix, aba)
// run W instances per vector register (W = 4 doubles / 8 floats under AVX2, 8 / 16
// under AVX-512, 2 / 4 with SSE2: the build's target, SCANDYN_NATIVE). Auto takes it
// where it applies (every joint revolute or prismatic; measured faster than the
// scalar recursion on iiwa, hyq, atlas and rope:1000, every algorithm: 1.3-2x with
// SSE2, bench/results/cpu-simd-*.csv); On also throws BackendError for a model it
// cannot take; Off never takes it. Exact (bit-identical to Off) in builds without FMA.
// Ignored on cuda.
enum class CpuSimd { Auto, Off, On };

struct BackendOptions {
  BackendKind backend = BackendKind::Serial;
  IdStrategy strategy = IdStrategy::Auto;  // inverse dynamics and bias forces
  FdMethod fd_method = FdMethod::Auto;     // forward dynamics
  bool fallback_aba = false;  // forward dynamics by jsi: an instance whose factorisation fails is
                              // computed again by aba (BatchStatus::fell_back counts them)
  int threads = 0;            // OpenMP threads, 0: openmp_threads()
  Index max_batch = 1;        // largest batch compute() will be given
  // ---- forward dynamics' run-time check (FdCheckMode; scandyn/algorithm/fd_check_batch.hpp)
  FdCheckMode fd_check = FdCheckMode::Auto;
  // thresholds on the check's error estimate (a relative error of qdd), per precision;
  // the defaults are the accuracy report's budgets (docs/accuracy.md: 0 false positives
  // on 1.6e5 clean random states, every result beyond the budget caught)
  double fd_check_tol_float = fd_check_threshold<float>();    // 1e-4
  double fd_check_tol_double = fd_check_threshold<double>();  // 1e-10
  // With the check on, a flagged instance is computed again (each retry checked again):
  // with fallback_aba (jsi) by the aba in the engine's precision (on cuda: the host's),
  // then with fallback_double (float engines) by the reference aba in double on the host
  // (the model widened exactly), rounded to float. Still flagged: Failure::ResidualTooLarge.
  bool fallback_double = false;  // float engines: flagged instances computed again by the double
                                 // aba (turns an Auto check on; with Off: BackendError)
                                 // (BatchStatus::fell_back counts the instances a retry fixed)
  CpuSimd simd = CpuSimd::Auto;  // serial and openmp: W instances per vector register (CpuSimd)
  // cuda: the devices a batch is sharded across (scandyn/sharded.hpp: contiguous ranges of
  // instances, one engine, stream and memory per device; max_batch stays the whole
  // batch's); empty: the device current at construction only. parse_devices("all")
  // lists every visible device. Other backends refuse a non-empty list.
  std::vector<int> devices;
};

// True when forward dynamics by `method` (resolved) on `backend` for a model of nv DoF
// runs the check under `mode`. Auto: on for jsi from 200 DoF on the CPU backends, where
// one RNEA and two ABA passes in double cost under 10% of the O(nv^2..nv^3) solve
// (bench/results/fd_check_engine_cost-*.csv); off for aba and parallel (the check costs
// 1.2-1.5x an ABA) and on cuda (the check runs on the host there).
bool fd_check_enabled(FdCheckMode mode, BackendKind backend, FdMethod method, Index nv);
// The threshold of the options for precision S.
template <class S>
double fd_check_tol(const BackendOptions& options) {
  return sizeof(S) <= sizeof(float) ? options.fd_check_tol_float : options.fd_check_tol_double;
}

// Thrown for a backend that is not built or cannot run, a model or option an engine
// cannot take, or a batch that does not fit.
class BackendError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Every engine says where and how it computes.
class Engine {
 public:
  virtual ~Engine() = default;
  // the variant actually run, as in benchmark rows: "recursion", "scan-local",
  // "aba", "jsi+aba", "thread", "aba_thread", "crba_block", ...
  virtual std::string strategy() const = 0;
  virtual BackendKind backend() const = 0;
  // True when compute() performs exactly the serial reference's arithmetic (the same
  // functions in the same order), so that its result is bit-identical to it.
  virtual bool exact() const { return false; }
};

template <class S>
class InverseDynamics : public Engine {
 public:
  // tau (nv x B) = RNEA(q, qd, qdd, fext) for every instance, gravity included.
  virtual void compute(const IdBatchIn<S>& in, const BatchView<S>& tau) = 0;
};

template <class S>
class BiasForces : public Engine {
 public:
  // h (nv x B) = RNEA(q, qd, 0, fext) for every instance: Coriolis, centrifugal, gravity.
  virtual void compute(const BiasBatchIn<S>& in, const BatchView<S>& h) = 0;
};

template <class S>
class MassMatrix : public Engine {
 public:
  // M(q) for every instance: nv * nv entries per instance, M(i, j) at entry i * nv + j
  // (BatchView::aos(M, nv * nv, B) is row-major per instance), both triangles written.
  virtual void compute(const BatchView<const S>& q, const BatchView<S>& M) = 0;
};

template <class S>
class ForwardDynamics : public Engine {
 public:
  // qdd (nv x B) = FD(q, qd, tau, fext) for every instance, gravity included. An
  // instance whose pivot is not positive and finite is reported in the status and
  // its qdd left unwritten.
  virtual BatchStatus compute(const FdBatchIn<S>& in, const BatchView<S>& qdd) = 0;
  // the method run (Auto resolved)
  virtual FdMethod method() const = 0;
};

// ---- kinematics: where frames are and how they move ------------------------------
//
// Frames are the model's (ModelTpl::frames: every URDF link, including links merged
// by fixed joints and the root; scandyn/model/frames.hpp finds them by name). The
// world frame is the base's (the URDF root link's).

// How a frame's pose is written.
enum class PoseFormat {
  Matrix,              // 16 entries: the 4 x 4 homogeneous matrix [R p; 0 0 0 1], row-major
  PositionQuaternion,  // 7 entries: p (x, y, z), then the unit quaternion of R (x, y, z, w), w >= 0
};
// (R: the frame's axes in world coordinates, R v maps frame to world coordinates;
// p: the frame's origin in world coordinates.)
SCANDYN_HD constexpr Index pose_width(PoseFormat f) { return f == PoseFormat::Matrix ? 16 : 7; }

// In which axes a frame Jacobian J (6 x nv) is written. Rows [angular; linear]
// (scandyn's spatial order): J qd = [w; v], w the frame's angular velocity and v the
// velocity of its origin. Pinocchio's frame Jacobians are [linear; angular]: its
// rows 0-2 are scandyn's rows 3-5 and the other way around.
enum class FrameReference {
  World,  // world axes (Pinocchio's LOCAL_WORLD_ALIGNED): w and v in world coordinates
  Local,  // the frame's own axes (Pinocchio's LOCAL): R^T w, R^T v
};

struct KinematicsOptions {
  std::vector<Index> frames;  // (F) indices into model.frames, any order, repeats allowed
  PoseFormat pose = PoseFormat::Matrix;
  FrameReference reference = FrameReference::World;
};

template <class S>
class Kinematics : public Engine {
 public:
  // For every instance, from q (nv x B), any of:
  //   poses  F * pose_width entries per instance: frame k's at k * pose_width + e;
  //   J      F * 6 * nv entries per instance: frame k's row r, column j at
  //          (k * 6 + r) * nv + j (each frame's 6 x nv block row-major); columns of
  //          joints that do not move the frame are 0.
  // A view with null data is not computed (its batch size is not checked).
  // BatchView::aos(poses, F * pose_width, B) is the (B, F, 4, 4) C array of Python.
  virtual void compute(const BatchView<const S>& q, const BatchView<S>& poses, const BatchView<S>& J) = 0;
  virtual const KinematicsOptions& options() const = 0;
};

// The factories: the engine of options.backend for the model in precision S (float
// or double). Throw BackendError (backend not in this build, no usable device, a
// model or strategy the backend cannot take, buffers beyond device memory).
template <class S>
std::unique_ptr<InverseDynamics<S>> make_inverse_dynamics(const ModelTpl<S>& model, const BackendOptions& options);
template <class S>
std::unique_ptr<BiasForces<S>> make_bias_forces(const ModelTpl<S>& model, const BackendOptions& options);
template <class S>
std::unique_ptr<MassMatrix<S>> make_mass_matrix(const ModelTpl<S>& model, const BackendOptions& options);
template <class S>
std::unique_ptr<ForwardDynamics<S>> make_forward_dynamics(const ModelTpl<S>& model, const BackendOptions& options);
// Frame poses and Jacobians; also throws BackendError for a frame index outside model.frames.
template <class S>
std::unique_ptr<Kinematics<S>> make_kinematics(const ModelTpl<S>& model, const BackendOptions& options,
                                               const KinematicsOptions& kinematics);

// Hybrid dynamics (Featherstone 2008, 9.2): for each DoF either its acceleration
// (prescribed) or its force is given; computes the rest. The prescribed set is the
// engine's, fixed at construction (prescribed(): nv entries, nonzero = the DoF's
// acceleration is given).
template <class S>
class HybridDynamics : public Engine {
 public:
  // qdd and tau (nv x B each, full vectors) for every instance, gravity included:
  // tau = M qdd + h (- J^T fext) on every row, qdd = in.qdd at prescribed DoFs, tau =
  // in.tau at the others (copied through). An instance whose articulated pivot (of
  // a DoF whose force is given) is not positive and finite is reported in the
  // status and its outputs left unwritten.
  virtual BatchStatus compute(const HybridBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& tau) = 0;
  virtual const std::vector<unsigned char>& prescribed() const = 0;
};

// The hybrid-dynamics engine of options.backend, by choose_hybrid_method (serial and
// openmp: the reference hybrid_dynamics per instance ("recursion"), or the parallel
// chain hybrid dynamics, scandyn/algorithm/chain_hybrid.hpp ("parallel"); cuda: one
// thread per instance up to cuda::kMaxThreadDofs DoF ("aba_thread"), or the chain
// scans on the device, scandyn/cuda/chain_hybrid.hpp ("parallel")). prescribed: nv
// entries. Throws BackendError as the other factories, as choose_hybrid_method, and for
// a prescribed mask whose size is not nv.
// Throws BackendError naming `what` ("hybrid dynamics", ...) and the model's first
// multi-DoF joint when the model has one (a floating base, a spherical joint): what
// takes revolute and prismatic joints only calls it first.
template <class S>
void require_one_dof_joints(const ModelTpl<S>& model, const char* what);

template <class S>
std::unique_ptr<HybridDynamics<S>> make_hybrid_dynamics(const ModelTpl<S>& model,
                                                        const std::vector<unsigned char>& prescribed,
                                                        const BackendOptions& options);

namespace cuda {
// The CUDA backend's one-thread-per-instance kernels take models of up to this many DoF.
inline constexpr Index kMaxThreadDofs = 64;
}  // namespace cuda

// ---- Auto choices: one function per algorithm, shared by every caller ------------

// Inverse dynamics (and bias forces) on the CPU backends: threads over instances
// (the recursion) when there are at least as many instances as threads or fewer
// than 4096 bodies; otherwise the local-frame scan across links. Measured
// crossovers: docs/accuracy-id-scan.md. (On CUDA: one thread per instance up to 64
// DoF, the scan beyond; see scandyn/cuda/inverse_dynamics.hpp.)
IdStrategy choose_id_strategy(BackendKind backend, Index nv, Index batch, int threads);

// Threads per instance from which Auto on openmp runs one long chain by the parallel
// chain forward dynamics (and the hybrid by its chain scans) rather than the ABA per
// instance. The chain scans do 7.3-7.7x the serial ABA's arithmetic on one thread
// (rope:4096, 2x10^4, 10^5, double, one instance, AMD EPYC:
// bench/results/fd-openmp-auto-crossover-amd-epyc-2c.csv) and scale with the threads;
// on the 16-core host of the H100 machine a step of rope:10^4 (10^5) through them took
// 0.7-0.8x (0.8-1.3x) the serial step's time on 8 threads, 0.9-1.2x (1.1-1.2x) on 12,
// 1.0-1.6x (2.0-2.2x) on 16 (docs/scenes.md, "One long chain on OpenMP").
inline constexpr int kChainFdThreadsPerInstance = 16;

// Forward dynamics for `batch` instances (the engine's max_batch) on `threads` threads:
// on serial aba; on openmp the parallel chain forward dynamics for unbranched chains
// from the base of at least 4096 links with at least kChainFdThreadsPerInstance
// threads per instance, else aba (over the instances); on cuda (batch and threads
// unused) aba up to 64 DoF (the thread kernels), aba by the general path for chains of
// up to 128 DoF and for larger trees, parallel for longer chains from the base
// (src/engine/engine.cpp says what was measured).
template <class S>
FdMethod choose_fd_method(BackendKind backend, const ModelTpl<S>& model, Index batch, int threads);

// Hybrid dynamics (make_hybrid_dynamics): Aba (the recursion per instance; on cuda one
// thread per instance, up to cuda::kMaxThreadDofs DoF) or Parallel (the chain scans with
// the prescribed joints rigid, unbranched chains from the base) for `requested`
// (options.fd_method). Auto: on serial and openmp Parallel where choose_fd_method picks
// it for `batch` instances on `threads` threads (openmp, chains of 4096 links and more,
// kChainFdThreadsPerInstance threads per instance), else Aba; on cuda Aba up to
// kMaxThreadDofs DoF, Parallel for longer unbranched chains from the base. Throws
// BackendError for the methods not offered (jsi, hybrid) and, on cuda, for Aba beyond
// kMaxThreadDofs DoF and for a model beyond it that is not an unbranched chain from the
// base (naming the body that branches). Parallel on a model that is not chains is
// refused by the engine itself (naming the body).
template <class S>
FdMethod choose_hybrid_method(BackendKind backend, const ModelTpl<S>& model, FdMethod requested, Index batch,
                              int threads);

// True for an unbranched chain hanging from the base: what the parallel chain
// forward dynamics (and the hybrid) take.
template <class S>
bool is_chain_from_base(const ModelTpl<S>& model);

// Threads the OpenMP backend uses when BackendOptions::threads is 0
// (omp_get_max_threads(); 1 in a build without OpenMP).
int openmp_threads();

// Host threads an engine of this backend runs: 1 on serial and cuda; on openmp
// `threads` when positive, else openmp_threads().
int backend_threads(BackendKind backend, int threads);

// Why a backend cannot run on this machine ("not available in this build", "no
// usable CUDA device: ..."), "" when it can.
std::string backend_unusable(BackendKind backend);

// ---- names: one parse and one to_string per enum -----------------------------
const char* to_string(BackendKind b);  // "serial", "openmp", "cuda"
const char* to_string(Precision p);    // "double", "float"
const char* to_string(IdStrategy s);   // "auto", "recursion", "scan-local", "scan-world"
const char* to_string(FdMethod m);     // "auto", "aba", "jsi", "parallel", "hybrid"
const char* to_string(FdCheckMode m);  // "auto", "on", "off"
// Each throws BackendError naming the value and the accepted names.
BackendKind parse_backend(const std::string& name);
Precision parse_precision(const std::string& name);
IdStrategy parse_strategy(const std::string& name);
FdMethod parse_fd_method(const std::string& name);
FdCheckMode parse_fd_check(const std::string& name);
const char* to_string(CpuSimd s);  // "auto", "off", "on"
CpuSimd parse_cpu_simd(const std::string& name);

// Throws BackendError unless the views describe the same number of instances, at
// most max_batch, with non-null data when there is any.
template <class S>
void check_batch(const IdBatchIn<S>& in, const BatchView<S>& tau, Index max_batch);
template <class S>
void check_batch(const FdBatchIn<S>& in, const BatchView<S>& qdd, Index max_batch);
template <class S>
void check_batch(const BiasBatchIn<S>& in, const BatchView<S>& h, Index max_batch);
template <class S>
void check_batch(const BatchView<const S>& q, const BatchView<S>& M, Index max_batch);
// Throws BackendError for a frame index outside model.frames (every kinematics engine
// checks its options so).
template <class S>
void check_kinematics_options(const ModelTpl<S>& model, const KinematicsOptions& kinematics);
// Kinematics: q and whichever of poses and J has data.
template <class S>
void check_batch(const BatchView<const S>& q, const BatchView<S>& poses, const BatchView<S>& J, Index max_batch);
template <class S>
void check_batch(const HybridBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& tau, Index max_batch);

// ---- derivatives (Carpentier & Mansard 2018; scandyn/algorithm/derivatives.hpp) ----
//
// Output layout: three nv x nv matrices per instance, each a BatchView of nv * nv
// entries, entry e = i * nv + j holding d y_i / d x_j (row i: the output DoF,
// column j: the variable): BatchView::aos(p, nv * nv, B) is row-major per instance,
// as the serial rnea_derivatives / aba_derivatives write; BatchView::soa(p, nv * nv,
// B) puts the instance innermost (CUDA's fast layout); any strides work, e.g. the
// three blocks of one instance next to each other: {p + k * nv * nv, B, 1, 3 * nv * nv}
// for block k. Every entry is written.

template <class S>
struct IdDerivativesOut {
  BatchView<S> dtau_dq;   // (nv * nv x B) d tau / d q
  BatchView<S> dtau_dqd;  // (nv * nv x B) d tau / d qd
  BatchView<S> M;         // (nv * nv x B) d tau / d qdd = M(q)
};

template <class S>
class IdDerivatives : public Engine {
 public:
  // The derivatives of tau = ID(q, qd, qdd, fext) (gravity included) for every instance.
  virtual void compute(const IdBatchIn<S>& in, const IdDerivativesOut<S>& out) = 0;
};

template <class S>
struct FdDerivativesOut {
  BatchView<S> dqdd_dq;    // (nv * nv x B) d qdd / d q
  BatchView<S> dqdd_dqd;   // (nv * nv x B) d qdd / d qd
  BatchView<S> dqdd_dtau;  // (nv * nv x B) d qdd / d tau = M(q)^-1
  BatchView<S> qdd;        // optional (nv x B): qdd = FD(q, qd, tau, fext) itself; data null: not written
};

template <class S>
class FdDerivatives : public Engine {
 public:
  // The derivatives of qdd = FD(q, qd, tau, fext) (by the ABA, gravity included) for
  // every instance. An instance whose articulated pivot (or a pivot of M = L L^T) is
  // not positive and finite is reported in the status, its outputs not meaningful.
  virtual BatchStatus compute(const FdBatchIn<S>& in, const FdDerivativesOut<S>& out) = 0;
};

// Serial and OpenMP: any model; CUDA: a thread per instance, models of up to
// cuda::kMaxThreadDofs DoF (BackendError beyond). options.strategy and fd_method
// must be Auto (one algorithm each).
template <class S>
std::unique_ptr<IdDerivatives<S>> make_id_derivatives(const ModelTpl<S>& model, const BackendOptions& options);
template <class S>
std::unique_ptr<FdDerivatives<S>> make_fd_derivatives(const ModelTpl<S>& model, const BackendOptions& options);

// ---- directional derivatives of forward dynamics (JVP, VJP; O(nv) per instance:
// scandyn/algorithm/directional_derivatives.hpp, scandyn/algorithm/chain_directional.hpp)

template <class S>
class FdDirectionalDerivatives : public Engine {
 public:
  // qdd = FD(in) and dqdd = (dqdd/dq) dq + (dqdd/dqd) dqd + M^-1 dtau (nv x B each, B =
  // in.q.batch). An instance whose articulated pivot is not positive and finite is
  // reported in the status, its outputs not meaningful.
  virtual BatchStatus jvp(const FdBatchIn<S>& in, const BatchView<const S>& dq, const BatchView<const S>& dqd,
                          const BatchView<const S>& dtau, const BatchView<S>& qdd, const BatchView<S>& dqdd) = 0;
  // qdd = FD(in) and, for a weight w on qdd, gq = (dqdd/dq)^T w, gqd = (dqdd/dqd)^T w,
  // gtau = M^-1 w (nv x B each).
  virtual BatchStatus vjp(const FdBatchIn<S>& in, const BatchView<const S>& w, const BatchView<S>& qdd,
                          const BatchView<S>& gq, const BatchView<S>& gqd, const BatchView<S>& gtau) = 0;
};

// Host memory. options.fd_method: Aba (aba_jvp / aba_vjp per instance, threads over
// instances: "aba_jvp"; any model, multi-DoF joints included: q of nq entries, dq and
// gq of nv in the tangent convention of the dense derivatives, fext one wrench per
// body), Parallel (unbranched chains of 1-DoF joints from a fixed base: the chunked
// scans of ChainFdDirectional on the engine's threads: "parallel"; BackendError for
// other models), Auto (Parallel for such chains of 4096 links or more, else Aba). On
// cuda (one device) the scans only, for such chains: Auto or Parallel, a directional
// cuda::ChainFdPlan behind the host views (on device memory call its launch_jvp /
// launch_vjp, scandyn/cuda/chain_fd.hpp); multi-DoF joints are refused there.
template <class S>
std::unique_ptr<FdDirectionalDerivatives<S>> make_fd_directional_derivatives(const ModelTpl<S>& model,
                                                                             const BackendOptions& options);

template <class S>
void check_batch(const IdBatchIn<S>& in, const IdDerivativesOut<S>& out, Index max_batch);
template <class S>
void check_batch(const FdBatchIn<S>& in, const FdDerivativesOut<S>& out, Index max_batch);

// ---- second-order derivatives of inverse dynamics (scandyn/algorithm/second_derivatives.hpp)
//
// Output layout: nv x nv x nv tensors per instance, each a BatchView of nv^3
// entries, entry e = (i * nv + j) * nv + k holding d^2 tau_i / dx_j dy_k:
// BatchView::aos(p, nv * nv * nv, B) is the serial rnea_second_derivatives' dense
// tensor per instance; BatchView::soa(p, nv * nv * nv, B) puts the instance
// innermost (CUDA's fast layout); any strides work. Every entry is written.

template <class S>
struct IdSecondDerivativesOut {
  BatchView<S> d2tau_dq2;    // (nv^3 x B) d^2 tau_i / dq_j dq_k (symmetric in j, k)
  BatchView<S> d2tau_dqd2;   // (nv^3 x B) d^2 tau_i / dqd_j dqd_k (symmetric in j, k)
  BatchView<S> d2tau_dqdqd;  // (nv^3 x B) d^2 tau_i / dq_j dqd_k
  BatchView<S> dM_dq;        // optional (nv^3 x B) d M_ij / dq_k; data null: not written
};

template <class S>
class IdSecondDerivatives : public Engine {
 public:
  // The second derivatives of tau = ID(q, qd, qdd, fext) (gravity included) for every
  // instance: 2 nv dual passes of the first-order recursion per instance.
  virtual void compute(const IdBatchIn<S>& in, const IdSecondDerivativesOut<S>& out) = 0;
};

// Serial and OpenMP: any model of 1-DoF joints; CUDA: a thread per instance, models of
// up to cuda::kMaxThreadDofs DoF (BackendError beyond). Multi-DoF joints (floating
// base, spherical) are refused; options.strategy must be Auto (one algorithm).
template <class S>
std::unique_ptr<IdSecondDerivatives<S>> make_id_second_derivatives(const ModelTpl<S>& model,
                                                                   const BackendOptions& options);
template <class S>
void check_batch(const IdBatchIn<S>& in, const IdSecondDerivativesOut<S>& out, Index max_batch);

// ---- closed kinematic loops (scandyn/algorithm/loops.hpp, loop_solver.hpp) ---------

struct LoopSet;

// Forward dynamics of a tree closed by loops: for every instance qdd (nv) and lambda
// (m = loops.rows()) with M qdd + h = tau + J^T lambda and J qdd + Jdot qd = 0,
// gravity included, exactly (no stabilisation), lambda of minimum norm (redundant
// loop rows are normal: the rank-revealing solve of loop_solver.hpp, one source on
// every backend). The loops are the engine's, fixed at construction.
template <class S>
class ConstrainedForwardDynamics : public Engine {
 public:
  // qdd (nv x B), lambda (m x B). An instance whose mass matrix is not positive
  // definite is reported (Failure::MassMatrixPivot, its DoF) and its outputs left
  // unwritten.
  virtual BatchStatus compute(const FdBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& lambda) = 0;
  // The loop-closure residual of every instance: phi (m x B), the position residual
  // (point loops: point a - point b in base coordinates; welds: 3 rotation rows first),
  // and velocity (m x B), J qd. A view with null data is not computed.
  virtual void residual(const BatchView<const S>& q, const BatchView<const S>& qd, const BatchView<S>& phi,
                        const BatchView<S>& velocity) = 0;
  virtual Index rows() const = 0;  // m: constraint rows (3 per point loop, 6 per weld)
};

// Serial and OpenMP: any size (dense per instance, O(nv^3 + m^3)); cuda: one thread
// per instance for small loop systems (scandyn/cuda/constrained_dynamics.hpp).
// The loops must outlive the engine's construction only (they are copied). Throws
// BackendError as the other factories, and for a model with multi-DoF joints.
template <class S>
std::unique_ptr<ConstrainedForwardDynamics<S>> make_constrained_forward_dynamics(const ModelTpl<S>& model,
                                                                                 const LoopSet& loops,
                                                                                 const BackendOptions& options);
template <class S>
void check_batch(const FdBatchIn<S>& in, const BatchView<S>& qdd, const BatchView<S>& lambda, Index max_batch);

}  // namespace scandyn
