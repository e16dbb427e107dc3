"""The one place the environments need kinematics: world positions of named link frames.

    frame_positions(env, q, ["iiwa_link_7"]) -> (B, F, 3)

Through ``scandyn.frame_placements`` (the kinematics engines: every backend, CUDA tensors
in place, (B, F, 4, 4) placements) on the simulator's backend, when the package has it
and takes q's device. Otherwise through the simulator binding's ``body_origins`` (the
library's joint transforms composed from the base, host memory, float64): then a state on
the GPU takes a device-to-host copy here, and the result goes back to the state's device.
Link frames are body frames: a link's origin is its joint's origin.
"""

import numpy as np


def _is_torch(x):
    return type(x).__module__.startswith("torch")


def frame_positions(env, q, frames):
    """(B, F, 3) positions in the base (world) frame of the link frames named in ``frames``
    at the states ``q`` (B, nv) of ``env`` (a scandyn.envs environment: its model and
    simulator); the same kind of array, dtype and device as q."""
    import scandyn

    placements = getattr(scandyn, "frame_placements", None)
    if placements is not None:
        # on the simulator's backend (serial for a few instances where openmp only costs)
        backend = env.sim.backend
        if backend == "cuda" and not _is_torch(q):
            backend = "auto"  # host arrays (the targets' draws) on the CPU
        try:
            T = placements(env.model, q, list(frames), backend=backend)
        except scandyn.DeviceError:
            T = None  # CUDA tensors where the package does not take them yet: below
        if T is not None:
            return T[..., :3, 3]
    # fallback until sd.frame_placements: the simulator binding's body origins
    names = env.model.link_names
    try:
        idx = [names.index(f) for f in frames]
    except ValueError:
        missing = [f for f in frames if f not in names]
        raise ValueError(f"no link named {missing[0]!r} in {env.model.name} (links: {', '.join(names)})") from None
    if _is_torch(q):
        import torch

        host = q.detach().to("cpu", torch.float64).numpy()
        origins = env.sim._s.body_origins(np.ascontiguousarray(host))
        return torch.as_tensor(origins[:, idx, :], device=q.device).to(q.dtype)
    origins = env.sim._s.body_origins(np.asarray(q, dtype=np.float64))
    return origins[:, idx, :].astype(q.dtype, copy=False)
