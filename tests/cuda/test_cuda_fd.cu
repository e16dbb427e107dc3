// Batched forward dynamics by the joint-space inertia on the GPU, one thread per
// instance (fd_jsi_instance, launch_fd_jsi_instances, CudaForwardDynamics), against
// the serial double references scandyn::fd_jsi (the same algorithm) and
// scandyn::aba (an independent one).
//
// Errors are scandyn::rel_err per instance, max |qdd - ref| / max(1, max |ref|),
// the worst over every instance of a batch. Tolerances:
//   double vs fd_jsi   1e-10 (the issue's bound). The device computes every entry
//                      with the reference's formulas in its order; what differs is
//                      FMA contraction and the device's sin/cos. On the host the
//                      device function is bit-identical to fd_jsi (measured: 0, every
//                      model and variant), asserted as <= 1e-13.
//   double vs aba      1e-9: a different elimination order, so the difference grows
//                      with cond(M): measured <= 4e-15 on the robots and random trees,
//                      1e-11 on chain:33, 8e-11 on chain:64.
//   float              the reference runs on the float-rounded inputs, so only float
//                      arithmetic is measured: <= 1e-4 on the robots (measured on the
//                      host: 4e-7 to 6e-7 for iiwa, hyq and atlas), and on generated
//                      models <= max(1e-4, 10 x the serial float fd_jsi's own error
//                      on the same inputs): cond(M) grows fast with chain length
//                      (serial float: 1e-5 on chain:8, 3e-3 on chain:33, 0.06 on
//                      chain:64, where float JSI is not usable).
// Outputs start as NaN, so an entry never written fails; with strided layouts the
// gaps between entries hold a sentinel that must survive compute(). Tests that need
// a device skip with "no CUDA device: ..."; the device function (run on the host),
// the model's ancestor masks, pivot failures and the argument errors are checked on
// every machine, CI included.
//
// One program from several translation units (tests/CMakeLists.txt): this one holds
// the tests of the engine on the device and those that need no device function;
// test_cuda_fd.jsi_host.cu, test_cuda_fd.aba_host.cu and test_cuda_fd.aba_shapes.cu
// run fd_jsi_instance / aba_instance on the host in each of their compile-time
// variants (the costly part to compile). Shared helpers: cuda_fd_test_util.hpp.
#include "cuda_fd_test_util.hpp"

using namespace scandyn;
using namespace scandyn::test::fd;

// ---- runs everywhere ------------------------------------------------------------------

TEST(CudaFdModel, AncestorMasks) {
  for (const Model& md : {robot("atlas.urdf"), robot("hyq.urdf"), test::random_model(64, 5), load_model("tree:60:2"),
                          load_model("chain:64")}) {
    const cuda::ThreadModel<double> tm(md);
    std::visit(
        [&](const auto& p) {
          for (Index k = 0; k < md.nv(); ++k) {
            unsigned long long want = 0;
            for (Index j = md.parent(k); j >= 0; j = md.parent(j)) want |= 1ull << j;
            EXPECT_EQ(p.ancestors[k], want) << md.name << " body " << k;
          }
        },
        tm.params());
  }
}

TEST(CudaFdErrors, WithoutADevice) {
  // arguments are checked before the device: these hold on every machine
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 4;
  o.strategy = IdStrategy::ScanLocal;
  EXPECT_THROW(cuda::CudaForwardDynamics<double>(load_model("chain:3"), o), BackendError);
  o.strategy = IdStrategy::Auto;
  o.max_batch = -1;
  EXPECT_THROW(cuda::CudaForwardDynamics<double>(load_model("chain:3"), o), BackendError);
  // no device: a BackendError naming why, never a crash
  o.max_batch = 4;
  if (!test::no_device_reason().empty()) {
    try {
      cuda::CudaForwardDynamics<float> e(load_model("chain:3").cast<float>(), o);
      ADD_FAILURE() << "an engine was made without a device";
    } catch (const BackendError& e) {
      EXPECT_NE(std::string(e.what()).find("no usable CUDA device"), std::string::npos) << e.what();
    }
  } else {
    cuda::CudaForwardDynamics<float> e(load_model("chain:3").cast<float>(), o);
    EXPECT_EQ(e.strategy(), "aba_thread");  // Auto: ABA up to 64 DoF
    EXPECT_EQ(e.backend(), BackendKind::Cuda);
  }
}

// ---- the ABA's model data ---------------------------------------------------------

