"""Every function against the C++ serial reference: bit-identical to `scandyn eval`
on the same backend and precision, serial vs OpenMP bit-identical where the engine
says it runs the reference's arithmetic (Engine::exact), and identities:
ID(FD(tau)) = tau, M symmetric positive definite, M qdd + h = ID, float32 close to
float64."""

import numpy as np
import pytest

import scandyn as sd
from conftest import DTYPES, states, run_cli

B = 37  # not a multiple of anything: uneven blocks per thread


def all_four(model, q, qd, qdd, tau, backend):
    return {
        "id": sd.inverse_dynamics(model, q, qd, qdd, backend=backend),
        "bias": sd.bias_forces(model, q, qd, backend=backend),
        "mass": sd.mass_matrix(model, q, backend=backend),
        "fd": sd.forward_dynamics(model, q, qd, tau, backend=backend),
    }


@pytest.mark.parametrize("dtype", DTYPES)
def test_shapes_and_dtypes(model, dtype):
    q, qd, qdd, tau = states(model, B, dtype)
    r = all_four(model, q, qd, qdd, tau, "auto")
    nv = model.nv
    for k in ("id", "bias", "fd"):
        assert r[k].shape == (B, nv) and r[k].dtype == dtype and r[k].flags.c_contiguous
    assert r["mass"].shape == (B, nv, nv) and r["mass"].dtype == dtype
    for v in r.values():
        assert np.isfinite(v).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_single_state_matches_batch_row(model, dtype):
    q, qd, qdd, tau = states(model, 3, dtype)
    r = all_four(model, q, qd, qdd, tau, "serial")
    one = all_four(model, q[1], qd[1], qdd[1], tau[1], "serial")
    for k in r:
        assert one[k].shape == r[k].shape[1:]
        np.testing.assert_array_equal(one[k], r[k][1])


@pytest.mark.parametrize("dtype", DTYPES)
def test_serial_vs_openmp_bit_identical(model, dtype):
    q, qd, qdd, tau = states(model, B, dtype, seed=1)
    serial = all_four(model, q, qd, qdd, tau, "serial")
    openmp = all_four(model, q, qd, qdd, tau, "openmp")
    engines = {
        "id": sd.InverseDynamics(model, backend="openmp", max_batch=B, dtype=dtype),
        "bias": sd.BiasForces(model, backend="openmp", max_batch=B, dtype=dtype),
        "mass": sd.MassMatrix(model, backend="openmp", max_batch=B, dtype=dtype),
        "fd": sd.ForwardDynamics(model, backend="openmp", max_batch=B, dtype=dtype),
    }
    for k in serial:
        if engines[k].exact:
            np.testing.assert_array_equal(openmp[k], serial[k], err_msg=k)
        else:  # a different association order (scans): close
            tol = 1e-9 if dtype == np.float64 else 2e-3
            np.testing.assert_allclose(openmp[k], serial[k], rtol=tol, atol=tol, err_msg=k)


@pytest.mark.parametrize("precision,dtype", [("double", np.float64), ("float", np.float32)])
def test_bit_identical_to_cli(cli, model, tmp_path, precision, dtype):
    """The module and `scandyn eval` (17 significant digits: exact for both precisions)
    on the serial backend give the same bits."""
    q, qd, qdd, tau = states(model, 9, dtype, seed=2)
    out = run_cli(cli, model.source, {"q": q, "qd": qd, "qdd": qdd, "tau": tau}, "id,fd,mass,bias",
                  tmp_path, backend="serial", precision=precision)
    r = all_four(model, q, qd, qdd, tau, "serial")
    nv = model.nv
    col = lambda prefix: np.stack([out[f"{prefix}_{i}"] for i in range(nv)], axis=1).astype(dtype)
    np.testing.assert_array_equal(r["id"], col("tau_id"))
    np.testing.assert_array_equal(r["fd"], col("qdd_fd"))
    np.testing.assert_array_equal(r["bias"], col("h"))
    M = np.stack([out[f"M_{i}_{j}"] for i in range(nv) for j in range(nv)], axis=1).reshape(-1, nv, nv)
    np.testing.assert_array_equal(r["mass"], M.astype(dtype))


def test_cli_and_module_agree_on_model(cli, model):
    import subprocess

    text = subprocess.run([cli, "info", "--model", model.source], check=True, capture_output=True,
                          text=True).stdout
    for name in model.joint_names:
        assert name in text
    assert f"{model.nv}" in text


@pytest.mark.parametrize("dtype", DTYPES)
def test_identities(model, dtype):
    q, qd, qdd, tau = states(model, B, dtype, seed=3)
    r = all_four(model, q, qd, qdd, tau, "auto")
    M, h = r["mass"].astype(np.float64), r["bias"].astype(np.float64)
    scale = 1.0 + np.abs(r["id"]).max()
    # M symmetric (both triangles written by the same arithmetic) and positive definite
    np.testing.assert_array_equal(r["mass"], np.swapaxes(r["mass"], 1, 2))
    assert (np.linalg.eigvalsh(M) > 0).all()
    # ID(q, qd, qdd) = M qdd + h
    tol = 1e-10 if dtype == np.float64 else 2e-3
    np.testing.assert_allclose(np.einsum("bij,bj->bi", M, qdd.astype(np.float64)) + h, r["id"],
                               rtol=0, atol=tol * scale)
    # ID(FD(tau)) = tau
    back = sd.inverse_dynamics(model, q, qd, r["fd"])
    np.testing.assert_allclose(back, tau, rtol=0, atol=(1e-9 if dtype == np.float64 else 5e-2) * scale)


