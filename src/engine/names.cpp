// src/engine/names.cpp: the engine API's names (to_string and parse_* of BackendKind,
// Precision, IdStrategy, FdMethod, FdCheckMode, CpuSimd: scandyn/engine.hpp) and which
// backends this build and machine can run (backend_unusable, openmp_threads,
// backend_threads). Apart from the factories (engine.cpp), so that what reads names
// (the scene reader, the command's arguments) does not pull every engine in.
#include <string>

#include "scandyn/build_config.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/engine.hpp"

#ifdef _OPENMP
#include <omp.h>
#endif

namespace scandyn {

// ---- names ----------------------------------------------------------------------

const char* to_string(BackendKind b) {
  switch (b) {
    case BackendKind::Serial: return "serial";
    case BackendKind::OpenMP: return "openmp";
    case BackendKind::Cuda: return "cuda";
  }
  return "?";
}

const char* to_string(Precision p) { return p == Precision::Double ? "double" : "float"; }

const char* to_string(IdStrategy s) {
  switch (s) {
    case IdStrategy::Auto: return "auto";
    case IdStrategy::Recursion: return "recursion";
    case IdStrategy::ScanLocal: return "scan-local";
    case IdStrategy::ScanWorld: return "scan-world";
  }
  return "?";
}

const char* to_string(FdMethod m) {
  switch (m) {
    case FdMethod::Auto: return "auto";
    case FdMethod::Aba: return "aba";
    case FdMethod::Jsi: return "jsi";
    case FdMethod::Parallel: return "parallel";
    case FdMethod::Hybrid: return "hybrid";
  }
  return "?";
}

const char* to_string(FdCheckMode m) {
  switch (m) {
    case FdCheckMode::Auto: return "auto";
    case FdCheckMode::On: return "on";
    case FdCheckMode::Off: return "off";
  }
  return "?";
}

const char* to_string(CpuSimd s) {
  switch (s) {
    case CpuSimd::Auto: return "auto";
    case CpuSimd::Off: return "off";
    case CpuSimd::On: return "on";
  }
  return "?";
}

namespace {

// The value of E whose to_string is name; BackendError naming what and the choices.
template <class E, std::size_t N>
E parse_name(const std::string& name, const E (&values)[N], const char* what) {
  std::string known;
  for (std::size_t k = 0; k < N; ++k) {
    if (name == to_string(values[k])) return values[k];
    known += k == 0 ? "" : k + 1 == N ? " or " : ", ";
    known += to_string(values[k]);
  }
  throw BackendError("unknown " + std::string(what) + " '" + name + "' (expected " + known + ")");
}

}  // namespace

BackendKind parse_backend(const std::string& name) {
  static constexpr BackendKind kAll[] = {BackendKind::Serial, BackendKind::OpenMP, BackendKind::Cuda};
  return parse_name(name, kAll, "backend");
}
Precision parse_precision(const std::string& name) {
  static constexpr Precision kAll[] = {Precision::Double, Precision::Float};
  return parse_name(name, kAll, "precision");
}
IdStrategy parse_strategy(const std::string& name) {
  static constexpr IdStrategy kAll[] = {IdStrategy::Auto, IdStrategy::Recursion, IdStrategy::ScanLocal,
                                        IdStrategy::ScanWorld};
  return parse_name(name, kAll, "strategy");
}
FdMethod parse_fd_method(const std::string& name) {
  static constexpr FdMethod kAll[] = {FdMethod::Auto, FdMethod::Aba, FdMethod::Jsi, FdMethod::Hybrid,
                                      FdMethod::Parallel};
  return parse_name(name, kAll, "forward-dynamics method");
}
CpuSimd parse_cpu_simd(const std::string& name) {
  static constexpr CpuSimd kAll[] = {CpuSimd::Auto, CpuSimd::Off, CpuSimd::On};
  return parse_name(name, kAll, "simd mode");
}

FdCheckMode parse_fd_check(const std::string& name) {
  static constexpr FdCheckMode kAll[] = {FdCheckMode::Auto, FdCheckMode::On, FdCheckMode::Off};
  return parse_name(name, kAll, "forward-dynamics check");
}

// ---- what this build and machine can run ---------------------------------------

int openmp_threads() {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}

int backend_threads(BackendKind backend, int threads) {
  if (backend != BackendKind::OpenMP) return 1;
  return threads > 0 ? threads : openmp_threads();
}

std::string backend_unusable(BackendKind backend) {
  switch (backend) {
    case BackendKind::Serial: return "";
    case BackendKind::OpenMP:
#if SCANDYN_HAS_OPENMP && defined(_OPENMP)
      return "";
#else
      return "backend 'openmp' is not available in this build";
#endif
    case BackendKind::Cuda: {
#if SCANDYN_HAS_CUDA
      const cuda::Result<int> count = cuda::device_count();
      if (!count) return count.error;
      if (count.value == 0) return "no usable CUDA device: the CUDA runtime reports 0 devices";
      return "";
#else
      return "backend 'cuda' is not available in this build";
#endif
    }
  }
  return "unknown backend";
}

}  // namespace scandyn
