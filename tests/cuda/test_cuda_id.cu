// Batched inverse dynamics on the GPU, one thread per instance (CudaInverseDynamics)
// against the serial double reference scandyn::rnea.
//
// Every instance of every batch is compared: max |tau - ref| / max(1, max |ref|) over
// the instance's DoFs (scandyn::rel_err) must be <= 1e-10 in double and 1e-4 in float
// on the robots (float: the reference runs on the float-rounded inputs, so only the
// arithmetic is measured). Outputs start as NaN, so an entry the kernel never wrote
// fails; with strided output layouts the gaps between entries hold a sentinel that
// must survive compute(). Tests that need a device skip with "no CUDA device: ...";
// the model checks and the no-device error run everywhere.
#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <random>
#include <string>
#include <type_traits>
#include <variant>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/cuda/device.hpp"
#include "cuda_test_util.hpp"
#include "scandyn/cuda/inverse_dynamics.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

using test::aos;
using test::Layout;
using test::pack;
using test::random_layout;
using test::robot;
using test::soa;

// ---- one batch against the reference -------------------------------------------

// B random instances of md: inputs as doubles exactly representable in S.
template <class S>
struct Batch {
  Index nv, B;
  std::vector<double> q, qd, qdd;     // (nv x B), entry (i, b) at i * B + b
  std::vector<Force<double>> fext;    // (B x nv)
  Batch(const Model& md, Index B_, unsigned seed) : nv(md.nv()), B(B_) {
    test::random_exact_batch<S>(nv, B, seed, q, qd, qdd, fext);
  }
  // instance b's reference torques
  void reference(const Model& md, Data& d, Index b, bool with_fext, std::vector<double>& tau) const {
    std::vector<double> qi(nv), qdi(nv), qddi(nv);
    for (Index i = 0; i < nv; ++i) {
      qi[i] = q[static_cast<std::size_t>(i) * B + b];
      qdi[i] = qd[static_cast<std::size_t>(i) * B + b];
      qddi[i] = qdd[static_cast<std::size_t>(i) * B + b];
    }
    tau.assign(nv, 0.0);
    rnea(md, d, qi.data(), qdi.data(), qddi.data(), tau.data(),
         with_fext ? fext.data() + static_cast<std::size_t>(b) * nv : nullptr);
  }
};

// The worst instance error of tau (entries at `out`) against the reference.
template <class S>
double worst_error(const Model& md, const Batch<S>& batch, bool with_fext, const std::vector<S>& tau_buf,
                   const Layout& out) {
  Data d(md, false);
  double worst = 0;
  std::vector<double> ref, ours(batch.nv);
  for (Index b = 0; b < batch.B; ++b) {
    batch.reference(md, d, b, with_fext, ref);
    for (Index i = 0; i < batch.nv; ++i) ours[i] = double(tau_buf[out.at(i, b)]);
    const double e = test::max_rel_err(ours, ref);
    if (!(e <= worst)) worst = e;  // NaN sticks
  }
  return worst;
}

constexpr double kSentinel = 12345.0;

