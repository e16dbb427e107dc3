// The simulator across devices (scandyn/sim/simulator.hpp, "Devices"): the scene's
// "devices", the CPU backends' refusal, the shard of an instance and the merged
// status, and the sharded backend over serial shards (the CPU stand-in for one
// CUDA backend per device) bit-identical to one serial backend over the whole batch:
// steps with torques, resets of scattered instances, the state, the contact
// readings, failures numbered as the caller's instances. With a CUDA device: the
// simulator on devices {0, 0} (two shards on one GPU) and on every visible device
// bit-identical to the simulator on the current device (float and double, euler and
// rk4, contacts).
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#include "scandyn/cuda/device.hpp"
#include "scandyn/engine.hpp"
#include "scandyn/sharded.hpp"
#include "scandyn/sim/scene.hpp"
#include "scandyn/sim/simulator.hpp"
#include "scene_util.hpp"
#include "test_util.hpp"
#include "../cpu_fallback/simulator_step.hpp"

namespace scandyn {
namespace {

using sim::Scene;
using sim::SceneError;
using sim::Simulator;

using test::scene_error;
using test::scene_from;


// A rope of 4 links with every joint effect and contacts of every link with a
// plane, B instances from a random initial state.
std::string rope_scene(const std::string& integrator, int B, const std::string& backend,
                       const std::string& extra = "") {
  // (links of 1 cm and 10 g: coefficients small enough for explicit steps of 0.1 ms;
  // the plane at z = -2.5 cm touches the lower links)
  return R"({"model": "rope:4", "dt": 1e-4, "integrator": ")" + integrator + R"(", "instances": )" +
         std::to_string(B) + R"(, "backend": ")" + backend + R"(", )" + extra + R"(
    "effects": {"gravity": true, "damping": 1e-6, "springs": {"stiffness": 1e-4},
                "contacts": {"planes": [{"normal": [0, 0, 1], "offset": -0.025}], "all_links": {"radius": 0.002},
                             "stiffness": 10, "damping": 0.01, "friction": 0.5}},
    "initial": {"q": 0.3, "qd": 0, "random": {"seed": 3, "q": 0.8, "qd": 1}}})";
}

bool cuda_usable() { return backend_unusable(BackendKind::Cuda).empty(); }

// ---- the scene's "devices" --------------------------------------------------------

TEST(SimDevicesScene, ListsStringsAndCurrent) {
  const std::string base = R"({"model": "chain:2", "dt": 1e-3, "backend": "cuda", "devices": )";
  EXPECT_EQ(scene_from(base + "[0, 1]}").devices, (std::vector<int>{0, 1}));
  EXPECT_EQ(scene_from(base + "\"1,1\"}").devices, (std::vector<int>{1, 1}));
  EXPECT_TRUE(scene_from(base + "\"current\"}").devices.empty());
  EXPECT_TRUE(scene_from(base + "[]}").devices.empty());
  EXPECT_TRUE(scene_from(R"({"model": "chain:2", "dt": 1e-3})").devices.empty());  // the default: current
  // on a backend "auto" chose, the devices apply only where it chose cuda
  const Scene a = scene_from(R"({"model": "chain:2", "dt": 1e-3, "backend": "auto", "devices": "all"})");
  EXPECT_EQ(a.devices.empty(), a.backend != BackendKind::Cuda);
}

