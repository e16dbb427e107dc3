"""The simulation step of a quadruped standing on a ground plane: MuJoCo Warp beside scandyn, same GPU.

    python3 bench/compare/mujoco_step.py --scandyn build-gpu/scandyn --out OUT.csv
        [--scene scenes/hyq_floating.json] [--instances 1000000 ...] [--min-time 0.5] [--device cuda:0]

Rows (bench/compare/common.py's columns, algo `step`, evals_per_second = instance-steps per
second): for each instance count, scandyn's step of the scene (`scandyn bench --algo step --scene`,
cuda, float) and of the same scene without its "contacts" key, then MuJoCo Warp's step of the
equivalent MuJoCo model with and without contacts.

The MuJoCo model, built from the scene's own keys (a floating-base model whose contacts are
points on links against planes):
- the model's URDF through MuJoCo's URDF importer as mujoco_peer.load_mjmodel reads it (visuals
  and collisions removed, fixed joints fused), its root body on a free joint; gravity (0, 0,
  -9.81); the scene's dt; integrator implicitfast (scandyn's implicit: damping and contacts
  linearised); joint damping as the scene's "damping";
- one sphere geom per contact point (the point's link, position and radius; no mass), colliding
  with the planes only (contype / conaffinity), condim 3, the scene's friction; one plane geom per
  plane (normal +z only);
- zero torques; the scene's initial q plus the uniform noise its "random" block declares (drawn
  here by NumPy, not scandyn's generator: the same distribution, other draws).
What differs, and the table says so: MuJoCo's contacts are soft constraints (default solref /
solimp, pyramidal friction cones) solved every step by its Newton solver (default iterations and
tolerance); scandyn's are a compliant spring-damper with regularised Coulomb friction and no
solver (docs/scenes.md). MuJoCo's joint limits are constraints at the URDF's ranges; scandyn's
the scene's spring-dampers. So the rows compare the cost of a step of the same robot in the same
situation, not the same numbers; the note of each MuJoCo row gives its mean contacts per world
and mean base height after the timed steps, so that a reader sees that both stand on the plane.

Timing: MuJoCo Warp's step is captured once as a CUDA graph (its solver loops as conditional
nodes) and the graph is launched back to back (common.timed, scandyn bench's procedure); the
state stays on the device. scandyn's rows come from its bench command with --min-time the same.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

import common
import mujoco_peer

HERE = os.path.dirname(os.path.abspath(__file__))


def scene_model_path(scene, scene_path):
    m = scene['model']
    if os.path.isabs(m) or os.path.exists(m):
        return m
    for d in (os.path.dirname(os.path.abspath(scene_path)), common.models_dir()):
        p = os.path.join(d, m)
        if os.path.exists(p):
            return p
    raise FileNotFoundError('%s: model %s not found beside the scene or in %s' % (scene_path, m, common.models_dir()))


def scandyn_q_layout(scandyn, urdf):
    """[(joint name, q index)] of the joints past the free base, from `scandyn info --floating-base`."""
    out = subprocess.run([scandyn, 'info', '--model', urdf, '--floating-base'], check=True, capture_output=True,
                         text=True).stdout
    lines = out.splitlines()
    start = next(i for i, l in enumerate(lines) if l.startswith('index'))
    joints = []
    for l in lines[start + 1:]:
        if not l.strip():
            break
        f = l.split()
        if f[4] != 'free':
            joints.append((f[3], int(f[1])))
    return joints


def build_mjmodel(scene, urdf, contacts):
    """The scene as a MuJoCo model (see the module comment); contacts=False: the contact flag off."""
    import mujoco
    effects = scene.get('effects', {})
    c = effects.get('contacts')
    if scene.get('base') != 'floating' or not c:
        raise ValueError('mujoco_step.py takes a floating-base scene with contacts')
    if c.get('spheres') or c.get('all_links'):
        raise ValueError('mujoco_step.py: only contact points against planes are translated')
    spec = mujoco.MjSpec.from_string(mujoco_peer.urdf_for_mujoco(urdf))
    root = spec.worldbody.bodies[0]
    root.add_freejoint()
    for pl in c.get('planes', []):
        n = pl['normal']
        if abs(n[0]) > 0 or abs(n[1]) > 0 or n[2] <= 0:
            raise ValueError('mujoco_step.py: planes with normal +z only (got %s)' % n)
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], pos=[0, 0, pl.get('offset', 0.0) / n[2]],
                                contype=0, conaffinity=1, condim=3)
    bodies = {b.name: b for b in spec.bodies}
    mu = c.get('friction', 0.0)
    for p in c['points']:
        if p['link'] not in bodies:
            raise ValueError('mujoco_step.py: link %s is not a MuJoCo body (fused?)' % p['link'])
        bodies[p['link']].add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[p.get('radius', 0.0), 0, 0],
                                   pos=p.get('position', [0, 0, 0]), contype=1, conaffinity=0, condim=3,
                                   friction=[mu, 0.005, 0.0001], density=0, mass=0)
    spec.option.timestep = scene['dt']
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.gravity = [0, 0, -9.81] if effects.get('gravity') else [0, 0, 0]
    if not contacts:
        spec.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    mjm = spec.compile()
    damping = effects.get('damping', 0.0)
    if not np.isscalar(damping):
        raise ValueError('mujoco_step.py: a per-DoF damping list is not translated')
    mjm.dof_damping[6:] = damping  # the joints past the free base
    return mjm


def initial_qpos(scene, mjm, layout, B, seed):
    """(B, nq) MuJoCo qpos from the scene's initial q and random block (scandyn q: p, quaternion x y z w, joints)."""
    import mujoco
    init = scene.get('initial', {})
    q0 = np.asarray(init.get('q'), dtype=np.float64)
    rnd = init.get('random', {})
    rng = np.random.default_rng(seed)
    nv = len(q0) - 1
    rq = np.asarray(rnd.get('q', [0.0] * nv), dtype=np.float64)
    rqd = np.asarray(rnd.get('qd', [0.0] * nv), dtype=np.float64)
    # scandyn's random q block has nv entries: the base's 6 (position, rotation) then the joints'
    qs = np.tile(q0, (B, 1))
    qs[:, :3] += rng.uniform(-1, 1, (B, 3)) * rq[:3]
    qs[:, 7:] += rng.uniform(-1, 1, (B, nv - 6)) * rq[6:]
    if np.any(rq[3:6]):
        raise ValueError('mujoco_step.py: a random base rotation is not translated')
    qpos = np.zeros((B, mjm.nq))
    qpos[:, 0:3] = qs[:, 0:3]
    qpos[:, 3] = qs[:, 6]        # w
    qpos[:, 4:7] = qs[:, 3:6]    # x y z
    for name, iq in layout:
        j = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_JOINT, name)
        if j < 0:
            raise ValueError('joint %s not in the MuJoCo model' % name)
        qpos[:, mjm.jnt_qposadr[j]] = qs[:, iq]
    qvel = np.zeros((B, mjm.nv))
    qvel[:, :6] = rng.uniform(-1, 1, (B, 6)) * rqd[:6]
    for name, iq in layout:
        j = mujoco.mj_name2id(mjm, mujoco.mjtObj.mjOBJ_JOINT, name)
        qvel[:, mjm.jnt_dofadr[j]] = rng.uniform(-1, 1, B) * rqd[iq - 1]
    return qpos, qvel