// Runs the engine's host path: inputs in layout lin (one per array), tau in lout.
// Returns the worst instance error; checks the gaps of tau.
template <class S>
double host_run(const Model& md, Index B, bool with_fext, const Layout& lq, const Layout& lqd, const Layout& lqdd,
                const Layout& lout, unsigned seed = 1, IdStrategy strategy = IdStrategy::Auto) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv();
  Batch<S> batch(md, B, seed);
  const bool broadcast = lq.bs == 0 && B > 1;
  if (broadcast) {
    // one state for all instances: the reference uses instance 0 everywhere
    for (auto* v : {&batch.q, &batch.qd, &batch.qdd})
      for (Index i = 0; i < nv; ++i)
        for (Index b = 0; b < B; ++b) (*v)[static_cast<std::size_t>(i) * B + b] = (*v)[static_cast<std::size_t>(i) * B];
  }
  const std::vector<S> q = pack<S>(batch.q, nv, B, lq, 0.0), qd = pack<S>(batch.qd, nv, B, lqd, 0.0),
                       qdd = pack<S>(batch.qdd, nv, B, lqdd, 0.0);
  std::vector<Force<S>> fext = test::cast_wrenches<S>(batch.fext);
  std::vector<S> tau = test::sentinel_output<S>(lout, nv, B, kSentinel);

  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  o.strategy = strategy;
  auto engine = make_inverse_dynamics<S>(m, o);
  const IdStrategy used = strategy == IdStrategy::Auto ? choose_id_strategy(BackendKind::Cuda, nv, B, 1) : strategy;
  EXPECT_EQ(engine->strategy(), used == IdStrategy::ScanLocal ? "scan-local" : "thread");
  EXPECT_EQ(engine->backend(), BackendKind::Cuda);
  const IdBatchIn<S> in{{q.data() + lq.base, B, lq.ds, lq.bs},
                        {qd.data() + lqd.base, B, lqd.ds, lqd.bs},
                        {qdd.data() + lqdd.base, B, lqdd.ds, lqdd.bs},
                        with_fext ? fext.data() : nullptr};
  engine->compute(in, BatchView<S>{tau.data() + lout.base, B, lout.ds, lout.bs});

  EXPECT_EQ(test::gap_writes(tau, lout, nv, B, kSentinel), 0u)
      << "compute() wrote between tau's entries (layout " << lout.name << ")";
  return worst_error<S>(md, batch, with_fext, tau, lout);
}

template <class S>
double host_run_soa(const Model& md, Index B, bool with_fext, IdStrategy strategy = IdStrategy::Auto) {
  const Layout l = soa(md.nv(), B);
  return host_run<S>(md, B, with_fext, l, l, l, l, 1, strategy);
}

// The flags of ThreadModel's parameter block, whatever its capacity.
template <class S>
std::vector<int> flags_of(const cuda::ThreadModel<S>& tm) {
  return std::visit([](const auto& p) { return std::vector<int>(p.flags, p.flags + p.nv); }, tm.params());
}

// The CPU float engine's error on the same inputs: the scale of float rounding for a model.
double cpu_float_error(const Model& md, Index B, bool with_fext) {
  const ModelTpl<float> m = md.cast<float>();
  const Index nv = m.nv();
  Batch<float> batch(md, B, 1);
  std::vector<float> q(batch.q.begin(), batch.q.end()), qd(batch.qd.begin(), batch.qd.end()),
      qdd(batch.qdd.begin(), batch.qdd.end()), tau(static_cast<std::size_t>(nv) * B);
  std::vector<Force<float>> fext = test::cast_wrenches<float>(batch.fext);
  BackendOptions o;
  o.max_batch = B;
  auto engine = make_inverse_dynamics<float>(m, o);
  using V = BatchView<const float>;
  engine->compute({V::soa(q.data(), nv, B), V::soa(qd.data(), nv, B), V::soa(qdd.data(), nv, B),
                   with_fext ? fext.data() : nullptr},
                  BatchView<float>::soa(tau.data(), nv, B));
  return worst_error<float>(md, batch, with_fext, tau, soa(nv, B));
}

}  // namespace

// ---- runs everywhere: the model as the kernels see it, and the errors --------------

