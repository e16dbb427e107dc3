"""The one place the environments need kinematics: world positions of named link frames.

    frame_positions(env, q, ["iiwa_link_7"]) -> (B, F, 3)

Through ``scandyn.frame_placements`` (the kinematics engines, (B, F, 4, 4) placements) on
the simulator's backend. Where the package does not take CUDA tensors (DeviceError), q
goes through the host: a device-to-host copy of q and a host-to-device copy of the
positions, per call.
"""



def _is_torch(x):
    return type(x).__module__.startswith("torch")


def frame_positions(env, q, frames):
    """(B, F, 3) positions in the base (world) frame of the frames named in ``frames`` (URDF
    links, ``env.model.frames``) at the states ``q`` (B, nv) of ``env`` (a scandyn.envs
    environment: its model and simulator); the same kind of array, dtype and device as q."""
    import scandyn

    backend = env.sim.backend
    if backend == "cuda" and not _is_torch(q):
        backend = "auto"  # host arrays (the targets' draws) on the CPU
    try:
        T = scandyn.frame_placements(env.model, q, list(frames), backend=backend)
    except scandyn.DeviceError:
        if not _is_torch(q):
            raise
        import torch

        host = scandyn.frame_placements(env.model, q.detach().cpu().numpy(), list(frames))
        T = torch.as_tensor(host, device=q.device)
    return T[..., :3, 3]
