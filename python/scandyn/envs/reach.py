"""IiwaReach: the KUKA iiwa arm (7 DoF, gravity, joint damping) moving its last link's
origin (iiwa_link_7) to a target point, by joint torques.

    observation (17,): q (7), qd (7), target (3, base frame, m)
    action (7,) in [-1, 1]: tau = action * torque_scale (N m)
    reward: -|p_ee - target| (m), p_ee the origin of iiwa_link_7 after the step

Episode: an initial q drawn around zero (U(-0.3, 0.3) rad per joint, qd = 0) and a target
that the arm can reach: the end-effector position at a joint configuration drawn in the
middle half of each joint's range. No termination but a non-finite state; truncation
after max_episode_steps (default 200 steps of 10 ms: 5 simulator steps of 2 ms each).
"""

import numpy as np

from .kinematics import frame_positions
from .simulator_env import SimulatorVectorEnv


class IiwaReach(SimulatorVectorEnv):
    model_spec = "iiwa"
    actuated = tuple(range(7))
    # N m per unit action: about twice the largest gravity torque of each joint
    torque_scale = (150.0, 150.0, 60.0, 60.0, 20.0, 10.0, 5.0)
    obs_dim = 17
    end_effector = "iiwa_link_7"

    def __init__(self, num_envs=1, device="cpu", dtype=np.float32, max_episode_steps=200, frame_skip=5,
                 dt=2e-3, damping=0.5, backend=None, tensors=None):
        super().__init__(num_envs, device=device, dtype=dtype, max_episode_steps=max_episode_steps,
                         frame_skip=frame_skip, dt=dt, effects={"gravity": True, "damping": damping},
                         backend=backend, tensors=tensors)
        self.target = self._zeros((self.num_envs, 3))  # (B, 3) per sub-environment
        self._lower = np.asarray(self.model.q_lower)
        self._upper = np.asarray(self.model.q_upper)

    def end_effector_positions(self, q):
        """(B, 3) the origin of iiwa_link_7 at the states q (B, 7)."""
        return frame_positions(self, q, [self.end_effector])[:, 0, :]

    def _draw(self, n):
        rng = self.np_random
        q0 = rng.uniform(-0.3, 0.3, (n, 7))
        mid = 0.5 * (self._lower + self._upper)
        half = 0.25 * (self._upper - self._lower)
        q_goal = rng.uniform(mid - half, mid + half, (n, 7))
        target = frame_positions(self, q_goal, [self.end_effector])[:, 0, :]
        return q0, np.zeros((n, 7)), {"target": target}

    def _observe(self, q, qd):
        return self._cat([q, qd, self.target])

    def _reward(self, q, qd, tau):
        d = self.end_effector_positions(q) - self.target
        return -((d * d).sum(1) ** 0.5)