TEST(CudaIdModel, CapacityAndFlags) {
  EXPECT_EQ(cuda::ThreadModel<double>(robot("iiwa.urdf")).capacity(), 8);
  EXPECT_EQ(cuda::ThreadModel<float>(robot("hyq.urdf").cast<float>()).capacity(), 16);
  EXPECT_EQ(cuda::ThreadModel<double>(robot("atlas.urdf")).capacity(), 32);
  EXPECT_EQ(cuda::ThreadModel<double>(load_model("chain:8")).capacity(), 8);
  EXPECT_EQ(cuda::ThreadModel<double>(load_model("chain:9")).capacity(), 16);
  EXPECT_EQ(cuda::ThreadModel<double>(load_model("chain:50")).capacity(), 64);
  EXPECT_EQ(cuda::ThreadModel<double>(load_model("chain:64")).capacity(), 64);

  // atlas: torso body 2 has children 3 (next), 10 and 11; legs hang from the base
  const cuda::ThreadModel<double> tm(robot("atlas.urdf"));
  const auto& p = std::get<cuda::ThreadModelParams<double, 32>>(tm.params());
  EXPECT_EQ(p.nv, 30);
  EXPECT_EQ(p.flags[0], cuda::kParentIsBase);
  EXPECT_EQ(p.flags[1], cuda::kParentIsPrev);
  EXPECT_EQ(p.flags[2], cuda::kParentIsPrev | cuda::kStacked);
  EXPECT_EQ(p.flags[10], 0);                 // parent 2, not the previous body
  EXPECT_EQ(p.flags[11], cuda::kOpensSlot);  // ... and the highest-numbered such child
  EXPECT_EQ(p.flags[9], cuda::kParentIsPrev);
  EXPECT_EQ(p.flags[18], cuda::kParentIsBase);
  EXPECT_EQ(p.a0.v.z, 9.81);
  // the flags by their definitions, on trees with many branch points (the branch
  // slots in the bits from kSlotShift: test_cuda_fd's BranchSlots)
  for (const Model& md : {robot("atlas.urdf"), test::random_model(40, 4), load_model("tree:60:2")}) {
    const std::vector<int> flags = flags_of(cuda::ThreadModel<double>(md));
    const Index n = md.nv();
    ASSERT_EQ(static_cast<Index>(flags.size()), n);
    int stacked = 0;
    for (Index i = 0; i < n; ++i) {
      const Index p = md.parent(i);
      bool other_child = false, later_sibling = false;
      for (Index j = i + 2; j < n; ++j) other_child = other_child || md.parent(j) == i;
      for (Index j = i + 1; j < n; ++j) later_sibling = later_sibling || md.parent(j) == p;
      const bool opens = p >= 0 && p != i - 1 && !later_sibling;  // the parent's last branch child
      const int want = (p < 0 ? cuda::kParentIsBase : 0) | (p >= 0 && p == i - 1 ? cuda::kParentIsPrev : 0) |
                       (other_child ? cuda::kStacked : 0) | (opens ? cuda::kOpensSlot : 0);
      EXPECT_EQ(flags[i] & ((1 << cuda::kSlotShift) - 1), want) << md.name << " body " << i;
      stacked += other_child;
    }
    EXPECT_GT(stacked, 0) << md.name;
  }
}

// rnea_instance run on the host (it is __host__ __device__): the kernel's loops,
// flags and stack against the reference, on every machine.
template <class S, bool kKeepXup, bool kUnrolled>
double host_instance_error(const Model& md, Index B, bool with_fext) {
  const ModelTpl<S> m = md.cast<S>();
  const cuda::ThreadModel<S> tm(m);
  const Index nv = m.nv();
  Batch<S> batch(md, B, 11);
  const Layout l = aos(nv, B);  // each instance contiguous
  const std::vector<S> q = pack<S>(batch.q, nv, B, l, 0), qd = pack<S>(batch.qd, nv, B, l, 0),
                       qdd = pack<S>(batch.qdd, nv, B, l, 0);
  std::vector<Force<S>> fext = test::cast_wrenches<S>(batch.fext);
  std::vector<S> tau(l.size, std::numeric_limits<S>::quiet_NaN());
  for (Index b = 0; b < B; ++b) {
    const std::size_t o = static_cast<std::size_t>(b) * nv;
    const Force<S>* f = with_fext ? fext.data() + o : nullptr;
    std::visit(
        [&](const auto& p) {
          using P = std::decay_t<decltype(p)>;
          cuda::rnea_instance<S, P::capacity, kKeepXup, kUnrolled>(p, {q.data() + o, 1}, {qd.data() + o, 1},
                                                                   {qdd.data() + o, 1}, f, {tau.data() + o, 1});
        },
        tm.params());
  }
  return worst_error<S>(md, batch, with_fext, tau, l);
}

