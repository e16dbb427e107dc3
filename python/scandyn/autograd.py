"""Analytical derivatives and differentiable dynamics: torch.autograd.Function and
jax.custom_vjp wrappers whose backward passes run scandyn's derivatives.

    import scandyn as sd, scandyn.autograd as ad, torch
    m = sd.load_model("iiwa")
    q = torch.zeros(8, m.nv, dtype=torch.float64, requires_grad=True)
    tau = ad.torch_inverse_dynamics(m, q, qd, qdd)        # backward: dtau/dq, dtau/dqd, M
    qdd = ad.torch_forward_dynamics(m, q, qd, tau)        # backward: dqdd/dq, dqdd/dqd, M^-1
    step = ad.StepDerivatives({"model": "iiwa", "dt": 1e-3, "effects": {"gravity": True}})
    q1, qd1 = ad.torch_step(step, q, qd, tau)             # backward: the step's Jacobian
    qs, qds = ad.torch_rollout(step, q0, qd0, taus)       # (T, B, nv); backward: the rollout's adjoint
    loss(qs, qds).backward()

The derivatives (Carpentier & Mansard 2018; the step's and the rollout's adjoint) are
the library's (scandyn/engine.hpp: make_id_derivatives, make_fd_derivatives;
scandyn/sim/step_derivatives.hpp), on host memory (CPU tensors and NumPy arrays,
float32 or float64; serial or openmp). The wrappers compute the values in forward and
the derivatives at the saved inputs in backward (first order: no double backward).
jax_* are the same through jax.custom_vjp and jax.pure_callback (CPU). docs/derivatives.md.
"""

import json
import os

import numpy as np

from . import _scandyn as _ext
from . import _api
from ._api import resolve_model_spec
from .errors import DeviceError, DTypeError


def _host(x, dtype=None):
    """A C-contiguous NumPy array of x (a CPU tensor is detached and shared, not copied)."""
    if hasattr(x, "detach"):
        x = x.detach()
        if x.device.type != "cpu":
            raise DeviceError("scandyn.autograd takes host arrays (CPU tensors)")
        x = x.numpy()
    a = np.ascontiguousarray(x, dtype=dtype)
    if a.dtype not in (np.float32, np.float64):
        raise DTypeError(f"arrays must be float32 or float64, got {a.dtype}")
    return a


def _backend(backend):
    return _api._resolve_backend(backend)


def _matrices(mats, q):
    """The (B, nv, nv) results shaped like q's leading dimensions."""
    lead = np.shape(q)[:-1]
    return tuple(m.reshape(lead + m.shape[-2:]) for m in mats)


# ---- the derivatives on NumPy arrays ----------------------------------------------


def id_derivatives(model, q, qd, qdd, backend="auto"):
    """(dtau/dq, dtau/dqd, M) of tau = ID(q, qd, qdd), gravity included: (B, nv, nv)
    each for (B, nv) inputs ((nv, nv) for (nv,)); entry [..., i, j] = d tau_i / d x_j."""
    q = _host(q)
    qd, qdd = _host(qd, q.dtype), _host(qdd, q.dtype)
    return _matrices(_ext.id_derivatives(model._m, q, qd, qdd, _backend(backend)), q)


def fd_derivatives(model, q, qd, tau, backend="auto"):
    """(qdd, dqdd/dq, dqdd/dqd, dqdd/dtau = M^-1) of qdd = FD(q, qd, tau) by the ABA."""
    q = _host(q)
    qd, tau = _host(qd, q.dtype), _host(tau, q.dtype)
    qdd, *mats = _ext.fd_derivatives(model._m, q, qd, tau, _backend(backend))
    return (qdd.reshape(q.shape),) + _matrices(mats, q)


