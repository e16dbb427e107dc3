"""MuJoCo peers of the GPU comparison: MuJoCo Warp (`mujoco_warp`) and MJX (`mujoco.mjx`, JAX).

Model conversion (URDF -> MuJoCo), the same for both:
- the URDF is read by MuJoCo's own URDF importer after removing <visual>/<collision> (no
  geometry is needed; no contacts exist) and adding <mujoco><compiler discardvisual="true"
  balanceinertia="false" fusestatic="true"/></mujoco>; fixed joints are fused into their
  parent body (same physics as scandyn's merge); the root link is welded to the world, so the
  base is fixed, as in scandyn (docs/models.md: fixed-base trees; hyq and atlas are not floating);
- joint damping, armature, friction loss and stiffness are set to 0 (iiwa.urdf declares
  damping that MuJoCo would otherwise apply as a passive force); contacts, constraints (and
  so joint limits) are disabled; gravity (0, 0, -9.81);
- MuJoCo orders joints by its body tree as it reads the file; scandyn by depth-first preorder
  with siblings sorted by joint name. Columns are matched by joint name (`perm`); for the
  ropes and iiwa the orders agree, for hyq and atlas they may not.
- MuJoCo rejects a body whose inertia is not positive definite or breaks the triangle
  inequality; GRiD's atlas.urdf has four (docs/models.md), so atlas cannot be loaded as it is
  (the error is recorded in the row's note).
- MuJoCo's compiler refuses a body tree 1024 or more bodies deep ("depth limit exceeded in
  signature computation"; MJCF files fail even earlier, at the XML parser's nesting limit), so
  rope:10000 and longer cannot be loaded by either peer; load_mjmodel shows this with a
  1024-body probe chain (2 s) instead of the URDF import, which runs for minutes at that depth.
- MuJoCo Warp's put_model recurses once per tree level (Python), so the recursion limit is
  raised to fit the tree.

Computations, smooth dynamics only (MuJoCo's own functions, the minimal pipeline for each):
- id   kinematics, com_pos, com_vel, rne(flg_acc=True)              -> qfrc_bias = M qacc + h
- bias kinematics, com_pos, com_vel, rne(flg_acc=False)             -> qfrc_bias = h
- mass kinematics, com_pos, crb                                     -> M (sparse CSR; densified
                                                                       for the check only)
- fd   kinematics, com_pos, crb, factor_m, com_vel, rne, fwd_acceleration
                                                                    -> qacc_smooth = M^-1 (qfrc_applied - h)
Both compute in float32: MuJoCo Warp always; MJX with JAX's default matmul precision, which on
Ampere and newer GPUs rounds the factors of float32 matrix products to TF32 (10-bit mantissa),
or with gpu.py --mjx-matmul-precision highest.
Timing: MuJoCo Warp's sequence is captured once as a CUDA graph (wp.ScopedCapture, as its
own testspeed does) and the graph is launched back to back; MJX's is one jax.jit(jax.vmap(.))
call on device arrays with block_until_ready. The batch stays on the device; no host copies
are timed.
"""
import os
import re
import sys
import tempfile
import time

import numpy as np

import common


def urdf_for_mujoco(urdf_path):
    text = open(urdf_path).read()
    text = re.sub(r'<visual\b.*?</visual>', '', text, flags=re.S)
    text = re.sub(r'<collision\b.*?</collision>', '', text, flags=re.S)
    text = re.sub(r'(<robot\b[^>]*>)', r'\1\n<mujoco><compiler discardvisual="true" balanceinertia="false" '
                  r'fusestatic="true" strippath="true"/></mujoco>', text, count=1)
    return text


def urdf_depth(urdf_path):
    """Bodies on the longest root-to-leaf path of the URDF's joint tree (the root link not counted)."""
    import xml.etree.ElementTree as ET
    parent = {j.find('child').get('link'): j.find('parent').get('link')
              for j in ET.parse(urdf_path).getroot().findall('joint')}
    depth = {}
    for link in parent:
        path = []
        while link in parent and link not in depth:
            path.append(link)
            link = parent[link]
        d = depth.get(link, 0)
        for l in reversed(path):
            d += 1
            depth[l] = d
    return max(depth.values(), default=0)


DEPTH_PROBE = 1024


def depth_probe(mujoco, n):
    """MuJoCo's compiler on an n-body chain of unit hinges: None if it compiles, else its error."""
    spec = mujoco.MjSpec()
    b = spec.worldbody
    for _ in range(n):
        b = b.add_body(pos=[0, 0, -0.1])
        b.add_joint(type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0, 1, 0])
        b.explicitinertial, b.mass, b.inertia = True, 0.1, [1e-4, 1e-4, 1e-5]
    try:
        spec.compile()
        return None
    except Exception as e:  # noqa: BLE001
        return str(e).splitlines()[0]