// Branch slots (ThreadModel): kOpensSlot on each branch point's highest-numbered
// branch child h(p); two branch points whose ranges [p, h(p)) overlap never share a
// slot; and no more slots than the most ranges over one body (interval colouring is
// optimal).
TEST(CudaFdAbaModel, BranchSlots) {
  std::vector<std::pair<std::string, Model>> models;
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) models.emplace_back(file, robot(file));
  for (auto& m : generated_models()) models.push_back(std::move(m));
  for (const char* spec : {"tree:12:4", "tree:20:2", "tree:20:3", "tree:64:7"})
    models.emplace_back(spec, load_model(spec));
  for (const auto& named : models) {
    SCOPED_TRACE(named.first);
    const Model& md = named.second;
    const Index nv = md.nv();
    const cuda::ThreadModel<double> tm(md);
    std::vector<Index> h(nv, -1);  // highest-numbered branch child
    for (Index i = 0; i < nv; ++i)
      if (md.parent(i) >= 0 && md.parent(i) != i - 1) h[md.parent(i)] = i;
    std::visit(
        [&](const auto& p) {
          Index most = 0;
          for (Index i = 0; i < nv; ++i) {
            const bool opens = md.parent(i) >= 0 && h[md.parent(i)] == i;
            EXPECT_EQ((p.flags[i] & cuda::kOpensSlot) != 0, opens) << "body " << i;
            EXPECT_EQ((p.flags[i] & cuda::kStacked) != 0, h[i] >= 0) << "body " << i;
            if (h[i] < 0) {
              EXPECT_EQ(cuda::branch_slot(p.flags[i]), 0) << "body " << i;
              continue;
            }
            EXPECT_LT(cuda::branch_slot(p.flags[i]), tm.branch_slots()) << "body " << i;
            Index over = 0;  // ranges [j, h(j)) holding body i (the most are at a range's start)
            for (Index j = 0; j <= i; ++j)
              if (h[j] > i) ++over;
            most = std::max(most, over);
            for (Index j = 0; j < i; ++j)
              if (h[j] > i) EXPECT_NE(cuda::branch_slot(p.flags[j]), cuda::branch_slot(p.flags[i])) << j << ", " << i;
          }
          EXPECT_EQ(tm.branch_slots(), most);
        },
        tm.params());
  }
  EXPECT_EQ(cuda::ThreadModel<double>(robot("atlas.urdf")).branch_slots(), 1);
  EXPECT_EQ(cuda::ThreadModel<double>(robot("hyq.urdf")).branch_slots(), 0);  // four legs on the base
  EXPECT_EQ(cuda::ThreadModel<double>(load_model("tree:12:4")).branch_slots(), 2);
}

// The kernel launch_aba_instances picks by shape.
TEST(CudaFdAbaModel, KernelChoiceByShape) {
  using cuda::AbaKernel;
  auto pick = [](const Model& md, bool fl) {
    return fl ? cuda::choose_aba_kernel(cuda::ThreadModel<float>(md.cast<float>()))
              : cuda::choose_aba_kernel(cuda::ThreadModel<double>(md));
  };
  for (bool fl : {false, true}) {
    EXPECT_EQ(pick(robot("iiwa.urdf"), fl), AbaKernel::Chains);
    EXPECT_EQ(pick(robot("hyq.urdf"), fl), AbaKernel::Chains);
    EXPECT_EQ(pick(load_model("chain:64"), fl), AbaKernel::Chains);
    EXPECT_EQ(pick(load_model("curtain:3:5"), fl), AbaKernel::Chains);
    EXPECT_EQ(pick(load_model("tree:30:1"), fl), AbaKernel::Tree);
  }
  EXPECT_EQ(pick(robot("atlas.urdf"), true), AbaKernel::Branches);
  EXPECT_EQ(pick(robot("atlas.urdf"), false), AbaKernel::Tree);
  EXPECT_STREQ(cuda::to_string(AbaKernel::Chains), "chain");
  EXPECT_STREQ(cuda::to_string(AbaKernel::Branches), "slots");
  EXPECT_STREQ(cuda::to_string(AbaKernel::Tree), "tree");
}

