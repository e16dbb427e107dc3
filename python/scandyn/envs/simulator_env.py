"""SimulatorVectorEnv: a Gymnasium VectorEnv over one scandyn.Simulator (B instances =
num_envs sub-environments), and SingleEnv, one sub-environment as a gymnasium.Env.

A task (reach.py, swingup.py) gives the scene, the actuated DoFs and their torque scale,
the initial-state and parameter draws, the observation and the reward; this class does
the Gymnasium side: spaces, seeding, the batched step, autoreset, arrays on the
simulator's device.

Arrays: on the CPU (device="cpu") NumPy in and out (torch CPU tensors with
tensors="torch"); on the GPU (device="cuda": torch's current device; "cuda:N": device N)
torch tensors on the simulator's device in and out; a step reads one bool per instance back to the host (whether the state is
finite).
Observations, rewards and actions have the env's dtype (float32 by default, the
simulator's precision: float64 runs the scene in double); terminated / truncated are bool.
"""

import numpy as np
import gymnasium as gym
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from .._api import load_model
from ..simulator import Simulator


def _torch():
    import torch

    return torch


def _resolve_device(device):
    """The env's device as "cpu" or "cuda:N": "cuda" (or a torch.device without an index)
    is torch's current CUDA device (torch.cuda.set_device's: LOCAL_RANK's GPU under
    torchrun, one process per GPU), "cuda:N" / torch.device("cuda", N) is device N."""
    text = str(device)
    if text == "cuda":
        try:
            torch = _torch()
        except ImportError:  # the simulator then takes the CUDA runtime's current device
            return text
        if torch.cuda.is_available():
            return f"cuda:{torch.cuda.current_device()}"
    return text