def test_float32_close_to_float64(model):
    q, qd, qdd, tau = states(model, B, np.float64, seed=4)
    d = all_four(model, q, qd, qdd, tau, "auto")
    f = all_four(model, *(a.astype(np.float32) for a in (q, qd, qdd, tau)), "auto")
    for k in ("id", "bias", "mass"):
        scale = np.abs(d[k]).max()
        np.testing.assert_allclose(f[k], d[k], rtol=0, atol=1e-4 * scale, err_msg=k)


@pytest.mark.parametrize("dtype", DTYPES)
def test_fext(model, dtype):
    """External wrenches: bias(q, qd, fext) + M qdd = ID(q, qd, qdd, fext), FD(ID(fext), fext) = qdd,
    and fext changes the result (it is read)."""
    q, qd, qdd, tau = states(model, 5, dtype, seed=5)
    fext = np.random.default_rng(6).uniform(-1, 1, (5, model.nv, 6)).astype(dtype)
    t0 = sd.inverse_dynamics(model, q, qd, qdd)
    t1 = sd.inverse_dynamics(model, q, qd, qdd, fext=fext)
    assert np.abs(t1 - t0).max() > 1e-3
    h1 = sd.bias_forces(model, q, qd, fext=fext)
    M = sd.mass_matrix(model, q)
    tol = 1e-10 if dtype == np.float64 else 2e-3
    scale = 1.0 + np.abs(t1).max()
    np.testing.assert_allclose(np.einsum("bij,bj->bi", M, qdd) + h1, t1, rtol=0, atol=tol * scale)
    qdd1 = sd.forward_dynamics(model, q, qd, t1, fext=fext)
    back = sd.inverse_dynamics(model, q, qd, qdd1, fext=fext)
    np.testing.assert_allclose(back, t1, rtol=0, atol=(1e-9 if dtype == np.float64 else 5e-2) * scale)
    # one state with (nv, 6)
    np.testing.assert_array_equal(
        sd.inverse_dynamics(model, q[2], qd[2], qdd[2], fext=fext[2], backend="serial"),
        sd.inverse_dynamics(model, q, qd, qdd, fext=fext, backend="serial")[2])


@pytest.mark.parametrize("method", ["aba", "jsi"])
def test_fd_methods(model, method):
    q, qd, qdd, tau = states(model, B, np.float64, seed=7)
    ref = sd.forward_dynamics(model, q, qd, tau, method="aba", backend="serial")
    got = sd.forward_dynamics(model, q, qd, tau, method=method, backend="openmp")
    np.testing.assert_allclose(got, ref, rtol=1e-8, atol=1e-8)
    e = sd.ForwardDynamics(model, method=method, max_batch=B)
    assert e.method == method


def test_fd_parallel_on_a_chain():
    m = sd.load_model("rope:64")
    q, qd, qdd, tau = states(m, 4, np.float64, seed=8)
    ref = sd.forward_dynamics(m, q, qd, tau, method="aba")
    got = sd.forward_dynamics(m, q, qd, tau, method="parallel")
    np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_engines_reused_and_grown():
    m = sd.load_model("iiwa")
    q, qd, qdd, tau = states(m, 8, np.float64)
    sd.inverse_dynamics(m, q, qd, qdd)
    (e,) = [v for k, v in m._engines.items() if k[0] == "InverseDynamics"]
    sd.inverse_dynamics(m, q[:3], qd[:3], qdd[:3])
    assert [v for k, v in m._engines.items() if k[0] == "InverseDynamics"] == [e]  # reused
    q2, qd2, qdd2, _ = states(m, 20, np.float64)
    sd.inverse_dynamics(m, q2, qd2, qdd2)
    (e2,) = [v for k, v in m._engines.items() if k[0] == "InverseDynamics"]
    assert e2 is not e and e2.max_batch == 20
    m.clear_cache()
    assert not m._engines


def test_engine_classes(model):
    q, qd, qdd, tau = states(model, 6, np.float32)
    idf = sd.InverseDynamics(model, backend="serial", max_batch=6, dtype=np.float32)
    assert idf.backend == "serial" and idf.dtype == np.float32 and idf.nv == model.nv and idf.exact
    np.testing.assert_array_equal(idf(q, qd, qdd), sd.inverse_dynamics(model, q, qd, qdd, backend="serial"))
    assert "InverseDynamics" in repr(idf)
    for strategy in ("recursion", "scan-local", "scan-world"):
        e = sd.InverseDynamics(model, backend="openmp", max_batch=6, dtype="float64", strategy=strategy)
        assert e.strategy.split("-simd")[0] == strategy  # recursion-simd<W>: the CPU SIMD path
        q64, qd64, qdd64, _ = states(model, 6, np.float64)
        np.testing.assert_allclose(e(q64, qd64, qdd64), sd.inverse_dynamics(model, q64, qd64, qdd64),
                                   rtol=1e-9, atol=1e-9)


def test_lists_are_accepted():
    m = sd.load_model("iiwa")
    z = [0.0] * m.nv
    tau = sd.inverse_dynamics(m, z, z, z)
    assert tau.shape == (m.nv,) and tau.dtype == np.float64
    np.testing.assert_array_equal(tau, sd.bias_forces(m, np.zeros(m.nv), np.zeros(m.nv)))