TEST(SimDevicesScene, BadValuesAndCpuBackendsAreOneError) {
  const std::string base = R"({"model": "chain:2", "dt": 1e-3, "backend": "cuda", "devices": )";
  EXPECT_EQ(scene_error(base + "3}"),
            "test.json: devices: expected \"all\", \"current\", a list of CUDA device ordinals such as [0, 1] or a "
            "string such as \"0,1\", got 3");
  EXPECT_EQ(scene_error(base + "[0, -1]}"), "test.json: devices[1]: expected an integer from 0 to 999999, got -1");
  EXPECT_NE(scene_error(base + "\"0;1\"}").find("test.json: devices: devices '0;1': '0;1' is not a device ordinal"),
            std::string::npos);
  EXPECT_EQ(scene_error(R"({"model": "chain:2", "dt": 1e-3, "backend": "openmp", "devices": [0]})"),
            "test.json: devices: CUDA devices for the cuda backend; the scene's backend is 'openmp' (remove \"devices\" "
            "or use \"backend\": \"cuda\")");
  // the default backend is serial
  EXPECT_NE(scene_error(R"({"model": "chain:2", "dt": 1e-3, "devices": "all"})").find("the scene's backend is 'serial'"),
            std::string::npos);
  if (!cuda_usable()) {  // "all" asks the CUDA runtime when the backend is cuda
    EXPECT_NE(scene_error(base + "\"all\"}").find("test.json: devices: devices 'all': no usable CUDA device"),
              std::string::npos);
  }
}

TEST(SimDevices, CpuBackendsRefuseADeviceList) {
  Scene s = scene_from(rope_scene("euler", 4, "serial"));
  s.devices = {0, 1};
  for (BackendKind b : {BackendKind::Serial, BackendKind::OpenMP}) {
    try {
      Simulator<double> sim(s, b);
      ADD_FAILURE() << "no error on " << to_string(b);
    } catch (const BackendError& e) {
      EXPECT_EQ(std::string(e.what()),
                std::string("devices 0,1: only the cuda backend runs on devices (backend '") + to_string(b) + "')");
    }
  }
}

TEST(SimDevices, ANonShardedSimulatorIsOneShard) {
  Simulator<double> sim(scene_from(rope_scene("euler", 5, "serial")));
  EXPECT_EQ(sim.shards(), 1);
  EXPECT_EQ(sim.shard_device(0), -1);
  EXPECT_EQ(sim.shard_range(0).count, 5);
  EXPECT_EQ(sim.q(0).data, sim.q().data);
  EXPECT_THROW(sim.q(1), std::out_of_range);
  EXPECT_TRUE(sim.torques_on_device() == sim.on_device());
}

// ---- routing ----------------------------------------------------------------------

TEST(SimDevices, ShardOfIsTheShardRangeHoldingTheInstance) {
  for (Index B : {1, 2, 5, 7, 64, 1001})
    for (int n : {1, 2, 3, 4, 7, 8})
      for (Index b = 0; b < B; ++b) {
        const ShardRange r = shard_range(B, n, sim::detail::shard_of(B, n, b));
        ASSERT_TRUE(r.begin <= b && b < r.begin + r.count) << "B " << B << " n " << n << " b " << b;
      }
}

TEST(SimDevices, MergedStatusNumbersInstancesAsTheBatch) {
  // B = 10 over 3 shards: [0, 4), [4, 7), [7, 10)
  std::vector<BatchStatus> st(3);
  st[2].record(1, 2, Failure::NonFinite);  // instance 8
  st[2].failed = 3;
  st[1].record(2, 5, Failure::ArticulatedPivot);  // instance 6
  st[1].failed = 2;
  const BatchStatus m = sim::detail::merge_shard_statuses(st, 10);
  EXPECT_EQ(m.failed, 5);
  EXPECT_EQ(m.first_instance, 6);
  EXPECT_EQ(m.first_dof, 5);
  EXPECT_EQ(m.failure, Failure::ArticulatedPivot);
  EXPECT_EQ(m.failed_dof, nullptr);
  // counts saturate at the largest Index
  st[1].failed = st[2].failed = std::numeric_limits<Index>::max();
  EXPECT_EQ(sim::detail::merge_shard_statuses(st, 10).failed, std::numeric_limits<Index>::max());
  EXPECT_TRUE(sim::detail::merge_shard_statuses(std::vector<BatchStatus>(3), 10).ok());
}

// ---- the sharded backend over serial shards -----------------------------------------

template <class S>
using Backend = std::unique_ptr<sim::detail::SimBackend<S>>;