class WarpStep:
    """MuJoCo Warp's mjw.step over B worlds, captured as a CUDA graph."""

    def __init__(self, mjm, qpos, qvel, device, nconmax, njmax):
        import warp as wp
        import mujoco_warp as mjw
        wp.config.quiet = True
        wp.init()
        self.wp, self.mjw, self.device = wp, mjw, device
        B = qpos.shape[0]
        with wp.ScopedDevice(device):
            self.m = mjw.put_model(mjm)
            self.d = mjw.make_data(mjm, nworld=B, nconmax=nconmax, njmax=njmax)
            self.d.qpos.assign(wp.array(qpos.astype(np.float32), dtype=float))
            self.d.qvel.assign(wp.array(qvel.astype(np.float32), dtype=float))
            mjw.step(self.m, self.d)  # compiles the kernels
            wp.synchronize_device(device)
            self.graph = None
            if wp.get_device(device).is_cuda:
                with wp.ScopedCapture(device=device) as cap:
                    mjw.step(self.m, self.d)
                self.graph = cap.graph
        self.strategy = 'graph' if self.graph is not None else 'launch'
        self.steps = 1  # steps taken from the initial state (the first compiled the kernels)
        self.version = 'mujoco-warp %s, warp %s' % (mujoco_peer._version('mujoco-warp', mjw), wp.__version__)

    def call(self):
        self.steps += 1
        if self.graph is not None:
            self.wp.capture_launch(self.graph)
        else:
            with self.wp.ScopedDevice(self.device):
                self.mjw.step(self.m, self.d)

    def sync(self):
        self.wp.synchronize_device(self.device)

    def stats(self):
        """(mean contacts per world, mean base height, fraction of finite states)."""
        qpos = self.d.qpos.numpy()
        nacon = int(self.d.nacon.numpy()[0])
        finite = np.isfinite(qpos).all(axis=1)
        return nacon / qpos.shape[0], float(np.mean(qpos[finite, 2])) if finite.any() else float('nan'), float(finite.mean())


