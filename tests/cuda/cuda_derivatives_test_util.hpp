// tests/cuda/cuda_derivatives_test_util.hpp: what the CUDA derivative engines' tests
// (test_cuda_derivatives.cu, test_cuda_derivatives_multi_dof.cu) share: the serial
// engines' results they compare with, and the forward dynamics derivatives'
// compute_async on device pointers and a stream, next to the serial engine on the same
// inputs.
#pragma once

#include <cuda_runtime.h>
#include <gtest/gtest.h>

#include <cstddef>
#include <vector>

#include "cuda_test_util.hpp"
#include "scandyn/cuda/derivatives.hpp"
#include "scandyn/engine.hpp"
#include "test_util.hpp"

namespace scandyn::test {

// The serial engines (B instances) on id_in and fd_in: id_ref the inverse dynamics'
// blocks, fd_ref and qdd_ref (nv x B aos) the forward dynamics'. Returns the forward
// dynamics' status.
template <class S>
BatchStatus serial_derivatives(const ModelTpl<S>& model, Index B, const IdBatchIn<S>& id_in, const FdBatchIn<S>& fd_in,
                               DerivativeBlocks<S>& id_ref, DerivativeBlocks<S>& fd_ref, std::vector<S>& qdd_ref) {
  BackendOptions o;
  o.max_batch = B;
  make_id_derivatives(model, o)->compute(id_in, {id_ref.v[0], id_ref.v[1], id_ref.v[2]});
  return make_fd_derivatives(model, o)->compute(
      fd_in, {fd_ref.v[0], fd_ref.v[1], fd_ref.v[2], BatchView<S>::aos(qdd_ref.data(), model.nv(), B)});
}

// cuda::CudaFdDerivatives' compute_async on device pointers (soa; qdd not requested) on
// a stream of its own, from the soa host inputs q (nq x B), qd and tau (nv x B); and the
// serial engine on soa host views of the same inputs. got: the device's three blocks
// (nv^2 x B soa each, laid out as ref.data); ref (made soa by the caller: nv, B, true):
// the serial engine's; failed: the device's failure codes (B).
inline void fd_derivatives_on_a_stream(const Model& model, Index B, const std::vector<double>& q,
                                       const std::vector<double>& qd, const std::vector<double>& tau,
                                       std::vector<double>& got, DerivativeBlocks<double>& ref,
                                       std::vector<int>& failed) {
  const Index nv = model.nv(), nq = model.nq();
  const std::size_t nn = static_cast<std::size_t>(nv) * nv;
  DeviceArray<double> dq, dqd, dtau, dout;
  ASSERT_CUDA(dq.alloc(q.size()));
  ASSERT_CUDA(dqd.alloc(qd.size()));
  ASSERT_CUDA(dtau.alloc(tau.size()));
  ASSERT_CUDA(dout.alloc(3 * nn * B));
  DeviceArray<int> dfailed;
  ASSERT_CUDA(dfailed.alloc(B));
  ASSERT_CUDA(cudaMemcpy(dq.ptr, q.data(), q.size() * 8, cudaMemcpyHostToDevice));
  ASSERT_CUDA(cudaMemcpy(dqd.ptr, qd.data(), qd.size() * 8, cudaMemcpyHostToDevice));
  ASSERT_CUDA(cudaMemcpy(dtau.ptr, tau.data(), tau.size() * 8, cudaMemcpyHostToDevice));
  cuda::CudaFdDerivatives<double> e(model, device_path_options());
  using V = BatchView<const double>;
  BatchView<double> out[3];
  for (int k = 0; k < 3; ++k) out[k] = BatchView<double>::soa(dout.ptr + k * nn * B, nv * nv, B);
  cudaStream_t stream;
  ASSERT_CUDA(cudaStreamCreate(&stream));
  ASSERT_CUDA(e.compute_async({V::soa(dq.ptr, nq, B), V::soa(dqd.ptr, nv, B), V::soa(dtau.ptr, nv, B)},
                              {out[0], out[1], out[2], {}}, dfailed.ptr, stream));
  ASSERT_CUDA(cudaStreamSynchronize(stream));
  ASSERT_CUDA(cudaStreamDestroy(stream));
  got.assign(3 * nn * B, 0.0);
  failed.assign(B, 0);
  ASSERT_CUDA(cudaMemcpy(got.data(), dout.ptr, got.size() * 8, cudaMemcpyDeviceToHost));
  ASSERT_CUDA(cudaMemcpy(failed.data(), dfailed.ptr, B * sizeof(int), cudaMemcpyDeviceToHost));
  BackendOptions s;
  s.max_batch = B;
  ASSERT_TRUE(make_fd_derivatives(model, s)
                  ->compute({V::soa(q.data(), nq, B), V::soa(qd.data(), nv, B), V::soa(tau.data(), nv, B)},
                            {ref.v[0], ref.v[1], ref.v[2], {}})
                  .ok());
}

}  // namespace scandyn::test
