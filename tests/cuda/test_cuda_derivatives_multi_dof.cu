// The CUDA derivative engines (scandyn/cuda/derivatives.hpp) on models with multi-DoF
// joints (a floating base, spherical joints): the general kernels
// (id_derivatives_general_kernel, fd_derivatives_general_kernel, one thread per
// instance over rnea_derivatives_general_instance / aba_general +
// fd_derivatives_general_instance) against the serial engines on floating iiwa, hyq and
// atlas, ball ropes, random floating trees with spherical joints and random free
// chains, with external wrenches, double and float, host views in aos (row-major
// blocks: the factor over the DoF runs) and soa (instance innermost: the tree walks)
// layouts, and compute_async on device pointers; on the host (CI) the kernels'
// per-instance functions (scandyn/cuda/derivatives_general.hpp) against the serial engines. A model whose capacity (the smallest
// of 8, 16, 32, 64 that holds its nv) this build does not compile
// (SCANDYN_CUDA_ALL_CAPACITIES=OFF: 8 only) is skipped with the reason printed. Device
// tests skip with the reason when no device is usable; the host tests (the engines take
// these models; the refusal beyond 64 DoF names the limit) run everywhere.
#include <gtest/gtest.h>

#include <cmath>
#include <iostream>
#include <random>
#include <string>
#include <vector>

#include "cuda_derivatives_test_util.hpp"
#include "cuda_test_util.hpp"
#include "floating_models.hpp"
#include "scandyn/cuda/derivatives.hpp"
#include "scandyn/cuda/derivatives_general.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

template <class S>
using Blocks = test::DerivativeBlocks<S>;

// The capacity of the general kernels that holds nv DoF (GeneralDerivativeModel's).
Index capacity_for(Index nv) { return nv <= 8 ? 8 : nv <= 16 ? 16 : nv <= 32 ? 32 : 64; }

// "" when the general derivative kernels of this build take the model, else why not.
std::string not_compiled_reason(const Model& m) {
  const Index cap = capacity_for(m.nv());
  if (cuda::compiled_capacity(cap)) return "";
  return "skipped: nv = " + std::to_string(m.nv()) + " needs the capacity-" + std::to_string(cap) +
         " kernels, which this build does not compile (SCANDYN_CUDA_ALL_CAPACITIES=OFF: capacity 8 only)";
}

// Whether the general derivative kernels of this build take the model; when not, a
// note with the reason.
bool compiled_here(const std::string& name, const Model& m) {
  const std::string why = not_compiled_reason(m);
  if (!why.empty()) std::cout << "[ note ] " << name << ": " << why << "\n";
  return why.empty();
}

std::vector<std::pair<std::string, Model>> models() {
  std::vector<std::pair<std::string, Model>> m;
  // small enough for capacity 8 (every build)
  m.emplace_back("random_floating_model(1)", test::random_floating_model(1, 2));  // a free body: nv 6
  m.emplace_back("ballrope:2", load_model("ballrope:2"));                         // two spherical joints: nv 6
  m.emplace_back("random_free_chain(2)", test::random_free_chain(2, 3));          // nv 7
  m.emplace_back("random_free_chain(3)", test::random_free_chain(3, 4));          // nv 8
  // capacity 16 and beyond
  m.emplace_back("ballrope:2 (floating)", test::load_floating("ballrope:2"));           // free + spherical: nv 9
  m.emplace_back("random_floating_model(2)", test::random_floating_model(2, 5, 1.0));  // free + spherical: nv 9
  m.emplace_back("ballrope:3", load_model("ballrope:3"));  // nv 9
  m.emplace_back("ballrope:3 (floating)", test::load_floating("ballrope:3"));
  m.emplace_back("iiwa (floating)", test::load_floating(test::model_path("iiwa.urdf")));    // nv 13
  m.emplace_back("hyq (floating)", test::load_floating(test::model_path("hyq.urdf")));      // nv 18
  m.emplace_back("atlas (floating)", test::load_floating(test::model_path("atlas.urdf")));  // nv 36
  m.emplace_back("random_free_chain(12)", test::random_free_chain(12, 9));
  for (int n : {3, 5, 8, 12, 20})
    m.emplace_back("random_floating_model(" + std::to_string(n) + ")", test::random_floating_model(n, 10 + n));
  m.emplace_back("ballrope:21", load_model("ballrope:21"));  // nv 63, nq 84: capacity 64
  return m;
}

using test::block_err;