TEST(CudaIdModel, DeviceFunctionOnTheHost) {
  std::vector<std::pair<std::string, Model>> models;
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) models.emplace_back(file, robot(file));
  for (const char* spec : {"tree:30:1", "chain:50", "chain:1", "chain:9", "chain:64", "curtain:3:5", "tree:60:2"})
    models.emplace_back(spec, load_model(spec));
  models.emplace_back("random_model(12)", test::random_model(12, 3));
  models.emplace_back("random_model(40)", test::random_model(40, 4));
  models.emplace_back("random_model(64)", test::random_model(64, 5));
  for (const auto& [name, md] : models) {
    SCOPED_TRACE(name);
    for (bool fx : {false, true}) {
      // every variant of the function: transforms kept or recomputed, unrolled or not
      const double ftol = std::max(1e-4, 10 * cpu_float_error(md, 20, fx));
      EXPECT_LE((host_instance_error<double, false, false>(md, 20, fx)), 1e-12);
      EXPECT_LE((host_instance_error<double, false, true>(md, 20, fx)), 1e-12);
      EXPECT_LE((host_instance_error<double, true, true>(md, 20, fx)), 1e-12);
      EXPECT_LE((host_instance_error<float, false, false>(md, 20, fx)), ftol);
      EXPECT_LE((host_instance_error<float, false, true>(md, 20, fx)), ftol);
      EXPECT_LE((host_instance_error<float, true, false>(md, 20, fx)), ftol);
    }
  }
}

TEST(CudaIdErrors, WithoutADevice) {
  // arguments are checked before the device: these hold on every machine
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 4;
  o.strategy = IdStrategy::Recursion;
  try {
    make_inverse_dynamics<double>(load_model("chain:200"), o);
    ADD_FAILURE() << "chain:200 (200 DoF) was accepted by the thread-per-instance strategy";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("at most 64"), std::string::npos) << e.what();
  }
  EXPECT_THROW(cuda::ThreadModel<float>(load_model("chain:65").cast<float>()), BackendError);
  o.strategy = IdStrategy::ScanWorld;
  try {
    make_inverse_dynamics<double>(load_model("chain:3"), o);
    ADD_FAILURE() << "scan-world was accepted";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("scan-world"), std::string::npos) << e.what();
  }
  // auto: a thread per instance up to 64 DoF, the link scans beyond
  EXPECT_EQ(choose_id_strategy(BackendKind::Cuda, 64, 1000000, 1), IdStrategy::Recursion);
  EXPECT_EQ(choose_id_strategy(BackendKind::Cuda, 65, 1, 1), IdStrategy::ScanLocal);
  o.strategy = IdStrategy::Recursion;
  o.max_batch = -1;
  EXPECT_THROW(make_inverse_dynamics<double>(load_model("chain:3"), o), BackendError);
  // no device: a BackendError naming why, never a crash
  o.max_batch = 4;
  if (!test::no_device_reason().empty()) {
    try {
      make_inverse_dynamics<float>(load_model("chain:3").cast<float>(), o);
      ADD_FAILURE() << "an engine was made without a device";
    } catch (const BackendError& e) {
      EXPECT_NE(std::string(e.what()).find("no usable CUDA device"), std::string::npos) << e.what();
    }
  } else {
    auto e = make_inverse_dynamics<float>(load_model("chain:3").cast<float>(), o);
    EXPECT_EQ(e->strategy(), "thread");
  }
}

// ---- on the device ----------------------------------------------------------------

TEST(CudaId, RobotsMatchReference) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) {
    const Model& md = robot(file);
    for (Index B : {1, 31, 32, 33, 1000, 100000}) {
      for (bool fx : {false, true}) {
        if (B == 100000 && fx && std::string(file) != "iiwa.urdf") continue;  // keep the run short
        SCOPED_TRACE(std::string(file) + " B=" + std::to_string(B) + (fx ? " fext" : ""));
        EXPECT_LE(host_run_soa<double>(md, B, fx), 1e-10);
        EXPECT_LE(host_run_soa<float>(md, B, fx), 1e-4);
      }
    }
  }
}

