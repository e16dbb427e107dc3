"""What examples/multi_gpu_torchrun.py and examples/multi_gpu_mpi.py share: one process
per GPU, each with its own shard of the IiwaReach environments on its own device, a
small torch policy trained by an evolution strategy whose gradient estimates are
averaged across the processes, and a --measure mode that times a fixed rollout.

scandyn has no communication layer: each process runs its own simulator on its own GPU
(scandyn.envs.IiwaReach(device="cuda:N")); everything that crosses processes here goes
through the launcher's library (torch.distributed or mpi4py), behind the small `Comm`
classes below. The front ends only differ in how they find their rank, their device and
their Comm.

Training (default): each iteration every rank runs one episode of its shard of the
population (instance i with the policy's parameters theta + sigma eps_i, antithetic
pairs), rank-normalises its returns into a local gradient estimate, and the estimates
are averaged across ranks (an all-reduce, weighted by each rank's instances); every rank
then takes the same Adam step, so theta stays identical everywhere. Prints the
population's and the unperturbed policy's mean return per step, and instance-steps per
second per rank and in total (simulator steps: env steps x frame_skip).

--measure (rollout): N environments (split across ranks) x T env steps with the policy
in the loop, after a warm-up; --measure id / fd: iiwa inverse or forward dynamics on
each rank's share of N instances (device tensors, out=), T calls timed; --measure step:
the RL step of scenes/iiwa_rl.json (the simulator's fused ABA + Euler step with gravity
and damping, what `scandyn bench --algo step` times) on each rank's share of N
instances, T steps timed; the slowest rank's time sets the total rate. Rank 0 prints one
JSON line (and appends it to --out): launcher, world size, devices, instance-steps/s
per rank and in total, so that one process on one GPU and two processes on two GPUs
can be compared.
"""

import argparse
import json
import os
import socket
import sys
import time

# NVLink multicast (NVLS) stays off in every process we start (docs/scaling.md): NCCL's
# NVLS algorithms, torch's symmetric memory and NVSHMEM would otherwise use it.
NVLS_OFF = {"NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1", "NVSHMEM_DISABLE_NVLS": "1"}


def disable_nvlink_multicast():
    """Sets NVLS_OFF in os.environ; call before the communication library starts."""
    os.environ.update(NVLS_OFF)


def shard_range(total, world, rank):
    """(begin, count) of rank's share of `total` items: contiguous ranges in rank order,
    the first total % world ranks one item longer (scandyn's own sharding rule,
    scandyn/sharded.hpp)."""
    if world < 1 or not 0 <= rank < world:
        raise ValueError(f"rank {rank} of a world of {world}")
    base, extra = divmod(total, world)
    return rank * base + min(rank, extra), base + (1 if rank < extra else 0)


# ---- communication: what the launchers' libraries do for us ------------------------


class LocalComm:
    """One process: nothing to exchange."""

    name = "single"

    def __init__(self):
        self.rank, self.world = 0, 1

    def allreduce_sum(self, tensor):
        return tensor

    def allreduce_max(self, value):
        return float(value)

    def barrier(self):
        pass

    def close(self):
        pass


class TorchComm:
    """torch.distributed (NCCL on GPUs, gloo on CPUs), set up by the caller."""

    name = "torchrun"

    def __init__(self, dist, device):
        self.dist, self.device = dist, device
        self.rank, self.world = dist.get_rank(), dist.get_world_size()

    def allreduce_sum(self, tensor):
        self.dist.all_reduce(tensor, op=self.dist.ReduceOp.SUM)
        return tensor

    def allreduce_max(self, value):
        import torch

        t = torch.tensor([float(value)], dtype=torch.float64, device=self.device)
        self.dist.all_reduce(t, op=self.dist.ReduceOp.MAX)
        return float(t.item())

    def barrier(self):
        # an all-reduce rather than dist.barrier(): it needs no device guess from NCCL
        self.allreduce_max(0.0)

    def close(self):
        self.dist.destroy_process_group()


class MpiComm:
    """mpi4py's COMM_WORLD: tensors go through host memory (NumPy buffers)."""

    name = "mpirun"

    def __init__(self, comm):
        from mpi4py import MPI

        self.MPI, self.comm = MPI, comm
        self.rank, self.world = comm.Get_rank(), comm.Get_size()

    def allreduce_sum(self, tensor):
        import numpy as np

        host = tensor.detach().cpu().numpy().astype(np.float64)
        self.comm.Allreduce(self.MPI.IN_PLACE, host, op=self.MPI.SUM)
        tensor.copy_(tensor.new_tensor(host))
        return tensor

    def allreduce_max(self, value):
        return float(self.comm.allreduce(float(value), op=self.MPI.MAX))

    def barrier(self):
        self.comm.Barrier()

    def close(self):
        pass


