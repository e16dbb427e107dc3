"""Several GPUs from Python (docs/scaling.md): the engines' devices= argument (host
batches sharded across CUDA devices by BackendOptions::devices), its checks, the
simulator's and the environments' device, and the multi-process examples
(examples/multi_gpu_torchrun.py, examples/multi_gpu_mpi.py, shared code in
examples/multi_gpu_common.py).

Without a CUDA build and a GPU the sharded engines' results are not checked here (they
skip with the reason); the argument checks, the examples' sharding rule and, where torch
(and torchrun / mpi4py with mpirun) are installed, the examples' CPU paths run
everywhere."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

import scandyn as sd
from scandyn.simulator import _device_ordinal

from conftest import states

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
EXAMPLES = os.path.join(ROOT, "examples")

cuda_reason = sd.backend_unusable("cuda")


def _gpus():
    if cuda_reason:
        return 0
    try:
        return len(sd._scandyn.parse_devices("all"))
    except sd.BackendError:
        return 0


needs_gpu = pytest.mark.skipif(bool(cuda_reason), reason=f"backend cuda: {cuda_reason}")
ENGINES = [sd.InverseDynamics, sd.BiasForces, sd.MassMatrix, sd.ForwardDynamics]


# ---- devices=: the checks (every build) ----------------------------------------------


@pytest.mark.parametrize("cls", ENGINES)
def test_devices_on_a_cpu_backend_is_refused(cls):
    m = sd.load_model("iiwa")
    with pytest.raises(sd.BackendError, match=r"devices 0,1: only the cuda backend runs on devices \(backend 'serial'\)"):
        cls(m, backend="serial", devices=[0, 1])


@pytest.mark.parametrize("devices", ["x", "0,-1", "0,,1", "1;2"])
def test_devices_text_is_checked_by_the_library(devices):
    m = sd.load_model("iiwa")
    with pytest.raises(sd.BackendError, match=r"is not a device ordinal"):
        sd.InverseDynamics(m, backend="cuda", devices=devices)


def test_negative_ordinal_in_a_list_is_refused():
    m = sd.load_model("iiwa")
    with pytest.raises(sd.BackendError, match=r"devices '0,-1': '-1' is not a device ordinal"):
        sd.MassMatrix(m, backend="cuda", devices=[0, -1])


@pytest.mark.parametrize("devices", [1, True, 2.5, [0.0], ["0"], [True], object()])
def test_devices_of_the_wrong_type(devices):
    m = sd.load_model("iiwa")
    with pytest.raises(TypeError, match="devices"):
        sd.ForwardDynamics(m, backend="cuda", devices=devices)


def test_device_and_devices_together():
    m = sd.load_model("iiwa")
    with pytest.raises(sd.DeviceError, match=r"device=0 and devices='0,1' together"):
        sd.InverseDynamics(m, backend="cuda", device=0, devices=[0, 1])


@pytest.mark.parametrize("devices", [None, "current", "", []])
def test_current_device_only_is_any_backend(devices):
    """None, "current", "" and [] are the default (the current device only): CPU engines
    take them and compute as without them."""
    m = sd.load_model("iiwa")
    q, qd, qdd, _ = states(m, 5, np.float64)
    e = sd.InverseDynamics(m, backend="serial", max_batch=5, devices=devices)
    assert e.devices == [] and e.device == -1
    np.testing.assert_array_equal(e(q, qd, qdd), sd.InverseDynamics(m, backend="serial", max_batch=5)(q, qd, qdd))
    np.testing.assert_array_equal(sd.inverse_dynamics(m, q, qd, qdd, backend="serial", devices=devices),
                                  e(q, qd, qdd))


@pytest.mark.skipif(not cuda_reason, reason="checks the message of a machine without CUDA")
def test_all_devices_without_cuda():
    m = sd.load_model("iiwa")
    with pytest.raises(sd.BackendError, match=r"devices 'all': .*no usable CUDA device"):
        sd.InverseDynamics(m, backend="cuda", devices="all")
    q, qd, qdd, tau = states(m, 4, np.float64)
    # backend 'auto' with devices= is cuda (only cuda runs on devices), not a silent CPU run
    with pytest.raises(sd.BackendError):
        sd.forward_dynamics(m, q, qd, tau, devices=[0, 1])
    with pytest.raises(sd.BackendError, match=r"only the cuda backend runs on devices"):
        sd.mass_matrix(m, q, backend="openmp" if sd.has_openmp else "serial", devices=[0])


def test_device_ordinal_of_the_simulator():
    assert _device_ordinal(None) == -1
    assert _device_ordinal("cuda") == -1  # the current device
    assert _device_ordinal("cpu") == -1
    assert _device_ordinal("cuda:1") == 1
    assert _device_ordinal(3) == 3
    assert _device_ordinal(np.int64(2)) == 2
    with pytest.raises(sd.DeviceError):
        _device_ordinal(-1)
    with pytest.raises(sd.DeviceError):
        _device_ordinal("gpu:0")
    with pytest.raises(TypeError):
        _device_ordinal(True)


def test_cpu_simulator_ignores_the_device():
    scene = {"model": "iiwa", "instances": 3, "dt": 1e-3, "backend": "serial"}
    a, b = sd.Simulator(scene), sd.Simulator(scene, device=None)
    a.step(None)
    b.step(None)
    assert a.device == b.device == "cpu"
    np.testing.assert_array_equal(a.q, b.q)


# ---- devices= on GPUs (skipped without CUDA) ------------------------------------------


def _call(cls, e, m, q, qd, qdd, tau, out=None):
    if cls is sd.InverseDynamics:
        return e(q, qd, qdd, out=out)
    if cls is sd.BiasForces:
        return e(q, qd, out=out)
    if cls is sd.MassMatrix:
        return e(q, out=out)
    return e(q, qd, tau, out=out)


@needs_gpu
@pytest.mark.parametrize("cls", ENGINES)
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_sharded_equals_one_device(cls, dtype):
    """Two shards on device 0 (devices=[0, 0]: what one GPU can test) give the one-device
    engine's results on host arrays, an odd batch split 51 + 50, written in place."""
    m = sd.load_model("iiwa")
    B = 101
    q, qd, qdd, tau = states(m, B, dtype, seed=3)
    one = cls(m, backend="cuda", max_batch=B, dtype=dtype, device=0)
    two = cls(m, backend="cuda", max_batch=B, dtype=dtype, devices=[0, 0])
    assert two.devices == [0, 0] and two.device == 0 and two.backend == "cuda"
    assert two.strategy.endswith("-x2"), two.strategy
    want = _call(cls, one, m, q, qd, qdd, tau)
    got = _call(cls, two, m, q, qd, qdd, tau)
    np.testing.assert_array_equal(got, want)
    # the caller's layout: a Fortran-order out (batch stride 1) is written in place
    if cls is not sd.MassMatrix:
        out = np.empty((m.nv, B), dtype=dtype).T
        assert _call(cls, two, m, q, qd, qdd, tau, out=out) is out
        np.testing.assert_array_equal(out, want)


