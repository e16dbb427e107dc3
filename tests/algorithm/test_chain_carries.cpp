// The hybrid's host pass 1 (ChainInertiaCarries, scandyn/algorithm/chain_fd.hpp):
// the articulated inertias at chunk boundaries with several host threads against the
// serial recursion the hybrid ran before (a copy of it below, the independent truth),
// its report of written chunks, a failed pivot, and dual_from_articulated.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <thread>

#include "scandyn/algorithm/chain_fd.hpp"
#include "scandyn/model/load.hpp"
#include "test_util.hpp"

using namespace scandyn;

namespace {

// The chain's constants and q (n x B, SoA) bound to a ChainFdData, with the
// per-link scratch the walk of pass 1 needs (for the failure tests).
template <class S>
struct Chain {
  ChainBodies<S> bodies;
  std::vector<S> q, tau;
  std::vector<Force<S>> U, w;
  std::vector<S> D;
  std::vector<int> failed;
  ChainFdData<S> d;

  Chain(const Model& model, Index B, const std::vector<double>& q_in) {
    const ModelTpl<S> m = model.cast<S>();
    const Index n = m.nbodies();
    bodies = ChainBodies<S>::from(m, B);
    q = test::cast_vector<S>(q_in);
    tau.assign(q.size(), S(0));
    U.resize(q.size());
    w.resize(q.size());
    D.resize(q.size());
    failed.assign(static_cast<std::size_t>(B), -1);
    d.n = n;
    d.batch = B;
    d.q = BatchView<const S>::soa(q.data(), n, B);
    d.qd = d.q;
    d.tau = BatchView<const S>::soa(tau.data(), n, B);
    d.body = bodies.body.data();
    d.Phi = bodies.Phi.data();
    d.body_class = bodies.body_class.data();
    d.a0 = base_acceleration(m.gravity);
    d.U = U.data();
    d.w = w.data();
    d.D = D.data();
    d.failed = failed.data();
  }
  Index chunks(Index chunk) const { return (d.count() + chunk - 1) / chunk; }
  Index last(Index c, Index chunk) const { return std::min(d.count(), (c + 1) * chunk) - 1; }
};

// The serial recursion launch_hybrid ran on the host (one thread, from the last
// link to the first): Ia of link last(c) + 1 on entering chunk c.
template <class S>
std::vector<ABInertia<S>> serial_carries(const Chain<S>& ch, Index chunk) {
  const ChainFdData<S>& d = ch.d;
  const Index chunks = ch.chunks(chunk), n = d.n;
  std::vector<ABInertia<S>> out(static_cast<std::size_t>(chunks));
  ABInertia<S> Ia_next{};
  Transform<S> Xnext = Transform<S>::identity();
  Index g = d.count() - 1;
  for (Index c = chunks - 1; c >= 0; --c) {
    out[c] = Ia_next;
    for (; g >= c * chunk; --g) {
      const Index i = g % n, b = g / n;
      const Body<S>& body = ch.bodies.body[ch.bodies.body_class[i]];
      ABInertia<S> IA = ABInertia<S>::from(body.I);
      if (ch.bodies.has_child(i)) IA += Ia_next.transform_transpose(Xnext);
      Force<S> U;
      S D, u;
      aba_joint_terms(body, IA, Force<S>::zero(), S(0), U, D, u);
      Ia_next = IA.minus_outer(U, S(1) / D);
      Xnext = joint_transform(body, d.q.at(i, b));
    }
  }
  return out;
}

template <class S>
std::vector<ABInertia<S>> threaded_carries(const Chain<S>& ch, Index chunk, int threads, int* used = nullptr,
                                           std::vector<Index>* starts = nullptr) {
  std::vector<ABInertia<S>> out(static_cast<std::size_t>(ch.chunks(chunk)));
  ChainInertiaCarries<S> carries(threads);
  carries.compute(ch.d, chunk, out.data());
  if (used) *used = carries.threads_used();
  if (starts) *starts = carries.range_starts();
  return out;
}

template <class S>
double max_entry(const ABInertia<S>& I) {
  const Mat6<S> M = to_mat6(I);
  double m = 0;
  for (int k = 0; k < 36; ++k) m = std::max(m, std::fabs(double(M.m[k])));
  return m;
}
template <class S>
double rel_diff(const ABInertia<S>& a, const ABInertia<S>& b) {
  const Mat6<S> A = to_mat6(a), B = to_mat6(b);
  double m = 0;
  for (int k = 0; k < 36; ++k) m = std::max(m, std::fabs(double(A.m[k]) - double(B.m[k])));
  return m / std::max(max_entry(a), 1e-300);
}

// The largest relative difference over the chunks whose carry is read (link
// last(c) has a child); NaN when any such carry is not finite.
template <class S>
double max_rel_diff(const Chain<S>& ch, Index chunk, const std::vector<ABInertia<S>>& a,
                    const std::vector<ABInertia<S>>& b) {
  double worst = 0;
  for (Index c = 0; c < ch.chunks(chunk); ++c) {
    if (!ch.d.has_child(ch.last(c, chunk))) continue;
    const double r = rel_diff(a[c], b[c]);
    if (!std::isfinite(r)) return NAN;
    worst = std::max(worst, r);
  }
  return worst;
}

bool same_bits(const ABInertia<float>& a, const ABInertia<float>& b) { return std::memcmp(&a, &b, sizeof a) == 0; }
bool same_bits(const ABInertia<double>& a, const ABInertia<double>& b) { return std::memcmp(&a, &b, sizeof a) == 0; }

std::string test_format(double x) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.2e", x);
  return buf;
}