TEST(CudaFdAbaErrors, WithoutADevice) {
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 4;
  if (test::no_device_reason().empty()) {
    // beyond kMaxThreadDofs: the general path's ABA (GeneralPlan, one thread per instance)
    cuda::CudaForwardDynamics<double> g(load_model("chain:65"), o, FdMethod::Aba);
    EXPECT_EQ(g.strategy(), "aba_general");
    EXPECT_EQ(g.method(), FdMethod::Aba);
    cuda::CudaForwardDynamics<float> e(load_model("chain:3").cast<float>(), o, FdMethod::Aba);
    EXPECT_EQ(e.strategy(), "aba_thread");
    EXPECT_EQ(e.method(), FdMethod::Aba);
    cuda::CudaForwardDynamics<float> j(load_model("chain:3").cast<float>(), o);
    EXPECT_EQ(j.method(), FdMethod::Aba);  // Auto: ABA up to 64 DoF
  }
}

// ---- on the device ----------------------------------------------------------------

namespace {

// Runs the engine's host path: inputs in layouts lq, lqd, ltau, qdd in lout.
// Returns the worst instance errors; checks the gaps of qdd and that all succeeded.
template <class S>
Errors host_run(const Model& md, Index B, bool with_fext, const Layout& lq, const Layout& lqd, const Layout& ltau,
                const Layout& lout, unsigned seed = 1, FdMethod alg = FdMethod::Jsi) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv();
  Batch<S> batch(md, B, seed);
  if (lq.bs == 0 && B > 1) batch.broadcast();  // one state for all instances
  const std::vector<S> q = pack<S>(batch.q, nv, B, lq, 0.0), qd = pack<S>(batch.qd, nv, B, lqd, 0.0),
                       tau = pack<S>(batch.tau, nv, B, ltau, 0.0);
  std::vector<Force<S>> fext = test::cast_wrenches<S>(batch.fext);
  std::vector<S> qdd = test::sentinel_output<S>(lout, nv, B, kSentinel);

  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  cuda::CudaForwardDynamics<S> engine(m, o, alg);
  EXPECT_EQ(engine.strategy(), alg == FdMethod::Aba ? "aba_thread"
                               : md.nv() > cuda::kMaxThreadDofs ? "jsi_dense"
                                                                : "jsi_thread");
  const FdBatchIn<S> in{{q.data() + lq.base, B, lq.ds, lq.bs},
                        {qd.data() + lqd.base, B, lqd.ds, lqd.bs},
                        {tau.data() + ltau.base, B, ltau.ds, ltau.bs},
                        with_fext ? fext.data() : nullptr};
  std::vector<int> failed(B, -2);
  const BatchStatus st = engine.compute(in, BatchView<S>{qdd.data() + lout.base, B, lout.ds, lout.bs},
                                                failed.data());
  EXPECT_TRUE(st.ok()) << st.message();
  EXPECT_EQ(std::count(failed.begin(), failed.end(), -1), B);

  EXPECT_EQ(test::gap_writes(qdd, lout, nv, B, kSentinel), 0u)
      << "compute() wrote between qdd's entries (layout " << lout.name << ")";
  return worst_errors<S>(md, batch, with_fext, qdd, lout);
}

template <class S>
Errors host_run_soa(const Model& md, Index B, bool with_fext, FdMethod alg = FdMethod::Jsi) {
  const Layout l = soa(md.nv(), B);
  return host_run<S>(md, B, with_fext, l, l, l, l, 1, alg);
}

