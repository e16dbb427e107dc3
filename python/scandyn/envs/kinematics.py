"""The one place the environments need kinematics: world positions of named link frames.

    frame_positions(env, q, ["iiwa_link_7"]) -> (B, F, 3)

Through ``scandyn.frame_placements`` (the kinematics engines, (B, F, 4, 4) placements):
host arrays on the simulator's CPU backend (OpenMP for a CUDA scene: the draws of
targets are NumPy), torch CUDA tensors on their device, queued on torch's current
stream with no copy and no synchronisation. The one exception: a model beyond the CUDA
kinematics engine's size (``scandyn.Kinematics.cuda_max_dofs`` DoF) goes through the
host (a device-to-host copy of q, a host-to-device copy of the positions).
"""


def _is_torch(x):
    return type(x).__module__.startswith("torch")


def frame_positions(env, q, frames):
    """(B, F, 3) positions in the base (world) frame of the frames named in ``frames`` (URDF
    links, ``env.model.frames``) at the states ``q`` (B, nv) of ``env`` (a scandyn.envs
    environment: its model and simulator); the same kind of array, dtype and device as q."""
    import scandyn

    frames = list(frames)
    if _is_torch(q) and q.is_cuda and env.model.nv > scandyn.Kinematics.cuda_max_dofs:
        import torch

        host = scandyn.frame_placements(env.model, q.detach().cpu().numpy(), frames)
        return torch.as_tensor(host[..., :3, 3], device=q.device)
    backend = "auto" if env.sim.backend == "cuda" else env.sim.backend  # "auto": q's device
    return scandyn.frame_placements(env.model, q, frames, backend=backend)[..., :3, 3]
