"""The one place the environments need kinematics: world positions of named link frames.

    frame_positions(env, q, ["iiwa_link_7"]) -> (B, F, 3)

Through ``scandyn.frame_placements`` (the kinematics engines of issue 18: every backend,
CUDA tensors in place, (B, F, 4, 4) placements) when the package has it. Until those
engines are in the package, through the simulator binding's ``body_origins`` (the
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
        T = placements(env.model, q, list(frames))
        if isinstance(T, tuple):  # (positions, quaternions)
            return T[0]
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
