"""scandyn from Python in a few lines: dynamics, the simulator, an environment.

    python examples/quickstart.py            # CPU; on a machine with a GPU the simulator runs there too
"""

import numpy as np

import scandyn as sd

# dynamics of a batch of states (the models ship with the package)
m = sd.load_model("iiwa")
q = np.random.default_rng(0).uniform(-1, 1, (1024, m.nv))
qd = np.zeros_like(q)
tau = sd.inverse_dynamics(m, q, qd, np.zeros_like(q))   # (1024, 7): gravity torques
qdd = sd.forward_dynamics(m, q, qd, tau)                 # ~0: holding still
print(f"{m.name}: nv={m.nv}, max |qdd| under gravity compensation: {np.abs(qdd).max():.2e}")

# the simulator: a scene as a dict (or a file, scenes/*.json); q and qd are its own memory
sim = sd.Simulator({"model": "iiwa", "effects": {"gravity": True, "damping": 0.5}, "dt": 1e-3,
                    "precision": "float", "backend": "auto", "instances": 4096,
                    "initial": {"random": {"seed": 1, "q": 0.5}}})
print(sim)
for _ in range(100):
    sim.step()                    # zero torques: the arms fall under gravity, damped
sim.reset([0, 1])                 # two instances start over
q_now = sim.q                     # (4096, 7) view; a torch tensor on the GPU for a CUDA scene
print(f"t = {sim.t:.3f} s, q[2] = {np.asarray(q_now[2].tolist()).round(3)}")

# a Gymnasium vector environment (pip install gymnasium)
try:
    import scandyn.envs
except ImportError as e:
    print(f"(scandyn.envs needs gymnasium: {e})")
else:
    envs = sd.envs.IiwaReach(num_envs=16)
    obs, info = envs.reset(seed=0)
    total = np.zeros(16, np.float32)
    for _ in range(50):
        obs, reward, terminated, truncated, info = envs.step(envs.action_space.sample())
        total += reward
    print(f"IiwaReach, random actions: mean return over 50 steps {total.mean():.2f} (reward: -distance in m)")