// A condition estimate of M over the instances: nv max|M| max|M^-1| (from the serial
// did's M and dfd's M^-1), which scales dfd's rounding (double's tolerance).
template <class S>
double cond_estimate(const Blocks<S>& id, const Blocks<S>& fd, Index nv, Index B) {
  double worst = 1;
  for (Index b = 0; b < B; ++b) {
    double m = 0, mi = 0;
    for (Index e = 0; e < nv * nv; ++e) {
      m = std::max(m, std::fabs(double(id.v[2].at(e, b))));
      mi = std::max(mi, std::fabs(double(fd.v[2].at(e, b))));
    }
    worst = std::max(worst, nv * m * mi);
  }
  return worst;
}

struct Errors {
  double id = 0, fd = 0, qdd = 0, cond = 1;
};

// The cuda engines against the serial ones in precision S on B random states with
// external wrenches; outputs in soa or aos host views.
template <class S>
Errors compare_with_serial(const Model& model_d, bool soa, unsigned seed) {
  const ModelTpl<S> model = model_d.cast<S>();
  const Index nv = model.nv(), B = 37;
  const test::SoaInputs<S> x(test::random_soa_states(model_d, B, seed, true));
  const IdBatchIn<S> id_in = x.id();
  const FdBatchIn<S> fd_in = x.fd();
  Blocks<S> id_ref(nv, B, false), fd_ref(nv, B, false), id_cuda(nv, B, soa), fd_cuda(nv, B, soa);
  std::vector<S> qdd_ref(nv * B), qdd_cuda(nv * B, S(NAN));
  const BatchStatus sr = test::serial_derivatives(model, B, id_in, fd_in, id_ref, fd_ref, qdd_ref);
  EXPECT_TRUE(sr.ok()) << "serial: " << sr.message();
  BackendOptions o;
  o.max_batch = B;
  o.backend = BackendKind::Cuda;
  const auto id = make_id_derivatives(model, o);
  const auto fd = make_fd_derivatives(model, o);
  EXPECT_EQ(id->strategy(), "general");
  EXPECT_EQ(fd->strategy(), "general");
  id->compute(id_in, {id_cuda.v[0], id_cuda.v[1], id_cuda.v[2]});
  const BatchStatus st =
      fd->compute(fd_in, {fd_cuda.v[0], fd_cuda.v[1], fd_cuda.v[2], BatchView<S>::aos(qdd_cuda.data(), nv, B)});
  EXPECT_TRUE(st.ok()) << "cuda: " << st.message();
  Errors e;
  e.id = block_err(id_cuda, id_ref, nv, B);
  e.fd = block_err(fd_cuda, fd_ref, nv, B);
  e.qdd = test::max_rel_err(qdd_cuda, qdd_ref);
  e.cond = cond_estimate(id_ref, fd_ref, nv, B);
  return e;
}

// Double: did and qdd to 1e-10 relative to each block's largest entry (or 1); dfd to
// max(1e-10, 1e-14 cond(M)) (M^-1 amplifies the device's different rounding: FMA
// contraction, the library's sin/cos).
TEST(CudaMultiDofDerivatives, MatchSerialDouble) {
  SKIP_WITHOUT_CUDA_DEVICE();
  int ran = 0;
  for (const auto& [name, model] : models()) {
    if (!compiled_here(name, model)) continue;
    ++ran;
    for (bool soa : {false, true}) {
      const Errors e = compare_with_serial<double>(model, soa, 7 + static_cast<unsigned>(model.nv()));
      const double fd_tol = std::max(1e-10, 1e-14 * e.cond);
      EXPECT_LT(e.id, 1e-10) << name << (soa ? " soa" : " aos");
      EXPECT_LT(e.fd, fd_tol) << name << (soa ? " soa" : " aos") << " (cond estimate " << e.cond << ")";
      EXPECT_LT(e.qdd, 1e-10) << name << (soa ? " soa" : " aos");
      std::cout << "[ info ] double " << name << (soa ? " soa" : " aos") << ": did " << e.id << ", dfd " << e.fd
                << " (tolerance " << fd_tol << "), qdd " << e.qdd << "\n";
    }
  }
  if (ran == 0) GTEST_SKIP() << "no model fits the capacities this build compiles";
}