template <class S>
Backend<S> serial_backend(const sim::SimSetup<S>& setup) {
  return cpu::make_simulator_step(setup, BackendKind::Serial);
}

// q and qd of every instance (nq x B, nv x B)
template <class S>
std::vector<S> state_of(sim::detail::SimBackend<S>& b, Index nq, Index nv, Index B) {
  std::vector<S> x(static_cast<std::size_t>((nq + nv) * B));
  b.read_state(x.data(), x.data() + nq * B);
  return x;
}

template <class S>
void expect_sharded_serial_identical(const std::string& integrator, int shards) {
  const Index B = 23;
  Simulator<S> sim(scene_from(rope_scene(integrator, B, "serial")));
  const sim::SimSetup<S>& setup = sim.setup();
  const Index nq = sim.nq(), nv = sim.nv(), P = sim.contact_count();
  Backend<S> one = serial_backend(setup);
  Backend<S> many = sim::detail::make_sharded_sim_backend<S>(setup, std::vector<int>(shards, 0), false,
                                                             &serial_backend<S>);
  EXPECT_EQ(many->shard_count(), shards);
  EXPECT_EQ(many->strategy(), one->strategy() + (shards > 1 ? "-x" + std::to_string(shards) : ""));
  EXPECT_TRUE(many->shard_count() == 1 || many->shard(1)->q().batch == shard_range(B, shards, 1).count);
  EXPECT_FALSE(many->tau_on_device());
  // the simulator's initial state, written to both as rows of every instance (in reverse order)
  std::vector<S> x0(static_cast<std::size_t>((nq + nv) * B));
  sim.read_state(x0.data(), x0.data() + nq * B);
  std::vector<Index> all;
  std::vector<S> qrows, qdrows;
  auto rows_of = [&](const std::vector<S>& x, const std::vector<Index>& which) {
    qrows.clear(), qdrows.clear();
    for (Index b : which) {
      for (Index i = 0; i < nq; ++i) qrows.push_back(x[i * B + b]);
      for (Index i = 0; i < nv; ++i) qdrows.push_back(x[nq * B + i * B + b]);
    }
  };
  for (Index b = B - 1; b >= 0; --b) all.push_back(b);
  rows_of(x0, all);
  for (auto* b : {one.get(), many.get()}) b->write_instances(all.data(), B, qrows.data(), qdrows.data());
  // torques (B x nv rows: dof stride 1, batch stride nv)
  std::vector<S> tau(static_cast<std::size_t>(B * nv));
  for (std::size_t k = 0; k < tau.size(); ++k) tau[k] = S(1e-5) * S(std::sin(0.7 * double(k)));
  const BatchView<const S> tv{tau.data(), B, 1, nv};
  auto compare = [&](const char* when) {
    const std::vector<S> a = state_of(*one, nq, nv, B), b = state_of(*many, nq, nv, B);
    ASSERT_EQ(std::memcmp(a.data(), b.data(), a.size() * sizeof(S)), 0) << when;
    std::vector<sim::ContactReading<S>> ra(static_cast<std::size_t>(B * P)), rb(ra.size());
    one->read_contact_forces(ra.data());
    many->read_contact_forces(rb.data());
    for (std::size_t k = 0; k < ra.size(); ++k) {
      ASSERT_EQ(ra[k].force.z, rb[k].force.z) << when << " reading " << k;
      ASSERT_EQ(ra[k].in_contact, rb[k].in_contact) << when << " reading " << k;
    }
  };
  compare("initial");
  for (int s = 0; s < 20; ++s) one->step(tv), many->step(tv);
  compare("after 20 steps");
  // a reset of scattered instances (the initial rows of others), then steps without torques
  const std::vector<Index> some{B - 1, 0, 11, 3, 12};
  std::vector<Index> from{2, 5, 7, 19, 22};
  rows_of(x0, from);
  for (auto* b : {one.get(), many.get()}) b->write_instances(some.data(), 5, qrows.data(), qdrows.data());
  for (int s = 0; s < 10; ++s) one->step({}), many->step({});
  compare("after the reset");
  ASSERT_TRUE(one->status().ok()) << sim::failure_message(one->status());
  EXPECT_TRUE(many->status().ok());
  // a state that is not finite in instances 17 and 9: failures as the batch numbers them
  const std::vector<Index> broken{17, 9};
  std::vector<S> q2(static_cast<std::size_t>(2 * nq), S(0)), qd2(static_cast<std::size_t>(2 * nv), S(0));
  qd2[0] = qd2[static_cast<std::size_t>(nv)] = std::numeric_limits<S>::infinity();
  for (auto* b : {one.get(), many.get()}) {
    b->write_instances(broken.data(), 2, q2.data(), qd2.data());
    b->step({});
  }
  const BatchStatus sa = one->status(), sb = many->status();
  EXPECT_EQ(sb.failed, sa.failed);
  EXPECT_EQ(sb.first_instance, 9);
  EXPECT_EQ(sb.first_instance, sa.first_instance);
  EXPECT_EQ(sb.first_dof, sa.first_dof);
  EXPECT_EQ(sb.failure, sa.failure);
  many->clear_status();
  EXPECT_TRUE(many->status().ok());
}

