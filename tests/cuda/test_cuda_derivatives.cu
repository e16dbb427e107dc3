// The CUDA derivative engines (scandyn/cuda/derivatives.hpp) against the serial
// engines: every model shape of the thread-per-instance kernels (chains at the
// capacities 8..64 and past them, trees, chains from the base, random trees with
// prismatic joints, branched trees of up to 8 DoF), the robots, with external
// wrenches, double and float, host views in aos and soa layouts, and compute_async on
// device pointers. Device tests skip with the reason when no device is usable; the
// argument checks run everywhere. Each comparison runs under the default kernels and
// the A/B switches of kernels/derivatives.cu (read at every launch):
// SCANDYN_DFD_KERNEL=packed|tree and SCANDYN_DID_KERNEL=recursion.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdlib>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "cuda_derivatives_test_util.hpp"
#include "cuda_test_util.hpp"
#include "scandyn/cuda/derivatives.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

template <class S>
using Blocks = test::DerivativeBlocks<S>;

using test::block_err;

// Sets an environment variable (null: unsets it) for its lifetime, then restores it.
class ScopedEnv {
 public:
  ScopedEnv(const char* name, const char* value) : name_(name) {
    if (const char* old = std::getenv(name)) old_ = old;
    if (value)
      setenv(name, value, 1);
    else
      unsetenv(name);
  }
  ~ScopedEnv() {
    if (old_)
      setenv(name_, old_->c_str(), 1);
    else
      unsetenv(name_);
  }
  ScopedEnv(const ScopedEnv&) = delete;
  ScopedEnv& operator=(const ScopedEnv&) = delete;

 private:
  const char* name_;
  std::optional<std::string> old_;
};

// The kernel choices under test: the defaults (lean chains), then the switches
// (SCANDYN_DFD_KERNEL, SCANDYN_DID_KERNEL; null: unset).
struct KernelChoice {
  const char* dfd;
  const char* did;
};
constexpr KernelChoice kKernelChoices[] = {{nullptr, nullptr}, {"packed", "recursion"}, {"tree", nullptr}};

std::string choice_name(const KernelChoice& c) {
  return std::string(" [SCANDYN_DFD_KERNEL=") + (c.dfd ? c.dfd : "") + " SCANDYN_DID_KERNEL=" + (c.did ? c.did : "") +
         "]";
}

std::vector<std::pair<std::string, Model>> models() {
  auto m = test::thread_shape_models();
  for (const char* f : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) m.emplace_back(f, test::load_robot(f));
  // branched trees at capacity 8 (the forward dynamics' packed factor in registers,
  // packed_fd_solve: dense loops over the tree's exact zeros)
  m.emplace_back("random_model(8)", test::random_model(8, 6));
  m.emplace_back("random_model(6)", test::random_model(6, 7));
  m.emplace_back("random_chains_from_base(7)", test::random_chains_from_base(7, 8, {2, 5}));
  return m;
}