class SimulatorVectorEnv(VectorEnv):
    """A vector of ``num_envs`` sub-environments stepped as one simulator batch.

    Step: ``actions`` (num_envs, nu) in [-1, 1] (clipped to it) are the torques of the
    actuated DoFs divided by ``torque_scale``; the other DoFs get no torque. One env step
    is ``frame_skip`` simulator steps with those torques held.

    Episodes: ``truncated`` after ``max_episode_steps`` env steps; ``terminated`` when a
    sub-environment's state is no longer finite (its observation is then zeros and its
    reward 0) or when the task says so. Autoreset is gymnasium's next-step mode
    (``metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP``): the step after a
    sub-environment terminated or was truncated resets it, ignores its action and returns
    its first observation with reward 0 and terminated = truncated = False.

    Seeding: ``reset(seed=s)`` seeds ``np_random`` (gymnasium's seeding); every random draw
    (initial states, task parameters such as targets) comes from it, in float64 on the
    host, and then goes to the simulator's device: one seed gives the same episodes on
    every device, up to the precision. ``reset(options={"reset_mask": mask})`` resets only
    the sub-environments where the boolean mask (num_envs,) is true (the others keep
    their state and episode counters) and returns every sub-environment's observation.
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    # set by the task
    model_spec = None          # the scene's model
    actuated = ()              # the DoFs the actions drive
    torque_scale = None        # (nu,) N m (or N) for action 1
    obs_dim = 0

    def __init__(self, num_envs=1, device="cpu", dtype=np.float32, max_episode_steps=200, frame_skip=1,
                 dt=1e-3, effects=None, integrator="euler", backend=None, tensors=None):
        self.num_envs = int(num_envs)
        if self.num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.dtype = np.dtype(dtype)
        if self.dtype not in (np.float32, np.float64):
            raise TypeError(f"dtype must be float32 or float64, got {dtype!r}")
        self.max_episode_steps = int(max_episode_steps)
        self.frame_skip = int(frame_skip)
        from .. import backend_unusable

        if device == "auto":
            device = "cuda" if not backend_unusable("cuda") else "cpu"
        self.device = _resolve_device(device)
        on_gpu = self.device.startswith("cuda")
        if backend is None:
            backend = "cuda" if on_gpu else ("openmp" if not backend_unusable("openmp") else "serial")
        self.scene = {
            "model": self.model_spec,
            "effects": effects if effects is not None else {"gravity": True},
            "integrator": integrator,
            "dt": float(dt),
            "precision": "float" if self.dtype == np.float32 else "double",
            "backend": backend,
            "instances": self.num_envs,
        }
        if tensors not in (None, "numpy", "torch"):
            raise ValueError(f"tensors must be None, 'numpy' or 'torch', got {tensors!r}")
        if on_gpu and tensors == "numpy":
            raise ValueError("device='cuda' keeps the tensors on the GPU: tensors='numpy' is not possible")
        self._torch = on_gpu or tensors == "torch"
        self.model = load_model(self.model_spec)
        self.sim = Simulator(self.scene, arrays="torch" if self._torch else "numpy",
                             device=self.device if on_gpu else None)
        if on_gpu:
            self.device = self.sim.device  # "cuda:N", the GPU holding the state
        self.nv = self.sim.nv
        if self._torch:
            torch = _torch()
            self._dev = torch.device(self.sim.device)
            self._tdtype = getattr(torch, self.dtype.name)
        nu = len(self.actuated)
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (nu,), dtype=self.dtype)
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (self.obs_dim,), dtype=self.dtype)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self._scale = self._array(np.asarray(self.torque_scale, dtype=np.float64))
        self._act_index = self._array(np.asarray(self.actuated, dtype=np.int64))
        self._tau = self._zeros((self.num_envs, self.nv))       # (B, nv) the torques of a step
        self._steps = np.zeros(self.num_envs, dtype=np.int64)  # env steps in the episode
        self._autoreset = np.zeros(self.num_envs, dtype=bool)  # reset at the next step
        self._alive = None                                      # (B,) bool: state finite

    # ---- arrays on the env's device ------------------------------------------------------

    def _array(self, host):
        """A host array (float64 or int) on the env's device (floats in the env's dtype)."""
        if not self._torch:
            return host.astype(self.dtype) if host.dtype.kind == "f" else host
        torch = _torch()
        t = torch.as_tensor(host, device=self._dev)
        return t.to(self._tdtype) if t.is_floating_point() else t

    def _zeros(self, shape):
        if not self._torch:
            return np.zeros(shape, dtype=self.dtype)
        return _torch().zeros(shape, dtype=self._tdtype, device=self._dev)

    def _bool(self, host):
        return _torch().as_tensor(host, device=self._dev) if self._torch else host.copy()

    def _cat(self, parts):
        return _torch().cat(parts, dim=1) if self._torch else np.concatenate(parts, axis=1)

    def _finite_rows(self, x):
        if self._torch:
            return _torch().isfinite(x).all(dim=1).cpu().numpy()
        return np.isfinite(x).all(axis=1)

    # ---- what a task gives -----------------------------------------------------------------

    def _draw(self, n):
        """Initial states and task parameters for n sub-environments from self.np_random:
        (q0 (n, nv), qd0 (n, nv), params) as host float64 arrays; params is a dict of
        (n, ...) arrays the task keeps per sub-environment."""
        raise NotImplementedError

    def _observe(self, q, qd):
        """(B, obs_dim) observations of the states (q, qd) (B, nv)."""
        raise NotImplementedError

    def _reward(self, q, qd, tau):
        """(B,) rewards after a step to (q, qd) under the actions' torques."""
        raise NotImplementedError

    # ---- Gymnasium API ---------------------------------------------------------------------

    def _start(self, idx):
        """Draws and writes the initial state and parameters of the sub-environments idx (host ints)."""
        if len(idx) == 0:
            return
        q0, qd0, params = self._draw(len(idx))
        where = self._array(idx) if self._torch else idx
        self.sim.q[where] = self._array(q0)
        self.sim.qd[where] = self._array(qd0)
        for name, value in params.items():
            getattr(self, name)[where] = self._array(value)
        self._steps[idx] = 0
        self._autoreset[idx] = False

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed, options=options)
        mask = None if options is None else options.get("reset_mask")
        if mask is None:
            idx = np.arange(self.num_envs)
        else:
            if self._torch and not isinstance(mask, np.ndarray):
                mask = mask.detach().cpu().numpy()
            mask = np.asarray(mask)
            if mask.dtype != bool or mask.shape != (self.num_envs,):
                raise ValueError(f"options['reset_mask'] must be a bool array of shape ({self.num_envs},), "
                                 f"got {mask.dtype} {mask.shape}")
            idx = np.flatnonzero(mask)
        self._start(idx)
        q, qd = self.sim.q, self.sim.qd
        self._alive = self._finite_rows(self._cat([q, qd]))
        return self._observe(q, qd), {}

    def step(self, actions):
        if self._alive is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        if self._torch:
            torch = _torch()
            a = torch.as_tensor(actions, device=self._dev).to(self._tdtype)
            a = a.clamp(-1.0, 1.0)
        else:
            a = np.clip(np.asarray(actions, dtype=self.dtype), -1.0, 1.0)
        if tuple(a.shape) != (self.num_envs, len(self.actuated)):
            raise ValueError(f"actions have shape {tuple(a.shape)}, expected {(self.num_envs, len(self.actuated))}")
        self._tau[:, self._act_index] = a * self._scale
        # unchecked (no synchronisation): a non-finite state ends that episode below; the
        # simulator's status keeps counting failed instance-steps (sim.status())
        self.sim.step_many(self.frame_skip, self._tau, check=False)
        self._steps += 1
        q, qd = self.sim.q, self.sim.qd
        alive = self._finite_rows(self._cat([q, qd]))
        terminated = ~alive
        truncated = self._steps >= self.max_episode_steps
        # the step's reward before the next-step resets
        reward = self._reward(q, qd, self._tau)
        resetting = np.flatnonzero(self._autoreset)
        self._start(resetting)
        terminated[resetting] = False
        truncated[resetting] = False
        self._autoreset = terminated | truncated
        self._alive = self._finite_rows(self._cat([q, qd]))
        obs = self._observe(q, qd)
        zero = ~self._alive | np.isin(np.arange(self.num_envs), resetting)
        if zero.any():
            where = self._bool(zero)
            reward[where] = 0
            obs[self._bool(~self._alive)] = 0
        return obs, reward, self._bool(terminated), self._bool(truncated), {}

    def close_extras(self, **kwargs):
        self.sim = None

    def __repr__(self):
        return f"{type(self).__name__}(num_envs={self.num_envs}, device={self.device!r}, dtype={self.dtype.name})"


class SingleEnv(gym.Env):
    """One sub-environment of a SimulatorVectorEnv task as a gymnasium.Env (NumPy, the CPU):
    ``SingleEnv(IiwaReach, max_episode_steps=100)``. Same spaces as the vector env's single
    ones; reset(seed=) seeds it as the vector env's. After terminated or truncated, call
    reset() (gymnasium's Env contract)."""

    metadata = {"render_modes": []}

    def __init__(self, task, **kwargs):
        kwargs.setdefault("device", "cpu")
        self.vector = task(num_envs=1, **kwargs)
        self.observation_space = self.vector.single_observation_space
        self.action_space = self.vector.single_action_space

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        if seed is not None or self.vector._np_random is None:
            self.vector.np_random = self.np_random  # one generator for both
        obs, info = self.vector.reset(options=options)
        return obs[0], info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.vector.step(np.asarray(action)[None])
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), info
