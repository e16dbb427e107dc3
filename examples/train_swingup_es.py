"""Trains a small PyTorch MLP policy on scandyn.envs.RopeSwingUp (or IiwaReach) with an
evolution strategy, one policy perturbation per simulated instance, and checks that the
return improves.

    python examples/train_swingup_es.py                       # CPU: 64 instances, about a minute
    python examples/train_swingup_es.py --device cuda --envs 16384 --iters 100
    python examples/train_swingup_es.py --task reach

Each iteration: the vector env's num_envs sub-environments run one episode, sub-environment
i with the policy's parameters theta + sigma eps_i (antithetic pairs eps, -eps); the
returns, rank-normalised, weight the eps into a gradient estimate for Adam (OpenAI-ES,
Salimans et al. 2017). The perturbed policies run as one batched forward
(torch.func.vmap over functional_call). Prints the mean return of the population and of
the unperturbed policy per iteration; exits non-zero unless the unperturbed policy's
return at the end beats the first one by --min-gain.

Needs gymnasium and torch (pip install gymnasium torch).
"""

import argparse
import sys
import time

import numpy as np
import torch
from torch.func import functional_call, vmap

import scandyn as sd
import scandyn.envs


def make_env(args, num_envs):
    kw = dict(num_envs=num_envs, device=args.device, max_episode_steps=args.steps, backend=args.backend)
    if args.task == "swingup":
        return sd.envs.RopeSwingUp(links=args.links, torque_scale=args.torque, **kw)
    return sd.envs.IiwaReach(**kw)


def as_torch(x, device):
    return x if isinstance(x, torch.Tensor) else torch.from_numpy(np.asarray(x)).to(device)


def episode(env, policy, params, seed, device):
    """Returns (num_envs,) of one episode, sub-environment i run by params[i] (a dict of
    batched tensors), or all by the unperturbed policy when params is None."""
    obs, _ = env.reset(seed=seed)
    total = torch.zeros(env.num_envs, device=device)
    act_fn = vmap(lambda p, o: functional_call(policy, p, (o,))) if params is not None else policy
    with torch.no_grad():
        for _ in range(env.max_episode_steps):
            o = as_torch(obs, device).float()
            a = act_fn(params, o) if params is not None else policy(o)
            obs, reward, terminated, truncated, _ = env.step(a if env.device.startswith("cuda") else a.cpu().numpy())
            total += as_torch(reward, device).float()
    return total


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--task", choices=["swingup", "reach"], default="swingup")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (the simulator and the policy)")
    ap.add_argument("--backend", default=None,
                    help="simulator backend (default: serial on cpu, where a few instances step fastest "
                         "on one thread; cuda on cuda); openmp spreads many instances over the cores")
    ap.add_argument("--envs", type=int, default=64, help="population size = simulated instances (even)")
    ap.add_argument("--iters", type=int, default=40)
    ap.add_argument("--steps", type=int, default=100, help="env steps per episode")
    ap.add_argument("--links", type=int, default=4, help="rope links (swingup)")
    ap.add_argument("--torque", type=float, default=0.004, help="N m per unit action (swingup)")
    ap.add_argument("--sigma", type=float, default=0.1)
    ap.add_argument("--lr", type=float, default=0.03)
    ap.add_argument("--hidden", type=int, default=32)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--min-gain", type=float, default=None,
                    help="required gain of the return (default: 10%% of the return's range over an episode)")
    args = ap.parse_args()
    if args.envs % 2:
        ap.error("--envs must be even (antithetic pairs)")
    device = torch.device(args.device)
    if args.backend is None:
        args.backend = "cuda" if device.type == "cuda" else "serial"
    torch.manual_seed(args.seed)

    env = make_env(args, args.envs)
    evaluation = make_env(args, 8)
    od, nu = env.single_observation_space.shape[0], env.single_action_space.shape[0]
    policy = torch.nn.Sequential(torch.nn.Linear(od, args.hidden), torch.nn.Tanh(),
                                 torch.nn.Linear(args.hidden, nu), torch.nn.Tanh()).to(device)
    names = [n for n, _ in policy.named_parameters()]
    theta = torch.nn.utils.parameters_to_vector(policy.parameters()).detach()
    theta.requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=args.lr)
    shapes = [p.shape for p in policy.parameters()]
    print(f"{args.task}: {env}, policy {od}-{args.hidden}-{nu} ({theta.numel()} parameters), "
          f"simulator {env.sim.backend} ({env.sim.strategy})")

    def unflatten(flat):  # (B, P) -> {name: (B, *shape)}
        out, k = {}, 0
        for n, s in zip(names, shapes):
            size = int(np.prod(s))
            out[n] = flat[:, k:k + size].reshape(flat.shape[0], *s)
            k += size
        return out

    def evaluate(seed):
        torch.nn.utils.vector_to_parameters(theta.detach(), policy.parameters())
        return episode(evaluation, policy, None, seed, device).mean().item()

    half = args.envs // 2
    first = evaluate(10**6)
    print(f"iter   0: unperturbed return {first:9.3f}")
    start = time.perf_counter()
    for it in range(1, args.iters + 1):
        eps = torch.randn(half, theta.numel(), device=device)
        eps = torch.cat([eps, -eps])
        population = unflatten(theta.detach()[None] + args.sigma * eps)
        returns = episode(env, policy, population, seed=it, device=device)
        ranks = torch.empty_like(returns)
        ranks[returns.argsort()] = torch.arange(args.envs, device=device, dtype=returns.dtype)
        weights = ranks / (args.envs - 1) - 0.5
        opt.zero_grad()
        theta.grad = -(weights[:, None] * eps).sum(0) / (args.envs * args.sigma)
        opt.step()
        line = f"iter {it:3d}: population return {returns.mean().item():9.3f}"
        if it % 5 == 0 or it == args.iters:
            line += f"   unperturbed return {evaluate(10**6):9.3f}"
        print(line, flush=True)
    last = evaluate(10**6)
    elapsed = time.perf_counter() - start
    steps = args.iters * args.envs * args.steps * env.frame_skip
    print(f"{args.iters} iterations in {elapsed:.1f} s ({steps / elapsed:.3g} simulated instance-steps/s)")
    # rewards per step lie in [-1, 1] (swingup) or around -1..0 m (reach): 10% of that range per episode
    gain = args.min_gain if args.min_gain is not None else 0.1 * args.steps
    print(f"unperturbed return: {first:.3f} -> {last:.3f} (required gain {gain:.3f})")
    if not last >= first + gain:
        print("FAILED: the return did not improve enough", file=sys.stderr)
        return 1
    print("OK: the return improved")
    return 0


if __name__ == "__main__":
    sys.exit(main())
