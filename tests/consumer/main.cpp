// A consumer of the installed package: loads the chain:3 generator, runs the
// reference RNEA on a fixed state and checks the torques are finite; also calls
// the CUDA device query, which must link (and may report that there is no device).
// Exit status 0 on success, 1 on a non-finite result, 2 on an exception.
#include <cmath>
#include <cstdio>
#include <exception>
#include <vector>

#include "scandyn/algorithm/reference.hpp"
#include "scandyn/build_config.hpp"
#include "scandyn/cuda/device.hpp"
#include "scandyn/model/load.hpp"

int main() {
  try {
    const scandyn::Model model = scandyn::load_model("chain:3");
    const int n = model.nv();
    if (n != 3) {
      std::fprintf(stderr, "consumer: chain:3 has %d DoF, expected 3\n", n);
      return 1;
    }
    scandyn::Data data(model);
    std::vector<double> q(n), qd(n), qdd(n), tau(n, std::nan(""));
    for (int i = 0; i < n; ++i) {
      q[i] = 0.3 * (i + 1);
      qd[i] = -0.2 * i;
      qdd[i] = 0.1;
    }
    scandyn::rnea(model, data, q.data(), qd.data(), qdd.data(), tau.data());
    for (int i = 0; i < n; ++i) {
      std::printf("tau_%d = %.17g\n", i, tau[i]);
      if (!std::isfinite(tau[i])) {
        std::fprintf(stderr, "consumer: tau_%d is not finite\n", i);
        return 1;
      }
    }
    // Links the CUDA part of the library when there is one; no device is fine.
    const auto count = scandyn::cuda::device_count();
    if (count) {
      std::printf("consumer: %d CUDA device(s)\n", count.value);
    } else {
      std::printf("consumer: %s\n", count.error.c_str());
    }
    std::printf("consumer: scandyn %s (CUDA %d, OpenMP %d) ok\n", SCANDYN_VERSION,
                SCANDYN_HAS_CUDA, SCANDYN_HAS_OPENMP);
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "consumer: %s\n", e.what());
    return 2;
  }
}
