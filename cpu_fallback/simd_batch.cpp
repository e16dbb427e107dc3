// cpu_fallback/simd_batch.cpp: the SIMD path of the CPU engines (simd_batch.hpp):
// the reference algorithms instantiated over NativePack<float> and NativePack<double>,
// and the gathers and scatters between batch views and packs.
#include "simd_batch.hpp"

#include "../src/algorithm/reference_impl.hpp"

namespace scandyn {

SCANDYN_INSTANTIATE(NativePack<float>)
SCANDYN_INSTANTIATE(NativePack<double>)

namespace cpu {

template <class S>
bool simd_supported(const ModelTpl<S>& model) {
  for (const Body<S>& b : model.bodies)
    if (b.type != JointType::Revolute && b.type != JointType::Prismatic) return false;
  return true;
}

template <class S>
bool use_simd(const ModelTpl<S>& model, CpuSimd simd) {
  if (simd == CpuSimd::Off) return false;
  if (simd == CpuSimd::On)
    for (Index i = 0; i < model.nv(); ++i) {
      const JointType t = model.bodies[i].type;
      if (t != JointType::Revolute && t != JointType::Prismatic)
        throw BackendError("simd: the SIMD path takes revolute and prismatic joints only; joint '" +
                           (i < Index(model.joint_names.size()) ? model.joint_names[i] : std::to_string(i)) +
                           "' is neither (use --simd off or auto)");
    }
  return SimdBatch<S>::W > 1 && simd_supported(model);
}

template <class S>
SimdBatch<S>::SimdBatch(const ModelTpl<S>& model, bool mass_matrix)
    : nv_(model.nv()), model_(model.template cast<P>()), data_(model_, /*mass_matrix=*/false) {
  const std::size_t n = static_cast<std::size_t>(nv_);
  q_.resize(n);
  qd_.resize(n);
  x_.resize(n);
  out_.resize(mass_matrix ? n * n : n);  // a 10^5-link rope's id must not reserve nv^2 packs
  fext_.resize(n);
}

// Entries 0..n-1 of instances b..b+W-1: one vector load per entry when the
// instances of an entry are contiguous (batch_stride 1), else lane by lane.
template <class S>
void SimdBatch<S>::load(const BatchView<const S>& v, Index b, Index n, P* out) const {
  if (v.batch_stride == 1) {
    for (Index i = 0; i < n; ++i) out[i] = P::load(&v.at(i, b));
    return;
  }
  for (Index i = 0; i < n; ++i)
    for (int l = 0; l < W; ++l) out[i].set(l, v.at(i, b + l));
}

template <class S>
void SimdBatch<S>::store(const P* in, const BatchView<S>& v, Index b, Index n) const {
  if (v.batch_stride == 1) {
    for (Index i = 0; i < n; ++i) in[i].store(&v.at(i, b));
    return;
  }
  for (Index i = 0; i < n; ++i)
    for (int l = 0; l < W; ++l) v.at(i, b + l) = in[i][l];
}

template <class S>
const Force<typename SimdBatch<S>::P>* SimdBatch<S>::load_fext(const Force<S>* fext, Index b) {
  if (!fext) return nullptr;
  const auto set = [](Vec3<P>& to, const Vec3<S>& from, int l) {
    to.x.set(l, from.x);
    to.y.set(l, from.y);
    to.z.set(l, from.z);
  };
  for (Index i = 0; i < nv_; ++i)
    for (int l = 0; l < W; ++l) {
      const Force<S>& f = fext[static_cast<std::size_t>(b + l) * nv_ + i];
      set(fext_[i].n, f.n, l);
      set(fext_[i].f, f.f, l);
    }
  return fext_.data();
}

template <class S>
void SimdBatch<S>::rnea(const BatchView<const S>& q, const BatchView<const S>& qd, const BatchView<const S>& qdd,
                        const Force<S>* fext, const BatchView<S>& tau, Index b) {
  load(q, b, nv_, q_.data());
  load(qd, b, nv_, qd_.data());
  const Force<P>* f = load_fext(fext, b);
  if (qdd.data) {
    load(qdd, b, nv_, x_.data());
    scandyn::rnea(model_, data_, q_.data(), qd_.data(), x_.data(), out_.data(), f);
  } else {
    scandyn::bias_forces(model_, data_, q_.data(), qd_.data(), out_.data(), f);
  }
  store(out_.data(), tau, b, nv_);
}

template <class S>
void SimdBatch<S>::crba(const BatchView<const S>& q, const BatchView<S>& M, Index b) {
  load(q, b, nv_, q_.data());
  scandyn::crba(model_, data_, q_.data(), out_.data());
  store(out_.data(), M, b, nv_ * nv_);
}

template <class S>
bool SimdBatch<S>::aba(const BatchView<const S>& q, const BatchView<const S>& qd, const BatchView<const S>& tau,
                       const Force<S>* fext, const BatchView<S>& qdd, Index b) {
  load(q, b, nv_, q_.data());
  load(qd, b, nv_, qd_.data());
  load(tau, b, nv_, x_.data());
  const Status st = scandyn::aba(model_, data_, q_.data(), qd_.data(), x_.data(), out_.data(), load_fext(fext, b));
  if (!st.ok()) return false;
  store(out_.data(), qdd, b, nv_);
  return true;
}

template bool simd_supported(const ModelTpl<float>&);
template bool simd_supported(const ModelTpl<double>&);
template bool use_simd(const ModelTpl<float>&, CpuSimd);
template bool use_simd(const ModelTpl<double>&, CpuSimd);
template class SimdBatch<float>;
template class SimdBatch<double>;

}  // namespace cpu
}  // namespace scandyn
