// The host side of the CUDA engines' pinned staging pipeline, without a device
// (src/engine/host_staging.hpp): the switches' parsers, the partition of a batch
// into chunks, and the gather / scatter of a chunk of strided views (every entry
// once, nothing between entries written), serial and on OpenMP threads.
#include <gtest/gtest.h>

#include <cstddef>
#include <stdexcept>
#include <string>
#include <vector>

#include "../src/engine/host_staging.hpp"

using namespace scandyn;
namespace hs = scandyn::host_staging;

namespace {

TEST(HostStaging, ParsesTheSwitches) {
  EXPECT_EQ(hs::parse_mode(nullptr), hs::Mode::Pinned);
  EXPECT_EQ(hs::parse_mode(""), hs::Mode::Pinned);
  EXPECT_EQ(hs::parse_mode("pinned"), hs::Mode::Pinned);
  EXPECT_EQ(hs::parse_mode("pageable"), hs::Mode::Pageable);
  EXPECT_THROW(hs::parse_mode("Pinned"), std::invalid_argument);
  EXPECT_THROW(hs::parse_mode("pinned "), std::invalid_argument);
  EXPECT_STREQ(hs::to_string(hs::Mode::Pageable), "pageable");

  EXPECT_EQ(hs::chunk_instances(112, "1000"), 1000);
  EXPECT_EQ(hs::chunk_instances(112, "1"), 1);
  for (const char* bad : {"0", "-5", "12x", "x", "99999999999"})
    EXPECT_THROW(hs::chunk_instances(112, bad), std::invalid_argument) << bad;
  EXPECT_EQ(hs::chunk_instances(112, nullptr), static_cast<Index>(hs::kChunkBytes / 112));
  EXPECT_EQ(hs::chunk_instances(hs::kChunkBytes * 3, nullptr), 1) << "at least one instance";
  EXPECT_EQ(hs::chunk_instances(0, nullptr), static_cast<Index>(hs::kChunkBytes));
}

TEST(HostStaging, ChunksPartitionTheBatch) {
  for (Index chunk : {1, 7, 64})
    for (Index B : {Index(0), Index(1), chunk - 1, chunk, chunk + 1, 3 * chunk + chunk / 2, 10 * chunk}) {
      if (B < 0) continue;
      const Index K = hs::chunk_count(B, chunk);
      EXPECT_EQ(K, (B + chunk - 1) / chunk);
      Index next = 0;
      for (Index k = 0; k < K; ++k) {
        const hs::Range r = hs::chunk_range(B, chunk, k);
        EXPECT_EQ(r.begin, next) << "B=" << B << " chunk=" << chunk << " k=" << k;
        EXPECT_GE(r.count, 1);
        EXPECT_LE(r.count, chunk);
        if (k + 1 < K) {
          EXPECT_EQ(r.count, chunk);
        }
        next += r.count;
      }
      EXPECT_EQ(next, B) << "B=" << B << " chunk=" << chunk;
    }
}

struct Strides {
  const char* name;
  std::ptrdiff_t ds, bs;
};

// Strides of a w x B view: dense, padded, negative, interleaved, broadcast.
std::vector<Strides> strides(Index w, Index B) {
  return {{"aos", 1, w},           {"soa", B, 1},          {"aos-neg+3", 1, -(w + 3)},
          {"soa-neg+2", -(B + 2), 1}, {"interleaved", 2, -2 * (w + 1)}, {"soa-interleaved", 2 * B, 2},
          {"soa-both-neg", -B, -1},   {"broadcast", 1, 0}};
}

TEST(HostStaging, PackAndUnpackEveryEntryOnce) {
  const Index w = 7;
  for (int threads : {1, 4})
    for (Index B : {Index(1), Index(63), Index(20000)}) {  // 20000 x 7 doubles: the parallel path
      for (const Strides& st : strides(w, B)) {
        SCOPED_TRACE(std::string(st.name) + " B=" + std::to_string(B) + " threads=" + std::to_string(threads));
        const bool broadcast = st.bs == 0;
        std::ptrdiff_t lo = 0, hi = 0;
        for (std::ptrdiff_t e : {st.ds * (w - 1), st.bs * (B - 1)}) (e < 0 ? lo : hi) += e;
        const std::size_t size = static_cast<std::size_t>(hi - lo + 1);
        std::vector<double> host(size, -1.0);
        const BatchView<double> v{host.data() - lo, B, st.ds, st.bs};
        for (Index b = 0; b < B; ++b)
          for (Index i = 0; i < w; ++i) v.at(i, b) = 1000.0 * b + i;
        const BatchView<const double> cv{v.data, B, v.dof_stride, v.batch_stride};
        const hs::Layout layout = hs::choose_layout(cv, w, false);
        EXPECT_EQ(layout == hs::Layout::Broadcast, broadcast && B > 1);
        const Index chunk = B > 100 ? 6000 : 10;
        for (Index k = 0; k < hs::chunk_count(B, chunk); ++k) {
          const hs::Range r = hs::chunk_range(B, chunk, k);
          std::vector<double> packed(hs::packed_entries(layout, w, r.count), -2.0);
          hs::pack(cv, w, r, layout, packed.data(), threads);
          const BatchView<double> pv = hs::packed_view(packed.data(), layout, w, r.count);
          for (Index b = 0; b < r.count; ++b)
            for (Index i = 0; i < w; ++i)
              ASSERT_EQ(pv.at(i, b), broadcast ? 1000.0 * (B - 1) + i : 1000.0 * (r.begin + b) + i)
                  << "entry " << i << " of instance " << r.begin + b;
        }
        if (broadcast) continue;  // outputs are never broadcast
        // the scatter: every entry from its packed place, the gaps untouched
        const hs::Layout out_layout = hs::choose_layout(v, w, true);
        EXPECT_EQ(out_layout, layout);
        std::vector<double> out(size, -1.0);
        const BatchView<double> ov{out.data() - lo, B, st.ds, st.bs};
        for (Index k = 0; k < hs::chunk_count(B, chunk); ++k) {
          const hs::Range r = hs::chunk_range(B, chunk, k);
          std::vector<double> packed(hs::packed_entries(out_layout, w, r.count));
          const BatchView<double> pv = hs::packed_view(packed.data(), out_layout, w, r.count);
          for (Index b = 0; b < r.count; ++b)
            for (Index i = 0; i < w; ++i) pv.at(i, b) = 1000.0 * (r.begin + b) + i;
          hs::unpack(static_cast<const double*>(packed.data()), out_layout, ov, w, r, threads);
        }
        EXPECT_EQ(out, host);
      }
    }
}

TEST(HostStaging, LayoutFollowsTheViewsOrientation) {
  const Index w = 7, B = 100;
  std::vector<float> x(static_cast<std::size_t>(w) * B * 4);
  EXPECT_EQ(hs::choose_layout(BatchView<float>::aos(x.data(), w, B), w, true), hs::Layout::InstanceMajor);
  EXPECT_EQ(hs::choose_layout(BatchView<float>::soa(x.data(), w, B), w, true), hs::Layout::DofMajor);
  EXPECT_EQ(hs::choose_layout(BatchView<const float>{x.data(), B, 1, 0}, w, false), hs::Layout::Broadcast);
  EXPECT_EQ(hs::choose_layout(BatchView<float>{x.data(), 1, 1, 0}, w, false), hs::Layout::InstanceMajor)
      << "one instance is no broadcast";
  const BatchView<float> p = hs::packed_view(x.data(), hs::Layout::DofMajor, w, B);
  EXPECT_EQ(p.dof_stride, B);
  EXPECT_EQ(p.batch_stride, 1);
}

TEST(HostStaging, CopyBytes) {
  for (std::size_t n : {std::size_t(0), std::size_t(1), std::size_t(1000), std::size_t(3) << 20}) {
    std::vector<unsigned char> a(n), b(n, 0);
    for (std::size_t k = 0; k < n; ++k) a[k] = static_cast<unsigned char>(k * 131 + 7);
    hs::copy_bytes(b.data(), a.data(), n, 4);
    EXPECT_EQ(a, b) << n;
  }
}

}  // namespace
