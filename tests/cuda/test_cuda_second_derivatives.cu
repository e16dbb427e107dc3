// The CUDA second-order derivative engine (scandyn/cuda/second_derivatives.hpp)
// against the serial engine: iiwa, hyq, a random tree with prismatic joints and a
// 40-link chain (the kernel's capacities 8, 16, 64), with external wrenches, double
// and float, host views in aos and soa layouts (batches that are not a multiple of
// the block size), and compute_async on device pointers and a stream. Device tests
// skip with the reason when no device is usable; the argument checks run everywhere.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include "cuda_test_util.hpp"
#include "scandyn/cuda/second_derivatives.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "second_order_tensors.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using test::SecondOrderTensors;

// max over instances and tensors of max |a - b| / max |b| (b's largest entry in that
// tensor of that instance); infinite when a has an entry that is not finite.
template <class S>
double tensor_err(SecondOrderTensors<S>& a, SecondOrderTensors<S>& b) {
  double worst = 0;
  for (int t = 0; t < 4; ++t)
    for (Index i = 0; i < a.B; ++i) {
      double scale = 0, err = 0;
      for (Index e = 0; e < a.n3; ++e) {
        const double x = double(a.view(t).at(e, i)), y = double(b.view(t).at(e, i));
        if (!std::isfinite(x)) return INFINITY;
        scale = std::max(scale, std::fabs(y));
        err = std::max(err, std::fabs(x - y));
      }
      worst = std::max(worst, scale > 0 ? err / scale : err);
    }
  return worst;
}

std::vector<std::pair<std::string, Model>> models() {
  std::vector<std::pair<std::string, Model>> m;
  m.emplace_back("iiwa", test::load_robot("iiwa.urdf"));
  m.emplace_back("hyq", test::load_robot("hyq.urdf"));
  m.emplace_back("random_model(12) (prismatic joints)", test::random_model(12, 9));
  m.emplace_back("chain:40", load_model("chain:40"));
  return m;
}

// Tolerances against the serial engine in the same precision (the device contracts
// to FMA and uses its own sin/cos): double 1e-9 relative to the tensor's largest
// entry; float, on models of up to 16 DoF, 1e-3.
template <class S>
void compare_with_serial(const std::string& name, const Model& model_d, bool soa) {
  SCOPED_TRACE(name + (soa ? " soa" : " aos"));
  const ModelTpl<S> model = model_d.cast<S>();
  const Index nv = model.nv(), B = nv > 16 ? 70 : 100;  // not multiples of the block (64)
  std::mt19937_64 rng(nv + 5);
  const std::vector<S> q = test::cast_vector<S>(test::random_vector(rng, nv * B, -1.5, 1.5)),
                       qd = test::cast_vector<S>(test::random_vector(rng, nv * B, -1.5, 1.5)),
                       qdd = test::cast_vector<S>(test::random_vector(rng, nv * B, -3, 3));
  const std::vector<Force<S>> fext = test::cast_wrenches<S>(test::random_wrenches<double>(rng, nv * B, 1.0));
  using V = BatchView<const S>;
  const IdBatchIn<S> in{V::aos(q.data(), nv, B), V::aos(qd.data(), nv, B), V::aos(qdd.data(), nv, B), fext.data()};
  BackendOptions o;
  o.max_batch = B;
  SecondOrderTensors<S> ref(nv, B, false), got(nv, B, soa);
  make_id_second_derivatives(model, o)->compute(in, ref.out());
  o.backend = BackendKind::Cuda;
  const auto engine = make_id_second_derivatives(model, o);
  EXPECT_EQ(engine->strategy(), "thread");
  engine->compute(in, got.out());
  EXPECT_LT(tensor_err(got, ref), sizeof(S) == 8 ? 1e-9 : 1e-3);
}

TEST(CudaSecondDerivatives, MatchSerialDouble) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (auto& [name, model] : models())
    for (bool soa : {false, true}) compare_with_serial<double>(name, model, soa);
}

TEST(CudaSecondDerivatives, MatchSerialFloat) {
  SKIP_WITHOUT_CUDA_DEVICE();
  for (auto& [name, model] : models())
    if (model.nv() <= 16) compare_with_serial<float>(name, model, true);
}