std::vector<double> random_q(Index count, unsigned seed) {
  std::mt19937_64 rng(seed);
  return test::random_vector(rng, static_cast<int>(count), -1, 1);
}

// The serial recursion's own carry: bit-identical unless the compiler may contract
// into FMAs differently in the library and in the copy above (-march=native with
// FMA), then within a few roundings.
template <class S>
::testing::AssertionResult serial_bits(const ABInertia<S>& got, const ABInertia<S>& ref) {
#if defined(__FMA__)
  const double r = rel_diff(got, ref);
  if (r < test::Tol<S>(1e-13, 1e-5) || (std::isnan(r) && std::isnan(max_entry(ref)))) return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure() << "relative difference " << r;
#else
  if (same_bits(got, ref)) return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure() << "not bit-identical (relative difference " << rel_diff(got, ref) << ")";
#endif
}

// One thread: the serial recursion itself.
template <class S>
void expect_one_thread_is_serial(const Model& m, Index B, Index chunk) {
  const Chain<S> ch(m, B, random_q(m.nv() * B, 11));
  const auto ref = serial_carries(ch, chunk);
  int used = 0;
  const auto got = threaded_carries(ch, chunk, 1, &used);
  EXPECT_EQ(used, 1);
  for (Index c = 0; c < ch.chunks(chunk); ++c)
    EXPECT_TRUE(serial_bits(got[c], ref[c])) << m.name << " B " << B << " chunk size " << chunk << " chunk " << c;
}

}  // namespace

TEST(ChainCarries, DualFromArticulatedInvertsTheProjection) {
  // articulated_from_dual(b, dual_from_articulated(b, IA)) = IA - U U^T / D
  const Model m = test::random_chain(6, 3);
  std::mt19937_64 rng(5);
  for (Index i = 0; i < m.nbodies(); ++i) {
    const Body<double>& b = m.bodies[i];
    ABInertia<double> IA = ABInertia<double>::from(b.I);
    IA += ABInertia<double>::from(m.bodies[(i + 1) % m.nbodies()].I)
              .transform_transpose(joint_transform(b, test::random_vector(rng, 1, -2, 2)[0]));
    Force<double> U;
    double D, u;
    aba_joint_terms(b, IA, Force<double>::zero(), 0.0, U, D, u);
    const ABInertia<double> Ia = IA.minus_outer(U, 1.0 / D);
    EXPECT_LT(rel_diff(articulated_from_dual(b, dual_from_articulated(b, IA)), Ia), 1e-12) << i;
  }
  ABInertia<double> bad = ABInertia<double>::from(m.bodies[0].I);
  bad.Ivv.xx = -1;  // not positive definite
  EXPECT_TRUE(std::isnan(dual_from_articulated(m.bodies[0], bad).m[0]));
}

TEST(ChainCarries, OneThreadIsTheSerialRecursion) {
  for (const char* spec : {"rope:1", "rope:7", "rope:1000", "rope:10007"})
    for (Index B : {1, 3})
      for (Index chunk : {1, 8, 13}) {
        const Model m = make_generated(spec);
        expect_one_thread_is_serial<double>(m, B, chunk);
        expect_one_thread_is_serial<float>(m, B, chunk);
      }
  expect_one_thread_is_serial<double>(test::random_chains_from_base(90, 3, {1, 3, 10, 41, 77}), 2, 8);
}