class StepDerivatives:
    """The derivatives of one scene's simulator step and of its rollouts (the scene's
    model, effects, integrator and dt; its instances and initial state are not used).
    ``scene``: a scene file's path or a dict of its keys (as scandyn.Simulator). dtype:
    float64 (default) or float32. Covered: euler, rk4, implicit; gravity, damping,
    springs, limits, external wrenches (constant); contacts, prescribed motion, loops
    and multi-DoF joints raise BackendError naming them."""

    def __init__(self, scene, backend="auto", dtype=np.float64):
        if isinstance(scene, dict):
            scene = dict(scene)
            if isinstance(scene.get("model"), str):
                scene["model"] = resolve_model_spec(scene["model"])
            text, source, base = json.dumps(scene, allow_nan=False), "<scene dict>", os.getcwd()
        else:
            path = os.fspath(scene)
            with open(path) as f:
                text = f.read()
            source, base = path, os.path.dirname(os.path.abspath(path))
        self.dtype = np.dtype(dtype)
        cls = {np.dtype(np.float64): _ext.StepDerivatives64, np.dtype(np.float32): _ext.StepDerivatives32}.get(self.dtype)
        if cls is None:
            raise DTypeError(f"dtype must be float32 or float64, got {self.dtype}")
        self._s = cls(text, source, base, _backend(backend))

    nv = property(lambda self: self._s.nv)
    dt = property(lambda self: self._s.dt)

    def _in(self, *xs):
        return [_host(x, self.dtype) for x in xs]

    def jacobian(self, q, qd, tau):
        """(q', qd', J): the step from (q, qd) under tau, and J = d(q', qd') / d(q, qd,
        tau), (B, 2 nv, 3 nv) (rows q', qd'; columns q, qd, tau)."""
        q, qd, tau = self._in(q, qd, tau)
        qn, qdn, J = self._s.jacobian(q, qd, tau)
        lead = q.shape[:-1]
        return qn.reshape(q.shape), qdn.reshape(q.shape), J.reshape(lead + J.shape[-2:])

    def rollout(self, q0, qd0, tau):
        """(q, qd), each (T, B, nv): the states after each of the T steps of tau (T, B, nv)
        from (q0, qd0) (B, nv) ((nv,) and (T, nv) give (T, nv))."""
        q0, qd0, tau = self._in(q0, qd0, tau)
        if q0.ndim == 1:
            q, qd = self._s.rollout(q0[None], qd0[None], np.ascontiguousarray(tau[:, None]))
            return q[:, 0], qd[:, 0]
        return self._s.rollout(q0, qd0, tau)

    def rollout_vjp(self, q0, qd0, tau, gq, gqd):
        """(gq0, gqd0, gtau): the gradient of a loss L with dL/dq_t = gq, dL/dqd_t = gqd
        (T, B, nv), by the adjoint recursion (checkpointed: O(sqrt(T)) states kept)."""
        q0, qd0, tau, gq, gqd = self._in(q0, qd0, tau, gq, gqd)
        if q0.ndim == 1:
            g0, gd0, gt = self._s.vjp(q0[None], qd0[None], np.ascontiguousarray(tau[:, None]),
                                      np.ascontiguousarray(gq[:, None]), np.ascontiguousarray(gqd[:, None]))
            return g0[0], gd0[0], gt[:, 0]
        return self._s.vjp(q0, qd0, tau, gq, gqd)

    def rollout_jvp(self, q0, qd0, tau, dq0, dqd0, dtau):
        """(dq, dqd), each (T, B, nv): the trajectory's tangent along (dq0, dqd0, dtau)."""
        q0, qd0, tau, dq0, dqd0, dtau = self._in(q0, qd0, tau, dq0, dqd0, dtau)
        if q0.ndim == 1:
            dq, dqd = self._s.jvp(q0[None], qd0[None], np.ascontiguousarray(tau[:, None]), dq0[None], dqd0[None],
                                  np.ascontiguousarray(dtau[:, None]))
            return dq[:, 0], dqd[:, 0]
        return self._s.jvp(q0, qd0, tau, dq0, dqd0, dtau)


# ---- torch.autograd.Function --------------------------------------------------------