def load_mjmodel(model, scandyn_names):
    """-> (mujoco.MjModel, perm) where scandyn DoF k is MuJoCo DoF perm[k]."""
    import mujoco
    # MuJoCo's compiler limits the body tree's depth, and its URDF import of a chain thousands of
    # links deep runs for minutes before reaching that error: a chain of DEPTH_PROBE bodies, which
    # compiles in about 2 s, shows first whether a deeper tree can be compiled at all
    depth = urdf_depth(model.urdf)
    if depth >= DEPTH_PROBE:
        err = depth_probe(mujoco, DEPTH_PROBE)
        if err:
            raise RuntimeError('MuJoCo %s cannot compile a body tree %d deep: a chain of %d bodies already '
                               'fails with "%s"' % (mujoco.__version__, depth, DEPTH_PROBE, err))
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, os.path.basename(model.urdf))
        with open(path, 'w') as fh:
            fh.write(urdf_for_mujoco(model.urdf))
        mjm = mujoco.MjModel.from_xml_path(path)
    mjm.dof_damping[:] = 0
    mjm.dof_armature[:] = 0
    mjm.dof_frictionloss[:] = 0
    mjm.jnt_stiffness[:] = 0
    mjm.opt.gravity[:] = (0, 0, -9.81)
    for bit in ('mjDSBL_CONTACT', 'mjDSBL_CONSTRAINT', 'mjDSBL_LIMIT', 'mjDSBL_PASSIVE', 'mjDSBL_SPRING',
                'mjDSBL_DAMPER', 'mjDSBL_FRICTIONLOSS'):
        if hasattr(mujoco.mjtDisableBit, bit):
            mjm.opt.disableflags |= int(getattr(mujoco.mjtDisableBit, bit))
    if mjm.nq != mjm.nv or mjm.nv != len(scandyn_names):
        raise RuntimeError('MuJoCo model has nq %d nv %d, scandyn %d DoF' % (mjm.nq, mjm.nv, len(scandyn_names)))
    names = [mujoco.mj_id2name(mjm, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(mjm.njnt)]
    pos = {n: mjm.jnt_dofadr[j] for j, n in enumerate(names)}
    missing = [n for n in scandyn_names if n not in pos]
    if missing:
        raise RuntimeError('joints missing in the MuJoCo model: %s' % missing[:5])
    perm = np.array([pos[n] for n in scandyn_names])
    return mjm, perm


def to_mj(x, perm):
    """(B, nv) in scandyn's DoF order -> MuJoCo's."""
    y = np.empty_like(x)
    y[:, perm] = x
    return y


def from_mj(y, perm, algo):
    if algo == 'mass':
        return y[:, perm][:, :, perm]
    return y[:, perm]


timed = common.timed  # bench's timing procedure (common.py)


# ---- MuJoCo Warp ----------------------------------------------------------------------------------

class WarpRunner:
    library = 'mujoco-warp'

    def __init__(self, device):
        import warp as wp
        import mujoco_warp as mjw
        self.wp, self.mjw = wp, mjw
        wp.config.quiet = True
        wp.init()
        self.device = device
        self.version = 'mujoco-warp %s, warp %s' % (_version('mujoco-warp', mjw), wp.__version__)

    def prepare(self, mjm, algo, B, S=None):
        """S: dict of (B, nv) arrays in MuJoCo order (q, qd, qdd, tau); random if None."""
        wp, mjw = self.wp, self.mjw
        # put_model builds each leaf's ancestor chain recursively, one Python frame per tree level
        # (io.py); the default limit of 1000 frames stops it on a chain deeper than about 990 bodies
        sys.setrecursionlimit(max(sys.getrecursionlimit(), 2 * mjm.nbody + 1000))
        with wp.ScopedDevice(self.device):
            m = mjw.put_model(mjm)
            d = mjw.make_data(mjm, nworld=B)
            if S is None:
                rng = np.random.default_rng(42)
                S = {k: rng.uniform(-1, 1, (B, mjm.nv)) for k in ('q', 'qd', 'qdd', 'tau')}
            for field, k in (('qpos', 'q'), ('qvel', 'qd'), ('qacc', 'qdd'), ('qfrc_applied', 'tau')):
                getattr(d, field).assign(wp.array(S[k].astype(np.float32), dtype=float))
        seq = {
            'id': lambda: (mjw.kinematics(m, d), mjw.com_pos(m, d), mjw.com_vel(m, d), mjw.rne(m, d, flg_acc=True)),
            'bias': lambda: (mjw.kinematics(m, d), mjw.com_pos(m, d), mjw.com_vel(m, d), mjw.rne(m, d)),
            'mass': lambda: (mjw.kinematics(m, d), mjw.com_pos(m, d), mjw.crb(m, d)),
            'fd': lambda: (mjw.kinematics(m, d), mjw.com_pos(m, d), mjw.crb(m, d), mjw.factor_m(m, d),
                           mjw.com_vel(m, d), mjw.rne(m, d), mjw.fwd_acceleration(m, d)),
        }[algo]
        self.m, self.d, self.mjm, self.algo = m, d, mjm, algo
        with wp.ScopedDevice(self.device):
            seq()  # compiles the kernels (first use)
            wp.synchronize_device(self.device)
            self.graph = None
            if wp.get_device(self.device).is_cuda:
                with wp.ScopedCapture(device=self.device) as cap:
                    seq()
                self.graph = cap.graph
        self.strategy = 'graph' if self.graph is not None else 'launch'
        self.seq = seq

    def call(self):
        if self.graph is not None:
            self.wp.capture_launch(self.graph)
        else:
            with self.wp.ScopedDevice(self.device):
                self.seq()

    def sync(self):
        self.wp.synchronize_device(self.device)

    def result(self):
        d, m, nv = self.d, self.m, self.mjm.nv
        if self.algo in ('id', 'bias'):
            return d.qfrc_bias.numpy().astype(np.float64)
        if self.algo == 'fd':
            return d.qacc_smooth.numpy().astype(np.float64)
        Mcsr = d.M.numpy().astype(np.float64)
        rownnz, rowadr, colind = m.M_rownnz.numpy(), m.M_rowadr.numpy(), m.M_colind.numpy()
        out = np.zeros((Mcsr.shape[0], nv, nv))
        for i in range(nv):
            for k in range(rowadr[i], rowadr[i] + rownnz[i]):
                j = colind[k]
                out[:, i, j] = Mcsr[:, k]
                out[:, j, i] = Mcsr[:, k]
        return out


# ---- MJX (JAX) ------------------------------------------------------------------------------------

class MjxRunner:
    library = 'mujoco-mjx'

    def __init__(self, device, matmul_precision=''):
        import jax
        from mujoco import mjx
        self.jax, self.mjx = jax, mjx
        # JAX's default computes float32 matrix products in TF32 on Ampere and newer GPUs (10-bit
        # mantissa); 'highest' asks for float32 products, at whatever cost
        if matmul_precision:
            jax.config.update('jax_default_matmul_precision', matmul_precision)
        self.strategy = 'jit-vmap' + ('-' + matmul_precision if matmul_precision else '')
        self.dev = jax.devices('gpu' if device.startswith('cuda') else 'cpu')[0]
        self.version = 'mujoco-mjx %s (impl jax), jax %s' % (_version('mujoco-mjx', None), jax.__version__)

    def prepare(self, mjm, algo, B, S=None):
        jax, mjx = self.jax, self.mjx
        jnp = jax.numpy
        m = mjx.put_model(mjm, device=self.dev, impl='jax')
        d0 = mjx.make_data(m, device=self.dev, impl='jax')
        if S is None:
            rng = np.random.default_rng(42)
            S = {k: rng.uniform(-1, 1, (B, mjm.nv)) for k in ('q', 'qd', 'qdd', 'tau')}
        arrs = [jax.device_put(jnp.asarray(S[k], dtype=jnp.float32), self.dev) for k in ('q', 'qd', 'qdd', 'tau')]

        def one(q, qd, qdd, tau):
            d = d0.replace(qpos=q, qvel=qd, qacc=qdd, qfrc_applied=tau)
            d = mjx.kinematics(m, d)
            d = mjx.com_pos(m, d)
            if algo == 'mass':
                return mjx.full_m(m, mjx.crb(m, d))
            if algo == 'fd':
                d = mjx.factor_m(m, mjx.crb(m, d))
            d = mjx.com_vel(m, d)
            d = mjx.rne(m, d, flg_acc=(algo == 'id'))
            if algo == 'fd':
                return mjx.fwd_acceleration(m, d).qacc_smooth
            return d.qfrc_bias

        f = jax.jit(jax.vmap(one))
        self.out = None
        self.fn = lambda: f(*arrs)
        self.out = self.fn()
        self.out.block_until_ready()
        self.algo = algo

    def call(self):
        self.out = self.fn()

    def sync(self):
        self.out.block_until_ready()

    def result(self):
        return np.asarray(self.out, dtype=np.float64)


def _version(dist, mod):
    try:
        from importlib import metadata
        return metadata.version(dist)
    except Exception:  # noqa: BLE001
        return getattr(mod, '__version__', '?')


def check(runner, model, scandyn_names, ref, S, algos):
    """The equality check: runner's results on the states S (scandyn order) against ref."""
    mjm, perm = load_mjmodel(model, scandyn_names)
    Smj = {k: to_mj(v, perm) for k, v in S.items()}
    errs = {}
    for a in algos:
        runner.prepare(mjm, a, S['q'].shape[0], Smj)
        runner.call()
        runner.sync()
        errs[a] = common.rel_err(from_mj(runner.result(), perm, a), ref[a])
    return errs, mjm
