// Parallel scans over chains and trees, and inverse dynamics by scans.
#include <gtest/gtest.h>

#include <cstdint>
#include <numeric>
#include <random>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/algorithm/rnea_scan.hpp"
#include "scandyn/model/load.hpp"
#include "scandyn/scan/elements.hpp"
#include "scandyn/scan/omp_scan.hpp"
#include "test_util.hpp"

#ifdef _OPENMP
#include <omp.h>
#endif

using namespace scandyn;

namespace {

// An exact, associative, non-commutative element: 2x2 matrices over Z/2^64.
struct M2 {
  std::uint64_t a, b, c, d;
  bool operator==(const M2& o) const { return a == o.a && b == o.b && c == o.c && d == o.d; }
};
M2 mul(const M2& x, const M2& y) {
  return {x.a * y.a + x.b * y.c, x.a * y.b + x.b * y.d, x.c * y.a + x.d * y.c, x.c * y.b + x.d * y.d};
}
M2 transpose(const M2& x) { return {x.a, x.c, x.b, x.d}; }
struct V2 {
  std::uint64_t x, y;
  bool operator==(const V2& o) const { return x == o.x && y == o.y; }
};
V2 mulv(const M2& m, const V2& v) { return {m.a * v.x + m.b * v.y, m.c * v.x + m.d * v.y}; }
V2 addv(const V2& p, const V2& q) { return {p.x + q.x, p.y + q.y}; }

// prefix op: node after ancestor prefix, like ComposePose (e * acc)
struct MulAfter {
  M2 operator()(const M2& acc, const M2& e) const { return mul(e, acc); }
};

// the integer mirror of ForceAffine: G -> B + Y^T G
struct Aff {
  M2 Y;
  V2 B;
};
struct AffCompose {
  Aff operator()(const Aff& o, const Aff& d) const { return {mul(d.Y, o.Y), addv(o.B, mulv(transpose(o.Y), d.B))}; }
};
struct AffKnown {
  Aff operator()(const Aff& o, const Aff& d) const { return {o.Y, addv(o.B, mulv(transpose(o.Y), d.B))}; }
};
struct AffFold {
  void operator()(Aff& p, const Aff& c) const { p.B = addv(p.B, mulv(transpose(p.Y), c.B)); }
};

M2 random_m2(std::mt19937_64& g) { return {g(), g(), g(), g()}; }

// random preorder parent arrays: chain, comb, random tree, forest of chains
std::vector<Index> shape(const std::string& kind, int n, std::mt19937_64& g) {
  std::vector<Index> p(n);
  for (int i = 0; i < n; ++i) {
    if (kind == "chain") p[i] = i - 1;
    else if (kind == "random") p[i] = i == 0 ? -1 : static_cast<Index>(g() % (i + 1)) - 1;
    else if (kind == "forest") p[i] = (i % 97 == 0) ? -1 : i - 1;
    else if (kind == "deep")  // long chains with occasional branches back up the tree
      p[i] = i == 0 ? -1 : (g() % 50 == 0 ? static_cast<Index>(g() % i) : i - 1);
  }
  return p;
}

int thread_counts[] = {1, 2, 3, 4, 7};

template <class F>
void with_threads(int t, F f) {
  (void)t;  // without OpenMP: one thread
#pragma omp parallel num_threads(t)
  f();
}

}  // namespace

TEST(ChainScan, MatchesStdInclusiveScanExactly) {
  std::mt19937_64 g(1);
  for (int n : {1, 2, 3, 5, 7, 8, 9, 63, 64, 65, 1023, 1024, 1025, 4096, 100000, 1000000}) {
    std::vector<M2> in(n);
    for (auto& x : in) x = random_m2(g);
    std::vector<M2> expect(n);
    std::inclusive_scan(in.begin(), in.end(), expect.begin(), MulAfter{});
    for (int t : thread_counts) {
      // pieces of a few hundred nodes, or as cut for t threads
      for (Index piece : {Index(1), Index(3), Index(257), default_max_piece(n, t)}) {
        if (n >= 100000 && piece < 257) continue;
        const TreeScanPlan plan = make_tree_scan_plan(shape("chain", n, g), piece);
        std::vector<M2> x = in, carry(plan.pieces.size());
        with_threads(t, [&] { chain_inclusive_scan(plan, x.data(), carry.data(), MulAfter{}); });
        ASSERT_TRUE(x == expect) << "n=" << n << " threads=" << t << " piece=" << piece;
      }
    }
  }
}