// compute_async: device pointers with their own strides, the caller's stream.
template <class S>
Errors device_run(const Model& md, Index B, const Layout& lin, const Layout& lout, bool with_fext) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv();
  Batch<S> batch(md, B, 7);
  const std::vector<S> q = pack<S>(batch.q, nv, B, lin, 0.0), qd = pack<S>(batch.qd, nv, B, lin, 0.0),
                       tau = pack<S>(batch.tau, nv, B, lin, 0.0);
  std::vector<Force<S>> fext = test::cast_wrenches<S>(batch.fext);
  std::vector<S> qdd(lout.size, std::numeric_limits<S>::quiet_NaN());
  std::vector<int> failed(B, -2);

  BackendOptions o;
  o.backend = BackendKind::Cuda;
  // the thread kernels' device path is not limited by the staging buffers; the
  // dense path's scratch is sized by max_batch
  o.max_batch = md.nv() > cuda::kMaxThreadDofs ? B : 1;
  cuda::CudaForwardDynamics<S> engine(m, o, FdMethod::Jsi);
  test::DeviceArray<S> dq, dqd, dtau, dqdd;
  test::DeviceArray<Force<S>> dfext;
  test::DeviceArray<int> dfailed;
  Errors none{std::nan(""), std::nan("")};
  if (dq.alloc(lin.size) != cudaSuccess || dqd.alloc(lin.size) != cudaSuccess || dtau.alloc(lin.size) != cudaSuccess ||
      dqdd.alloc(lout.size) != cudaSuccess || dfext.alloc(fext.size()) != cudaSuccess ||
      dfailed.alloc(static_cast<std::size_t>(B)) != cudaSuccess) {
    ADD_FAILURE() << "cudaMalloc failed";
    return none;
  }
  EXPECT_EQ(cudaMemcpy(dq.ptr, q.data(), lin.size * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(dqd.ptr, qd.data(), lin.size * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(dtau.ptr, tau.data(), lin.size * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(dfext.ptr, fext.data(), fext.size() * sizeof(Force<S>), cudaMemcpyHostToDevice), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(dqdd.ptr, qdd.data(), lout.size * sizeof(S), cudaMemcpyHostToDevice), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(dfailed.ptr, failed.data(), B * sizeof(int), cudaMemcpyHostToDevice), cudaSuccess);
  cudaStream_t stream;
  EXPECT_EQ(cudaStreamCreateWithFlags(&stream, cudaStreamNonBlocking), cudaSuccess);
  // a cudaMemcpy from pageable memory may return before its DMA lands, and a non-blocking
  // stream does not wait for the legacy stream: finish the uploads first
  EXPECT_EQ(cudaDeviceSynchronize(), cudaSuccess);
  const FdBatchIn<S> in{{dq.ptr + lin.base, B, lin.ds, lin.bs},
                        {dqd.ptr + lin.base, B, lin.ds, lin.bs},
                        {dtau.ptr + lin.base, B, lin.ds, lin.bs},
                        with_fext ? dfext.ptr : nullptr};
  const BatchView<S> out{dqdd.ptr + lout.base, B, lout.ds, lout.bs};
  EXPECT_EQ(engine.compute_async(in, out, dfailed.ptr, stream), cudaSuccess);
  EXPECT_EQ(cudaStreamSynchronize(stream), cudaSuccess);
  EXPECT_EQ(cudaStreamDestroy(stream), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(qdd.data(), dqdd.ptr, lout.size * sizeof(S), cudaMemcpyDeviceToHost), cudaSuccess);
  EXPECT_EQ(cudaMemcpy(failed.data(), dfailed.ptr, B * sizeof(int), cudaMemcpyDeviceToHost), cudaSuccess);
  EXPECT_EQ(std::count(failed.begin(), failed.end(), -1), B);
  return worst_errors<S>(md, batch, with_fext, qdd, lout);
}

}  // namespace

TEST(CudaFd, RobotsMatchReferences) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) {
    const Model& md = robot(file);
    for (Index B : {1, 31, 32, 33, 1000, 100000}) {
      for (bool fx : {false, true}) {
        if (B == 100000 && (fx || std::string(file) != "iiwa.urdf")) continue;  // keep the run short
        SCOPED_TRACE(std::string(file) + " B=" + std::to_string(B) + (fx ? " fext" : ""));
        const Errors d = host_run_soa<double>(md, B, fx);
        EXPECT_LE(d.jsi, kDoubleTol);
        EXPECT_LE(d.aba, kAbaTol);
        EXPECT_LE(host_run_soa<float>(md, B, fx).jsi, kFloatTol);
      }
    }
  }
}

TEST(CudaFd, GeneratedTreesAndChains) {
  SKIP_WITHOUT_CUDA_DEVICE();
  // every capacity and its boundaries, branch points, prismatic joints, arbitrary
  // axes, numberings that are not preorders, up to 64 DoF
  for (const auto& [name, md] : generated_models()) {
    for (Index B : {33, 1000}) {
      SCOPED_TRACE(name + " B=" + std::to_string(B));
      const Errors d = host_run_soa<double>(md, B, B == 33);
      EXPECT_LE(d.jsi, jsi_tol(md));
      EXPECT_LE(d.aba, kAbaTol);
      const double ftol = float_tol(md, B, B == 33, 1);  // host_run's inputs
      EXPECT_LE(host_run_soa<float>(md, B, B == 33).jsi, ftol);
    }
  }
}

