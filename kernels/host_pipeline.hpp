// kernels/host_pipeline.hpp (internal): the CUDA engines' pinned host path.
//
// compute() of a thread-per-instance engine takes HOST views in the user's
// (pageable) memory. Copied straight from there (kernels/staging.hpp, the
// "pageable" path), the driver bounces every copy through its own small pinned
// buffers, slowly and without overlap with the kernel. This pipeline instead owns a
// ring of kSlots pinned (cudaMallocHost) slots, each with a device slot of the same
// size, reused from call to call (allocated at the first call for a full chunk of the
// engine's max_batch, grown only when a later call's arrays need more per instance,
// e.g. the first call with fext), and runs the batch in chunks of instances; for chunk k:
//   1. host threads (OpenMP, src/engine/host_staging.cpp) gather the user's views
//      of the chunk's instances into pinned slot k % kSlots (pack);
//   2. one cudaMemcpyAsync of the packed inputs to the device slot, on the
//      upload stream;
//   3. the kernel on the chunk (the engine's launch on a sub-batch of `count`
//      instances), on the compute stream, after an event of 2;
//   4. one cudaMemcpyAsync of the outputs back into the pinned slot, on the download
//      stream, after an event of 3;
//   5. after packing chunk k + kSlots - 1, the host waits for chunk k's download
//      (the only host synchronisation) and scatters it into the user's output views
//      (unpack), which frees slot k % kSlots for chunk k + kSlots.
// So packing chunk k + 1, the DMA of chunk k and the kernel of chunk k - 1 overlap.
// The kernels are one thread per instance, so a chunk is a contiguous range of
// instances and the results are bit-identical to the whole batch's in one launch.
// A failed copy or launch, or a fault seen at a wait, drains the streams and throws
// BackendError; the ring stays allocated and the next call starts clean.
// Not installed: it is no part of the public API.
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <cstddef>
#include <cstdlib>
#include <stdexcept>
#include <string>

#include "../src/engine/host_staging.hpp"
#include "staging.hpp"

namespace scandyn {
namespace cuda {
namespace detail {

// SCANDYN_HOST_STAGING (pageable | pinned; unset: pinned), a bad value as BackendError.
inline host_staging::Mode host_staging_from_env() {
  try {
    return host_staging::parse_mode(std::getenv("SCANDYN_HOST_STAGING"));
  } catch (const std::invalid_argument& e) {
    throw BackendError(std::string("backend 'cuda': ") + e.what());
  }
}

// SCANDYN_HOST_CHUNK_INSTANCES: the instances per chunk, 0 when unset (the default:
// host_staging::chunk_instances, about kChunkBytes), a bad value as BackendError.
inline Index host_chunk_override_from_env() {
  const char* value = std::getenv("SCANDYN_HOST_CHUNK_INSTANCES");
  if (!value || !*value) return 0;
  try {
    return host_staging::chunk_instances(0, value);
  } catch (const std::invalid_argument& e) {
    throw BackendError(std::string("backend 'cuda': ") + e.what());
  }
}

// Instances per chunk: the override, else about kChunkBytes of bytes_per_instance.
inline Index host_chunk(Index override_instances, std::size_t bytes_per_instance) {
  return override_instances > 0 ? override_instances : host_staging::chunk_instances(bytes_per_instance, nullptr);
}

// Byte offsets of one chunk's arrays in a slot (pinned and device alike): the
// inputs first, then the outputs, each array aligned to 256 bytes.
struct SlotLayout {
  static constexpr int kMaxArrays = 8;
  static constexpr std::size_t kAlign = 256;
  std::size_t offset[kMaxArrays] = {};
  int arrays = 0;
  std::size_t inputs_end = 0;  // inputs in [0, inputs_end), outputs in [inputs_end, end)
  std::size_t end = 0;

