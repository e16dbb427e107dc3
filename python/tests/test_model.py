"""Models from Python: names, DoF order, the shipped models, and loading errors."""

import os

import numpy as np
import pytest

import scandyn as sd


def test_iiwa():
    m = sd.load_model("iiwa")
    assert m.nv == 7 and m.name == "iiwa14"
    assert m.joint_names == [f"iiwa_joint_{i}" for i in range(1, 8)]
    assert m.parents == [-1, 0, 1, 2, 3, 4, 5]
    assert m.joint_types == ["revolute"] * 7
    assert m.q_lower.shape == (7,) and (m.q_lower < m.q_upper).all()
    np.testing.assert_array_equal(m.gravity, [0, 0, -9.81])
    assert "iiwa14" in repr(m)


def test_same_model_by_name_path_and_package_path():
    a = sd.load_model("iiwa")
    b = sd.load_model(sd.models.path("iiwa"))
    c = sd.load_model("iiwa.urdf")
    q = np.linspace(-1, 1, 7)
    for m in (b, c):
        assert m.joint_names == a.joint_names
        np.testing.assert_array_equal(sd.mass_matrix(m, q), sd.mass_matrix(a, q))


def test_shipped_models():
    assert {"iiwa", "hyq", "atlas"} <= set(sd.models.names())
    assert os.path.isfile(sd.models.path("hyq"))
    with pytest.raises(sd.ModelError, match="no shipped model"):
        sd.models.path("nope")


def test_generators():
    m = sd.load_model("rope:1000")
    assert m.nv == 1000 and m.parents[:3] == [-1, 0, 1]
    t = sd.load_model("tree:30:7")
    assert t.nv == 30 and all(p < i for i, p in enumerate(t.parents))


def test_hyq_is_a_tree():
    m = sd.load_model("hyq")
    assert m.nv == 12 and m.parents.count(-1) >= 1 and all(p < i for i, p in enumerate(m.parents))


def test_missing_file():
    with pytest.raises(sd.ModelError) as e:
        sd.load_model("/nonexistent/robot.urdf")
    assert "/nonexistent/robot.urdf" in str(e.value)
    assert isinstance(e.value, ValueError) and isinstance(e.value, sd.Error)


def test_bad_generator_spec():
    with pytest.raises(sd.ModelError, match="rope:0"):
        sd.load_model("rope:0")


def test_nonphysical_inertia():
    with pytest.raises(sd.ModelError, match="not positive definite"):
        sd.load_model("atlas")
    m = sd.load_model("atlas", allow_nonphysical_inertia=True)
    assert m.nv > 20


def test_malformed_urdf(tmp_path):
    p = tmp_path / "bad.urdf"
    p.write_text("<robot name='x'><link name='a'/><joint name='j' type='revolute'>")
    with pytest.raises(sd.ModelError, match="bad.urdf"):
        sd.load_model(str(p))
