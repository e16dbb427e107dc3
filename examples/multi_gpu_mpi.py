"""IiwaReach on several GPUs, one process per GPU, under mpirun: the same training and
--measure rollout as examples/multi_gpu_torchrun.py (shared code:
examples/multi_gpu_common.py), with the rank from mpi4py's COMM_WORLD, the GPU
(node-local rank) % (visible GPUs), and the gradient estimates, returns and timings
reduced by mpi4py's allreduce (through host memory). scandyn itself exchanges nothing
between processes (docs/scaling.md).

    mpirun -n 2 -x NCCL_NVLS_ENABLE=0 python examples/multi_gpu_mpi.py --measure --out rollout.jsonl
    mpirun -n 2 python examples/multi_gpu_mpi.py                         # train
    mpirun -n 2 python examples/multi_gpu_mpi.py --device cpu            # CPUs only
    mpirun -n 16 --hostfile hosts python examples/multi_gpu_mpi.py       # two machines of 8 GPUs

NCCL_NVLS_ENABLE=0, TORCH_SYMM_MEM_DISABLE_MULTICAST=1 and NVSHMEM_DISABLE_NVLS=1 are set
in each process (nothing here uses NCCL; they keep NVLink multicast off for whatever
else the process loads). Needs mpi4py, torch and gymnasium.
"""

import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import multi_gpu_common as common  # noqa: E402


def main(argv=None):
    args = common.parse_args(__doc__, argv)
    common.disable_nvlink_multicast()
    from mpi4py import MPI

    world = MPI.COMM_WORLD
    # the node-local rank picks the GPU: (local rank) % (GPUs visible to the process)
    local_rank = world.Split_type(MPI.COMM_TYPE_SHARED, key=world.Get_rank()).Get_rank()
    device = common.pick_device(args.device, local_rank)
    comm = common.MpiComm(world)
    return common.run(comm, device, args)


if __name__ == "__main__":
    sys.exit(main())
