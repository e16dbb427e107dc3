// src/engine/host_staging.cpp: the host side of the CUDA engines' pinned staging
// pipeline (src/engine/host_staging.hpp): the switches' parsers, and the gathers and
// scatters of a chunk on OpenMP threads (compiled with -fopenmp as the rest of the
// library; without OpenMP they run on one thread).
#include "host_staging.hpp"

#include <algorithm>
#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string>

#include "scandyn/engine.hpp"

namespace scandyn {
namespace host_staging {

Mode parse_mode(const char* value) {
  if (!value || !*value || std::strcmp(value, "pinned") == 0) return Mode::Pinned;
  if (std::strcmp(value, "pageable") == 0) return Mode::Pageable;
  throw std::invalid_argument(std::string("SCANDYN_HOST_STAGING='") + value + "': expected pageable or pinned");
}

const char* to_string(Mode mode) { return mode == Mode::Pinned ? "pinned" : "pageable"; }

Index chunk_instances(std::size_t bytes_per_instance, const char* value) {
  if (value && *value) {
    errno = 0;
    char* end = nullptr;
    const long long n = std::strtoll(value, &end, 10);
    if (errno != 0 || end == value || *end != '\0' || n < 1 || n > 0x7fffffffLL)
      throw std::invalid_argument(std::string("SCANDYN_HOST_CHUNK_INSTANCES='") + value +
                                  "': expected a positive number of instances");
    return static_cast<Index>(n);
  }
  const std::size_t per = std::max<std::size_t>(bytes_per_instance, 1);
  return static_cast<Index>(std::clamp<std::size_t>(kChunkBytes / per, 1, 0x7fffffff));
}

namespace {

// Below this many bytes a block is copied on one thread (a parallel region costs
// a few microseconds).
constexpr std::size_t kParallelBytes = std::size_t(256) << 10;

int team(std::size_t bytes, int threads) {
  if (bytes < kParallelBytes) return 1;
  const int t = threads > 0 ? threads : openmp_threads();
  // at least kParallelBytes / 4 per thread
  const std::size_t most = std::max<std::size_t>(bytes / (kParallelBytes / 4), 1);
  return static_cast<int>(std::min<std::size_t>(static_cast<std::size_t>(std::max(t, 1)), most));
}

// f(lo, hi) over `parts` even pieces of [0, n) on `parts` threads.
template <class F>
void split(Index n, int parts, F&& f) {
  if (parts <= 1) {
    f(Index(0), n);
    return;
  }
#pragma omp parallel for num_threads(parts) schedule(static)
  for (int p = 0; p < parts; ++p) {
    const Index lo = static_cast<Index>(static_cast<long long>(n) * p / parts);
    const Index hi = static_cast<Index>(static_cast<long long>(n) * (p + 1) / parts);
    if (lo < hi) f(lo, hi);
  }
}

// Moves entries between a host view's instances r and a packed block: to_packed
// gathers (pack), else scatters (unpack). `packed` is T* or const T*.
template <bool kToPacked, class T, class P>
void move_chunk(const BatchView<T>& v, Index w, Range r, Layout layout, P* packed, int threads) {
  const Index n = r.count;
  if (n <= 0 || w <= 0) return;
  const std::ptrdiff_t ds = v.dof_stride, bs = v.batch_stride;
  T* const base = v.data + static_cast<std::ptrdiff_t>(r.begin) * bs;  // instance r.begin, DoF 0
  const std::size_t sz = sizeof(T);
  if (layout == Layout::Broadcast) {  // (inputs only) w entries of instance r.begin
    if constexpr (kToPacked)
      for (Index i = 0; i < w; ++i) packed[i] = base[i * ds];
    return;
  }
  const int parts = team(static_cast<std::size_t>(n) * w * sz, threads);
  if (layout == Layout::InstanceMajor) {
    if ((w == 1 || ds == 1) && (n == 1 || bs == w)) {  // dense rows: one block
      split(n, parts, [&](Index lo, Index hi) {
        const std::size_t bytes = static_cast<std::size_t>(hi - lo) * w * sz;
        if constexpr (kToPacked) std::memcpy(packed + static_cast<std::ptrdiff_t>(lo) * w, base + lo * bs, bytes);
        else std::memcpy(base + lo * bs, packed + static_cast<std::ptrdiff_t>(lo) * w, bytes);
      });
      return;
    }
    split(n, parts, [&](Index lo, Index hi) {
      for (Index k = lo; k < hi; ++k) {
        T* const h = base + k * bs;
        P* const p = packed + static_cast<std::ptrdiff_t>(k) * w;
        if (ds == 1) {
          if constexpr (kToPacked) std::memcpy(p, h, w * sz);
          else std::memcpy(h, p, w * sz);
        } else {
          for (Index i = 0; i < w; ++i) {
            if constexpr (kToPacked) p[i] = h[i * ds];
            else h[i * ds] = p[i];
          }
        }
      }
    });
    return;
  }
  // DofMajor: row i holds the chunk's n entries of DoF i
  split(n, parts, [&](Index lo, Index hi) {
    for (Index i = 0; i < w; ++i) {
      T* const h = base + i * ds;
      P* const p = packed + static_cast<std::ptrdiff_t>(i) * n;
      if (bs == 1) {
        if constexpr (kToPacked) std::memcpy(p + lo, h + lo * bs, static_cast<std::size_t>(hi - lo) * sz);
        else std::memcpy(h + lo * bs, p + lo, static_cast<std::size_t>(hi - lo) * sz);
      } else {
        for (Index k = lo; k < hi; ++k) {
          if constexpr (kToPacked) p[k] = h[k * bs];
          else h[k * bs] = p[k];
        }
      }
    }
  });
}

}  // namespace

template <class T>
void pack(const BatchView<const T>& v, Index w, Range r, Layout layout, T* dst, int threads) {
  move_chunk<true>(v, w, r, layout, dst, threads);
}

template <class T>
void unpack(const T* src, Layout layout, const BatchView<T>& v, Index w, Range r, int threads) {
  move_chunk<false>(v, w, r, layout, src, threads);
}

void copy_bytes(void* dst, const void* src, std::size_t bytes, int threads) {
  if (bytes == 0) return;
  const int parts = team(bytes, threads);
  if (parts <= 1) {
    std::memcpy(dst, src, bytes);
    return;
  }
  unsigned char* const d = static_cast<unsigned char*>(dst);
  const unsigned char* const s = static_cast<const unsigned char*>(src);
#pragma omp parallel for num_threads(parts) schedule(static)
  for (int p = 0; p < parts; ++p) {
    const std::size_t lo = bytes * p / parts, hi = bytes * (p + 1) / parts;
    std::memcpy(d + lo, s + lo, hi - lo);
  }
}

#define SCANDYN_INSTANTIATE(T)                                                                       \
  template void pack(const BatchView<const T>&, Index, Range, Layout, T*, int);                     \
  template void unpack(const T*, Layout, const BatchView<T>&, Index, Range, int);
SCANDYN_INSTANTIATE(float)
SCANDYN_INSTANTIATE(double)
#undef SCANDYN_INSTANTIATE

}  // namespace host_staging
}  // namespace scandyn