@needs_gpu
def test_function_api_shards_host_arrays():
    m = sd.load_model("iiwa")
    q, qd, qdd, tau = states(m, 64, np.float64, seed=5)
    want = sd.inverse_dynamics(m, q, qd, qdd, backend="cuda")
    np.testing.assert_array_equal(sd.inverse_dynamics(m, q, qd, qdd, devices=[0, 0]), want)
    np.testing.assert_array_equal(sd.forward_dynamics(m, q, qd, tau, devices=[0, 0]),
                                  sd.forward_dynamics(m, q, qd, tau, backend="cuda"))


@needs_gpu
def test_all_lists_every_device():
    m = sd.load_model("iiwa")
    e = sd.BiasForces(m, backend="cuda", max_batch=8, devices="all")
    assert e.devices == list(range(_gpus()))


@needs_gpu
def test_sharded_engine_refuses_cuda_arrays():
    torch = pytest.importorskip("torch", reason="torch is not installed")
    if not torch.cuda.is_available():
        pytest.skip("torch without CUDA")
    m = sd.load_model("iiwa")
    q, qd, qdd, _ = (torch.as_tensor(a, device="cuda:0") for a in states(m, 8, np.float64))
    e = sd.InverseDynamics(m, backend="cuda", max_batch=8, devices=[0, 0])
    with pytest.raises(sd.DeviceError, match=r"shards host batches over CUDA devices 0,0"):
        e(q, qd, qdd)
    # the function API: only the arrays' own device may be named
    want = sd.inverse_dynamics(m, q, qd, qdd)
    torch.testing.assert_close(sd.inverse_dynamics(m, q, qd, qdd, devices=[0]), want, rtol=0, atol=0)
    with pytest.raises(sd.DeviceError, match=r"CUDA arrays run on their own device"):
        sd.inverse_dynamics(m, q, qd, qdd, devices=[0, 0])