TEST(CudaFd, StridedHostLayouts) {
  SKIP_WITHOUT_CUDA_DEVICE();
  test::strided_host_layout_trials("tau", "qdd",
                                   [](const Model& md, Index B, bool fx, const Layout& lq, const Layout& lqd,
                                      const Layout& ltau, const Layout& lout, int trial) {
                                     EXPECT_LE(host_run<double>(md, B, fx, lq, lqd, ltau, lout, trial).jsi, kDoubleTol);
                                     EXPECT_LE(host_run<float>(md, B, fx, lq, lqd, ltau, lout, trial).jsi, kFloatTol);
                                   });
}

TEST(CudaFd, DevicePointersOnAStream) {
  SKIP_WITHOUT_CUDA_DEVICE();
  test::device_layout_trials([](const Model& md, Index B, const Layout& lin, const Layout& lout) {
    EXPECT_LE(device_run<double>(md, B, lin, lout, B != 1).jsi, kDoubleTol);
    EXPECT_LE(device_run<float>(md, B, lin, lout, B != 1).jsi, kFloatTol);
  });
  SCOPED_TRACE("iiwa B=100000");
  EXPECT_LE(device_run<float>(robot("iiwa.urdf"), 100000, soa(7, 100000), soa(7, 100000), false).jsi, kFloatTol);
}

// Failed factorisations: reported per instance, named by compute()'s status, their
// qdd left as it was; the other instances of the batch are unaffected.
template <class S>
void failures_on_device(const Model& md, Index B) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv();
  Batch<S> batch(md, B, 21);
  // instances 3, 10, 11, ... get a NaN or inf position of a joint that is not a root
  // (M does not depend on a root's position: a NaN there gives NaN qdd, as in fd_jsi)
  std::vector<Index> nonroot;
  for (Index i = 0; i < nv; ++i)
    if (md.parent(i) >= 0) nonroot.push_back(i);
  std::vector<Index> want(B, -1);
  DataTpl<S> d(m);
  for (Index b = 3; b < B; b += 7 + b % 3) {
    batch.q[batch.at(nonroot[b % nonroot.size()], b)] = b % 2 ? std::numeric_limits<double>::quiet_NaN()
                                                              : std::numeric_limits<double>::infinity();
  }
  Index failures = 0, first = -1;
  for (Index b = 0; b < B; ++b) {
    std::vector<S> qi(nv), qdi(nv), ti(nv), out(nv);
    for (Index i = 0; i < nv; ++i)
      qi[i] = S(batch.q[batch.at(i, b)]), qdi[i] = S(batch.qd[batch.at(i, b)]), ti[i] = S(batch.tau[batch.at(i, b)]);
    want[b] = fd_jsi(m, d, qi.data(), qdi.data(), ti.data(), out.data()).failed_dof;
    if (want[b] >= 0 && failures++ == 0) first = b;
  }
  ASSERT_GT(failures, 1);
  const Layout l = soa(nv, B);
  const std::vector<S> q = pack<S>(batch.q, nv, B, l, 0.0), qd = pack<S>(batch.qd, nv, B, l, 0.0),
                       tau = pack<S>(batch.tau, nv, B, l, 0.0);
  const FdBatchIn<S> in{{q.data(), B, l.ds, l.bs}, {qd.data(), B, l.ds, l.bs}, {tau.data(), B, l.ds, l.bs}};

  // host path
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  cuda::CudaForwardDynamics<S> engine(m, o, FdMethod::Jsi);
  for (int rep = 0; rep < 2; ++rep) {  // the second time reuses the kept entries' buffer
    std::vector<S> qdd(l.size, S(kSentinel));
    std::vector<int> failed(B, -2);
    const BatchStatus st = engine.compute(in, BatchView<S>::soa(qdd.data(), nv, B), rep ? failed.data() : nullptr);
    EXPECT_EQ(st.failed, failures);
    EXPECT_EQ(st.first_instance, first);
    EXPECT_EQ(st.first_dof, want[first]);
    EXPECT_EQ(st.message(), "instance " + std::to_string(first) + ": mass matrix pivot at DoF " +
                                std::to_string(want[first]) + " is not positive (and " +
                                std::to_string(failures - 1) + " more instance" + (failures > 2 ? "s)" : ")"));
    Data dd(md);
    std::vector<double> jsi, ab, ours(nv);
    for (Index b = 0; b < B; ++b) {
      if (rep) EXPECT_EQ(failed[b], want[b]) << "instance " << b;
      for (Index i = 0; i < nv; ++i) ours[i] = double(qdd[l.at(i, b)]);
      if (want[b] >= 0) {
        for (Index i = 0; i < nv; ++i) EXPECT_EQ(ours[i], kSentinel) << "instance " << b << " DoF " << i;
      } else {
        batch.reference(md, dd, b, false, jsi, ab);
        EXPECT_LE(test::max_rel_err(ours, jsi), test::Tol<S>(kDoubleTol, kFloatTol)) << "instance " << b;
      }
    }
  }

  // device path
  test::DeviceArray<S> dbuf;
  test::DeviceArray<int> dfailed;
  ASSERT_CUDA(dbuf.alloc(4 * l.size));
  ASSERT_CUDA(dfailed.alloc(static_cast<std::size_t>(B)));
  std::vector<S> qdd(l.size, S(kSentinel));
  for (const auto& [k, v] : {std::make_pair(0, &q), std::make_pair(1, &qd), std::make_pair(2, &tau),
                             std::make_pair(3, static_cast<const std::vector<S>*>(&qdd))})
    ASSERT_CUDA(cudaMemcpy(dbuf.ptr + k * l.size, v->data(), l.size * sizeof(S), cudaMemcpyHostToDevice));
  const FdBatchIn<S> din{{dbuf.ptr, B, l.ds, l.bs}, {dbuf.ptr + l.size, B, l.ds, l.bs},
                         {dbuf.ptr + 2 * l.size, B, l.ds, l.bs}};
  ASSERT_CUDA(engine.compute_async(din, {dbuf.ptr + 3 * l.size, B, l.ds, l.bs}, dfailed.ptr, nullptr));
  ASSERT_CUDA(cudaDeviceSynchronize());
  std::vector<int> failed(B);
  ASSERT_CUDA(cudaMemcpy(qdd.data(), dbuf.ptr + 3 * l.size, l.size * sizeof(S), cudaMemcpyDeviceToHost));
  ASSERT_CUDA(cudaMemcpy(failed.data(), dfailed.ptr, B * sizeof(int), cudaMemcpyDeviceToHost));
  for (Index b = 0; b < B; ++b) {
    EXPECT_EQ(failed[b], want[b]) << "instance " << b;
    if (want[b] >= 0)
      for (Index i = 0; i < nv; ++i) EXPECT_EQ(qdd[l.at(i, b)], S(kSentinel)) << "instance " << b << " DoF " << i;
    else
      for (Index i = 0; i < nv; ++i) EXPECT_TRUE(std::isfinite(qdd[l.at(i, b)])) << "instance " << b << " DoF " << i;
  }
}

