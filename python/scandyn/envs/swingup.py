"""RopeSwingUp: a short rope (rope:N, N links of 1 cm and 10 g, alternating x / y joints,
gravity, joint damping) hanging from a fixed point, driven by torques on its top two
joints (the x and y joints at the suspension), rewarded for raising its tip.

    observation (2N + 3,): q (N), qd (N), the tip position (3, base frame, m)
    action (2,) in [-1, 1]: torques on joints 0 and 1 = action * torque_scale (N m)
    reward: z_tip / (N - 1) cm, in [-1, 1]: -1 hanging straight down, 1 straight up

The tip is the origin of the last link (its joint). Episode: the rope near hanging (q
drawn in U(-0.1, 0.1) rad, qd in U(-0.5, 0.5) rad/s per joint); no termination but a
non-finite state; truncation after max_episode_steps (default 200 steps of 10 ms).
"""

import numpy as np

from .kinematics import frame_positions
from .simulator_env import SimulatorVectorEnv


class RopeSwingUp(SimulatorVectorEnv):
    actuated = (0, 1)

    def __init__(self, num_envs=1, links=4, device="cpu", dtype=np.float32, max_episode_steps=200,
                 frame_skip=10, dt=1e-3, damping=1e-5, torque_scale=0.01, backend=None, tensors=None):
        if links < 2:
            raise ValueError(f"links must be >= 2, got {links}")
        self.links = int(links)
        self.model_spec = f"rope:{self.links}"
        self.torque_scale = (torque_scale, torque_scale)
        self.obs_dim = 2 * self.links + 3
        super().__init__(num_envs, device=device, dtype=dtype, max_episode_steps=max_episode_steps,
                         frame_skip=frame_skip, dt=dt, effects={"gravity": True, "damping": damping},
                         backend=backend, tensors=tensors)
        self.tip = self.model.link_names[-1]
        self._reach = 0.01 * (self.links - 1)  # the tip's distance from the suspension

    def tip_positions(self, q):
        """(B, 3) the tip (origin of the last link) at the states q (B, N)."""
        return frame_positions(self, q, [self.tip])[:, 0, :]

    def _draw(self, n):
        rng = self.np_random
        return rng.uniform(-0.1, 0.1, (n, self.links)), rng.uniform(-0.5, 0.5, (n, self.links)), {}

    def _observe(self, q, qd):
        return self._cat([q, qd, self.tip_positions(q)])

    def _reward(self, q, qd, tau):
        return self.tip_positions(q)[:, 2] / self._reach