// The dynamics operators themselves against std::inclusive_scan: the parallel
// scan reassociates, so equality holds to rounding (double: 1e-12 relative to the
// values' scale on chains of 10^5 transforms near identity).
TEST(ChainScan, DynamicsOperatorsMatchStdInclusiveScan) {
  std::mt19937_64 g(11);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int n : {1, 2, 3, 64, 65, 4096, 100000}) {
    std::vector<MotionAffine<double>> in(n);
    std::vector<Transform<double>> poses(n);
    for (int i = 0; i < n; ++i) {
      // small rotations and offsets, as along a rope
      const Transform<double> X{rpy_matrix(0.01 * u(g), 0.01 * u(g), 0.01 * u(g)), {0.01 * u(g), 0.01 * u(g), -0.01}};
      in[i] = {X, {{u(g), u(g), u(g)}, {u(g), u(g), u(g)}}};
      poses[i] = X;
    }
    std::vector<MotionAffine<double>> expect(n);
    std::inclusive_scan(in.begin(), in.end(), expect.begin(), ComposeMotionAffine{});
    std::vector<Transform<double>> expect_pose(n);
    std::inclusive_scan(poses.begin(), poses.end(), expect_pose.begin(), ComposePose{});
    for (int t : {1, 3, 4}) {
      const TreeScanPlan plan = make_tree_scan_plan(shape("chain", n, g), n >= 4096 ? 1000 : 7);
      std::vector<MotionAffine<double>> x = in, carry(plan.pieces.size());
      std::vector<Transform<double>> p = poses, carry_p(plan.pieces.size());
      with_threads(t, [&] {
        chain_inclusive_scan(plan, x.data(), carry.data(), ComposeMotionAffine{});
        chain_inclusive_scan(plan, p.data(), carry_p.data(), ComposePose{});
      });
      double err = 0, scale = 1;
      for (int i = 0; i < n; ++i) {
        for (int k = 0; k < 6; ++k) {
          err = std::max(err, std::fabs(x[i].b[k] - expect[i].b[k]));
          scale = std::max(scale, std::fabs(expect[i].b[k]));
        }
        for (int k = 0; k < 9; ++k) err = std::max(err, std::fabs(p[i].E.m[k] - expect_pose[i].E.m[k]));
        err = std::max(err, std::fabs(p[i].r.z - expect_pose[i].r.z) / std::max(1.0, std::fabs(expect_pose[i].r.z)));
      }
      EXPECT_LT(err / scale, 1e-12) << "n=" << n << " threads=" << t;
    }
  }
}

TEST(TreeScan, PrefixMatchesRecursionExactly) {
  std::mt19937_64 g(2);
  for (const char* kind : {"chain", "random", "forest", "deep"})
    for (int n : {1, 2, 17, 300, 5000}) {
      const std::vector<Index> parent = shape(kind, n, g);
      std::vector<M2> in(n), expect(n);
      for (auto& x : in) x = random_m2(g);
      for (int i = 0; i < n; ++i) expect[i] = parent[i] < 0 ? in[i] : mul(in[i], expect[parent[i]]);
      for (int t : thread_counts)
        for (Index piece : {Index(2), Index(50), Index(n)}) {
          const TreeScanPlan plan = make_tree_scan_plan(parent, piece);
          std::vector<M2> x = in, carry(plan.pieces.size());
          with_threads(t, [&] { tree_prefix_scan(plan, x.data(), carry.data(), MulAfter{}, MulAfter{}); });
          ASSERT_TRUE(x == expect) << kind << " n=" << n << " threads=" << t << " piece=" << piece;
        }
    }
}

TEST(TreeScan, SuffixMatchesRecursionExactly) {
  std::mt19937_64 g(3);
  for (const char* kind : {"chain", "random", "forest", "deep"})
    for (int n : {1, 2, 17, 300, 5000}) {
      const std::vector<Index> parent = shape(kind, n, g);
      std::vector<Aff> in(n);
      for (auto& e : in) e = {random_m2(g), {g(), g()}};
      // recursion: F_i = f_i + sum_c Y_c^T F_c over children, B_i = Y_i^T F_i,
      // with the element holding B_i = Y_i^T f_i
      std::vector<V2> F(n);
      for (int i = 0; i < n; ++i) F[i] = {0, 0};
      std::vector<V2> Bexp(n);
      for (int i = n - 1; i >= 0; --i) {
        Bexp[i] = addv(in[i].B, mulv(transpose(in[i].Y), F[i]));
        if (parent[i] >= 0) F[parent[i]] = addv(F[parent[i]], Bexp[i]);
      }
      for (int t : thread_counts)
        for (Index piece : {Index(2), Index(50), Index(n)}) {
          const TreeScanPlan plan = make_tree_scan_plan(parent, piece);
          std::vector<Aff> x = in, carry(plan.pieces.size());
          with_threads(t, [&] {
            tree_suffix_scan(plan, x.data(), carry.data(), AffCompose{}, AffKnown{}, AffFold{});
          });
          for (int i = 0; i < n; ++i)
            ASSERT_TRUE(x[i].B == Bexp[i]) << kind << " n=" << n << " node " << i << " threads=" << t;
        }
    }
}