TEST(CudaFd, PivotFailuresReported) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) {
    SCOPED_TRACE(file);
    failures_on_device<double>(robot(file), 200);
    failures_on_device<float>(robot(file), 200);
  }
  // a singular model: every instance fails at the last DoF
  const Model md = massless_leaf(5);
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 40;
  cuda::CudaForwardDynamics<double> engine(md, o, FdMethod::Jsi);
  std::vector<double> x(5 * 40, 0.25), qdd(5 * 40, kSentinel);
  using V = BatchView<const double>;
  const FdBatchIn<double> in{V::soa(x.data(), 5, 40), V::soa(x.data(), 5, 40), V::soa(x.data(), 5, 40)};
  const BatchStatus st = engine.compute(in, BatchView<double>::soa(qdd.data(), 5, 40));
  EXPECT_EQ(st.failed, 40);
  EXPECT_EQ(st.first_instance, 0);
  EXPECT_EQ(st.first_dof, 4);
  EXPECT_EQ(st.message(), "instance 0: mass matrix pivot at DoF 4 is not positive (and 39 more instances)");
  EXPECT_EQ(std::count(qdd.begin(), qdd.end(), kSentinel), 5 * 40) << "a failed instance's qdd was written";
}

// ---- the ABA on the device (FdMethod::Aba) ------------------------------------------
//
// Against the serial double aba: double 1e-10 (the device's FMA contractions and
// sin/cos); float max(1e-4, 10 x the serial float aba's error on the same inputs).
TEST(CudaFdAba, MatchesReferences) {
  SKIP_WITHOUT_CUDA_DEVICE();
  std::vector<std::pair<std::string, Model>> models;
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) models.emplace_back(file, robot(file));
  for (auto& m : generated_models()) models.push_back(std::move(m));
  for (const auto& [name, md] : models) {
    for (Index B : {1, 33, 1000}) {
      const bool fx = B != 1000;
      SCOPED_TRACE(name + " B=" + std::to_string(B) + (fx ? " fext" : ""));
      EXPECT_LE(host_run_soa<double>(md, B, fx, FdMethod::Aba).aba, kDoubleTol);
      EXPECT_LE(host_run_soa<float>(md, B, fx, FdMethod::Aba).aba, aba_float_tol(md, B, fx, 1));
    }
  }
}

