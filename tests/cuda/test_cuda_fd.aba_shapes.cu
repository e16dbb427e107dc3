// test_cuda_fd, part: aba_instance on the host with the branch slots of the ABA kernels
// for shapes (chains: 0; register slots: 1, 2). Tolerances: tests/cuda/test_cuda_fd.cu.
#include "cuda_fd_test_util.hpp"

using namespace scandyn;
using namespace scandyn::test::fd;

// The ABA kernels for shapes (aba_instance's kSlots) on the host: the chain kernel
// (0) on every model without branch children, register slots (1, 2) on every model
// that needs at most as many, against the serial aba (double 1e-12, float
// max(1e-4, 10 x the serial float aba's own error), as DeviceFunctionOnTheHost).
TEST(CudaFdAbaModel, ShapeKernelsOnTheHost) {
  std::vector<std::pair<std::string, Model>> models;
  for (const char* file : {"iiwa.urdf", "hyq.urdf", "atlas.urdf"}) models.emplace_back(file, robot(file));
  for (auto& m : generated_models()) models.push_back(std::move(m));
  for (const char* spec : {"tree:12:4", "tree:20:2"}) models.emplace_back(spec, load_model(spec));
  int tested[3] = {0, 0, 0};  // models run with 0, 1, 2 slots
  for (const auto& [name, md] : models) {
    SCOPED_TRACE(name);
    const Index slots = cuda::ThreadModel<double>(md).branch_slots();
    for (bool fx : {false, true}) {
      SCOPED_TRACE(fx ? "fext" : "no fext");
      std::vector<Errors> dbl, flt;
      if (slots == 0) {
        dbl = {host_instance_errors<double, false, true, true, 0>(md, 20, fx),
               host_instance_errors<double, false, false, true, 0>(md, 20, fx),
               host_instance_errors<double, true, false, true, 0>(md, 20, fx)};
        flt = {host_instance_errors<float, false, true, true, 0>(md, 20, fx),
               host_instance_errors<float, false, false, true, 0>(md, 20, fx)};
      }
      if (slots <= 1) {
        for (const Errors& e : {host_instance_errors<double, false, true, true, 1>(md, 20, fx),
                                host_instance_errors<double, false, false, true, 1>(md, 20, fx)})
          dbl.push_back(e);
        flt.push_back(host_instance_errors<float, false, false, true, 1>(md, 20, fx));
      }
      if (slots <= 2) {
        for (const Errors& e : {host_instance_errors<double, false, true, true, 2>(md, 20, fx),
                                host_instance_errors<double, true, false, true, 2>(md, 20, fx)})
          dbl.push_back(e);
        flt.push_back(host_instance_errors<float, false, false, true, 2>(md, 20, fx));
      }
      for (const Errors& e : dbl) EXPECT_LE(e.aba, 1e-12);
      if (!flt.empty()) {
        const double ftol = aba_float_tol(md, 20, fx, kHostSeed);
        for (const Errors& e : flt) EXPECT_LE(e.aba, ftol);
      }
    }
    for (Index k = slots; k < 3; ++k) ++tested[k];
  }
  EXPECT_GE(tested[0], 8);  // iiwa, hyq, chains, rope, curtain
  EXPECT_GE(tested[1], 9);  // ... and atlas
  EXPECT_GE(tested[2], 11); // ... and tree:12:4, tree:20:2
}