TEST(TreeScanPlan, SegmentsAndPieces) {
  // 0-1-2 chain, 3 child of 1, 4 child of 3, 5 a second root
  const TreeScanPlan p = make_tree_scan_plan({-1, 0, 1, 1, 3, -1}, 2);
  ASSERT_EQ(p.num_segments(), 3);
  EXPECT_EQ(p.seg_begin, (std::vector<Index>{0, 3, 5}));
  EXPECT_EQ(p.seg_end, (std::vector<Index>{3, 5, 6}));
  EXPECT_EQ(p.seg_parent_node, (std::vector<Index>{-1, 1, -1}));
  EXPECT_EQ(p.num_levels(), 2);
  EXPECT_TRUE(p.has_split_segments);  // [0,3) in pieces of <= 2
  Index covered = 0;
  for (const auto& pc : p.pieces) covered += pc.end - pc.begin;
  EXPECT_EQ(covered, 6);
}

// ---- inverse dynamics by scans -------------------------------------------------

template <class S>
double scan_vs_reference(const Model& md, ScanForm form, int threads, unsigned seed, bool with_fext) {
  const ModelTpl<S> m = md.cast<S>();
  const int n = m.nv();
  std::mt19937_64 g(seed);
  const auto q = test::cast_vector<S>(test::random_vector(g, n, -1, 1));
  const auto qd = test::cast_vector<S>(test::random_vector(g, n, -1, 1));
  const auto qdd = test::cast_vector<S>(test::random_vector(g, n, -1, 1));
  const std::vector<Force<S>> fext = test::random_wrenches<S>(g, n, 1);
  // reference in double on the same (rounded) inputs
  Data dd(md, /*mass_matrix=*/false);
  std::vector<double> ref(n);
  std::vector<Force<double>> fext_d(n);
  for (int i = 0; i < n; ++i) fext_d[i] = fext[i].template cast<double>();
  const std::vector<double> qd_(q.begin(), q.end()), qdd_d(qd.begin(), qd.end()), qddd(qdd.begin(), qdd.end());
  rnea(md, dd, qd_.data(), qdd_d.data(), qddd.data(), ref.data(), with_fext ? fext_d.data() : nullptr);
  ScanWorkspace<S> ws(m, threads);
  std::vector<S> tau(n, std::numeric_limits<S>::quiet_NaN());
  rnea_scan(m, ws, form, q.data(), qd.data(), qdd.data(), tau.data(), with_fext ? fext.data() : nullptr);
  return test::max_rel_err(tau, ref);
}

TEST(RneaScan, EqualsReferenceOnRandomTrees) {
  for (int n : {1, 2, 7, 30, 200, 1000})
    for (unsigned seed : {1u, 2u})
      for (int t : {1, 3}) {
        const Model m = test::random_model(n, seed * 31 + n);
        for (ScanForm form : {ScanForm::Local, ScanForm::World}) {
          const char* f = form == ScanForm::Local ? "local" : "world";
          EXPECT_LT(scan_vs_reference<double>(m, form, t, seed, true), 1e-10) << f << " n=" << n << " t=" << t;
          EXPECT_LT(scan_vs_reference<float>(m, form, t, seed, true), 2e-3) << f << " float n=" << n << " t=" << t;
        }
      }
}

TEST(RneaScan, EqualsReferenceOnRobotsAndGenerators) {
  std::vector<std::string> specs = {"iiwa.urdf", "hyq.urdf", "atlas.urdf", "tree:500:4", "curtain:10:30", "chain:50"};
  for (const auto& s : specs) {
    const Model m = s.find(".urdf") != std::string::npos ? test::load_robot(s) : load_model(s);
    for (ScanForm form : {ScanForm::Local, ScanForm::World})
      for (int t : {1, 4}) {
        EXPECT_LT(scan_vs_reference<double>(m, form, t, 5, true), 1e-10) << s;
        EXPECT_LT(scan_vs_reference<float>(m, form, t, 5, false), 1e-4) << s;
      }
  }
}

TEST(RneaScan, EqualsReferenceOnLongRopes) {
  // pieces are cut for the thread count, so the multi-piece path runs
  for (int n : {1000, 20000, 100000}) {
    const Model m = load_model("rope:" + std::to_string(n));
    for (ScanForm form : {ScanForm::Local, ScanForm::World})
      EXPECT_LT(scan_vs_reference<double>(m, form, 4, 9, true), 1e-10) << "rope:" << n;
  }
}