def scandyn_row(scandyn, scene_path, B, min_time, tmp):
    csv_path = os.path.join(tmp, 'bench.csv')
    if os.path.exists(csv_path):
        os.remove(csv_path)
    cmd = [scandyn, 'bench', '--algo', 'step', '--scene', scene_path, '--backend', 'cuda', '--precision', 'float',
           '--instances', str(B), '--min-time', str(min_time), '--csv', csv_path]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError('%s: exit %d: %s' % (' '.join(cmd), r.returncode, r.stderr.strip()[-400:]))
    import csv
    with open(csv_path) as fh:
        rows = list(csv.DictReader(fh))
    return rows[-1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--scandyn', required=True)
    ap.add_argument('--out', required=True)
    ap.add_argument('--scene', default=os.path.join(common.REPO, 'scenes', 'hyq_floating.json'))
    ap.add_argument('--instances', type=int, nargs='+', default=[10000, 1000000])
    ap.add_argument('--min-time', type=float, default=0.5)
    ap.add_argument('--device', default='cuda:0')
    ap.add_argument('--nconmax', type=int, default=8, help='MuJoCo Warp contacts per world (allocation)')
    ap.add_argument('--njmax', type=int, default=64, help='MuJoCo Warp constraint rows per world (allocation)')
    ap.add_argument('--skip-scandyn', action='store_true')
    args = ap.parse_args()
    scene = json.load(open(args.scene))
    urdf = scene_model_path(scene, args.scene)
    layout = scandyn_q_layout(args.scandyn, urdf)
    rows = common.Rows(args.out)
    name = os.path.splitext(os.path.basename(urdf))[0]
    links = 6 + len(layout)
    with tempfile.TemporaryDirectory() as tmp:
        bare = dict(scene, effects={k: v for k, v in scene['effects'].items() if k != 'contacts'})
        bare_path = os.path.join(tmp, 'no_contacts.json')
        json.dump(bare, open(bare_path, 'w'))
        for B in args.instances:
            if not args.skip_scandyn:
                for path, what in ((args.scene, 'with contacts'), (bare_path, 'without contacts')):
                    try:
                        r = scandyn_row(args.scandyn, path, B, args.min_time, tmp)
                        rows.add(algo='step', strategy=r['strategy'], backend='cuda', precision='float', model=name,
                                 links=links, instances=B, seconds_per_call=float(r['seconds_per_call']),
                                 library='scandyn', version='scandyn bench',
                                 note='%s (%s)' % (what, os.path.basename(args.scene)))
                    except Exception as e:  # noqa: BLE001
                        rows.add(algo='step', backend='cuda', precision='float', model=name, links=links,
                                 instances=B, library='scandyn', note='failed: %s' % str(e)[:300])
            for contacts in (True, False):
                what = 'with contacts' if contacts else 'without contacts'
                try:
                    mjm = build_mjmodel(scene, urdf, contacts)
                    qpos, qvel = initial_qpos(scene, mjm, layout, B, seed=scene.get('initial', {}).get('random', {}).get('seed', 0))
                    ws = WarpStep(mjm, qpos, qvel, args.device, args.nconmax, args.njmax)
                    t = common.timed(ws.call, ws.sync, args.min_time)
                    ncon, z, finite = ws.stats()
                    rows.add(algo='step', strategy='%s:implicitfast' % ws.strategy, backend='cuda', precision='float',
                             model=name, links=links, instances=B, seconds_per_call=t, library='mujoco-warp',
                             version=ws.version,
                             note='%s; after %d steps %.2f contacts per world, mean base height %.3f m, '
                                  '%.4f of the worlds finite' % (what, ws.steps, ncon, z, finite))
                    del ws
                except Exception as e:  # noqa: BLE001
                    rows.add(algo='step', backend='cuda', precision='float', model=name, links=links, instances=B,
                             library='mujoco-warp', note='%s: failed: %s' % (what, str(e).splitlines()[0][:300]))
    return 0


if __name__ == '__main__':
    sys.exit(main())