TEST(CudaSecondDerivatives, DevicePointersOnAStream) {
  SKIP_WITHOUT_CUDA_DEVICE();
  const Model model = test::load_robot("hyq.urdf");
  const Index nv = model.nv(), B = 300, n3 = nv * nv * nv;
  std::mt19937_64 rng(5);
  const std::vector<double> q = test::random_vector(rng, nv * B, -1, 1), qd = test::random_vector(rng, nv * B, -1, 1),
                            qdd = test::random_vector(rng, nv * B, -1, 1);
  const std::vector<Force<double>> fext = test::random_wrenches<double>(rng, nv * B, 1.0);
  test::DeviceArray<double> dq, dqd, dqdd, dout;
  test::DeviceArray<Force<double>> dfext;
  const std::size_t bytes = q.size() * sizeof(double);
  ASSERT_CUDA(dq.alloc(q.size()));
  ASSERT_CUDA(dqd.alloc(q.size()));
  ASSERT_CUDA(dqdd.alloc(q.size()));
  ASSERT_CUDA(dfext.alloc(fext.size()));
  ASSERT_CUDA(dout.alloc(4 * static_cast<std::size_t>(n3) * B));
  ASSERT_CUDA(cudaMemcpy(dq.ptr, q.data(), bytes, cudaMemcpyHostToDevice));
  ASSERT_CUDA(cudaMemcpy(dqd.ptr, qd.data(), bytes, cudaMemcpyHostToDevice));
  ASSERT_CUDA(cudaMemcpy(dqdd.ptr, qdd.data(), bytes, cudaMemcpyHostToDevice));
  ASSERT_CUDA(cudaMemcpy(dfext.ptr, fext.data(), fext.size() * sizeof(Force<double>), cudaMemcpyHostToDevice));
  cuda::CudaIdSecondDerivatives<double> e(model, test::device_path_options());
  using V = BatchView<const double>;
  BatchView<double> out[4];
  for (int t = 0; t < 4; ++t) out[t] = BatchView<double>::soa(dout.ptr + static_cast<std::size_t>(t) * n3 * B, n3, B);
  cudaStream_t stream;
  ASSERT_CUDA(cudaStreamCreate(&stream));
  ASSERT_CUDA(e.compute_async({V::soa(dq.ptr, nv, B), V::soa(dqd.ptr, nv, B), V::soa(dqdd.ptr, nv, B), dfext.ptr},
                              {out[0], out[1], out[2], out[3]}, stream));
  ASSERT_CUDA(cudaStreamSynchronize(stream));
  ASSERT_CUDA(cudaStreamDestroy(stream));
  SecondOrderTensors<double> got(nv, B, true);
  ASSERT_CUDA(cudaMemcpy(got.data.data(), dout.ptr, got.data.size() * sizeof(double), cudaMemcpyDeviceToHost));
  // against the serial engine on soa host views of the same inputs
  SecondOrderTensors<double> ref(nv, B, true);
  BackendOptions s;
  s.max_batch = B;
  make_id_second_derivatives(model, s)->compute(
      {V::soa(q.data(), nv, B), V::soa(qd.data(), nv, B), V::soa(qdd.data(), nv, B), fext.data()}, ref.out());
  EXPECT_LT(tensor_err(got, ref), 1e-9);
  // a batch size that disagrees is refused before any launch
  EXPECT_EQ(e.compute_async({V::soa(dq.ptr, nv, B), V::soa(dqd.ptr, nv, B - 1), V::soa(dqdd.ptr, nv, B)},
                            {out[0], out[1], out[2], {}}, nullptr),
            cudaErrorInvalidValue);
}

TEST(CudaSecondDerivativesErrors, ArgumentsAndNoDevice) {
  BackendOptions o;
  o.backend = BackendKind::Cuda;
  o.max_batch = 4;
  // beyond the thread-per-instance capacity, and multi-DoF joints: refused before any
  // device work
  EXPECT_THROW(make_id_second_derivatives(load_model("chain:65"), o), BackendError);
  EXPECT_THROW(make_id_second_derivatives(test::load_floating("chain:3"), o), BackendError);
  if (!test::no_device_reason().empty())
    EXPECT_THROW(make_id_second_derivatives(load_model("chain:3"), o), BackendError);
}

}  // namespace
}  // namespace scandyn
