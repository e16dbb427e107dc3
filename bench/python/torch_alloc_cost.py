#!/usr/bin/env python3
"""What a new result tensor costs from Python on a CUDA device: the allocation that
separates the mass matrix's out=None call from its out= call at B = 1
(bench/python/call_overhead.py), and the candidates to replace it.

    python3 bench/python/torch_alloc_cost.py > OUT.txt

Each line: microseconds per call of one way to get a (1, 7, 7) float32 result on
cuda:0 (iiwa's mass matrix at B = 1, entry-major strides), the result dropped at once
(its free included), averaged over 20000 calls after 200 warm-up calls, plus the cost
of the torch calls the Python layer makes on every call. Needs torch with CUDA.
"""
import time

import torch


def per_call(f, n=20000):
    for _ in range(200):
        f()
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(n):
        f()
    seconds = (time.perf_counter() - t0) / n
    torch.cuda.synchronize()
    return seconds


def main():
    q = torch.rand((1, 7), device="cuda")
    b, nv, dt, dev = 1, 7, torch.float32, q.device
    size, stride = (b, nv, nv), (1, nv * b, b)
    pool = []

    def from_pool():  # views cut from one block of 256 results (they share its version counter)
        if not pool:
            pool.extend(torch.empty((256, nv, nv, b), dtype=dt, device=dev).permute(0, 3, 1, 2).unbind(0))
        return pool.pop()

    import torch.utils.dlpack as dl
    rows = [
        ("q.new_empty_strided(size, stride, dtype=)  [the default]",
         lambda: q.new_empty_strided(size, stride, dtype=dt)),
        ("q.new_empty_strided(size, stride)", lambda: q.new_empty_strided(size, stride)),
        ("torch.empty_strided(size, stride, dtype=, device=)",
         lambda: torch.empty_strided(size, stride, dtype=dt, device=dev)),
        ("torch.empty(size, dtype=, device=)", lambda: torch.empty(size, dtype=dt, device=dev)),
        ("q.new_empty(size)", lambda: q.new_empty(size)),
        ("torch.empty(size)  [host memory]", lambda: torch.empty(size)),
        ("a view from a pool of unbind() views, blocks of 256", from_pool),
        ("torch._C._cuda_getCurrentRawStream(0)", lambda: torch._C._cuda_getCurrentRawStream(0)),
        ("q.get_device()", lambda: q.get_device()),
        ("q.is_cuda", lambda: q.is_cuda),
        ("torch.utils.dlpack.to_dlpack(q)", lambda: dl.to_dlpack(q)),
        ("q.__dlpack__()", lambda: q.__dlpack__()),
        ("torch._C._from_dlpack(to_dlpack(q))", lambda: torch._C._from_dlpack(dl.to_dlpack(q))),
        ("torch._C._cuda_isCurrentStreamCapturing()", lambda: torch._C._cuda_isCurrentStreamCapturing()),
    ]
    print(f"# {torch.cuda.get_device_name(0)}, torch {torch.__version__}; microseconds per call")
    for name, f in rows:
        print(f"{name:66s} {per_call(f) * 1e6:7.3f}")


if __name__ == "__main__":
    main()