TEST(CudaId, GeneratedTreesAndChains) {
  SKIP_WITHOUT_CUDA_DEVICE();
  // every capacity, its boundaries, branch points (curtain, random trees) and
  // prismatic joints with arbitrary axes (random_model)
  std::vector<std::pair<std::string, Model>> models;
  for (const char* spec : {"tree:30:1", "chain:50", "chain:1", "chain:8", "chain:9", "chain:16", "chain:17",
                           "chain:32", "chain:33", "chain:64", "curtain:3:5", "tree:60:2", "rope:40"})
    models.emplace_back(spec, load_model(spec));
  models.emplace_back("random_model(12)", test::random_model(12, 3));
  models.emplace_back("random_model(40)", test::random_model(40, 4));
  for (const auto& [name, md] : models) {
    for (Index B : {33, 1000}) {
      SCOPED_TRACE(name + " B=" + std::to_string(B));
      EXPECT_LE(host_run_soa<double>(md, B, B == 33), 1e-10);
      // float: within 10x of what the serial float reference gets on the same inputs
      const double cpu = cpu_float_error(md, B, B == 33);
      EXPECT_LE(host_run_soa<float>(md, B, B == 33), std::max(1e-4, 10 * cpu)) << "cpu float error " << cpu;
    }
  }
}

TEST(CudaId, StridedHostLayouts) {
  SKIP_WITHOUT_CUDA_DEVICE();
  test::strided_host_layout_trials("qdd", "tau",
                                   [](const Model& md, Index B, bool fx, const Layout& lq, const Layout& lqd,
                                      const Layout& lqdd, const Layout& lout, int trial) {
                                     EXPECT_LE(host_run<double>(md, B, fx, lq, lqd, lqdd, lout, trial), 1e-10);
                                     EXPECT_LE(host_run<float>(md, B, fx, lq, lqd, lqdd, lout, trial), 1e-4);
                                   });
}

// compute_async: device pointers with their own strides, the caller's stream.
template <class S>
void device_run(const Model& md, Index B, const Layout& lin, const Layout& lout, bool with_fext, double tol,
                IdStrategy strategy = IdStrategy::Auto) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv();
  Batch<S> batch(md, B, 7);
  const std::vector<S> q = pack<S>(batch.q, nv, B, lin, 0.0), qd = pack<S>(batch.qd, nv, B, lin, 0.0),
                       qdd = pack<S>(batch.qdd, nv, B, lin, 0.0);
  std::vector<Force<S>> fext = test::cast_wrenches<S>(batch.fext);
  std::vector<S> tau(lout.size, std::numeric_limits<S>::quiet_NaN());

  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.strategy = strategy;
  // the thread strategy's device path is not limited by the staging buffers; the
  // scans' scratch is sized by max_batch
  o.max_batch = strategy == IdStrategy::ScanLocal || nv > cuda::kMaxThreadDofs ? B : 1;
  cuda::CudaInverseDynamics<S> engine(m, o);
  test::DeviceArray<S> dq, dqd, dqdd, dtau;
  test::DeviceArray<Force<S>> dfext;
  ASSERT_CUDA(dq.alloc(lin.size));
  ASSERT_CUDA(dqd.alloc(lin.size));
  ASSERT_CUDA(dqdd.alloc(lin.size));
  ASSERT_CUDA(dtau.alloc(lout.size));
  ASSERT_CUDA(dfext.alloc(fext.size()));
  ASSERT_CUDA(cudaMemcpy(dq.ptr, q.data(), lin.size * sizeof(S), cudaMemcpyHostToDevice));
  ASSERT_CUDA(cudaMemcpy(dqd.ptr, qd.data(), lin.size * sizeof(S), cudaMemcpyHostToDevice));
  ASSERT_CUDA(cudaMemcpy(dqdd.ptr, qdd.data(), lin.size * sizeof(S), cudaMemcpyHostToDevice));
  ASSERT_CUDA(cudaMemcpy(dfext.ptr, fext.data(), fext.size() * sizeof(Force<S>), cudaMemcpyHostToDevice));
  ASSERT_CUDA(cudaMemcpy(dtau.ptr, tau.data(), lout.size * sizeof(S), cudaMemcpyHostToDevice));
  cudaStream_t stream;
  ASSERT_CUDA(cudaStreamCreateWithFlags(&stream, cudaStreamNonBlocking));
  // a cudaMemcpy from pageable memory may return before its DMA lands, and a non-blocking
  // stream does not wait for the legacy stream: finish the uploads first
  ASSERT_CUDA(cudaDeviceSynchronize());
  const IdBatchIn<S> in{{dq.ptr + lin.base, B, lin.ds, lin.bs},
                        {dqd.ptr + lin.base, B, lin.ds, lin.bs},
                        {dqdd.ptr + lin.base, B, lin.ds, lin.bs},
                        with_fext ? dfext.ptr : nullptr};
  const BatchView<S> out{dtau.ptr + lout.base, B, lout.ds, lout.bs};
  EXPECT_EQ(engine.compute_async(in, out, stream), cudaSuccess);
  EXPECT_EQ(cudaStreamSynchronize(stream), cudaSuccess);
  EXPECT_EQ(cudaStreamDestroy(stream), cudaSuccess);
  ASSERT_CUDA(cudaMemcpy(tau.data(), dtau.ptr, lout.size * sizeof(S), cudaMemcpyDeviceToHost));
  EXPECT_LE(worst_error<S>(md, batch, with_fext, tau, lout), tol);
}