// Tolerances against the serial engine in the same precision (the device contracts
// to FMA and its ABA uses the library's sin/cos): double 1e-9 relative to each
// block's largest entry (or 1); float, on models of up to 16 DoF, 1e-3 for inverse
// dynamics and 1e-2 for forward dynamics (float rounding times cond(M)).
template <class S>
void compare_with_serial(const std::string& name, const Model& model_d, bool soa) {
  const ModelTpl<S> model = model_d.cast<S>();
  const Index nv = model.nv(), B = 37;
  std::mt19937_64 rng(nv + 3);
  const auto cast = [](const std::vector<double>& v) { return std::vector<S>(v.begin(), v.end()); };
  const std::vector<S> q = cast(test::random_vector(rng, nv * B, -1.5, 1.5)),
                       qd = cast(test::random_vector(rng, nv * B, -1.5, 1.5)),
                       x = cast(test::random_vector(rng, nv * B, -3, 3));
  std::vector<Force<S>> fext;
  for (const auto& f : test::random_wrenches<double>(rng, nv * B, 1.0)) fext.push_back(f.template cast<S>());
  using V = BatchView<const S>;
  const IdBatchIn<S> id_in{V::aos(q.data(), nv, B), V::aos(qd.data(), nv, B), V::aos(x.data(), nv, B), fext.data()};
  const FdBatchIn<S> fd_in{V::aos(q.data(), nv, B), V::aos(qd.data(), nv, B), V::aos(x.data(), nv, B), fext.data()};
  Blocks<S> id_ref(nv, B, false), fd_ref(nv, B, false), id_cuda(nv, B, soa), fd_cuda(nv, B, soa);
  std::vector<S> qdd_ref(nv * B), qdd_cuda(nv * B, S(NAN));
  ASSERT_TRUE(test::serial_derivatives(model, B, id_in, fd_in, id_ref, fd_ref, qdd_ref).ok());
  BackendOptions o;
  o.max_batch = B;
  o.backend = BackendKind::Cuda;
  make_id_derivatives(model, o)->compute(id_in, {id_cuda.v[0], id_cuda.v[1], id_cuda.v[2]});
  const BatchStatus st = make_fd_derivatives(model, o)->compute(
      fd_in, {fd_cuda.v[0], fd_cuda.v[1], fd_cuda.v[2], BatchView<S>::aos(qdd_cuda.data(), nv, B)});
  ASSERT_TRUE(st.ok()) << st.message();
  const bool dbl = sizeof(S) == 8;
  EXPECT_LT(block_err(id_cuda, id_ref, nv, B), dbl ? 1e-9 : 1e-3) << name;
  // FD derivatives go through M^-1: on chain:64 (cond(M) ~ 1e7) the device's rounding
  // (FMA, sin/cos) shows at ~1e-9, so long chains get 1e-8 in double
  EXPECT_LT(block_err(fd_cuda, fd_ref, nv, B), dbl ? (nv > 32 ? 1e-8 : 1e-9) : 1e-2) << name;
  EXPECT_LT(test::max_rel_err(qdd_cuda, qdd_ref), dbl ? 1e-9 : 1e-2) << name;
}

TEST(CudaDerivatives, MatchSerialDouble) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const KernelChoice& c : kKernelChoices) {
    const ScopedEnv dfd("SCANDYN_DFD_KERNEL", c.dfd), did("SCANDYN_DID_KERNEL", c.did);
    for (auto& [name, model] : models())
      for (bool soa : {false, true}) compare_with_serial<double>(name + choice_name(c), model, soa);
  }
}

TEST(CudaDerivatives, MatchSerialFloat) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (const KernelChoice& c : kKernelChoices) {
    const ScopedEnv dfd("SCANDYN_DFD_KERNEL", c.dfd), did("SCANDYN_DID_KERNEL", c.did);
    for (auto& [name, model] : models())
      if (model.nv() <= 16) compare_with_serial<float>(name + choice_name(c), model, true);
  }
}

TEST(CudaDerivatives, DevicePointersOnAStream) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model model = test::load_robot("iiwa.urdf");
  const Index nv = model.nv(), B = 1000;
  std::mt19937_64 rng(5);
  const std::vector<double> q = test::random_vector(rng, nv * B, -1, 1), qd = test::random_vector(rng, nv * B, -1, 1),
                            tau = test::random_vector(rng, nv * B, -1, 1);
  std::vector<double> got;
  std::vector<int> failed;
  Blocks<double> ref(nv, B, true);  // the serial engine on soa host views of the same inputs
  ASSERT_NO_FATAL_FAILURE(test::fd_derivatives_on_a_stream(model, B, q, qd, tau, got, ref, failed));
  double err = 0;
  for (std::size_t k = 0; k < got.size(); ++k) err = std::max(err, std::fabs(got[k] - ref.data[k]));
  EXPECT_LT(err, 1e-9);
  for (int f : failed) EXPECT_EQ(f, -1);
}

TEST(CudaDerivativesErrors, ArgumentsAndNoDevice) {
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 4;
  // beyond the thread-per-instance capacity: refused before any device work
  EXPECT_THROW(make_id_derivatives(load_model("chain:65"), o), BackendError);
  EXPECT_THROW(make_fd_derivatives(load_model("chain:65"), o), BackendError);
  o.fd_method = FdMethod::Jsi;
  EXPECT_THROW(make_fd_derivatives(load_model("chain:3"), o), BackendError);
  o.fd_method = FdMethod::Auto;
  if (!test::no_device_reason().empty()) {
    EXPECT_THROW(make_id_derivatives(load_model("chain:3"), o), BackendError);
    EXPECT_THROW(make_fd_derivatives(load_model("chain:3"), o), BackendError);
  }
}

}  // namespace
}  // namespace scandyn