  // Appends an array of `bytes`; returns its index.
  int add(std::size_t bytes) {
    offset[arrays] = end;
    end += (bytes + kAlign - 1) / kAlign * kAlign;
    return arrays++;
  }
  // The arrays added so far are the inputs.
  void close_inputs() { inputs_end = end; }
};

// What the engine's pack, launch and unpack see of one chunk.
struct HostChunk {
  host_staging::Range range;  // the chunk's instances in the batch
  SlotLayout layout;          // for range.count instances
  unsigned char* host = nullptr;    // the pinned slot
  unsigned char* device = nullptr;  // the device slot

  template <class T>
  T* host_array(int a) const { return reinterpret_cast<T*>(host + layout.offset[a]); }
  template <class T>
  T* device_array(int a) const { return reinterpret_cast<T*>(device + layout.offset[a]); }
};

// The inputs of a thread engine's batch (IdBatchIn / FdBatchIn: q with nq entries per
// instance, qd, and qdd or tau with nv, and optionally fext, one wrench per body) as a
// chunk's arrays 0-3: each view packed in the layout it suggests
// (host_staging::choose_layout), fext verbatim. What the pinned paths of inverse and
// forward dynamics share; each adds its outputs after close_inputs().
template <class S, class In>
struct PackedBatchInputs {
  BatchView<const S> views[3];
  Index widths[3];
  host_staging::Layout lay[3];
  const Force<S>* fext;
  Index nb;
  std::size_t fext_bytes;  // per instance

  PackedBatchInputs(const In& in, Index nq, Index nv, Index nbodies)
      : views{in.q, in.qd, third(in)}, widths{nq, nv, nv}, fext(in.fext), nb(nbodies),
        fext_bytes(in.fext ? static_cast<std::size_t>(nbodies) * sizeof(Force<S>) : 0) {
    for (int k = 0; k < 3; ++k) lay[k] = host_staging::choose_layout(views[k], widths[k], false);
  }
  // bytes per instance of the inputs (for the chunk size)
  std::size_t bytes_per_instance() const {
    return (static_cast<std::size_t>(widths[0]) + 2 * static_cast<std::size_t>(widths[1])) * sizeof(S) + fext_bytes;
  }
  // arrays 0, 1, 2 (the views) and 3 (fext) of n instances, then close_inputs()
  void add_to(SlotLayout& L, Index n) const {
    for (int k = 0; k < 3; ++k) L.add(host_staging::packed_entries(lay[k], widths[k], n) * sizeof(S));
    L.add(fext_bytes * static_cast<std::size_t>(n));
    L.close_inputs();
  }
  // host: the chunk's instances into its pinned arrays 0-3
  void pack(const HostChunk& c) const {
    for (int k = 0; k < 3; ++k) host_staging::pack(views[k], widths[k], c.range, lay[k], c.host_array<S>(k), 0);
    if (fext)
      host_staging::copy_bytes(c.host_array<unsigned char>(3), fext + static_cast<std::ptrdiff_t>(c.range.begin) * nb,
                               fext_bytes * static_cast<std::size_t>(c.range.count), 0);
  }
  // the chunk's batch on the device slot
  In device_batch(const HostChunk& c) const {
    const Index n = c.range.count;
    return In{host_staging::packed_view(c.device_array<const S>(0), lay[0], widths[0], n),
              host_staging::packed_view(c.device_array<const S>(1), lay[1], widths[1], n),
              host_staging::packed_view(c.device_array<const S>(2), lay[2], widths[2], n),
              fext ? c.device_array<const Force<S>>(3) : nullptr};
  }

 private:
  static BatchView<const S> third(const IdBatchIn<S>& in) { return in.qdd; }
  static BatchView<const S> third(const FdBatchIn<S>& in) { return in.tau; }
};

class HostPipeline {
 public:
  static constexpr int kSlots = 3;