TEST(SimDevicesSharded, SerialShardsAreBitIdenticalToOneBackend) {
  for (int shards : {1, 2, 3, 5}) {
    SCOPED_TRACE("shards " + std::to_string(shards));
    expect_sharded_serial_identical<double>("euler", shards);
    expect_sharded_serial_identical<float>("rk4", shards);
  }
  expect_sharded_serial_identical<double>("implicit", 4);
}

TEST(SimDevicesSharded, MoreShardsThanInstancesLeaveEmptyShards) {
  Simulator<double> sim(scene_from(rope_scene("euler", 2, "serial")));
  Backend<double> many = sim::detail::make_sharded_sim_backend<double>(sim.setup(), {0, 0, 0, 0}, false,
                                                                       &serial_backend<double>);
  EXPECT_EQ(many->shard(2), nullptr);
  const std::vector<Index> which{1, 0};
  std::vector<double> q(8, 0.1), qd(8, 0.0);
  many->write_instances(which.data(), 2, q.data(), qd.data());
  many->step({});
  EXPECT_TRUE(many->status().ok());
}

TEST(SimDevicesSharded, NoSingleViewOfTheState) {
  Simulator<double> sim(scene_from(rope_scene("euler", 6, "serial", R"("threads": 1,)")));
  Backend<double> many = sim::detail::make_sharded_sim_backend<double>(sim.setup(), {0, 0}, false,
                                                                       &serial_backend<double>);
  try {
    many->q();
    ADD_FAILURE() << "no error";
  } catch (const BackendError& e) {
    EXPECT_EQ(std::string(e.what()),
              "Simulator::q(): the simulator is sharded across 2 shards, with no single view of its memory: "
              "read_state() copies it to the host; q(k) views shard k");
  }
  EXPECT_THROW(many->qd(), BackendError);
  EXPECT_THROW(many->contact_forces(), BackendError);
  EXPECT_EQ(many->wrenches(), nullptr);  // none in this scene
  std::vector<double> tau(5 * 4);
  try {
    many->step({tau.data(), 5, 1, 4});
    ADD_FAILURE() << "no error";
  } catch (const BackendError& e) {
    EXPECT_EQ(std::string(e.what()), "Simulator::step: torques for 5 instances, the simulator has 6");
  }
}

// ---- CUDA ---------------------------------------------------------------------------

template <class S>
std::vector<S> read_all(Simulator<S>& sim) {
  std::vector<S> x(static_cast<std::size_t>((sim.nq() + sim.nv()) * sim.batch()));
  sim.read_state(x.data(), x.data() + sim.nq() * sim.batch());
  return x;
}

