"""scandyn.envs: the Gymnasium environments over the simulator.

gymnasium's own env checker on one sub-environment (SingleEnv), the vector API by hand
(spaces, batched results in the spaces, seeding, reset_mask, next-step autoreset),
gymnasium's vector wrappers and make_vec, and the steps against scandyn.Simulator stepping
the same torques. Kinematic truths: closed forms of the rope's tip and the iiwa's
end-effector (docs/models.md geometry, the URDF's joint origins)."""

import warnings

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium", reason="gymnasium is not installed (scripts/setup_python.sh installs it)")

import scandyn as sd  # noqa: E402
from scandyn import envs  # noqa: E402
from gymnasium.utils.env_checker import check_env  # noqa: E402
from gymnasium.vector import AutoresetMode  # noqa: E402

TASKS = [(envs.IiwaReach, {}), (envs.RopeSwingUp, {"links": 4})]
IDS = ["reach", "swingup"]


@pytest.mark.parametrize("task,kw", TASKS, ids=IDS)
def test_gymnasium_env_checker(task, kw):
    env = envs.SingleEnv(task, max_episode_steps=20, **kw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # unbounded observation Boxes are warned about, and allowed
        check_env(env, skip_render_check=True)


@pytest.mark.parametrize("task,kw", TASKS, ids=IDS)
def test_spaces_and_batched_results(task, kw):
    B = 6
    env = task(num_envs=B, max_episode_steps=10, **kw)
    nu, od = len(env.actuated), env.obs_dim
    assert env.num_envs == B and env.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert env.single_action_space == gym.spaces.Box(-1, 1, (nu,), np.float32)
    assert env.single_observation_space.shape == (od,) and env.single_observation_space.dtype == np.float32
    assert env.action_space.shape == (B, nu) and env.observation_space.shape == (B, od)
    assert env.action_space.dtype == np.float32 and env.observation_space.dtype == np.float32
    obs, info = env.reset(seed=0)
    assert obs in env.observation_space and info == {}
    env.action_space.seed(0)
    for _ in range(12):
        obs, rew, term, trunc, info = env.step(env.action_space.sample())
        assert obs in env.observation_space and obs.dtype == np.float32
        assert rew.shape == (B,) and rew.dtype == np.float32 and np.all(np.isfinite(rew))
        assert term.shape == trunc.shape == (B,) and term.dtype == trunc.dtype == bool
    env.close()
    assert env.closed


@pytest.mark.parametrize("task,kw", TASKS, ids=IDS)
def test_seeding_is_deterministic(task, kw):
    a, b = task(num_envs=4, **kw), task(num_envs=4, **kw)
    oa, _ = a.reset(seed=42)
    ob, _ = b.reset(seed=42)
    assert np.array_equal(oa, ob)
    acts = np.random.default_rng(0).uniform(-1, 1, (5, 4, len(a.actuated))).astype(np.float32)
    for act in acts:
        ra, rb = a.step(act), b.step(act)
        for x, y in zip(ra[:4], rb[:4]):
            assert np.array_equal(x, y)
    oc, _ = a.reset(seed=43)
    od, _ = a.reset(seed=42)
    assert not np.array_equal(oc, oa) and np.array_equal(od, oa)
    # the sub-environments start differently
    assert len({tuple(row) for row in oa}) == 4


def test_reset_mask_resets_only_those():
    env = envs.IiwaReach(num_envs=5)
    env.reset(seed=1)
    act = np.full((5, 7), 0.3, np.float32)
    for _ in range(3):
        obs, *_ = env.step(act)
    mask = np.array([False, True, False, False, True])
    new, _ = env.reset(options={"reset_mask": mask})
    assert np.array_equal(new[~mask], obs[~mask])
    assert not np.any(new[mask] == obs[mask], axis=1).all()
    assert np.all(new[mask][:, 7:14] == 0)  # qd = 0 at a start
    assert list(env._steps) == [3, 0, 3, 3, 0]
    with pytest.raises(ValueError, match="reset_mask"):
        env.reset(options={"reset_mask": np.ones(3, bool)})


def test_next_step_autoreset():
    T = 3
    a, b = envs.RopeSwingUp(num_envs=3, max_episode_steps=T), envs.RopeSwingUp(num_envs=3, max_episode_steps=T)
    a.reset(seed=5)
    b.reset(seed=5)
    act = np.zeros((3, 2), np.float32)
    for k in range(T):
        ra = a.step(act)
        b.step(act)
        assert not ra[2].any() and ra[3].all() == (k == T - 1)
    # the step after truncation resets: the first observation, reward 0, not done
    obs, rew, term, trunc, _ = a.step(np.ones((3, 2), np.float32))
    first, _ = b.reset()  # the same draws from the same generator
    assert np.array_equal(obs, first)
    assert np.all(rew == 0) and not term.any() and not trunc.any()
    # and the episode runs again
    obs2, rew2, *_ = a.step(act)
    obs2b, rew2b, *_ = b.step(act)
    assert np.array_equal(obs2, obs2b) and np.array_equal(rew2, rew2b)


def test_non_finite_state_terminates_and_resets():
    env = envs.IiwaReach(num_envs=3)
    env.reset(seed=0)
    env.sim.qd[1, 2] = np.nan
    obs, rew, term, trunc, _ = env.step(np.zeros((3, 7), np.float32))
    assert list(term) == [False, True, False] and not trunc.any()
    assert np.all(obs[1] == 0) and rew[1] == 0 and np.all(np.isfinite(obs))
    obs, rew, term, *_ = env.step(np.zeros((3, 7), np.float32))  # reset there
    assert not term.any() and np.all(np.isfinite(obs)) and rew[1] == 0 and np.all(obs[1, 7:14] == 0)


@pytest.mark.parametrize("task,kw", TASKS, ids=IDS)
def test_step_equals_the_simulator_stepping_the_same_torques(task, kw):
    env = task(num_envs=4, dtype=np.float64, **kw)
    env.reset(seed=3)
    sim = sd.Simulator(env.scene)
    sim.q[:] = env.sim.q
    sim.qd[:] = env.sim.qd
    rng = np.random.default_rng(9)
    for _ in range(4):
        act = rng.uniform(-1.5, 1.5, (4, len(env.actuated)))  # beyond [-1, 1]: clipped
        obs, *_ = env.step(act)
        tau = np.zeros((4, env.nv))
        tau[:, list(env.actuated)] = np.clip(act, -1, 1) * np.asarray(env.torque_scale)
        sim.step_many(env.frame_skip, tau)
        assert np.array_equal(env.sim.q, sim.q) and np.array_equal(env.sim.qd, sim.qd)
        assert np.array_equal(obs[:, :env.nv], sim.q) and np.array_equal(obs[:, env.nv:2 * env.nv], sim.qd)


def test_kinematics_against_closed_forms():
    rope = envs.RopeSwingUp(num_envs=1, links=5, dtype=np.float64)
    L = 0.04  # origin of link_4: 4 links of 1 cm below the suspension
    a = np.linspace(-3, 3, 7)
    q = np.zeros((7, 5))
    q[:, 0] = a  # joint 0 turns about x: (0, 0, -L) -> (0, L sin a, -L cos a)
    p = rope.tip_positions(q)
    np.testing.assert_allclose(p, np.stack([0 * a, L * np.sin(a), -L * np.cos(a)], 1), atol=1e-15)
    q = np.zeros((7, 5))
    q[:, 1] = a  # joint 1 turns about y at 1 cm below: (-(L - 0.01) sin a, 0, -0.01 - (L - 0.01) cos a)
    p = rope.tip_positions(q)
    np.testing.assert_allclose(p, np.stack([-(L - 0.01) * np.sin(a), 0 * a, -0.01 - (L - 0.01) * np.cos(a)], 1),
                               atol=1e-15)
    # reward: -1 hanging, 1 upright
    up = np.zeros((1, 5))
    up[0, 0] = np.pi
    assert rope._reward(np.zeros((1, 5)), None, None)[0] == pytest.approx(-1)
    assert rope._reward(up, None, None)[0] == pytest.approx(1)
    # iiwa at q = 0: straight up, the joint origins' heights added (iiwa.urdf)
    arm = envs.IiwaReach(num_envs=1, dtype=np.float64)
    z = 0.1575 + 0.2025 + 0.2045 + 0.2155 + 0.1845 + 0.2155 + 0.081
    np.testing.assert_allclose(arm.end_effector_positions(np.zeros((1, 7))), [[0, 0, z]], atol=1e-12)
    # joint 2 (about y at 0.36 m) by a: the rest of the arm (z - 0.36) tips over
    q = np.zeros((1, 7))
    q[0, 1] = 0.7
    r = z - 0.36
    np.testing.assert_allclose(arm.end_effector_positions(q), [[r * np.sin(0.7), 0, 0.36 + r * np.cos(0.7)]],
                               atol=1e-12)


def test_reach_reward_and_targets():
    env = envs.IiwaReach(num_envs=8, dtype=np.float64)
    obs, _ = env.reset(seed=0)
    target = obs[:, 14:17]
    assert np.array_equal(target, env.target)
    # a target is where the end effector is at some joint configuration: within the arm's reach
    assert np.all(np.linalg.norm(target - [0, 0, 0.36], axis=1) <= 1.261 - 0.36 + 1e-9)
    _, rew, *_ = env.step(np.zeros((8, 7)))
    d = np.linalg.norm(env.end_effector_positions(env.sim.q) - target, axis=1)
    np.testing.assert_allclose(rew, -d, rtol=1e-15)


def test_gymnasium_vector_tools():
    env = gym.make_vec("scandyn/IiwaReach-v0", num_envs=3, vectorization_mode="vector_entry_point",
                       max_episode_steps=4)
    assert isinstance(env.unwrapped, envs.IiwaReach) and env.num_envs == 3
    env = gym.wrappers.vector.RecordEpisodeStatistics(env)
    env.reset(seed=0)
    info = {}
    for _ in range(4):
        *_, info = env.step(env.action_space.sample())
    assert "episode" in info and np.all(info["episode"]["l"] == 4)
    single = gym.make("scandyn/RopeSwingUp-v0", max_episode_steps=50)
    obs, _ = single.reset(seed=0)
    assert obs.shape == (11,)


@pytest.mark.parametrize("task,kw", TASKS, ids=IDS)
def test_torch_tensors_path_equals_numpy(task, kw):
    """tensors="torch" on the CPU runs the GPU configuration's array code (torch tensors in
    and out, writes through torch views of the state): the same bits as NumPy."""
    torch = pytest.importorskip("torch", reason="torch is not installed (not needed in CI)")
    a = task(num_envs=4, tensors="torch", dtype=np.float64, max_episode_steps=3, **kw)
    b = task(num_envs=4, dtype=np.float64, max_episode_steps=3, **kw)
    oa, _ = a.reset(seed=1)
    ob, _ = b.reset(seed=1)
    assert isinstance(oa, torch.Tensor) and np.array_equal(oa.numpy(), ob)
    a.sim.qd[1, 1] = float("nan")  # terminates, then resets, in both
    b.sim.qd[1, 1] = np.nan
    for k in range(5):
        act = np.random.default_rng(k).uniform(-1, 1, (4, len(a.actuated)))
        ra, rb = a.step(torch.from_numpy(act)), b.step(act)
        assert all(isinstance(x, torch.Tensor) for x in ra[:4]) and ra[2].dtype == torch.bool
        for x, y in zip(ra[:4], rb[:4]):
            assert np.array_equal(x.numpy(), y)


cuda = pytest.mark.skipif(not sd.has_cuda or sd.backend_unusable("cuda") != "",
                          reason="no usable CUDA device (or the CUDA backend is not built)")


@cuda
@pytest.mark.parametrize("task,kw", TASKS, ids=IDS)
def test_cuda_envs_keep_torch_tensors_on_the_gpu_and_match_the_cpu(task, kw):
    torch = pytest.importorskip("torch", reason="torch is not installed")
    gpu = task(num_envs=16, device="cuda", dtype=np.float64, **kw)
    cpu = task(num_envs=16, device="cpu", dtype=np.float64, backend="serial", **kw)
    og, _ = gpu.reset(seed=7)
    oc, _ = cpu.reset(seed=7)
    assert isinstance(og, torch.Tensor) and og.is_cuda and og.dtype == torch.float64
    np.testing.assert_allclose(og.cpu().numpy(), oc, rtol=0, atol=1e-12)
    rng = np.random.default_rng(1)
    s = torch.cuda.Stream()
    for _ in range(5):
        act = rng.uniform(-1, 1, (16, len(gpu.actuated)))
        with torch.cuda.stream(s):
            og, rg, tg, ug, _ = gpu.step(torch.from_numpy(act).cuda())
            og, rg = og.clone(), rg.clone()
        oc, rc, tc, uc, _ = cpu.step(act)
        s.synchronize()
        assert og.is_cuda and rg.is_cuda and tg.is_cuda and tg.dtype == torch.bool
        np.testing.assert_allclose(og.cpu().numpy(), oc, rtol=0, atol=1e-9)
        np.testing.assert_allclose(rg.cpu().numpy(), rc, rtol=0, atol=1e-9)
        assert np.array_equal(tg.cpu().numpy(), tc) and np.array_equal(ug.cpu().numpy(), uc)