_TORCH = {}


def _torch_functions():
    if _TORCH:
        return _TORCH
    import torch

    def tensor(a, like):
        return torch.from_numpy(np.ascontiguousarray(a)).to(dtype=like.dtype, device=like.device)

    def vec_mat(g, m):  # g^T m over the leading dimensions: (..., n) x (..., n, k) -> (..., k)
        return torch.einsum("...i,...ij->...j", g, m)

    def dynamics_function(values, derivatives):
        """A Function (model, backend, q, qd, x) -> y = values(...) whose backward
        contracts g with derivatives(model, q, qd, x, backend) = (dy/dq, dy/dqd, dy/dx)."""

        class DynamicsFunction(torch.autograd.Function):
            @staticmethod
            def forward(ctx, model, backend, q, qd, x):
                ctx.model, ctx.backend = model, backend
                ctx.save_for_backward(q, qd, x)
                qh = _host(q)
                return tensor(values(model, qh, _host(qd, qh.dtype), _host(x, qh.dtype), backend=_backend(backend)), q)

            @staticmethod
            def backward(ctx, g):
                q, qd, x = ctx.saved_tensors
                mats = derivatives(ctx.model, q, qd, x, ctx.backend)
                return (None, None) + tuple(vec_mat(g, tensor(m, q)) if need else None
                                            for m, need in zip(mats, ctx.needs_input_grad[2:]))

        return DynamicsFunction

    InverseDynamicsFunction = dynamics_function(_api.inverse_dynamics, id_derivatives)
    ForwardDynamicsFunction = dynamics_function(_api.forward_dynamics, lambda *a: fd_derivatives(*a)[1:])

    class StepFunction(torch.autograd.Function):
        @staticmethod
        def forward(ctx, step, q, qd, tau):
            qn, qdn, J = step.jacobian(q, qd, tau)
            ctx.save_for_backward(tensor(J, q))
            ctx.nv = step.nv
            return tensor(qn, q), tensor(qdn, q)

        @staticmethod
        def backward(ctx, gq, gqd):
            (J,) = ctx.saved_tensors
            n = ctx.nv
            gz = vec_mat(torch.cat([gq, gqd], dim=-1), J)
            return None, gz[..., :n], gz[..., n:2 * n], gz[..., 2 * n:]

    class RolloutFunction(torch.autograd.Function):
        @staticmethod
        def forward(ctx, step, q0, qd0, tau):
            ctx.step = step
            ctx.save_for_backward(q0, qd0, tau)
            q, qd = step.rollout(q0, qd0, tau)
            return tensor(q, q0), tensor(qd, q0)

        @staticmethod
        def backward(ctx, gq, gqd):
            q0, qd0, tau = ctx.saved_tensors
            g0, gd0, gt = ctx.step.rollout_vjp(q0, qd0, tau, gq, gqd)
            return None, tensor(g0, q0), tensor(gd0, q0), tensor(gt, q0)

    _TORCH.update(id=InverseDynamicsFunction, fd=ForwardDynamicsFunction, step=StepFunction,
                  rollout=RolloutFunction)
    return _TORCH


def torch_inverse_dynamics(model, q, qd, qdd, backend="auto"):
    """tau = ID(q, qd, qdd) on CPU tensors, differentiable (backward: id_derivatives)."""
    return _torch_functions()["id"].apply(model, backend, q, qd, qdd)


def torch_forward_dynamics(model, q, qd, tau, backend="auto"):
    """qdd = FD(q, qd, tau) on CPU tensors, differentiable (backward: fd_derivatives)."""
    return _torch_functions()["fd"].apply(model, backend, q, qd, tau)


def torch_step(step, q, qd, tau):
    """(q', qd') = one simulator step of ``step`` (a StepDerivatives), differentiable
    (backward: the step's Jacobian)."""
    return _torch_functions()["step"].apply(step, q, qd, tau)


