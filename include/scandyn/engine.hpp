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

struct BackendOptions {
  BackendKind backend = BackendKind::Serial;
  IdStrategy strategy = IdStrategy::Auto;  // inverse dynamics and bias forces
  FdMethod fd_method = FdMethod::Auto;     // forward dynamics
  bool fallback_aba = false;  // forward dynamics by jsi: an instance whose factorisation fails is
                              // computed again by aba (BatchStatus::fell_back counts them)
  int threads = 0;            // OpenMP threads, 0: openmp_threads()
  Index max_batch = 1;        // largest batch compute() will be given
};

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

// Forward dynamics: on serial aba; on openmp the parallel chain forward dynamics for
// unbranched chains from the base of at least 4096 links, else aba; on cuda aba up to
// 64 DoF, parallel for longer chains from the base, jsi (dense) for larger trees.
template <class S>
FdMethod choose_fd_method(BackendKind backend, const ModelTpl<S>& model);

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
// Each throws BackendError naming the value and the accepted names.
BackendKind parse_backend(const std::string& name);
Precision parse_precision(const std::string& name);
IdStrategy parse_strategy(const std::string& name);
FdMethod parse_fd_method(const std::string& name);

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

}  // namespace scandyn