@needs_gpu
@pytest.mark.skipif(_gpus() < 2, reason="needs two CUDA devices")
def test_simulator_and_engine_on_device_1():
    """A simulator and an engine on device 1 while device 0 is current: made there, and
    their steps / calls run there."""
    torch = pytest.importorskip("torch", reason="torch is not installed")
    scene = {"model": "iiwa", "instances": 16, "dt": 1e-3, "backend": "cuda"}
    s1 = sd.Simulator(scene, device="cuda:1")
    assert s1.device == "cuda:1" and s1.q.device == torch.device("cuda", 1)
    s0 = sd.Simulator(scene, device=0)
    for _ in range(3):
        s0.step(None)
        s1.step(None)
    torch.testing.assert_close(s1.q.cpu(), s0.q.cpu(), rtol=0, atol=0)
    m = sd.load_model("iiwa")
    e = sd.InverseDynamics(m, backend="cuda", max_batch=16, devices=[1])
    assert e.devices == [1]
    q, qd, qdd, _ = states(m, 16, np.float64)
    np.testing.assert_array_equal(e(q, qd, qdd), sd.InverseDynamics(m, backend="cuda", max_batch=16)(q, qd, qdd))


@needs_gpu
def test_env_cuda_means_torchs_current_device():
    torch = pytest.importorskip("torch", reason="torch is not installed")
    pytest.importorskip("gymnasium", reason="gymnasium is not installed")
    import scandyn.envs  # noqa: F401

    env = sd.envs.IiwaReach(num_envs=4, device="cuda")
    assert env.device == f"cuda:{torch.cuda.current_device()}"
    obs, _ = env.reset(seed=0)
    assert obs.device == torch.device(env.device)


# ---- the examples ------------------------------------------------------------------------


sys.path.insert(0, EXAMPLES)
import multi_gpu_common as common  # noqa: E402  (imports neither torch nor mpi4py at the top)


@pytest.mark.parametrize("total,world", [(0, 1), (1, 2), (7, 2), (8, 2), (1000, 3), (5, 8)])
def test_shard_range_covers_the_batch(total, world):
    ranges = [common.shard_range(total, world, r) for r in range(world)]
    begin = 0
    for b, n in ranges:
        assert b == begin and n >= 0
        begin += n
    assert begin == total
    assert max(n for _, n in ranges) - min(n for _, n in ranges) <= 1
    with pytest.raises(ValueError):
        common.shard_range(total, world, world)


def test_nvlink_multicast_is_turned_off(monkeypatch):
    for k in common.NVLS_OFF:
        monkeypatch.setenv(k, "1" if k == "NCCL_NVLS_ENABLE" else "0")
    common.disable_nvlink_multicast()
    assert os.environ["NCCL_NVLS_ENABLE"] == "0"
    assert os.environ["TORCH_SYMM_MEM_DISABLE_MULTICAST"] == "1"
    assert os.environ["NVSHMEM_DISABLE_NVLS"] == "1"