def torch_rollout(step, q0, qd0, tau):
    """(q, qd), each (T, B, nv) (or (T, nv)): T simulator steps under tau (T, B, nv),
    differentiable (backward: the rollout's adjoint, StepDerivatives.rollout_vjp)."""
    return _torch_functions()["rollout"].apply(step, q0, qd0, tau)


# ---- jax.custom_vjp -----------------------------------------------------------------


def _jax_dynamics(values, derivatives, out_dim):
    """A jax.custom_vjp function f(q, qd, x) -> y of shape (..., out_dim): values(q, qd,
    x) and derivatives(q, qd, x) -> (dq, dqd, dx) (..., out_dim, n) are NumPy callbacks."""
    import jax
    import jax.numpy as jnp

    def shape(q, *tail):
        return jax.ShapeDtypeStruct(q.shape[:-1] + tail, q.dtype)

    @jax.custom_vjp
    def f(q, qd, x):
        return jax.pure_callback(lambda a, b, c: np.asarray(values(a, b, c), a.dtype), shape(q, out_dim), q, qd, x)

    def fwd(q, qd, x):
        return f(q, qd, x), (q, qd, x)

    def bwd(res, g):
        q, qd, x = res
        mats = jax.pure_callback(lambda a, b, c: tuple(np.asarray(m, a.dtype) for m in derivatives(a, b, c)),
                                 (shape(q, out_dim, q.shape[-1]), shape(q, out_dim, qd.shape[-1]),
                                  shape(q, out_dim, x.shape[-1])), q, qd, x)
        return tuple(jnp.einsum("...i,...ij->...j", g, m) for m in mats)

    f.defvjp(fwd, bwd)
    return f


def jax_inverse_dynamics(model, q, qd, qdd, backend="auto"):
    """tau = ID(q, qd, qdd) for JAX arrays (CPU), differentiable by jax.grad / jax.vjp."""
    f = _jax_dynamics(lambda a, b, c: _api.inverse_dynamics(model, a, b, c, backend=_backend(backend)),
                      lambda a, b, c: id_derivatives(model, a, b, c, backend), model.nv)
    return f(q, qd, qdd)


def jax_forward_dynamics(model, q, qd, tau, backend="auto"):
    """qdd = FD(q, qd, tau) for JAX arrays (CPU), differentiable by jax.grad / jax.vjp."""
    f = _jax_dynamics(lambda a, b, c: _api.forward_dynamics(model, a, b, c, backend=_backend(backend)),
                      lambda a, b, c: fd_derivatives(model, a, b, c, backend)[1:], model.nv)
    return f(q, qd, tau)


def jax_rollout(step, q0, qd0, tau):
    """(q, qd) (T, B, nv) of T simulator steps for JAX arrays (CPU), differentiable
    (the rollout's adjoint)."""
    import jax

    out = jax.ShapeDtypeStruct(tau.shape[:1] + q0.shape, q0.dtype)

    @jax.custom_vjp
    def f(q0, qd0, tau):
        return jax.pure_callback(lambda a, b, c: step.rollout(a, b, c), (out, out), q0, qd0, tau)

    def fwd(q0, qd0, tau):
        return f(q0, qd0, tau), (q0, qd0, tau)

    def bwd(res, g):
        q0, qd0, tau = res
        return jax.pure_callback(lambda a, b, c, d, e: step.rollout_vjp(a, b, c, d, e),
                                 (jax.ShapeDtypeStruct(q0.shape, q0.dtype), jax.ShapeDtypeStruct(q0.shape, q0.dtype),
                                  jax.ShapeDtypeStruct(tau.shape, tau.dtype)), q0, qd0, tau, g[0], g[1])

    f.defvjp(fwd, bwd)
    return f(q0, qd0, tau)


__all__ = [
    "StepDerivatives", "fd_derivatives", "id_derivatives", "jax_forward_dynamics", "jax_inverse_dynamics",
    "jax_rollout", "torch_forward_dynamics", "torch_inverse_dynamics", "torch_rollout", "torch_step",
]
