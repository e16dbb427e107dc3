"""GRiD peer of the GPU comparison (PyPI `grid-rbd`, A2R Lab).

GRiD generates CUDA for one URDF and compiles it with nvcc when the robot is first loaded
(`grid_rbd.load_robot`, cached under $GRID_RBD_CACHE_DIR); the build takes minutes for an arm
and longer for a humanoid, so gpu.py gives each build a time limit and records a timeout.
We use its PyTorch handle (CUDA tensors in, CUDA tensors out: the batch stays on the device,
as for the other libraries) with a fixed base, float32 (GRiD's validated precision; its fp64
tier is marked alpha), and only the algorithms compared:
- id   robot.inverse_dynamics(q, qd, qdd)   (RNEA; tau = M qdd + h)
- bias robot.inverse_dynamics(q, qd)        (qdd = None: the bias forces h)
- mass robot.crba(q)                        (dense nv x nv)
- fd   robot.forward_dynamics(q, qd, tau)   (GRiD's forward dynamics, M^-1 (tau - h))
- dfd  robot.forward_dynamics_gradient(q, qd, tau)   ((B, nv, 2 nv): [dqdd/dq | dqdd/dqd],
       built only when asked for: its code generation and compilation take longer)
gravity = -9.81 along z (GRiD's argument). One call covers at most max_batch_size instances
(a compile-time constant): gpu.py builds with the largest batch it times and, where GRiD
refuses a size, records it.
Joint order: GRiD's URDF parser orders joints itself; columns are matched by joint name
(`robot.joint_names`).
Timing: torch.cuda.synchronize() around rounds of back-to-back calls (the procedure of
`scandyn bench`), device tensors, no host copies.
"""
import time

import numpy as np

import common

ALGO_LIST = ['inverse_dynamics', 'crba', 'forward_dynamics']
GRADIENTS = {'dfd': 'forward_dynamics_gradient'}  # GRiD's algorithm of each derivative compared