TEST(CudaFdAba, PivotFailuresReported) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model md = massless_leaf(5);
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 40;
  cuda::CudaForwardDynamics<double> engine(md, o, FdMethod::Aba);
  std::vector<double> x(5 * 40, 0.25), qdd(5 * 40, kSentinel);
  std::vector<int> failed(40, -2);
  using V = BatchView<const double>;
  const FdBatchIn<double> in{V::soa(x.data(), 5, 40), V::soa(x.data(), 5, 40), V::soa(x.data(), 5, 40)};
  const BatchStatus st = engine.compute(in, BatchView<double>::soa(qdd.data(), 5, 40), failed.data());
  EXPECT_EQ(st.failed, 40);
  EXPECT_EQ(st.first_instance, 0);
  EXPECT_EQ(st.first_dof, 4);
  EXPECT_EQ(std::count(failed.begin(), failed.end(), 4), 40);
  EXPECT_EQ(std::count(qdd.begin(), qdd.end(), kSentinel), 5 * 40) << "a failed instance's qdd was written";
  EXPECT_EQ(st.failure, Failure::ArticulatedPivot);
  EXPECT_EQ(st.message(), "instance 0: articulated inertia pivot at DoF 4 is not positive (and 39 more instances)");
}

TEST(CudaFd, ErrorsWithADevice) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model md = load_model("chain:4");
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 8;
  cuda::CudaForwardDynamics<double> engine(md, o, FdMethod::Jsi);
  EXPECT_EQ(engine.device_bytes(), (10u * 4 * sizeof(double) + sizeof(int)) * 8);
  std::vector<double> x(4 * 16, 0.0), qdd(4 * 16, 0.0);
  std::vector<int> failed(16);
  using V = BatchView<const double>;
  // max_batch exceeded
  const FdBatchIn<double> big{V::soa(x.data(), 4, 9), V::soa(x.data(), 4, 9), V::soa(x.data(), 4, 9)};
  try {
    engine.compute(big, BatchView<double>::soa(qdd.data(), 4, 9));
    ADD_FAILURE() << "a batch over max_batch was accepted";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("max_batch"), std::string::npos) << e.what();
  }
  // batch sizes that disagree; qdd entries that overlap
  const FdBatchIn<double> ok{V::soa(x.data(), 4, 8), V::soa(x.data(), 4, 8), V::soa(x.data(), 4, 8)};
  EXPECT_THROW(engine.compute(ok, BatchView<double>::soa(qdd.data(), 4, 7)), BackendError);
  EXPECT_THROW(engine.compute(ok, BatchView<double>{qdd.data(), 8, 1, 0}), BackendError);
  EXPECT_THROW(engine.compute(ok, BatchView<double>{qdd.data(), 8, 1, 2}), BackendError);
  // the device path reports argument errors as values (host pointers are never touched)
  EXPECT_EQ(engine.compute_async(ok, BatchView<double>::soa(qdd.data(), 4, 7), failed.data(), nullptr),
            cudaErrorInvalidValue);
  EXPECT_EQ(engine.compute_async({V::soa(nullptr, 4, 8), ok.qd, ok.tau}, BatchView<double>::soa(qdd.data(), 4, 8),
                                 failed.data(), nullptr),
            cudaErrorInvalidValue);
  EXPECT_EQ(engine.compute_async(ok, BatchView<double>::soa(qdd.data(), 4, 8), nullptr, nullptr),
            cudaErrorInvalidValue);
  // B = 0: nothing to do, null pointers allowed
  const FdBatchIn<double> none{V::soa(nullptr, 4, 0), V::soa(nullptr, 4, 0), V::soa(nullptr, 4, 0)};
  EXPECT_EQ(engine.compute_async(none, BatchView<double>::soa(nullptr, 4, 0), nullptr, nullptr), cudaSuccess);
  BatchStatus st;
  EXPECT_NO_THROW(st = engine.compute(none, BatchView<double>::soa(nullptr, 4, 0)));
  EXPECT_TRUE(st.ok());
  // more than the device holds: the message names the bytes needed and free
  o.max_batch = 2000000000;
  try {
    cuda::CudaForwardDynamics<double> huge(load_model("chain:64"), o);
    ADD_FAILURE() << "an engine of " << huge.device_bytes() << " bytes was made";
  } catch (const BackendError& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find("10248000000000 bytes"), std::string::npos) << what;
    EXPECT_NE(what.find("bytes free"), std::string::npos) << what;
  }
  // the engine still works after the failures
  std::vector<double> q(4 * 8, 0.1), t(4 * 8, std::nan(""));
  const FdBatchIn<double> in{V::soa(q.data(), 4, 8), V::soa(q.data(), 4, 8), V::soa(q.data(), 4, 8)};
  EXPECT_TRUE(engine.compute(in, BatchView<double>::soa(t.data(), 4, 8)).ok());
  Data d(md);
  std::vector<double> ref(4), q1(4, 0.1);
  ASSERT_TRUE(fd_jsi(md, d, q1.data(), q1.data(), q1.data(), ref.data()).ok());
  for (Index b = 0; b < 8; ++b)
    for (Index i = 0; i < 4; ++i) EXPECT_NEAR(t[i * 8 + b], ref[i], 1e-12 * std::max(1.0, std::fabs(ref[i])));
}