TEST(CudaId, DevicePointersOnAStream) {
  SKIP_WITHOUT_CUDA_DEVICE();
  test::device_layout_trials([](const Model& md, Index B, const Layout& lin, const Layout& lout) {
    device_run<double>(md, B, lin, lout, B != 1, 1e-10);
    device_run<float>(md, B, lin, lout, B != 1, 1e-4);
  });
  SCOPED_TRACE("iiwa B=100000");
  device_run<float>(robot("iiwa.urdf"), 100000, soa(7, 100000), soa(7, 100000), false, 1e-4);
}

TEST(CudaId, ErrorsWithADevice) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model md = load_model("chain:4");
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 8;
  cuda::CudaInverseDynamics<double> engine(md, o);
  EXPECT_EQ(engine.device_bytes(), 10u * 4 * 8 * sizeof(double));
  std::vector<double> x(4 * 16, 0.0), tau(4 * 16, 0.0);
  using V = BatchView<const double>;
  // max_batch exceeded
  const IdBatchIn<double> big{V::soa(x.data(), 4, 9), V::soa(x.data(), 4, 9), V::soa(x.data(), 4, 9)};
  try {
    engine.compute(big, BatchView<double>::soa(tau.data(), 4, 9));
    ADD_FAILURE() << "a batch over max_batch was accepted";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("max_batch"), std::string::npos) << e.what();
  }
  // batch sizes that disagree; tau entries that overlap
  const IdBatchIn<double> ok{V::soa(x.data(), 4, 8), V::soa(x.data(), 4, 8), V::soa(x.data(), 4, 8)};
  EXPECT_THROW(engine.compute(ok, BatchView<double>::soa(tau.data(), 4, 7)), BackendError);
  EXPECT_THROW(engine.compute(ok, BatchView<double>{tau.data(), 8, 1, 0}), BackendError);
  EXPECT_THROW(engine.compute(ok, BatchView<double>{tau.data(), 8, 1, 2}), BackendError);
  // the device path reports argument errors as values
  EXPECT_EQ(engine.compute_async(ok, BatchView<double>::soa(tau.data(), 4, 7), nullptr), cudaErrorInvalidValue);
  EXPECT_EQ(engine.compute_async({V::soa(nullptr, 4, 8), ok.qd, ok.qdd}, BatchView<double>::soa(tau.data(), 4, 8),
                                 nullptr),
            cudaErrorInvalidValue);
  const IdBatchIn<double> none{V::soa(nullptr, 4, 0), V::soa(nullptr, 4, 0), V::soa(nullptr, 4, 0)};
  EXPECT_EQ(engine.compute_async(none, BatchView<double>::soa(nullptr, 4, 0), nullptr), cudaSuccess);
  EXPECT_NO_THROW(engine.compute(none, BatchView<double>::soa(nullptr, 4, 0)));
  // more than the device holds: the message names the bytes needed and free
  o.max_batch = 2000000000;
  try {
    cuda::CudaInverseDynamics<double> huge(load_model("chain:64"), o);
    ADD_FAILURE() << "an engine of " << huge.device_bytes() << " bytes was made";
  } catch (const BackendError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("10240000000000 bytes"), std::string::npos) << what;
    EXPECT_NE(what.find("bytes free"), std::string::npos) << what;
  }
  // the engine still works after the failures
  std::vector<double> q(4 * 8, 0.1), t(4 * 8, std::nan(""));
  const IdBatchIn<double> in{V::soa(q.data(), 4, 8), V::soa(q.data(), 4, 8), V::soa(q.data(), 4, 8)};
  engine.compute(in, BatchView<double>::soa(t.data(), 4, 8));
  Data d(md, false);
  std::vector<double> ref(4), q1(4, 0.1);
  rnea(md, d, q1.data(), q1.data(), q1.data(), ref.data());
  for (Index b = 0; b < 8; ++b)
    for (Index i = 0; i < 4; ++i) EXPECT_NEAR(t[i * 8 + b], ref[i], 1e-12 * std::max(1.0, std::fabs(ref[i])));
}