// Float against the serial float engine: did 1e-4 and dfd 1e-2 of each block's largest
// entry (the serial float against double: 1.6e-6 and 2.3e-3, atlas's M^-1). The ball
// ropes are left out (their 1e-8 kg m^2 links fail float's pivots).
TEST(CudaMultiDofDerivatives, MatchSerialFloat) {
  SKIP_WITHOUT_CUDA_DEVICE();
  int ran = 0;
  for (const auto& [name, model] : models()) {
    if (name.find("ballrope") != std::string::npos) continue;
    if (!compiled_here(name, model)) continue;
    ++ran;
    for (bool soa : {false, true}) {
      const Errors e = compare_with_serial<float>(model, soa, 11 + static_cast<unsigned>(model.nv()));
      EXPECT_LT(e.id, 1e-4) << name << (soa ? " soa" : " aos");
      EXPECT_LT(e.fd, 1e-2) << name << (soa ? " soa" : " aos");
      EXPECT_LT(e.qdd, 1e-2) << name << (soa ? " soa" : " aos");
      std::cout << "[ info ] float " << name << (soa ? " soa" : " aos") << ": did " << e.id << ", dfd " << e.fd
                << ", qdd " << e.qdd << "\n";
    }
  }
  if (ran == 0) GTEST_SKIP() << "no model fits the capacities this build compiles";
}

// compute_async on device pointers (soa), failed_dof written, qdd not requested.
TEST(CudaMultiDofDerivatives, DevicePointersOnAStream) {
  SKIP_WITHOUT_CUDA_DEVICE();
  Model model = test::load_floating(test::model_path("hyq.urdf"));
  if (!not_compiled_reason(model).empty()) model = test::random_free_chain(3, 4);  // nv 8
  const Index nv = model.nv(), B = 1000;
  const test::SoaStates x = test::random_soa_states(model, B, 21, false);
  std::vector<double> got;
  std::vector<int> failed;
  Blocks<double> ref(nv, B, true);
  ASSERT_NO_FATAL_FAILURE(test::fd_derivatives_on_a_stream(model, B, x.q, x.qd, x.u, got, ref, failed));
  double err = 0, scale = 1;
  for (std::size_t k = 0; k < got.size(); ++k) {
    err = std::max(err, std::fabs(got[k] - ref.data[k]));
    scale = std::max(scale, std::fabs(ref.data[k]));
  }
  EXPECT_LT(err / scale, 1e-9) << model.name;
  for (int f : failed) EXPECT_EQ(f, -1);
}

// Host only (CI): the engines no longer refuse multi-DoF joints on cuda (without a
// device they fail for the device's sake only); beyond 64 DoF the refusal names the
// limit, before any device work; the kernel model's capacity and DoF tree.
TEST(CudaMultiDofDerivativesHost, TakenUpToTheLimit) {
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 4;
  const bool device = test::no_device_reason().empty();
  for (const Model& m : {test::load_floating(test::model_path("hyq.urdf")), load_model("ballrope:3")}) {
    for (int k = 0; k < 2; ++k) {
      try {
        if (k == 0) {
          const auto e = make_id_derivatives(m, o);
          EXPECT_EQ(e->strategy(), "general");
        } else {
          const auto e = make_fd_derivatives(m, o);
          EXPECT_EQ(e->strategy(), "general");
        }
        EXPECT_TRUE(device) << m.name << ": made without a device";
      } catch (const BackendError& e) {
        const std::string what = e.what();
        EXPECT_EQ(what.find("revolute and prismatic"), std::string::npos) << what;
        EXPECT_EQ(what.find("multi-DoF"), std::string::npos) << what;
        // no device, or (SCANDYN_CUDA_ALL_CAPACITIES=OFF) a capacity not compiled
        EXPECT_TRUE(!device || !not_compiled_reason(m).empty()) << what;
        if (!not_compiled_reason(m).empty() && device)
          EXPECT_NE(what.find("SCANDYN_CUDA_ALL_CAPACITIES"), std::string::npos) << what;
      }
    }
  }
  // beyond kMaxThreadDofs: ballrope:22 has 66 DoF
  const Model big = load_model("ballrope:22");
  ASSERT_EQ(big.nv(), 66);
  for (int k = 0; k < 2; ++k) {
    try {
      if (k == 0) make_id_derivatives(big, o);
      else make_fd_derivatives(big, o);
      ADD_FAILURE() << "cuda took 66 DoF";
    } catch (const BackendError& e) {
      const std::string what = e.what();
      EXPECT_NE(what.find("66 DoF"), std::string::npos) << what;
      EXPECT_NE(what.find("at most 64"), std::string::npos) << what;
    }
  }
  try {
    cuda::GeneralDerivativeModel<double>{big};
    ADD_FAILURE() << "GeneralDerivativeModel took 66 DoF";
  } catch (const BackendError& e) {
    EXPECT_NE(std::string(e.what()).find("at most 64"), std::string::npos) << e.what();
  }
  // the kernel model: capacity by nv, the tree of DoFs as the serial reference's
  const Model rope = load_model("ballrope:2");  // nv 6, nq 8: capacity 8, compiled everywhere
  const cuda::GeneralDerivativeModel<double> g(rope);
  EXPECT_EQ(g.capacity(), 8);
  EXPECT_EQ(g.nv(), 6);
  EXPECT_EQ(g.nq(), 8);
  EXPECT_EQ(g.nbodies(), 2);
  const auto& p = std::get<cuda::GeneralDerivativeParams<double, 8>>(g.params());
  for (Index i = 0; i < 6; ++i) {
    EXPECT_EQ(p.dof_parent[i], i - 1);
    EXPECT_EQ(p.dof_last[i], 5);
    EXPECT_EQ(p.dof_run[i], 0);
  }
  const Model r63 = load_model("ballrope:21");
  constexpr int q64 = cuda::GeneralDerivativeParams<double, 64>::q_capacity;
  EXPECT_LE(r63.nq(), q64);
  EXPECT_EQ(cuda::GeneralDerivativeModel<double>(r63).capacity(), 64);
  EXPECT_EQ(cuda::GeneralDerivativeModel<double>(test::load_floating(test::model_path("hyq.urdf"))).capacity(), 32);
}

