// The second-order derivative engine (make_id_second_derivatives; scandyn/engine.hpp)
// on the CPU backends: serial and OpenMP equal to the serial rnea_second_derivatives
// bit for bit (the same instance function), in aos and soa layouts, with dM/dq and
// external wrenches, double and float; bad models, options and batches refused.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "scandyn/algorithm/second_derivatives.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "second_order_tensors.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

using test::SecondOrderTensors;

template <class S>
void engines_equal_the_serial_function(const std::string& name, const Model& model_d) {
  SCOPED_TRACE(name + (sizeof(S) == 8 ? " double" : " float"));
  const ModelTpl<S> model = model_d.cast<S>();
  const Index nv = model.nv(), B = 7, n3 = nv * nv * nv;
  std::mt19937_64 rng(11 + nv);
  const std::vector<S> q = test::cast_vector<S>(test::random_vector(rng, nv * B, -1.5, 1.5)),
                       qd = test::cast_vector<S>(test::random_vector(rng, nv * B, -1.5, 1.5)),
                       qdd = test::cast_vector<S>(test::random_vector(rng, nv * B, -3, 3));
  const std::vector<Force<S>> fext = test::cast_wrenches<S>(test::random_wrenches<double>(rng, nv * B, 1.0));
  // the serial function, instance by instance (row-major tensors)
  SecondDerivativeData<S> sd(model);
  std::vector<S> ref(4 * static_cast<std::size_t>(n3) * B);
  for (Index b = 0; b < B; ++b) {
    S* r = ref.data() + 4 * static_cast<std::size_t>(n3) * b;
    const std::size_t o = static_cast<std::size_t>(b) * nv;
    rnea_second_derivatives(model, sd, q.data() + o, qd.data() + o, qdd.data() + o, fext.data() + o, r, r + n3,
                            r + 2 * n3, r + 3 * n3);
  }
  using V = BatchView<const S>;
  const IdBatchIn<S> in{V::aos(q.data(), nv, B), V::aos(qd.data(), nv, B), V::aos(qdd.data(), nv, B), fext.data()};
  for (BackendKind kind : {BackendKind::Serial, BackendKind::OpenMP}) {
    if (!backend_unusable(kind).empty()) continue;
    for (bool soa : {false, true}) {
      BackendOptions o;
      o.backend = kind;
      o.max_batch = B;
      o.threads = 3;
      SecondOrderTensors<S> got(nv, B, soa);
      const auto engine = make_id_second_derivatives(model, o);
      EXPECT_TRUE(engine->exact());
      engine->compute(in, got.out());
      std::size_t differ = 0;
      for (Index b = 0; b < B; ++b)
        for (int t = 0; t < 4; ++t)
          for (Index e = 0; e < n3; ++e)
            differ += !(got.at(t, e, b) == ref[(4 * static_cast<std::size_t>(b) + t) * n3 + e]);
      EXPECT_EQ(differ, 0u) << to_string(kind) << (soa ? " soa" : " aos");
    }
  }
  // dM_dq is optional: without it the three tensors are the same
  BackendOptions o;
  o.max_batch = B;
  SecondOrderTensors<S> got(nv, B, true);
  IdSecondDerivativesOut<S> out = got.out();
  out.dM_dq = {};
  make_id_second_derivatives(model, o)->compute(in, out);
  for (Index e = 0; e < n3; ++e) {
    EXPECT_EQ(got.at(0, e, 2), ref[(4 * 2 + 0) * static_cast<std::size_t>(n3) + e]);
    EXPECT_TRUE(std::isnan(got.at(3, e, 2)));  // not written
  }
}

std::vector<std::pair<std::string, Model>> models() {
  std::vector<std::pair<std::string, Model>> m;
  m.emplace_back("iiwa", test::load_robot("iiwa.urdf"));
  m.emplace_back("hyq", test::load_robot("hyq.urdf"));
  m.emplace_back("random_model(10) (prismatic joints)", test::random_model(10, 9));
  return m;
}

TEST(SecondDerivativeEngines, SerialAndOpenMPEqualTheSerialFunctionDouble) {
  for (auto& [name, model] : models()) engines_equal_the_serial_function<double>(name, model);
}

TEST(SecondDerivativeEngines, SerialAndOpenMPEqualTheSerialFunctionFloat) {
  for (auto& [name, model] : models()) engines_equal_the_serial_function<float>(name, model);
}

TEST(SecondDerivativeEngines, RefusesMultiDofJointsOtherStrategiesAndBadBatches) {
  BackendOptions o;
  o.max_batch = 2;
  EXPECT_THROW(make_id_second_derivatives(test::load_floating("chain:3"), o), BackendError);
  o.strategy = IdStrategy::ScanLocal;
  EXPECT_THROW(make_id_second_derivatives(load_model("chain:3"), o), BackendError);
  o.strategy = IdStrategy::Auto;
  const Model model = load_model("chain:3");
  const auto engine = make_id_second_derivatives(model, o);
  std::vector<double> x(3 * 3, 0.1), t(4 * 27 * 3);
  using V = BatchView<const double>;
  auto tensor = [&](int k, Index B) { return BatchView<double>::aos(t.data() + k * 27 * 3, 27, B); };
  // three instances for a max_batch of 2
  EXPECT_THROW(engine->compute({V::aos(x.data(), 3, 3), V::aos(x.data(), 3, 3), V::aos(x.data(), 3, 3)},
                               {tensor(0, 3), tensor(1, 3), tensor(2, 3), {}}),
               BackendError);
  // dM_dq of another batch size
  EXPECT_THROW(engine->compute({V::aos(x.data(), 3, 2), V::aos(x.data(), 3, 2), V::aos(x.data(), 3, 2)},
                               {tensor(0, 2), tensor(1, 2), tensor(2, 2), tensor(3, 1)}),
               BackendError);
  // a tensor without data
  EXPECT_THROW(engine->compute({V::aos(x.data(), 3, 2), V::aos(x.data(), 3, 2), V::aos(x.data(), 3, 2)},
                               {tensor(0, 2), BatchView<double>{nullptr, 2, 1, 27}, tensor(2, 2), {}}),
               BackendError);
}

}  // namespace
}  // namespace scandyn