def _env():
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [os.path.dirname(os.path.dirname(sd.__file__)), os.environ.get("PYTHONPATH", "")]))
    env.update(OMP_NUM_THREADS="1", OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1")
    return env


def _run(cmd, timeout=300):
    return subprocess.run(cmd, cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("script", ["multi_gpu_torchrun.py", "multi_gpu_mpi.py"])
def test_example_help(script):
    """--help parses the shared arguments before torch or mpi4py are imported."""
    r = _run([sys.executable, os.path.join(EXAMPLES, script), "--help"])
    assert r.returncode == 0, r.stderr
    assert "--measure" in r.stdout and "NCCL_NVLS_ENABLE=0" in r.stdout


MEASURE = ["--device", "cpu", "--measure", "--envs", "6", "--steps", "3", "--warmup", "1"]
TRAIN = ["--device", "cpu", "--iters", "2", "--envs", "8", "--steps", "4", "--eval-envs", "4"]


def _row(stdout):
    rows = [json.loads(line) for line in stdout.splitlines() if line.startswith("{")]
    assert len(rows) == 1, stdout
    return rows[0]


def _check_row(row, launcher, world):
    assert row["launcher"] == launcher and row["world"] == world
    assert row["envs"] == 6 and sum(row["envs_per_rank"]) == 6 and len(row["per_rank_instance_steps_per_s"]) == world
    assert row["finite"] and row["instance_steps_per_s"] > 0
    assert all(r > 0 for r in row["per_rank_instance_steps_per_s"])
    assert row["env_steps"] == 3 and row["frame_skip"] == 5 and row["device"] == "cpu"


def _needs_torch():
    pytest.importorskip("torch", reason="torch is not installed (the examples' policy is a torch MLP)")
    pytest.importorskip("gymnasium", reason="gymnasium is not installed")


def test_torchrun_example_one_process(tmp_path):
    _needs_torch()
    out = tmp_path / "rows.jsonl"
    r = _run([sys.executable, os.path.join(EXAMPLES, "multi_gpu_torchrun.py"), *MEASURE, "--out", str(out)])
    assert r.returncode == 0, r.stderr
    row = _row(r.stdout)
    _check_row(row, "single", 1)
    assert json.loads(out.read_text()) == row
    r = _run([sys.executable, os.path.join(EXAMPLES, "multi_gpu_torchrun.py"), *TRAIN])
    assert r.returncode == 0, r.stderr
    assert "iter   2: population return per step" in r.stdout and "OK" in r.stdout
    for algo in ("id", "fd"):
        r = _run([sys.executable, os.path.join(EXAMPLES, "multi_gpu_torchrun.py"), "--device", "cpu", "--measure",
                  algo, "--envs", "6", "--steps", "2", "--warmup", "1"])
        assert r.returncode == 0, r.stderr
        row = _row(r.stdout)
        assert row["task"] == f"iiwa {algo}" and row["instances"] == 6 and row["instances_per_rank"] == [6]
        assert row["finite"] and row["evals_per_second"] > 0
    r = _run([sys.executable, os.path.join(EXAMPLES, "multi_gpu_torchrun.py"), "--device", "cpu", "--measure",
              "step", "--envs", "6", "--steps", "2", "--warmup", "1"])
    assert r.returncode == 0, r.stderr
    row = _row(r.stdout)
    assert row["task"] == "iiwa step" and row["instances"] == 6 and row["instances_per_rank"] == [6]
    assert row["finite"] and row["instance_steps_per_s"] > 0 and row["backend"] == "serial"


def test_torchrun_example_two_processes_gloo():
    _needs_torch()
    import torch.distributed as dist

    if not dist.is_available() or not dist.is_gloo_available():
        pytest.skip("torch.distributed with gloo is not available")
    launch = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]
    r = _run([*launch, os.path.join(EXAMPLES, "multi_gpu_torchrun.py"), *MEASURE])
    assert r.returncode == 0, r.stderr
    _check_row(_row(r.stdout), "torchrun", 2)
    r = _run([*launch, os.path.join(EXAMPLES, "multi_gpu_torchrun.py"), *TRAIN])
    assert r.returncode == 0, r.stderr
    assert "2 process(es)" in r.stdout and "OK" in r.stdout
    assert "rank 1 (cpu)" in r.stdout + r.stderr


def test_mpi_example():
    _needs_torch()
    pytest.importorskip("mpi4py", reason="mpi4py is not installed")
    r = _run([sys.executable, os.path.join(EXAMPLES, "multi_gpu_mpi.py"), *MEASURE])
    assert r.returncode == 0, r.stderr
    _check_row(_row(r.stdout), "mpirun", 1)
    mpirun = shutil.which("mpirun")
    if not mpirun:
        pytest.skip("mpirun is not installed (the one-process run above passed)")
    r = _run([mpirun, "-n", "2", "--oversubscribe", sys.executable, os.path.join(EXAMPLES, "multi_gpu_mpi.py"),
              *MEASURE])
    assert r.returncode == 0, r.stderr
    _check_row(_row(r.stdout), "mpirun", 2)
