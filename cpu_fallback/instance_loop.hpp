// cpu_fallback/instance_loop.hpp: the one instance loop of the CPU backends.
//
// Every serial and OpenMP engine (and the simulator's CPU step) runs its instances
// through for_instance_blocks: contiguous blocks of instances, one per thread, each
// thread with its own workspace slot t; one thread (serial, or a single instance)
// enters no parallel region at all, since entering one costs about as much as a
// 7-DoF robot's whole RNEA (~0.4 us). A failed instance is recorded one way: its
// entry of a per-instance failed-DoF array (-1: none), summarised by
// summarize_failures (scandyn/batch.hpp) into the BatchStatus that compute() returns.
#pragma once

#include <algorithm>
#include <vector>

#include "scandyn/engine.hpp"

#ifdef _OPENMP
#include <omp.h>
#endif

namespace scandyn {
namespace cpu {

// Threads an engine made with these options runs: 1 on serial, options.threads (or
// openmp_threads()) on openmp. Throws BackendError for openmp in a build without it.
int engine_threads(const BackendOptions& options);

// Threads that can get instances of an engine made for up to max_batch of them:
// for_instance_blocks runs at most min(threads, B) threads and B <= max_batch, so an
// engine keeps its per-instance workspaces (one per thread) for this many threads. A
// one-instance engine on 16 threads keeps one, not 16 copies of a 10^6-link model's.
inline int instance_threads(int threads, Index max_batch) {
  return static_cast<int>(std::max<Index>(1, std::min<Index>(threads, max_batch)));
}

// body(t, begin, end) for contiguous blocks [begin, end) covering [0, B), on
// min(threads, B) threads (static schedule: thread t gets block t; t <
// instance_threads(threads, B)).
template <class F>
void for_instance_blocks(int threads, Index B, F&& body) {
  threads = instance_threads(threads, B);
  if (threads <= 1) {
    body(0, Index(0), B);
    return;
  }
#pragma omp parallel num_threads(threads)
  {
#ifdef _OPENMP
    const int t = omp_get_thread_num();
    const int nt = omp_get_num_threads();
#else
    const int t = 0, nt = 1;
#endif
    const Index per = B / nt, extra = B % nt;
    const Index begin = t * per + std::min<Index>(t, extra);
    body(t, begin, begin + per + (t < extra ? 1 : 0));
  }
}

// One thread's contiguous copies of an instance's vectors: a row of n values per
// array, for views whose entries of one instance are not contiguous.
template <class S>
class RowScratch {
 public:
  RowScratch() = default;
  RowScratch(int threads, int arrays, std::size_t n)
      : arrays_(arrays), n_(n), data_(static_cast<std::size_t>(threads) * arrays * n) {}
  S* row(int t, int k) { return data_.data() + (static_cast<std::size_t>(t) * arrays_ + k) * n_; }

 private:
  int arrays_ = 0;
  std::size_t n_ = 0;
  std::vector<S> data_;
};

// Instance b's n entries of v as a contiguous array: v's own memory when its entries
// are contiguous (dof_stride 1, e.g. BatchView::aos), else copied into row.
template <class S>
const S* gather(const BatchView<const S>& v, Index b, Index n, S* row) {
  if (v.dof_stride == 1) return v.data + b * v.batch_stride;
  for (Index i = 0; i < n; ++i) row[i] = v.at(i, b);
  return row;
}

// Where instance b's n outputs are written: v's memory when contiguous, else row,
// which scatter() then copies to v.
template <class S>
S* output_row(const BatchView<S>& v, Index b, S* row) {
  return v.dof_stride == 1 ? v.data + b * v.batch_stride : row;
}
// Instance b's n entries of v, already written, as a contiguous row to read and
// rewrite: v's memory when contiguous, else copied into row (scatter() writes it back).
template <class S>
S* result_row(const BatchView<S>& v, Index b, Index n, S* row) {
  S* r = output_row(v, b, row);
  if (v.dof_stride != 1)
    for (Index i = 0; i < n; ++i) r[i] = v.at(i, b);
  return r;
}
template <class S>
void scatter(const S* row, const BatchView<S>& v, Index b, Index n) {
  if (v.dof_stride == 1) return;
  for (Index i = 0; i < n; ++i) v.at(i, b) = row[i];
}

}  // namespace cpu
}  // namespace scandyn