  // Streams and events on the device current now (the engine's); no memory yet.
  // SCANDYN_HOST_CHUNK_INSTANCES is read now (a bad value: BackendError).
  HostPipeline() : chunk_override_(host_chunk_override_from_env()) {
    check(cudaGetDevice(&device_), "cudaGetDevice");
    try {
      for (cudaStream_t* s : {&upload_, &compute_, &download_})
        check(cudaStreamCreateWithFlags(s, cudaStreamNonBlocking), "cudaStreamCreateWithFlags");
      for (int s = 0; s < kSlots; ++s)
        for (cudaEvent_t* e : {&uploaded_[s], &ran_[s], &downloaded_[s]})
          check(cudaEventCreateWithFlags(e, cudaEventDisableTiming), "cudaEventCreateWithFlags");
    } catch (...) {
      destroy();
      throw;
    }
  }
  ~HostPipeline() { destroy(); }
  HostPipeline(const HostPipeline&) = delete;
  HostPipeline& operator=(const HostPipeline&) = delete;

  std::size_t slot_bytes() const { return slot_bytes_; }
  int slots() const { return slots_; }
  // pinned bytes held (as many device bytes again)
  std::size_t ring_bytes() const { return slot_bytes_ * static_cast<std::size_t>(slots_); }
  // times the ring was allocated (1 after the first call while no call needs more)
  int allocations() const { return allocations_; }

  // Runs `batch` instances in chunks of SCANDYN_HOST_CHUNK_INSTANCES instances, else of
  // about kChunkBytes of `bytes_per_instance` (host_chunk):
  //   layout(n) -> SlotLayout          the arrays of a chunk of n instances;
  //   pack(const HostChunk&)           host: the inputs into chunk.host_array;
  //   launch(const HostChunk&, stream) -> cudaError_t  the kernels on the device slot;
  //   unpack(const HostChunk&)         host: the outputs from chunk.host_array.
  // `launching` / `running` name the kernels in errors ("launching ...: ").
  // capacity: the most instances a call of the engine takes (its max_batch): the ring
  // is sized at once for kSlots chunks of min(chunk, capacity) instances, so that a
  // later, larger call does not allocate pinned memory again.
  template <class Layout, class Pack, class Launch, class Unpack>
  void run(Index batch, std::size_t bytes_per_instance, Index capacity, Layout&& layout, Pack&& pack, Launch&& launch,
           Unpack&& unpack, const char* launching, const char* running) {
    using host_staging::chunk_count;
    using host_staging::chunk_range;
    if (batch <= 0) return;
    Index chunk = host_chunk(chunk_override_, bytes_per_instance);
    const Index full = std::max<Index>(1, std::min(chunk, std::max(capacity, batch)));
    chunk = std::max<Index>(1, std::min(chunk, batch));
    const Index K = chunk_count(batch, chunk);
    reserve(kSlots, layout(full).end);
    const Index lag = kSlots - 1;  // chunk k is unpacked after packing chunk k + lag
    try {
      for (Index k = 0; k < K + lag; ++k) {
        if (k < K) {
          const HostChunk c = chunk_at(batch, chunk, k, layout);
          const int s = static_cast<int>(k % kSlots);
          pack(c);  // slot s is free: chunk k - kSlots was unpacked in iteration k - 1
          check(cudaMemcpyAsync(c.device, c.host, c.layout.inputs_end, cudaMemcpyHostToDevice, upload_),
                "copying a chunk of the inputs to the device");
          check(cudaEventRecord(uploaded_[s], upload_), "cudaEventRecord");
          check(cudaStreamWaitEvent(compute_, uploaded_[s], 0), "cudaStreamWaitEvent");
          check(launch(c, compute_), launching);
          check(cudaEventRecord(ran_[s], compute_), "cudaEventRecord");
          check(cudaStreamWaitEvent(download_, ran_[s], 0), "cudaStreamWaitEvent");
          check(cudaMemcpyAsync(c.host + c.layout.inputs_end, c.device + c.layout.inputs_end,
                                c.layout.end - c.layout.inputs_end, cudaMemcpyDeviceToHost, download_),
                "copying a chunk of the outputs to the host");
          check(cudaEventRecord(downloaded_[s], download_), "cudaEventRecord");
        }
        const Index j = k - lag;
        if (j >= 0 && j < K) {
          check(cudaEventSynchronize(downloaded_[j % kSlots]), running);
          unpack(chunk_at(batch, chunk, j, layout));
        }
      }
    } catch (...) {
      drain();
      throw;
    }
  }