# ---- arguments, device, environments --------------------------------------------------


def parse_args(description, argv=None):
    ap = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="auto",
                    help="auto (cuda:LOCAL_RANK %% visible GPUs where CUDA is usable, else cpu), cpu or cuda")
    ap.add_argument("--backend", default=None,
                    help="simulator backend (default: cuda on a GPU, serial on the CPU: one core per process)")
    ap.add_argument("--envs", type=int, default=None,
                    help="environments in all processes together (default: 16384 on GPUs, 64 on CPUs; "
                         "--measure: 1048576 on GPUs, 256 on CPUs)")
    ap.add_argument("--steps", type=int, default=None,
                    help="env steps per episode (default 100); --measure: steps timed (default 200 on GPUs, 20 on CPUs)")
    ap.add_argument("--iters", type=int, default=30, help="training iterations")
    ap.add_argument("--sigma", type=float, default=0.1)
    ap.add_argument("--lr", type=float, default=0.03)
    ap.add_argument("--hidden", type=int, default=32)
    ap.add_argument("--eval-envs", type=int, default=16, help="environments of the unperturbed policy's evaluation")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--min-gain", type=float, default=None,
                    help="exit non-zero unless the unperturbed return per step gains at least this much")
    ap.add_argument("--measure", nargs="?", const="rollout", default=None, choices=["rollout", "id", "fd", "step"],
                    help="time instead of training: a fixed env rollout with the policy in the loop (rollout, "
                         "the default), iiwa inverse / forward dynamics on this rank's device tensors (id, fd; "
                         "--envs instances in all, --steps timed calls), or the simulator's RL step of "
                         "scenes/iiwa_rl.json (step; --envs instances in all, --steps timed steps)")
    ap.add_argument("--warmup", type=int, default=5, help="--measure: env steps before the timing")
    ap.add_argument("--out", default=None, help="--measure: append the JSON line to this file (rank 0)")
    return ap.parse_args(argv)


def pick_device(requested, local_rank):
    """The torch device of this process: cuda:(local_rank % visible GPUs) for "auto" where
    CUDA is usable (made torch's current device, so that "cuda" means it everywhere),
    else what was asked."""
    import torch

    if requested == "auto":
        requested = f"cuda:{local_rank % torch.cuda.device_count()}" if torch.cuda.is_available() else "cpu"
    device = torch.device(requested)
    if device.type == "cuda":
        if device.index is None:
            device = torch.device("cuda", torch.cuda.current_device())
        torch.cuda.set_device(device)
    return device


def resolve_defaults(args, device):
    gpu = device.type == "cuda"
    if args.backend is None:
        args.backend = "cuda" if gpu else "serial"
    if args.envs is None:
        args.envs = (1 << 20 if gpu else 256) if args.measure else (16384 if gpu else 64)
    if args.steps is None:
        args.steps = (200 if gpu else 20) if args.measure else 100
    return args


def make_env(num_envs, device, args, max_episode_steps):
    import scandyn as sd
    import scandyn.envs  # noqa: F401  (registers the tasks; needs gymnasium)

    return sd.envs.IiwaReach(num_envs=num_envs, device=str(device), backend=args.backend, tensors="torch",
                             max_episode_steps=max_episode_steps)


def make_policy(obs_dim, nu, hidden, seed, device):
    """The same MLP (obs -> hidden -> nu, tanh) on every rank: made on the CPU from one seed."""
    import torch

    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(obs_dim, hidden), torch.nn.Tanh(),
                               torch.nn.Linear(hidden, nu), torch.nn.Tanh()).to(device)


def synchronize(device):
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def log(comm, text):
    if comm.rank == 0:
        print(text, flush=True)


# ---- training ------------------------------------------------------------------------


def episode(env, act, device, seed):
    """(num_envs,) mean reward per env step of one episode from reset(seed=seed), actions
    from act(obs)."""
    import torch

    obs, _ = env.reset(seed=seed)
    total = torch.zeros(env.num_envs, device=device)
    with torch.no_grad():
        for _ in range(env.max_episode_steps):
            obs, reward, _, _, _ = env.step(act(obs.float()))
            total += reward.float()
    return total / env.max_episode_steps