// ---- beyond 64 DoF: CRBA per block, cuSOLVER's batched Cholesky ----------------------

TEST(CudaFdDense, MatchesReferences) {
  SKIP_WITHOUT_CUDA_DEVICE();
  std::vector<std::pair<std::string, Model>> models;
  for (const char* spec : {"chain:65", "rope:80", "chain:100", "curtain:3:30", "tree:200:5"})
    models.emplace_back(spec, load_model(spec));
  models.emplace_back("random_model(100)", test::random_model(100, 9));
  for (const auto& [name, md] : models) {
    BackendOptions o;
    o.backend = BackendKind::Cuda;
    o.max_batch = 1;
    EXPECT_EQ(cuda::CudaForwardDynamics<double>(md, o, FdMethod::Jsi).strategy(), "jsi_dense") << name;
    const double tol = jsi_tol(md);
    for (Index B : {1, 7, 33}) {
      const bool fx = B == 7;
      SCOPED_TRACE(name + " B=" + std::to_string(B) + (fx ? " fext" : ""));
      const Errors d = host_run_soa<double>(md, B, fx);
      EXPECT_LE(d.jsi, tol);
      EXPECT_LE(d.aba, std::max(kAbaTol, tol));
      EXPECT_LE(host_run_soa<float>(md, B, fx).jsi, float_tol(md, B, fx, 1));
    }
    const Layout l = soa(md.nv(), 9);
    EXPECT_LE(device_run<double>(md, 9, l, l, true).jsi, tol);
  }
}

TEST(CudaFdDense, PivotFailuresReported) {
  SKIP_WITHOUT_CUDA_DEVICE();
  // a massless leaf on a 70-body chain: M's last row and column vanish, every
  // instance fails at the last DoF (the leading minor of order 70), qdd untouched
  const Index n = 70, B = 12;
  const Model md = massless_leaf(int(n));
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = B;
  cuda::CudaForwardDynamics<double> engine(md, o, FdMethod::Jsi);
  EXPECT_EQ(engine.strategy(), "jsi_dense");
  std::vector<double> x(n * B, 0.25), qdd(n * B, kSentinel);
  using V = BatchView<const double>;
  const FdBatchIn<double> in{V::soa(x.data(), n, B), V::soa(x.data(), n, B), V::soa(x.data(), n, B)};
  const BatchStatus st = engine.compute(in, BatchView<double>::soa(qdd.data(), n, B));
  EXPECT_EQ(st.failed, B);
  EXPECT_EQ(st.first_instance, 0);
  EXPECT_EQ(st.first_dof, n - 1);
  EXPECT_EQ(std::count(qdd.begin(), qdd.end(), kSentinel), n * B) << "a failed instance's qdd was written";
  // over max_batch on the device path: an error value
  EXPECT_EQ(engine.compute_async({V::soa(x.data(), n, B + 1), V::soa(x.data(), n, B + 1), V::soa(x.data(), n, B + 1)},
                                 BatchView<double>::soa(qdd.data(), n, B + 1), nullptr, nullptr),
            cudaErrorInvalidValue);
}