 private:
  template <class Layout>
  HostChunk chunk_at(Index batch, Index chunk, Index k, Layout& layout) const {
    HostChunk c;
    c.range = host_staging::chunk_range(batch, chunk, k);
    c.layout = layout(c.range.count);
    const std::size_t at = static_cast<std::size_t>(k % kSlots) * slot_bytes_;
    c.host = host_ + at;
    c.device = device_buffer_ + at;
    return c;
  }

  // At least `slots` slots of `bytes` each (nothing is in flight between calls).
  void reserve(int slots, std::size_t bytes) {
    bytes = std::max<std::size_t>(bytes, SlotLayout::kAlign);
    if (slots <= slots_ && bytes <= slot_bytes_) return;
    slots = std::max(slots, slots_);
    bytes = std::max(bytes, slot_bytes_);
    release();
    int current = 0;
    check(cudaGetDevice(&current), "cudaGetDevice");
    if (current != device_) check(cudaSetDevice(device_), "cudaSetDevice");
    const std::size_t total = bytes * static_cast<std::size_t>(slots);
    try {
      void* h = nullptr;
      check(cudaMallocHost(&h, total), ("allocating " + std::to_string(total) + " bytes of pinned host memory for the "
                                        "host staging ring (SCANDYN_HOST_STAGING=pageable avoids it)").c_str());
      host_ = static_cast<unsigned char*>(h);
      device_buffer_ = static_cast<unsigned char*>(device_malloc(total, [&](std::size_t free_bytes, std::size_t) {
        return "backend 'cuda': the host staging ring needs " + std::to_string(total) + " bytes of device memory (" +
               std::to_string(slots) + " slots of " + std::to_string(bytes) + "); " + std::to_string(free_bytes) +
               " are free (SCANDYN_HOST_STAGING=pageable avoids it)";
      }));
    } catch (...) {
      release();
      if (current != device_) cudaSetDevice(current);
      throw;
    }
    if (current != device_) cudaSetDevice(current);
    slots_ = slots;
    slot_bytes_ = bytes;
    ++allocations_;
  }

  void release() {
    if (host_) cudaFreeHost(host_);
    if (device_buffer_) cudaFree(device_buffer_);
    host_ = nullptr;
    device_buffer_ = nullptr;
    slots_ = 0;
    slot_bytes_ = 0;
  }

  // Waits for whatever was queued (after an error), and clears a non-sticky error.
  void drain() {
    for (cudaStream_t s : {upload_, compute_, download_})
      if (s) (void)cudaStreamSynchronize(s);
    (void)cudaGetLastError();
  }

  void destroy() {
    drain();
    release();
    for (int s = 0; s < kSlots; ++s)
      for (cudaEvent_t e : {uploaded_[s], ran_[s], downloaded_[s]})
        if (e) cudaEventDestroy(e);
    for (cudaStream_t s : {upload_, compute_, download_})
      if (s) cudaStreamDestroy(s);
  }

  int device_ = 0;
  cudaStream_t upload_ = nullptr, compute_ = nullptr, download_ = nullptr;
  cudaEvent_t uploaded_[kSlots] = {}, ran_[kSlots] = {}, downloaded_[kSlots] = {};
  unsigned char* host_ = nullptr;           // kSlots pinned slots of slot_bytes_
  unsigned char* device_buffer_ = nullptr;  // the device slots, likewise
  std::size_t slot_bytes_ = 0;
  int slots_ = 0;
  int allocations_ = 0;
  Index chunk_override_ = 0;  // SCANDYN_HOST_CHUNK_INSTANCES, 0: none
};

}  // namespace detail
}  // namespace cuda
}  // namespace scandyn