def train(comm, device, args):
    import numpy as np
    import torch
    from torch.func import functional_call, vmap

    pairs_begin, pairs = shard_range(args.envs // 2, comm.world, comm.rank)
    if pairs < 1:
        raise SystemExit(f"--envs {args.envs}: fewer antithetic pairs than processes ({comm.world})")
    n_local = 2 * pairs
    _, n_eval = shard_range(args.eval_envs, comm.world, comm.rank)
    env = make_env(n_local, device, args, args.steps)
    evaluation = make_env(max(n_eval, 1), device, args, args.steps)
    od, nu = env.single_observation_space.shape[0], env.single_action_space.shape[0]
    policy = make_policy(od, nu, args.hidden, args.seed, device)
    names = [n for n, _ in policy.named_parameters()]
    shapes = [p.shape for p in policy.parameters()]
    theta = torch.nn.utils.parameters_to_vector(policy.parameters()).detach().clone().requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=args.lr)
    batched = vmap(lambda p, o: functional_call(policy, p, (o,)))
    log(comm, f"{comm.name}: {comm.world} process(es), rank 0 on {device}, IiwaReach {args.envs} envs in all "
              f"({n_local} on rank 0), policy {od}-{args.hidden}-{nu} ({theta.numel()} parameters), "
              f"simulator {env.sim.backend} ({env.sim.strategy})")

    def unflatten(flat):  # (B, P) -> {name: (B, *shape)}
        out, k = {}, 0
        for n, s in zip(names, shapes):
            size = int(np.prod(s))
            out[n] = flat[:, k:k + size].reshape(flat.shape[0], *s)
            k += size
        return out

    def evaluate():
        """The unperturbed policy's mean return per step over every rank's evaluation envs."""
        torch.nn.utils.vector_to_parameters(theta.detach(), policy.parameters())
        local = episode(evaluation, policy, device, seed=10**6 + comm.rank).sum() if n_eval > 0 else torch.zeros((), device=device)
        total = comm.allreduce_sum(local.reshape(1).double())
        return float(total.item()) / args.eval_envs

    gen = torch.Generator(device=device)
    first = evaluate()
    log(comm, f"iter   0: unperturbed return per step {first:8.4f}")
    steps_local = 0
    comm.barrier()
    start = time.perf_counter()
    for it in range(1, args.iters + 1):
        gen.manual_seed(args.seed * 1000003 + it * 1009 + comm.rank)  # each rank its own perturbations
        eps = torch.randn(pairs, theta.numel(), device=device, generator=gen)
        eps = torch.cat([eps, -eps])
        population = unflatten(theta.detach()[None] + args.sigma * eps)
        returns = episode(env, lambda o: batched(population, o), device, seed=it * 7919 + comm.rank)
        steps_local += n_local * args.steps * env.frame_skip
        ranks = torch.empty_like(returns)
        ranks[returns.argsort()] = torch.arange(n_local, device=device, dtype=returns.dtype)
        weights = ranks / max(n_local - 1, 1) - 0.5
        # this rank's estimate, weighted by its share of the instances, summed over ranks
        grad = -(weights[:, None] * eps).sum(0) / (n_local * args.sigma) * (n_local / args.envs)
        grad = comm.allreduce_sum(grad.double()).to(theta.dtype)
        mean_return = float(comm.allreduce_sum(returns.sum().reshape(1).double()).item()) / args.envs
        opt.zero_grad()
        theta.grad = grad
        opt.step()
        line = f"iter {it:3d}: population return per step {mean_return:8.4f}"
        if it % 5 == 0 or it == args.iters:
            line += f"   unperturbed {evaluate():8.4f}"
        log(comm, line)
    synchronize(device)
    elapsed_local = time.perf_counter() - start
    elapsed = comm.allreduce_max(elapsed_local)
    steps_all = comm.allreduce_sum(torch.tensor([float(steps_local)], dtype=torch.float64, device=device))
    print(f"rank {comm.rank} ({device}): {steps_local / elapsed_local:.4g} instance-steps/s "
          f"({steps_local} simulator steps in {elapsed_local:.1f} s, evaluations included)", flush=True)
    last = evaluate()
    log(comm, f"total: {float(steps_all.item()) / elapsed:.4g} instance-steps/s over {comm.world} process(es)")
    log(comm, f"unperturbed return per step: {first:.4f} -> {last:.4f}")
    if args.min_gain is not None and not last >= first + args.min_gain:
        log(comm, f"FAILED: the return gained less than --min-gain {args.min_gain}")
        return 1
    log(comm, "OK")
    return 0