// ---- the link scans (strategy scan-local) ------------------------------------------

// float tolerance for the scans: within 10x of the serial float recursion on the
// same inputs, and never looser than needed for float arithmetic on short models
double scan_float_tol(const Model& md, Index B, bool fx) { return std::max(1e-4, 10 * cpu_float_error(md, B, fx)); }

TEST(CudaIdScan, TreesChainsAndRobots) {
  SKIP_WITHOUT_CUDA_DEVICE();
  // chains (one level), branching trees (many levels, branch children folded into
  // their parents), prismatic joints with arbitrary axes, the robots forced onto
  // the scans, and models beyond the thread kernels' 64 DoF (auto picks the scans)
  std::vector<std::pair<std::string, Model>> models;
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) models.emplace_back(file, robot(file));
  for (const char* spec : {"chain:1", "chain:2", "rope:40", "chain:200", "curtain:3:5", "curtain:8:30", "tree:60:2",
                           "tree:1000:3"})
    models.emplace_back(spec, load_model(spec));
  models.emplace_back("random_model(12)", test::random_model(12, 3));
  models.emplace_back("random_model(200)", test::random_model(200, 6));
  for (const auto& [name, md] : models) {
    for (Index B : {1, 33, 257}) {
      const bool fx = B == 33;
      SCOPED_TRACE(name + " B=" + std::to_string(B) + (fx ? " fext" : ""));
      EXPECT_LE(host_run_soa<double>(md, B, fx, IdStrategy::ScanLocal), 1e-10);
      EXPECT_LE(host_run_soa<float>(md, B, fx, IdStrategy::ScanLocal), scan_float_tol(md, B, fx));
    }
  }
}

TEST(CudaIdScan, StridedLayoutsAndDevicePointers) {
  SKIP_WITHOUT_CUDA_DEVICE();
  std::mt19937_64 g(17);
  for (const char* spec : {"rope:300", "tree:500:7"}) {
    const Model md = load_model(spec);
    const Index nv = md.nv();
    for (int trial = 0; trial < 6; ++trial) {
      const test::LayoutTrial t = test::random_layout_trial(g, nv, trial, 37);
      SCOPED_TRACE(std::string(spec) + " B=" + std::to_string(t.B) + " q " + t.lq.name + " tau " + t.lout.name);
      EXPECT_LE(host_run<double>(md, t.B, t.fx, t.lq, t.lqd, t.l3, t.lout, trial, IdStrategy::ScanLocal), 1e-10);
    }
    for (Index B : {1, 64}) {
      SCOPED_TRACE(std::string(spec) + " device pointers B=" + std::to_string(B));
      device_run<double>(md, B, aos(nv, B), soa(nv, B), B > 1, 1e-10, IdStrategy::ScanLocal);
      device_run<float>(md, B, soa(nv, B), aos(nv, B), B > 1, scan_float_tol(md, B, B > 1), IdStrategy::ScanLocal);
    }
  }
}