// T threads on rope:N (one instance and batches), random chains and chains from the
// base: the carries the walks read agree with the serial recursion's within
// 1e-12 (double) / 1e-5 (float) relative to the carry's largest entry, and the two
// ranges next to the tip (walked from the tip's own carry) are bit-identical.
template <class S>
void expect_threads_agree(const Model& m, Index B, Index chunk, int threads, double tol) {
  const Chain<S> ch(m, B, random_q(m.nv() * B, 17));
  const auto ref = serial_carries(ch, chunk);
  int used = 0;
  std::vector<Index> starts;
  const auto got = threaded_carries(ch, chunk, threads, &used, &starts);
  const Index chunks = ch.chunks(chunk);
  const bool enough = chunks >= (threads + ChainInertiaCarries<S>::kReduceCost) * ChainInertiaCarries<S>::kMinChunksPerRange;
  if (enough) {
    EXPECT_EQ(used, threads) << m.name;
  }
  const double err = max_rel_diff(ch, chunk, got, ref);
  EXPECT_LT(err, tol) << m.name << " B " << B << " chunk " << chunk << " threads " << threads << " (used " << used
                      << ")";
  ::testing::Test::RecordProperty(m.name + "_B" + std::to_string(B) + "_c" + std::to_string(chunk) + "_t" + std::to_string(threads) +
                     (sizeof(S) == 4 ? "_float" : "_double"),
                 test_format(err));
  if (used >= 2) {  // ranges T - 1 and T: the serial recursion's own carries
    for (Index c = starts[static_cast<std::size_t>(used) - 1]; c < chunks; ++c)
      EXPECT_TRUE(serial_bits(got[c], ref[c])) << m.name << " chunk " << c;
  }
}

TEST(ChainCarries, ThreadsAgreeWithTheSerialRecursionOnRopes) {
  for (const char* spec : {"rope:1000", "rope:100000"})
    for (int threads : {2, 3, 4, 8})
      for (Index chunk : {8, 5}) {
        const Model m = make_generated(spec);
        expect_threads_agree<double>(m, 1, chunk, threads, 1e-12);
        expect_threads_agree<float>(m, 1, chunk, threads, 1e-5);
      }
  const Model m = make_generated("rope:1000");
  expect_threads_agree<double>(m, 6, 8, 3, 1e-12);  // ranges across instance boundaries
  expect_threads_agree<float>(m, 6, 8, 3, 1e-5);
}

TEST(ChainCarries, ThreadsAgreeWithTheSerialRecursionOnRandomChains) {
  for (unsigned seed : {1u, 2u}) {
    const Model m = test::random_chain(97, seed);
    for (int threads : {2, 4}) {
      expect_threads_agree<double>(m, 20, 8, threads, 1e-12);
      expect_threads_agree<double>(m, 20, 3, threads, 1e-12);
    }
  }
  const Model forest = test::random_chains_from_base(300, 3, {1, 3, 10, 41, 77, 200});
  expect_threads_agree<double>(forest, 5, 8, 3, 1e-12);
  expect_threads_agree<float>(forest, 5, 8, 3, 1e-5);
}

TEST(ChainCarries, ShortChainsRunOnFewerThreads) {
  const Model m = make_generated("rope:40");
  const Chain<double> ch(m, 1, random_q(40, 3));
  int used = 0;
  const auto got = threaded_carries(ch, 8, 4, &used);
  EXPECT_EQ(used, 1);  // 5 chunks: too few for ranges of kMinChunksPerRange
  const auto ref = serial_carries(ch, 8);
  for (Index c = 0; c < ch.chunks(8); ++c) EXPECT_TRUE(serial_bits(got[c], ref[c])) << c;
}

// The report: every chunk exactly once, on the calling thread, and its carry final
// when reported.
namespace {
struct Seen {
  const std::vector<ABInertia<double>>* out;
  std::vector<ABInertia<double>> snapshot;
  std::vector<int> times;
  std::thread::id caller;
  bool other_thread = false;
};
void on_ready(void* ctx, Index lo, Index hi) {
  Seen& s = *static_cast<Seen*>(ctx);
  if (std::this_thread::get_id() != s.caller) s.other_thread = true;
  for (Index c = lo; c < hi; ++c) {
    ++s.times[c];
    s.snapshot[c] = (*s.out)[c];
  }
}
}  // namespace