# ---- measuring --------------------------------------------------------------------------


def row_header(comm, device):
    """The fields every --measure row starts with: launcher, world size, host, device, GPU."""
    import torch

    return {"example": "multi_gpu", "launcher": comm.name, "world": comm.world, "host": socket.gethostname(),
            "device": device.type, "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else ""}


def emit_row(comm, row, out):
    """Rank 0 prints the row as one JSON line and appends it to `out` (when given)."""
    if comm.rank == 0:
        line = json.dumps(row)
        print(line, flush=True)
        if out:
            with open(out, "a") as f:
                f.write(line + "\n")


def measure(comm, device, args):
    import torch

    _, n_local = shard_range(args.envs, comm.world, comm.rank)
    if n_local < 1:
        raise SystemExit(f"--envs {args.envs}: fewer environments than processes ({comm.world})")
    total_steps = args.warmup + args.steps
    env = make_env(n_local, device, args, max_episode_steps=total_steps + 1)  # no reset inside the timing
    od, nu = env.single_observation_space.shape[0], env.single_action_space.shape[0]
    policy = make_policy(od, nu, args.hidden, args.seed, device)
    obs, _ = env.reset(seed=args.seed + comm.rank)
    with torch.no_grad():
        for _ in range(args.warmup):
            obs, _, _, _, _ = env.step(policy(obs.float()))
        synchronize(device)
        comm.barrier()
        start = time.perf_counter()
        for _ in range(args.steps):
            obs, reward, _, _, _ = env.step(policy(obs.float()))
        synchronize(device)
        elapsed_local = time.perf_counter() - start
    finite = bool(torch.isfinite(reward).all().item())
    elapsed = comm.allreduce_max(elapsed_local)
    steps_local = n_local * args.steps * env.frame_skip
    per_rank = torch.zeros(comm.world, dtype=torch.float64, device=device)
    per_rank[comm.rank] = steps_local / elapsed_local
    per_rank = comm.allreduce_sum(per_rank).tolist()
    devices = torch.zeros(comm.world, dtype=torch.float64, device=device)
    devices[comm.rank] = device.index if device.type == "cuda" else -1
    devices = [int(d) for d in comm.allreduce_sum(devices).tolist()]
    all_finite = comm.allreduce_max(0.0 if finite else 1.0) == 0.0
    row = {
        **row_header(comm, device), "cuda_devices": devices if device.type == "cuda" else [],
        "task": "IiwaReach", "envs": args.envs, "envs_per_rank": [shard_range(args.envs, comm.world, r)[1]
                                                                  for r in range(comm.world)],
        "env_steps": args.steps, "frame_skip": env.frame_skip, "backend": env.sim.backend,
        "policy": f"{od}-{args.hidden}-{nu}", "elapsed_s": elapsed,
        "instance_steps_per_s": args.envs * args.steps * env.frame_skip / elapsed,
        "per_rank_instance_steps_per_s": per_rank, "finite": all_finite,
    }
    print(f"rank {comm.rank} ({device}): {n_local} envs x {args.steps} steps, "
          f"{steps_local / elapsed_local:.4g} instance-steps/s", flush=True)
    emit_row(comm, row, args.out)
    return 0 if all_finite else 1


def measure_dynamics(comm, device, args):
    """--measure id|fd: iiwa inverse or forward dynamics in float on this rank's share of
    --envs instances, (B, nv) tensors on its device, results into a preallocated out=
    (scandyn's engine, the caller's stream); --steps calls timed after --warmup."""
    import torch

    import scandyn as sd

    _, n_local = shard_range(args.envs, comm.world, comm.rank)
    if n_local < 1:
        raise SystemExit(f"--envs {args.envs}: fewer instances than processes ({comm.world})")
    model = sd.load_model("iiwa")
    gen = torch.Generator(device=device)
    gen.manual_seed(args.seed + comm.rank)
    q, qd, x = (torch.rand(n_local, model.nv, device=device, generator=gen) * 2 - 1 for _ in range(3))
    out = torch.empty_like(q)
    backend = "cuda" if device.type == "cuda" else args.backend
    if args.measure == "id":
        engine = sd.InverseDynamics(model, backend=backend, max_batch=n_local, dtype=torch.float32)
    else:
        engine = sd.ForwardDynamics(model, backend=backend, max_batch=n_local, dtype=torch.float32)
    for _ in range(args.warmup):
        engine(q, qd, x, out=out)
    synchronize(device)
    comm.barrier()
    start = time.perf_counter()
    for _ in range(args.steps):
        engine(q, qd, x, out=out)
    synchronize(device)
    elapsed_local = time.perf_counter() - start
    finite = bool(torch.isfinite(out).all().item())
    return emit_timed_row(comm, device, args, n_local, elapsed_local, finite, {"task": f"iiwa {args.measure}"},
                          ("calls", "seconds_per_call", "evals_per_second"), ("calls", "evaluations/s"))


def emit_timed_row(comm, device, args, n_local, elapsed_local, finite, fields, keys, words):
    """The row of a --measure id / fd / step run: --steps timed repetitions on this rank's
    n_local of --envs instances in elapsed_local seconds; the slowest rank's time sets the
    rate. keys: the row's names of the count, the time per repetition and the rate;
    words: how the rank's line names a repetition and the rate. Exit status 1 when a rank's
    results are not finite."""
    elapsed = comm.allreduce_max(elapsed_local)
    all_finite = comm.allreduce_max(0.0 if finite else 1.0) == 0.0
    count, per, rate = keys
    row = {
        **row_header(comm, device), **fields, "precision": "float", "instances": args.envs,
        "instances_per_rank": [shard_range(args.envs, comm.world, r)[1] for r in range(comm.world)],
        count: args.steps, "elapsed_s": elapsed, per: elapsed / args.steps,
        rate: args.envs * args.steps / elapsed, "finite": all_finite,
    }
    print(f"rank {comm.rank} ({device}): {n_local} instances x {args.steps} {words[0]}, "
          f"{n_local * args.steps / elapsed_local:.4g} {words[1]}", flush=True)
    emit_row(comm, row, args.out)
    return 0 if all_finite else 1


def measure_step(comm, device, args):
    """--measure step: the RL step of scenes/iiwa_rl.json (float, fused ABA + Euler, gravity
    and damping) on this rank's share of --envs instances, the simulator on this rank's
    device, torques a (B, nv) tensor there; --steps steps timed after --warmup, queued
    without a status check (check=False), then one check of every instance's status."""
    import torch

    import scandyn as sd

    _, n_local = shard_range(args.envs, comm.world, comm.rank)
    if n_local < 1:
        raise SystemExit(f"--envs {args.envs}: fewer instances than processes ({comm.world})")
    scene_path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "scenes", "iiwa_rl.json")
    with open(scene_path) as f:
        scene = json.load(f)
    scene["instances"] = n_local
    scene["initial"]["random"]["seed"] = args.seed + comm.rank + 1
    backend = "cuda" if device.type == "cuda" else args.backend
    sim = sd.Simulator(scene, backend=backend, device=device if device.type == "cuda" else None,
                       arrays="torch")
    gen = torch.Generator(device=device)
    gen.manual_seed(args.seed + comm.rank)
    tau = (torch.rand(n_local, sim.nv, device=device, generator=gen) * 2 - 1).to(sim.qd.dtype)
    def check_status():
        failed, instance, dof, message = sim.status()
        if failed:
            raise SystemExit(f"rank {comm.rank}: {failed} failed instance-steps (first: instance {instance}, "
                             f"DoF {dof}): {message}")

    for _ in range(args.warmup):
        sim.step(tau, check=False)
    check_status()
    sim.synchronize()
    synchronize(device)
    comm.barrier()
    start = time.perf_counter()
    for _ in range(args.steps):
        sim.step(tau, check=False)
    sim.synchronize()
    synchronize(device)
    elapsed_local = time.perf_counter() - start
    check_status()  # names the first instance that failed in the timed steps
    finite = bool(torch.isfinite(sim.q).all().item() and torch.isfinite(sim.qd).all().item())
    return emit_timed_row(comm, device, args, n_local, elapsed_local, finite,
                          {"task": "iiwa step", "scene": "scenes/iiwa_rl.json", "backend": sim.backend},
                          ("steps", "seconds_per_step", "instance_steps_per_s"), ("steps", "instance-steps/s"))


def run(comm, device, args):
    resolve_defaults(args, device)
    try:
        if args.measure in ("id", "fd"):
            return measure_dynamics(comm, device, args)
        if args.measure == "step":
            return measure_step(comm, device, args)
        return measure(comm, device, args) if args.measure else train(comm, device, args)
    finally:
        comm.close()


if __name__ == "__main__":  # pragma: no cover
    sys.exit("run examples/multi_gpu_torchrun.py or examples/multi_gpu_mpi.py")
