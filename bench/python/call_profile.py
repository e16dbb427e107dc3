#!/usr/bin/env python3
"""Where a Python call's time goes on a CUDA device: host microseconds per call of the
package's steps for iiwa, float32, B = 1, on torch CUDA tensors (a call, its parts, and
torch's allocating calls), each timed over 3 x 20000 calls after 300 warm-up calls (a
synchronisation every 500 calls; the best of the 3). The whole call against its parts
shows what out=None adds to a call with out= (bench/python/call_overhead.py measures
both against the C++ rows).

    python3 bench/python/call_profile.py > OUT.txt

Needs torch with CUDA and a CUDA build of the package.
"""
import time

import numpy as np
import torch
import torch.utils.dlpack as dl

import scandyn as sd
from scandyn import _api


def per_call(f, n=20000):
    for _ in range(300):
        f()
    torch.cuda.synchronize()
    ts = []
    for _ in range(3):
        t0 = time.perf_counter()
        for i in range(n):
            f()
            if i % 500 == 499:
                torch.cuda.synchronize()
        torch.cuda.synchronize()
        ts.append((time.perf_counter() - t0) / n)
    return min(ts) * 1e6


def main():
    m = sd.load_model("iiwa")
    nv = m.nv
    dev = torch.device("cuda")
    g = torch.Generator(device=dev).manual_seed(1)
    q, qd, qdd = (torch.rand(1, nv, generator=g, device=dev) for _ in range(3))
    M = sd.MassMatrix(m, backend="cuda", max_batch=1, dtype=np.float32)
    ID = sd.InverseDynamics(m, backend="cuda", max_batch=1, dtype=np.float32)
    pre = torch.empty((nv, nv, 1), device=dev).permute(2, 0, 1)
    pre_id = torch.empty((1, nv), device=dev)
    s = torch._C._cuda_getCurrentRawStream(0)
    rows = [
        ("mass e(q) out=None", lambda: M(q)),
        ("mass e(q, out=entry-major)", lambda: M(q, out=pre)),
        ("mass: the extension's compute(capsules) alone", lambda: M._e.compute(dl.to_dlpack(q), dl.to_dlpack(pre), s)),
        ("mass: e._prepare alone (out=pre)", lambda: M._prepare((q,), pre, None, (nv,))),
        ("mass: _entry_major_mass(q) alone", lambda: _api._entry_major_mass(q, nv, "float32")),
        ("q.new_empty_strided((1,nv,nv), (1,nv,1))", lambda: q.new_empty_strided((1, nv, nv), (1, nv, 1))),
        ("id e(q, qd, qdd) out=None", lambda: ID(q, qd, qdd)),
        ("id e(q, qd, qdd, out=)", lambda: ID(q, qd, qdd, out=pre_id)),
        ("torch.empty((1,nv), dtype=, device=)", lambda: torch.empty((1, nv), dtype=torch.float32, device=dev)),
        ("q.new_empty((1,nv))", lambda: q.new_empty((1, nv))),
        ("q.new_empty_strided((1,nv), (nv,1))", lambda: q.new_empty_strided((1, nv), (nv, 1))),
        ("torch._C._cuda_getCurrentRawStream(0)", lambda: torch._C._cuda_getCurrentRawStream(0)),
        ("sd.mass_matrix(m, q)  [function API]", lambda: sd.mass_matrix(m, q)),
        ("sd.inverse_dynamics(m, q, qd, qdd)  [function API]", lambda: sd.inverse_dynamics(m, q, qd, qdd)),
    ]
    print(f"# {torch.cuda.get_device_name(0)}, torch {torch.__version__}; host microseconds per call")
    for name, f in rows:
        print(f"{name:60s} {per_call(f):7.3f}", flush=True)


if __name__ == "__main__":
    main()
