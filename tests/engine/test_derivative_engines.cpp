// The derivative engines (make_id_derivatives, make_fd_derivatives; scandyn/engine.hpp)
// on the CPU backends: OpenMP equal to serial bit for bit (the same reference per
// instance), serial equal to the reference functions, any strides of the output
// views, float against double, failures reported, bad batches refused.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "scandyn/algorithm/derivatives.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

namespace scandyn {
namespace {

struct Inputs {
  std::vector<double> q, qd, x;  // x: qdd (id) or tau (fd); instance-major, B x nv
  std::vector<Force<double>> fext;
};

Inputs make_inputs(Index nv, Index B, unsigned seed) {
  std::mt19937_64 rng(seed);
  Inputs in{test::random_vector(rng, nv * B, -1.5, 1.5), test::random_vector(rng, nv * B, -1.5, 1.5),
            test::random_vector(rng, nv * B, -3, 3), test::random_wrenches<double>(rng, nv * B, 1.0)};
  return in;
}

std::vector<std::pair<std::string, Model>> engine_models() {
  std::vector<std::pair<std::string, Model>> models;
  models.emplace_back("iiwa", test::load_robot("iiwa.urdf"));
  models.emplace_back("hyq", test::load_robot("hyq.urdf"));
  models.emplace_back("tree:25:4", load_model("tree:25:4"));
  models.emplace_back("random_model(20)", test::random_model(20, 9));
  return models;
}


template <class S>
using Blocks = test::DerivativeBlocks<S>;

TEST(DerivativeEngines, SerialIsTheReferenceAndOpenMPEqualsSerial) {
  for (auto& [name, model] : engine_models()) {
    SCOPED_TRACE(name);
    const Index nv = model.nv(), B = 9;
    const Inputs in = make_inputs(nv, B, 5 + nv);
    using V = BatchView<const double>;
    const IdBatchIn<double> id_in{V::aos(in.q.data(), nv, B), V::aos(in.qd.data(), nv, B), V::aos(in.x.data(), nv, B),
                                  in.fext.data()};
    const FdBatchIn<double> fd_in{V::aos(in.q.data(), nv, B), V::aos(in.qd.data(), nv, B), V::aos(in.x.data(), nv, B),
                                  in.fext.data()};
    std::vector<Blocks<double>> id_out, fd_out;
    for (BackendKind kind : {BackendKind::Serial, BackendKind::OpenMP}) {
      if (!backend_unusable(kind).empty()) continue;
      for (bool soa : {false, true}) {
        BackendOptions o;
        o.backend = kind;
        o.max_batch = B;
        o.threads = 3;
        id_out.emplace_back(nv, B, soa);
        make_id_derivatives(model, o)->compute(id_in, {id_out.back().v[0], id_out.back().v[1], id_out.back().v[2]});
        fd_out.emplace_back(nv, B, soa);
        std::vector<double> qdd(nv * B, NAN);
        const BatchStatus st = make_fd_derivatives(model, o)->compute(
            fd_in, {fd_out.back().v[0], fd_out.back().v[1], fd_out.back().v[2], BatchView<double>::aos(qdd.data(), nv, B)});
        ASSERT_TRUE(st.ok()) << st.message();
        for (double x : qdd) ASSERT_TRUE(std::isfinite(x));
      }
    }
    // the reference, instance by instance
    DerivativeDataTpl<double> dd(model);
    const std::size_t nn = static_cast<std::size_t>(nv) * nv;
    std::vector<double> ref(3 * nn), fref(3 * nn), qdd(nv);
    for (Index b = 0; b < B; ++b) {
      const std::size_t o = static_cast<std::size_t>(b) * nv;
      rnea_derivatives(model, dd, in.q.data() + o, in.qd.data() + o, in.x.data() + o, in.fext.data() + o,
                       MatrixRef<double>{ref.data(), nv, 1}, MatrixRef<double>{ref.data() + nn, nv, 1},
                       MatrixRef<double>{ref.data() + 2 * nn, nv, 1});
      ASSERT_TRUE(aba_derivatives(model, dd, in.q.data() + o, in.qd.data() + o, in.x.data() + o, in.fext.data() + o,
                                  qdd.data(), MatrixRef<double>{fref.data(), nv, 1},
                                  MatrixRef<double>{fref.data() + nn, nv, 1}, MatrixRef<double>{fref.data() + 2 * nn, nv, 1})
                      .ok());
      for (std::size_t e = 0; e < id_out.size(); ++e)
        for (int k = 0; k < 3; ++k)
          for (Index i = 0; i < nv; ++i)
            for (Index j = 0; j < nv; ++j) {
              ASSERT_EQ(id_out[e].at(k, i, j, b, nv), ref[k * nn + i * nv + j]) << "engine " << e << " block " << k;
              ASSERT_EQ(fd_out[e].at(k, i, j, b, nv), fref[k * nn + i * nv + j]) << "engine " << e << " block " << k;
            }
    }
  }
}

// float against double: relative to each block's largest entry, 1e-3 (the float
// ABA's and Cholesky's rounding on 7-25 DoF, cond(M) up to ~1e3 at these states).
TEST(DerivativeEngines, FloatAgreesWithDouble) {
  for (auto& [name, model] : engine_models()) {
    SCOPED_TRACE(name);
    const Index nv = model.nv(), B = 4;
    const Inputs in = make_inputs(nv, B, 77 + nv);
    const ModelTpl<float> mf = model.cast<float>();
    const std::vector<float> qf(in.q.begin(), in.q.end()), qdf(in.qd.begin(), in.qd.end()), xf(in.x.begin(), in.x.end());
    std::vector<Force<float>> ff;
    for (const auto& f : in.fext) ff.push_back(f.cast<float>());
    BackendOptions o;
    o.max_batch = B;
    Blocks<double> d(nv, B, false), dfd(nv, B, false);
    Blocks<float> f(nv, B, false), ffd(nv, B, false);
    using V = BatchView<const double>;
    using W = BatchView<const float>;
    make_id_derivatives(model, o)->compute({V::aos(in.q.data(), nv, B), V::aos(in.qd.data(), nv, B), V::aos(in.x.data(), nv, B), in.fext.data()},
                                           {d.v[0], d.v[1], d.v[2]});
    make_id_derivatives(mf, o)->compute({W::aos(qf.data(), nv, B), W::aos(qdf.data(), nv, B), W::aos(xf.data(), nv, B), ff.data()},
                                        {f.v[0], f.v[1], f.v[2]});
    ASSERT_TRUE(make_fd_derivatives(model, o)->compute({V::aos(in.q.data(), nv, B), V::aos(in.qd.data(), nv, B), V::aos(in.x.data(), nv, B), in.fext.data()},
                                                       {dfd.v[0], dfd.v[1], dfd.v[2], {}}).ok());
    ASSERT_TRUE(make_fd_derivatives(mf, o)->compute({W::aos(qf.data(), nv, B), W::aos(qdf.data(), nv, B), W::aos(xf.data(), nv, B), ff.data()},
                                                    {ffd.v[0], ffd.v[1], ffd.v[2], {}}).ok());
    for (int k = 0; k < 3; ++k)
      for (Index b = 0; b < B; ++b) {
        double scale = 1, scale_fd = 1, err = 0, err_fd = 0;
        for (Index e = 0; e < nv * nv; ++e) {
          scale = std::max(scale, std::fabs(d.v[k].at(e, b)));
          scale_fd = std::max(scale_fd, std::fabs(dfd.v[k].at(e, b)));
          err = std::max(err, std::fabs(d.v[k].at(e, b) - double(f.v[k].at(e, b))));
          err_fd = std::max(err_fd, std::fabs(dfd.v[k].at(e, b) - double(ffd.v[k].at(e, b))));
        }
        EXPECT_LT(err / scale, 1e-4) << "id block " << k;
        EXPECT_LT(err_fd / scale_fd, 1e-3) << "fd block " << k;
      }
  }
}

TEST(DerivativeEngines, FailuresAndBadBatches) {
  // a body without mass or inertia on a prismatic joint at the tip: M is singular
  Model m = load_model("chain:3");
  m.bodies[2].I = Inertia<double>::zero();
  const Index nv = 3, B = 2;
  std::vector<double> q(nv * B, 0.1), qd(nv * B, 0.2), tau(nv * B, 0.3), out(3 * nv * nv * B, NAN);
  BackendOptions o;
  o.max_batch = B;
  using V = BatchView<const double>;
  const FdBatchIn<double> in{V::aos(q.data(), nv, B), V::aos(qd.data(), nv, B), V::aos(tau.data(), nv, B)};
  Blocks<double> blocks(nv, B, false);
  const BatchStatus st = make_fd_derivatives(m, o)->compute(in, {blocks.v[0], blocks.v[1], blocks.v[2], {}});
  EXPECT_EQ(st.failed, 2);
  EXPECT_EQ(st.first_instance, 0);
  EXPECT_EQ(st.first_dof, 2);
  // batch sizes that disagree, and more than max_batch
  const Model iiwa = test::load_robot("iiwa.urdf");
  auto id = make_id_derivatives(iiwa, o);
  std::vector<double> x(7 * 3, 0.0);
  Blocks<double> b3(7, 3, false), b2(7, 2, false);
  EXPECT_THROW(id->compute({V::aos(x.data(), 7, 3), V::aos(x.data(), 7, 3), V::aos(x.data(), 7, 3)},
                           {b3.v[0], b3.v[1], b3.v[2]}),
               BackendError);
  EXPECT_THROW(id->compute({V::aos(x.data(), 7, 2), V::aos(x.data(), 7, 2), V::aos(x.data(), 7, 2)},
                           {b2.v[0], b2.v[1], b3.v[2]}),
               BackendError);
  o.strategy = IdStrategy::ScanLocal;
  EXPECT_THROW(make_id_derivatives(iiwa, o), BackendError);
}

}  // namespace
}  // namespace scandyn
