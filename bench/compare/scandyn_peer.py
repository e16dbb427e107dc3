"""scandyn from Python as a library of the GPU comparison (gpu.py --scandyn-via module).

The installed `scandyn` package (pip install .) on torch CUDA tensors: one engine per
algorithm and batch (sd.InverseDynamics, BiasForces, MassMatrix, ForwardDynamics with
backend='cuda', float32), called with out= on device-resident inputs, so each call is the
engine's compute_async on torch's current stream and nothing else (no copy, no
synchronisation; fd's failed DoFs go to the engine's device array and are not read while
timing, as in the command's device-resident rows). Strategy column: the engine's strategy
with "-py" (e.g. thread-py, aba_thread-py).

The check runs the function API on torch CUDA tensors of the CHECK_STATES states (scandyn's
DoF order: no permutation) against the double serial reference, like the peers. Timing:
common.timed (bench's procedure) with torch.cuda.synchronize as the wait.
"""
import numpy as np

import common

ENGINES = {'id': 'InverseDynamics', 'bias': 'BiasForces', 'mass': 'MassMatrix', 'fd': 'ForwardDynamics'}
INPUTS = {'id': ('q', 'qd', 'qdd'), 'bias': ('q', 'qd'), 'mass': ('q',), 'fd': ('q', 'qd', 'tau')}
FUNCTIONS = {'id': 'inverse_dynamics', 'bias': 'bias_forces', 'mass': 'mass_matrix', 'fd': 'forward_dynamics'}


class ScandynRunner:
    library = 'scandyn'

    def __init__(self, model, device='cuda:0'):
        import torch
        import scandyn as sd
        self.torch, self.sd = torch, sd
        self.device = torch.device(device)
        self.m = sd.load_model(model.spec, allow_nonphysical_inertia=model.nonphysical)
        self.version = 'scandyn %s (python module, torch %s)' % (sd.__version__, torch.__version__)
        self.strategy = ''
        self.call = None

    def states(self, batch, seed=7):
        """Random float32 states on the device, [-1, 1)."""
        g = self.torch.Generator(device=self.device).manual_seed(seed)
        return {k: self.torch.rand(batch, self.m.nv, generator=g, device=self.device) * 2 - 1
                for k in ('q', 'qd', 'qdd', 'tau')}

    def prepare(self, algo, batch):
        self.call = None
        self.torch.cuda.empty_cache()
        S = self.states(batch)
        e = getattr(self.sd, ENGINES[algo])(self.m, backend='cuda', max_batch=batch, dtype=np.float32)
        tail = (self.m.nv,) if algo == 'mass' else ()
        out = self.torch.empty((batch, self.m.nv) + tail, dtype=self.torch.float32, device=self.device)
        args = [S[k] for k in INPUTS[algo]]
        self.call = lambda: e(*args, out=out)
        self.strategy = e.strategy + '-py'

    def sync(self):
        self.torch.cuda.synchronize()


def check(runner, ref, S, algos):
    """The equality check: the function API on CUDA tensors of S (scandyn order) against ref."""
    torch, sd = runner.torch, runner.sd
    dev = {k: torch.tensor(v, dtype=torch.float32, device=runner.device) for k, v in S.items()}
    errs = {}
    for a in algos:
        got = getattr(sd, FUNCTIONS[a])(runner.m, *[dev[k] for k in INPUTS[a]])
        errs[a] = common.rel_err(got.cpu().numpy(), ref[a])
    return errs
