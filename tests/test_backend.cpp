// Batched inverse dynamics: every CPU backend and strategy against the reference.
#include <gtest/gtest.h>

#include <limits>
#include <random>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

struct Case {
  BackendKind backend;
  IdStrategy strategy;
  int threads;
};

std::vector<Case> cases() {
  std::vector<Case> c = {{BackendKind::Serial, IdStrategy::Recursion, 1},
                         {BackendKind::Serial, IdStrategy::ScanLocal, 1},
                         {BackendKind::Serial, IdStrategy::ScanWorld, 1}};
#if SCANDYN_HAS_OPENMP
  for (int t : {2})
    for (IdStrategy s : {IdStrategy::Auto, IdStrategy::Recursion, IdStrategy::ScanLocal, IdStrategy::ScanWorld})
      c.push_back({BackendKind::OpenMP, s, t});
#endif
  return c;
}

// Runs one engine on B random instances in the given layout and compares every
// instance with the reference RNEA on the same inputs.
template <class S>
double batch_error(const Model& md, const Case& c, Index B, bool soa, bool with_fext) {
  const ModelTpl<S> m = md.cast<S>();
  const Index nv = m.nv();
  std::mt19937_64 g(nv * 7 + B);
  const auto q = test::cast_vector<S>(test::random_vector(g, nv * B, -1, 1));
  const auto qd = test::cast_vector<S>(test::random_vector(g, nv * B, -1, 1));
  const auto qdd = test::cast_vector<S>(test::random_vector(g, nv * B, -1, 1));
  std::vector<Force<S>> fext(static_cast<std::size_t>(nv) * B);
  for (auto& f : fext) {
    const auto r = test::random_vector(g, 6, -1, 1);
    f = Force<S>{{S(r[0]), S(r[1]), S(r[2])}, {S(r[3]), S(r[4]), S(r[5])}};
  }
  std::vector<S> tau(static_cast<std::size_t>(nv) * B, std::numeric_limits<S>::quiet_NaN());
  auto view = [&](auto* p) {
    using T = std::remove_pointer_t<decltype(p)>;
    return soa ? BatchView<T>::soa(p, nv, B) : BatchView<T>::aos(p, nv, B);
  };
  BackendOptions o;
  o.backend = c.backend;
  o.strategy = c.strategy;
  o.threads = c.threads;
  o.max_batch = B;
  auto engine = make_inverse_dynamics<S>(m, o);
  IdBatchIn<S> in{view(q.data()), view(qd.data()), view(qdd.data()), with_fext ? fext.data() : nullptr};
  engine->compute(in, view(tau.data()));

  Data d(md, false);
  double worst = 0;
  std::vector<double> qi(nv), qdi(nv), qddi(nv), ref(nv), ours(nv);
  std::vector<Force<double>> fi(nv);
  for (Index b = 0; b < B; ++b) {
    for (Index i = 0; i < nv; ++i) {
      qi[i] = double(in.q.at(i, b));
      qdi[i] = double(in.qd.at(i, b));
      qddi[i] = double(in.qdd.at(i, b));
      fi[i] = fext[static_cast<std::size_t>(b) * nv + i].template cast<double>();
      ours[i] = double(view(tau.data()).at(i, b));
    }
    rnea(md, d, qi.data(), qdi.data(), qddi.data(), ref.data(), with_fext ? fi.data() : nullptr);
    const double e = test::max_rel_err(ours, ref);
    if (!(e <= worst)) worst = e;
  }
  return worst;
}

std::string label(const Case& c) {
  return std::string(to_string(c.backend)) + "/" + to_string(c.strategy) + "/t" + std::to_string(c.threads);
}

}  // namespace

TEST(Backend, EveryCpuEngineMatchesReference) {
  const std::vector<std::string> specs = {test::model_path("iiwa.urdf"), test::model_path("hyq.urdf"), "tree:60:2",
                                          "curtain:4:20"};
  for (const auto& s : specs) {
    const Model m = load_model(s);
    for (const Case& c : cases())
      for (Index B : {1, 5, 33})
        for (bool soa : {true, false}) {
          SCOPED_TRACE(s + " " + label(c) + " B=" + std::to_string(B) + (soa ? " soa" : " aos"));
          EXPECT_LT(batch_error<double>(m, c, B, soa, B != 5), 1e-10);
          EXPECT_LT(batch_error<float>(m, c, B, soa, false), 1e-4);
        }
  }
}

TEST(Backend, LongRopeAcrossLinks) {
  const Model m = load_model("rope:20000");
  for (const Case& c : cases()) {
    SCOPED_TRACE(label(c));
    EXPECT_LT(batch_error<double>(m, c, 2, true, true), 1e-10);
  }
}

TEST(Backend, AutoStrategyFollowsShape) {
  EXPECT_EQ(choose_id_strategy(BackendKind::OpenMP, 7, 1000000, 16), IdStrategy::Recursion);
  EXPECT_EQ(choose_id_strategy(BackendKind::OpenMP, 1000000, 1, 16), IdStrategy::ScanLocal);
  EXPECT_EQ(choose_id_strategy(BackendKind::OpenMP, 1000000, 32, 16), IdStrategy::Recursion);
  EXPECT_EQ(choose_id_strategy(BackendKind::OpenMP, 1000000, 1, 1), IdStrategy::Recursion);
}

TEST(Backend, Errors) {
  const Model m = load_model("chain:3");
  BackendOptions o;
  o.max_batch = 2;
  auto e = make_inverse_dynamics<double>(m, o);
  std::vector<double> x(9, 0.0);
  IdBatchIn<double> in{BatchView<const double>::soa(x.data(), 3, 3), BatchView<const double>::soa(x.data(), 3, 3),
                       BatchView<const double>::soa(x.data(), 3, 3)};
  EXPECT_THROW(e->compute(in, BatchView<double>::soa(x.data(), 3, 3)), BackendError);  // above max_batch
  IdBatchIn<double> mixed{BatchView<const double>::soa(x.data(), 3, 2), BatchView<const double>::soa(x.data(), 3, 2),
                          BatchView<const double>::soa(x.data(), 3, 1)};
  EXPECT_THROW(e->compute(mixed, BatchView<double>::soa(x.data(), 3, 2)), BackendError);  // qdd has 1
  IdBatchIn<double> two{BatchView<const double>::soa(x.data(), 3, 2), BatchView<const double>::soa(x.data(), 3, 2),
                        BatchView<const double>::soa(x.data(), 3, 2)};
  EXPECT_THROW(e->compute(two, BatchView<double>::soa(nullptr, 3, 2)), BackendError);  // null tau
  EXPECT_THROW(parse_backend("gpu"), BackendError);
  EXPECT_THROW(parse_strategy("fast"), BackendError);
  o.backend = BackendKind::Cuda;
#if SCANDYN_HAS_CUDA == 0
  EXPECT_THROW(make_inverse_dynamics<double>(m, o), BackendError);
#endif
}