class GridRunner:
    library = 'grid'

    def __init__(self, device='cuda', cache_dir=None, max_batch=1 << 20, cuda_arch=None, algos=()):
        import grid_rbd
        from importlib import metadata
        try:
            import torch
        except ImportError:
            torch = None
        self.grid, self.torch = grid_rbd, torch
        self.cache_dir, self.max_batch, self.cuda_arch = cache_dir, max_batch, cuda_arch
        self.algorithm_list = ALGO_LIST + [GRADIENTS[a] for a in algos if a in GRADIENTS]
        self.version = 'grid-rbd %s (%s)' % (metadata.version('grid-rbd'),
                                             'torch %s' % torch.__version__ if torch else 'no torch')
        self.robot = None
        self.backend = 'torch'
        self.strategy = 'torch'

    def load(self, model, scandyn_names, backend=None):
        """Generates and compiles (or takes from the cache) the robot; -> perm (scandyn DoF k is GRiD's perm[k])."""
        backend = backend or ('torch' if self.torch else 'numpy')
        opts = dict(backend=backend, floating_base=False, max_batch_size=self.max_batch, dtype='float32',
                    algorithm_list=self.algorithm_list, enable_mujoco_kernels=False)
        if self.cache_dir:
            opts['cache_dir'] = self.cache_dir
        if self.cuda_arch:
            opts['cuda_arch'] = self.cuda_arch
        try:
            self.robot = self.grid.load_robot(model.urdf, **opts)
            self.backend = backend
        except Exception as e:  # noqa: BLE001
            if backend != 'torch':
                raise
            # the torch ops could not be built here: GRiD's NumPy handle (host arrays; its
            # times include the copies, strategy `numpy-host`)
            print('grid: torch backend failed (%s: %s); using the numpy backend' % (type(e).__name__, e),
                  flush=True)
            opts['backend'] = 'numpy'
            self.robot = self.grid.load_robot(model.urdf, **opts)
            self.backend = 'numpy'
            self.version += ' (numpy handle: the torch one failed to build)'
        self.strategy = 'torch' if self.backend == 'torch' else 'numpy-host'
        base = getattr(self.robot, '_base', self.robot)  # the torch handle wraps the numpy one
        names = list(getattr(self.robot, 'joint_names', None) or base.joint_names)
        if len(names) != len(scandyn_names):
            raise RuntimeError('GRiD model has %d joints, scandyn %d' % (len(names), len(scandyn_names)))
        pos = {n: i for i, n in enumerate(names)}
        return np.array([pos[n] for n in scandyn_names])

    def prepare(self, algo, B, S=None, nv=None):
        torch = self.torch
        if self.backend == 'numpy':
            if S is None:
                rng = np.random.default_rng(42)
                S = {k: rng.uniform(-1, 1, (B, nv)) for k in ('q', 'qd', 'qdd', 'tau')}
            S = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in S.items()}
        elif S is None:
            g = torch.Generator(device='cuda').manual_seed(42)
            S = {k: torch.rand((B, nv), device='cuda', generator=g, dtype=torch.float32) * 2 - 1
                 for k in ('q', 'qd', 'qdd', 'tau')}
        else:
            S = {k: torch.as_tensor(v, dtype=torch.float32, device='cuda').contiguous() for k, v in S.items()}
        r = self.robot
        self.fn = {
            'id': lambda: r.inverse_dynamics(S['q'], S['qd'], S['qdd']),
            'bias': lambda: r.inverse_dynamics(S['q'], S['qd']),
            'mass': lambda: r.crba(S['q']),
            'fd': lambda: r.forward_dynamics(S['q'], S['qd'], S['tau']),
            'dfd': lambda: r.forward_dynamics_gradient(S['q'], S['qd'], S['tau']),
        }[algo]
        self.call()
        self.sync()
        self.algo = algo

    def call(self):
        if self.backend == 'numpy':
            self.out = self.fn()
            return
        with self.torch.no_grad():
            self.out = self.fn()

    def sync(self):
        if self.backend != 'numpy':
            self.torch.cuda.synchronize()

    def result(self):
        if self.backend == 'numpy':
            return np.asarray(self.out, dtype=np.float64)
        return self.out.detach().double().cpu().numpy()


def check(runner, model, scandyn_names, ref, S, algos):
    perm = runner.load(model, scandyn_names)
    Sg = {}
    for k, v in S.items():
        y = np.empty_like(v)
        y[:, perm] = v
        Sg[k] = y
    errs = {}
    for a in algos:
        runner.prepare(a, S['q'].shape[0], Sg)
        out = runner.result()
        if a == 'mass':
            out = out[:, perm][:, :, perm]
        elif a == 'dfd':  # [dqdd/dq | dqdd/dqd]: rows and each block's columns in scandyn's order
            nv = len(perm)
            out = out.reshape(len(out), nv, 2 * nv)[:, perm]
            out = np.concatenate([out[:, :, perm], out[:, :, nv + perm]], axis=2)
        else:
            out = out[:, perm]
        errs[a] = common.rel_err(out, ref[a])
    return errs


def timed(runner, min_time):
    from mujoco_peer import timed as t  # the same procedure for every library
    return t(runner.call, runner.sync, min_time)


if __name__ == '__main__':
    # build test without a GPU: python3 grid_peer.py URDF [CACHE_DIR]  (generates and compiles for sm_90)
    import sys
    t = time.time()
    import grid_rbd
    robot = grid_rbd.load_robot(sys.argv[1], backend='numpy', floating_base=False, max_batch_size=1 << 20,
                                dtype='float32', algorithm_list=ALGO_LIST, enable_mujoco_kernels=False,
                                cuda_arch=90, **({'cache_dir': sys.argv[2]} if len(sys.argv) > 2 else {}))
    print('built in %.0f s: nv %d, joints %s' % (time.time() - t, robot.nv, list(robot.joint_names)))