TEST(CudaIdScan, BatchesOfRopes) {
  SKIP_WITHOUT_CUDA_DEVICE();
  // the middle shapes: instances x links ~ 10^5 .. 10^6 in one scan per pass
  for (const auto& [spec, B] : std::vector<std::pair<std::string, Index>>{{"rope:1000", 100}, {"rope:100", 3000}}) {
    const Model md = load_model(spec);
    SCOPED_TRACE(spec + " B=" + std::to_string(B));
    EXPECT_LE(host_run_soa<double>(md, B, true), 1e-10);
    EXPECT_LE(host_run_soa<float>(md, B, false), scan_float_tol(md, 4, false));
  }
}

TEST(CudaIdScan, LongRopes) {
  SKIP_WITHOUT_CUDA_DEVICE();
  // one instance of a rope of 10^5 and 10^6 links: double to 1e-10 of the serial
  // double recursion; float within 10x of the serial float recursion's error
  for (const char* spec : {"rope:100000", "rope:1000000"}) {
    const Model md = load_model(spec);
    SCOPED_TRACE(spec);
    EXPECT_LE(host_run_soa<double>(md, 1, false), 1e-10);
    const double cpu = cpu_float_error(md, 1, false);
    EXPECT_LE(host_run_soa<float>(md, 1, false), std::max(1e-4, 10 * cpu)) << "cpu float error " << cpu;
  }
}

TEST(CudaIdScan, ErrorsAndScratch) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model md = load_model("rope:100");
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 8;
  cuda::CudaInverseDynamics<double> engine(md, o);
  EXPECT_EQ(engine.strategy(), "scan-local");
  ASSERT_NE(engine.scan_plan(), nullptr);
  EXPECT_EQ(engine.thread_model(), nullptr);
  EXPECT_EQ(engine.scan_plan()->levels(), 1);
  EXPECT_LE(engine.scan_plan()->body_classes(), 3);  // a rope's links share their constants (all but the ends)
  std::vector<double> x(100 * 9, 0.0), tau(100 * 9, 0.0);
  using V = BatchView<const double>;
  // over max_batch: an error value on the device path (the scratch is sized by it)
  const IdBatchIn<double> big{V::soa(x.data(), 100, 9), V::soa(x.data(), 100, 9), V::soa(x.data(), 100, 9)};
  EXPECT_EQ(engine.compute_async(big, BatchView<double>::soa(tau.data(), 100, 9), nullptr), cudaErrorInvalidValue);
  EXPECT_THROW(engine.compute(big, BatchView<double>::soa(tau.data(), 100, 9)), BackendError);
  // more than the device holds: the message names the scratch
  o.max_batch = 2000000;  // 2 * 10^9 elements per scan, 144 GB of v, a, F
  try {
    cuda::CudaInverseDynamics<double> huge(load_model("rope:1000"), o);
    ADD_FAILURE() << "an engine of " << huge.device_bytes() << " bytes was made";
  } catch (const BackendError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("max_batch 2000000"), std::string::npos) << what;
    EXPECT_NE(what.find("bytes free"), std::string::npos) << what;
  }
  // a tree: levels and branch children
  const Model tree = load_model("tree:60:2");
  o.max_batch = 2;
  o.strategy = IdStrategy::ScanLocal;  // 60 DoF: auto would take a thread per instance
  cuda::CudaInverseDynamics<double> t(tree, o);
  EXPECT_EQ(t.strategy(), "scan-local");
  EXPECT_GE(t.scan_plan()->levels(), 2);
}
