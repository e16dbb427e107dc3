"""Gymnasium environments over scandyn's simulator (needs gymnasium).

    import scandyn.envs
    envs = scandyn.envs.IiwaReach(num_envs=1024)               # NumPy on the CPU
    envs = scandyn.envs.IiwaReach(num_envs=10**5, device="cuda")  # torch tensors on the GPU
    obs, info = envs.reset(seed=0)
    obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())

Tasks: IiwaReach (reach.py), RopeSwingUp (swingup.py); the vector env's rules
(spaces, seeding, next-step autoreset, devices) are SimulatorVectorEnv's
(simulator_env.py); SingleEnv is one sub-environment as a gymnasium.Env. Registered with
gymnasium as "scandyn/IiwaReach-v0" and "scandyn/RopeSwingUp-v0" (gymnasium.make and
gymnasium.make_vec). docs/python.md, "Environments".
"""

import gymnasium as _gym

from .kinematics import frame_positions
from .reach import IiwaReach
from .simulator_env import SimulatorVectorEnv, SingleEnv
from .swingup import RopeSwingUp


def _single(task):
    def make(**kwargs):
        return SingleEnv(task, **kwargs)

    return make


for _name, _task in (("IiwaReach", IiwaReach), ("RopeSwingUp", RopeSwingUp)):
    _id = f"scandyn/{_name}-v0"
    if _id not in _gym.registry:
        _gym.register(_id, entry_point=_single(_task), vector_entry_point=_task)

__all__ = ["IiwaReach", "RopeSwingUp", "SimulatorVectorEnv", "SingleEnv", "frame_positions"]