// Host only (CI): the kernels' per-instance functions (id_derivatives_general_thread,
// fd_derivatives_general_thread of scandyn/cuda/derivatives_general.hpp, run on the
// host over GeneralDerivativeModel's parameter block, every capacity) against the
// serial engines on soa and aos outputs, with external wrenches and qdd: the same
// functions on the same inputs (equal bit for bit without -march=native; tolerance
// 1e-12 of each block's largest entry, dfd max(1e-12, 1e-14 cond(M)) where the
// compilers contract differently).
template <class S>
void host_composition(const std::string& name, const Model& model_d, bool soa) {
  const ModelTpl<S> model = model_d.cast<S>();
  const Index nv = model.nv(), B = 5;
  const test::SoaInputs<S> x(test::random_soa_states(model_d, B, 31, true));
  const IdBatchIn<S> id_in = x.id();
  const FdBatchIn<S> fd_in = x.fd();
  Blocks<S> id_ref(nv, B, false), fd_ref(nv, B, false), id_got(nv, B, soa), fd_got(nv, B, soa);
  std::vector<S> qdd_ref(nv * B), qdd_got(nv * B, S(NAN));
  ASSERT_TRUE(test::serial_derivatives(model, B, id_in, fd_in, id_ref, fd_ref, qdd_ref).ok()) << name;
  const cuda::GeneralDerivativeModel<S> g(model);
  std::visit(
      [&](const auto& p) {
        for (Index b = 0; b < B; ++b) {
          cuda::id_derivatives_general_thread(p, id_in, {id_got.v[0], id_got.v[1], id_got.v[2]}, b);
          EXPECT_EQ(cuda::fd_derivatives_general_thread(
                        p, fd_in, {fd_got.v[0], fd_got.v[1], fd_got.v[2], BatchView<S>::aos(qdd_got.data(), nv, B)},
                        b),
                    -1)
              << name;
        }
      },
      g.params());
  // M^-1 amplifies rounding differences by cond(M): the serial engine and the kernel's
  // composition are compiled apart (with -march=native, FMA contractions differ);
  // measured on an H200's host: floating ball ropes 5e-10..1e-9 (cond ~1e5-1e6), the
  // rest <= 2e-13
  const double tol = std::max(1e-12, 1e-14 * cond_estimate(id_ref, fd_ref, nv, B));
  const double eid = block_err(id_got, id_ref, nv, B), efd = block_err(fd_got, fd_ref, nv, B);
  EXPECT_LT(eid, 1e-12) << name << (soa ? " soa" : " aos");
  EXPECT_LT(efd, tol) << name << (soa ? " soa" : " aos");
  EXPECT_LT(test::max_rel_err(qdd_got, qdd_ref), 1e-12) << name;
  std::cout << "[ info ] host composition " << name << (soa ? " soa" : " aos") << ": did " << eid << ", dfd " << efd
            << "\n";
}

TEST(CudaMultiDofDerivativesHost, KernelCompositionMatchesSerial) {
  for (const auto& [name, model] : models())
    for (bool soa : {false, true}) host_composition<double>(name, model, soa);
}

}  // namespace
}  // namespace scandyn
