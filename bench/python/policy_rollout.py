"""A rollout with a torch MLP policy in the loop: scandyn.Simulator instances of a scene
(default scenes/iiwa_rl.json: 10^6 iiwa arms, float, gravity + damping, euler, dt 1 ms)
stepped for --steps steps, the torques computed each step by a 2-layer MLP from (q, qd)
read through the simulator's zero-copy views. Reports instance-steps per second and the
share of the time spent in scandyn's step.

    python bench/python/policy_rollout.py                         # the scene as it is (cuda where usable)
    python bench/python/policy_rollout.py --instances 4096 --steps 200 --backend openmp

On cuda the policy and the simulator share torch's current stream (Simulator.step orders
its own stream after it and it after the step, by events), so the loop never
synchronises; the time in scandyn is the sum of CUDA event intervals around each step on
that stream (the step's kernels as that stream sees them), the rest (the policy) is the
remainder of the loop's wall time. On the CPU both are wall-clock intervals.
Prints one JSON line.
"""

import argparse
import json
import os
import time

import torch

import scandyn as sd

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default=os.path.join(ROOT, "scenes", "iiwa_rl.json"))
    ap.add_argument("--instances", type=int, default=None, help="override the scene's instances")
    ap.add_argument("--backend", default=None, help="override the scene's backend")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--hidden", type=int, default=64)
    ap.add_argument("--warmup", type=int, default=10)
    args = ap.parse_args()

    with open(args.scene) as f:  # the file's keys with the overrides, read by the library as a dict
        scene = json.load(f)
    if args.instances:
        scene["instances"] = args.instances
    if args.backend:
        scene["backend"] = args.backend
    sim = sd.Simulator(scene, arrays="torch")
    dev = torch.device(sim.device)
    dtype = torch.float32 if sim.precision == "float" else torch.float64
    B, nv = sim.num_instances, sim.nv
    policy = torch.nn.Sequential(torch.nn.Linear(2 * nv, args.hidden), torch.nn.Tanh(),
                                 torch.nn.Linear(args.hidden, nv)).to(dev, dtype)
    obs = torch.empty(B, 2 * nv, device=dev, dtype=dtype)
    on_gpu = dev.type == "cuda"

    def one_step():
        with torch.no_grad():
            obs[:, :nv].copy_(sim.q)
            obs[:, nv:].copy_(sim.qd)
            return policy(obs)

    for _ in range(args.warmup):
        sim.step(one_step(), check=False)
    if on_gpu:
        torch.cuda.synchronize()
        marks = [(torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True))
                 for _ in range(args.steps)]
    sim_s = 0.0
    t0 = time.perf_counter()
    for k in range(args.steps):
        tau = one_step()
        if on_gpu:
            marks[k][0].record()
            sim.step(tau, check=False)
            marks[k][1].record()
        else:
            s0 = time.perf_counter()
            sim.step(tau, check=False)
            sim_s += time.perf_counter() - s0
    if on_gpu:
        torch.cuda.synchronize()
        sim_s = sum(a.elapsed_time(b) for a, b in marks) * 1e-3
    wall = time.perf_counter() - t0
    failed, first, _, message = sim.status()
    print(json.dumps({
        "scene": os.path.basename(args.scene), "instances": B, "nv": nv, "steps": args.steps,
        "backend": sim.backend, "strategy": sim.strategy, "precision": sim.precision,
        "device": torch.cuda.get_device_name(dev) if on_gpu else "cpu", "policy": f"{2 * nv}-{args.hidden}-{nv} MLP",
        "wall_s": round(wall, 4), "instance_steps_per_s": B * args.steps / wall,
        "scandyn_step_s": round(sim_s, 4), "scandyn_share": sim_s / wall,
        "failed_instance_steps": failed, "status": message,
    }))


if __name__ == "__main__":
    main()