// devices' simulator against the current device's: after resets and steps, the
// state, the contact readings and the status bit for bit
template <class S>
void expect_devices_identical(const std::string& integrator, const std::vector<int>& devices) {
  SCOPED_TRACE(integrator + (sizeof(S) == 4 ? " float" : " double") + " devices " + devices_string(devices));
  Scene scene = scene_from(rope_scene(integrator, 1001, "cuda"));
  Simulator<S> one(scene);
  scene.devices = devices;
  Simulator<S> many(scene);
  ASSERT_EQ(many.shards(), static_cast<int>(devices.size()));
  EXPECT_EQ(many.strategy(), one.strategy() + "-x" + std::to_string(devices.size()));
  EXPECT_TRUE(many.on_device());
  EXPECT_FALSE(many.torques_on_device());
  EXPECT_THROW(many.q(), BackendError);
  EXPECT_EQ(many.shard_device(1), devices[1]);
  ASSERT_EQ(read_all(one), read_all(many));
  for (int s = 0; s < 50; ++s) one.step(), many.step();
  one.reset({1000, 3, 500, 501, 0});
  many.reset({1000, 3, 500, 501, 0});
  for (int s = 0; s < 50; ++s) one.step(), many.step();
  const std::vector<S> a = read_all(one), b = read_all(many);
  ASSERT_EQ(std::memcmp(a.data(), b.data(), a.size() * sizeof(S)), 0);
  const std::size_t P = static_cast<std::size_t>(one.contact_count());
  std::vector<sim::ContactReading<S>> ra(P * 1001), rb(P * 1001);
  one.read_contact_forces(ra.data());
  many.read_contact_forces(rb.data());
  for (std::size_t k = 0; k < ra.size(); ++k) {
    ASSERT_EQ(ra[k].force.x, rb[k].force.x) << k;
    ASSERT_EQ(ra[k].force.z, rb[k].force.z) << k;
    ASSERT_EQ(ra[k].in_contact, rb[k].in_contact) << k;
  }
  const BatchStatus sa = one.status(), sb = many.status();
  EXPECT_TRUE(sa.ok()) << sim::failure_message(sa);
  EXPECT_EQ(sa.failed, sb.failed);
  EXPECT_EQ(sa.first_instance, sb.first_instance);
  EXPECT_EQ(one.energy(), many.energy());
}

TEST(SimDevicesCuda, TwoShardsOnOneDeviceAreBitIdentical) {
  if (const std::string why = backend_unusable(BackendKind::Cuda); !why.empty())
    GTEST_SKIP() << "backend cuda: " << why;
  const int d = cuda::current_device().value;
  for (const char* integrator : {"euler", "rk4"}) {
    expect_devices_identical<float>(integrator, {d, d});
    expect_devices_identical<double>(integrator, {d, d});
  }
  expect_devices_identical<float>("implicit", {d, d, d});
}

TEST(SimDevicesCuda, EveryDeviceIsBitIdentical) {
  if (const std::string why = backend_unusable(BackendKind::Cuda); !why.empty())
    GTEST_SKIP() << "backend cuda: " << why;
  const std::vector<int> all = parse_devices("all");
  if (all.size() < 2) GTEST_SKIP() << "one CUDA device visible (this test needs two)";
  expect_devices_identical<float>("euler", all);
  expect_devices_identical<double>("rk4", all);
}

TEST(SimDevicesCuda, AMissingDeviceIsNamed) {
  if (const std::string why = backend_unusable(BackendKind::Cuda); !why.empty())
    GTEST_SKIP() << "backend cuda: " << why;
  Scene scene = scene_from(rope_scene("euler", 10, "cuda"));
  scene.devices = {0, 999};
  try {
    Simulator<float> sim(scene);
    ADD_FAILURE() << "no error";
  } catch (const BackendError& e) {
    EXPECT_EQ(std::string(e.what()).rfind("device 999: ", 0), 0u) << e.what();
  }
}

}  // namespace
}  // namespace scandyn