TEST(ChainCarries, ReportsEveryChunkOnceWhenWritten) {
  for (int threads : {1, 2, 4}) {
    const Model m = make_generated("rope:20000");
    const Chain<double> ch(m, 1, random_q(20000, 9));
    std::vector<ABInertia<double>> out(static_cast<std::size_t>(ch.chunks(8)));
    Seen s{&out, std::vector<ABInertia<double>>(out.size()), std::vector<int>(out.size(), 0),
           std::this_thread::get_id()};
    ChainInertiaCarries<double> carries(threads);
    const auto origin = std::chrono::steady_clock::now();
    carries.compute(ch.d, 8, out.data(), on_ready, &s, &origin);
    EXPECT_EQ(carries.threads_used(), threads);
    EXPECT_FALSE(s.other_thread);
    for (std::size_t c = 0; c < out.size(); ++c) {
      EXPECT_EQ(s.times[c], 1) << "threads " << threads << " chunk " << c;
      EXPECT_TRUE(same_bits(s.snapshot[c], out[c])) << "threads " << threads << " chunk " << c;
    }
    // the intervals: walks cover every chunk once; reductions and the combine with T >= 2
    std::vector<int> walked(out.size(), 0);
    int reductions = 0, combines = 0;
    for (const auto& iv : carries.intervals()) {
      if (iv.start_ms < 0) continue;
      EXPECT_LE(iv.start_ms, iv.end_ms);
      if (iv.kind == ChainCarryInterval::Walk)
        for (Index c = iv.c_lo; c < iv.c_hi; ++c) ++walked[c];
      reductions += iv.kind == ChainCarryInterval::Reduce;
      combines += iv.kind == ChainCarryInterval::Combine;
    }
    for (std::size_t c = 0; c < out.size(); ++c) EXPECT_EQ(walked[c], 1) << c;
    EXPECT_EQ(reductions, threads > 1 ? threads - 1 : 0);
    EXPECT_EQ(combines, threads > 1 ? 1 : 0);
  }
}

// A failed pivot: the instance's carries below it are NaN (or, from the recursion
// before this one, whatever the failed step left), the walks of pass 1 report it
// (inertia_walk, what the device runs per chunk, on the host here), and the other
// instances' carries are those of the serial recursion.
namespace {
template <class S>
std::vector<int> walk_failures(Chain<S>& ch, Index chunk, const std::vector<ABInertia<S>>& carries) {
  std::fill(ch.failed.begin(), ch.failed.end(), -1);
  for (Index c = 0; c < ch.chunks(chunk); ++c) inertia_walk(ch.d, c * chunk, ch.last(c, chunk), carries[c]);
  return ch.failed;
}

template <class S>
void expect_failure_reported(const Model& m, Index B, const std::vector<double>& q, Index bad_instance,
                             Index bad_link, int threads) {
  const Index chunk = 8;
  Chain<S> ch(m, B, q);
  const auto ref = serial_carries(ch, chunk);
  int used = 0;
  const auto got = threaded_carries(ch, chunk, threads, &used);
  EXPECT_EQ(used, threads);
  const auto f_ref = walk_failures(ch, chunk, ref);
  const auto f_got = walk_failures(ch, chunk, got);
  const Index n = m.nbodies();
  for (Index b = 0; b < B; ++b) {
    if (b == bad_instance) {
      EXPECT_GE(f_ref[b], 0);
      EXPECT_GE(f_got[b], 0) << "threads " << threads << " link " << bad_link;
      EXPECT_LE(f_got[b], bad_link);
      continue;
    }
    EXPECT_EQ(f_ref[b], -1);
    EXPECT_EQ(f_got[b], -1) << "threads " << threads << " link " << bad_link << " instance " << b;
    for (Index c = 0; c < ch.chunks(chunk); ++c) {
      const Index e = ch.last(c, chunk);
      if (e / n != b || !ch.d.has_child(e)) continue;
      EXPECT_LT(rel_diff(got[c], ref[c]), test::Tol<S>(1e-12, 1e-4)) << "instance " << b << " chunk " << c;
    }
  }
}
}  // namespace

TEST(ChainCarries, NanPositionIsReportedByTheWalk) {
  const Model m = make_generated("rope:3000");
  const Index B = 3;
  for (int threads : {2, 4})
    for (Index link : {2990, 1500, 700, 20}) {  // the tip range, the middle ones, range 0
      std::vector<double> q = random_q(3000 * B, 4);
      q[static_cast<std::size_t>(link * B + 1)] = NAN;  // instance 1
      expect_failure_reported<double>(m, B, q, 1, link, threads);
      expect_failure_reported<float>(m, B, q, 1, link, threads);
    }
}

TEST(ChainCarries, NonPositivePivotIsReportedByTheWalk) {
  // link k's rotational inertia negative: D = S^T IA S < 0 at k (the serial recursion
  // shows it: the walk reports it from its carries)
  for (Index link : {2999, 1500, 400}) {
    Model m = make_generated("rope:3000");
    m.bodies[link].I.I = Sym3<double>{-1e6, -1e6, -1e6, 0, 0, 0};
    m.bodies[link].I.h = Vec3<double>{0, 0, 0};
    const Index B = 1;
    for (int threads : {2, 3}) {
      expect_failure_reported<double>(m, B, random_q(3000, 8), 0, link, threads);
      expect_failure_reported<float>(m, B, random_q(3000, 8), 0, link, threads);
    }
  }
}
