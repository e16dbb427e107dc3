"""IiwaReach on several GPUs, one process per GPU, under torchrun: each rank makes its
shard of the environments on cuda:LOCAL_RANK and trains the same torch policy by an
evolution strategy whose gradient estimates torch.distributed averages (all_reduce,
NCCL on GPUs, gloo on CPUs). scandyn itself exchanges nothing between processes
(docs/scaling.md); the shared code is examples/multi_gpu_common.py.

    torchrun --nproc-per-node 2 examples/multi_gpu_torchrun.py                 # train, 2 GPUs
    torchrun --nproc-per-node 2 examples/multi_gpu_torchrun.py --measure --out rollout.jsonl
    python examples/multi_gpu_torchrun.py --measure --out rollout.jsonl        # 1 process: the baseline
    torchrun --nproc-per-node 2 examples/multi_gpu_torchrun.py --device cpu    # gloo on CPUs
    torchrun --nnodes 2 --node-rank R --master-addr HOST --master-port 29500 \\
        --nproc-per-node 8 examples/multi_gpu_torchrun.py                       # two machines

NCCL_NVLS_ENABLE=0, TORCH_SYMM_MEM_DISABLE_MULTICAST=1 and NVSHMEM_DISABLE_NVLS=1 are set in
each process before torch.distributed starts (NVLink multicast stays off). Without
torchrun (no WORLD_SIZE) it runs as one process, without torch.distributed.
Needs torch and gymnasium.
"""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import multi_gpu_common as common  # noqa: E402


def main(argv=None):
    args = common.parse_args(__doc__, argv)
    common.disable_nvlink_multicast()
    import torch
    import torch.distributed as dist

    world = int(os.environ.get("WORLD_SIZE", "1"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    device = common.pick_device(args.device, local_rank)  # torch.cuda.set_device(cuda:LOCAL_RANK)
    if world > 1:
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        comm = common.TorchComm(dist, device)
    else:
        comm = common.LocalComm()
    return common.run(comm, device, args)


if __name__ == "__main__":
    sys.exit(main())
