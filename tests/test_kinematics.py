"""DH forward kinematics vs the MuJoCo model built from the same table, and vs the
published UR3 kinematics (also through an exported MJCF)."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from calib import se3
from calib.dh import NOMINAL_TABLES, DHDeltas, forward_kinematics
from twin.phantoms import PhantomConfig, build_phantom, build_tank
from twin.scene import Scene, SceneModel, export_scene
from twin.tools import ToolsConfig

from .conftest import perturbed_table

N_CONFIGS = 1000
POS_TOL_M = 1e-9
ROT_TOL_RAD = 1e-9


def scene_for(table) -> Scene:
    pc = PhantomConfig()
    return Scene(
        table, ToolsConfig(), build_phantom(pc), pc.T_base_phantom, build_tank(pc), pc.T_base_tank
    )


@pytest.mark.parametrize("model", ["ur3", "ur3e"])
@pytest.mark.parametrize("perturbed", [False, True], ids=["nominal", "perturbed"])
def test_mujoco_matches_dh_fk(rng, model, perturbed):
    table = perturbed_table(rng, model) if perturbed else NOMINAL_TABLES[model]
    sm = SceneModel(scene_for(table))
    q = rng.uniform(-2 * np.pi, 2 * np.pi, (N_CONFIGS, 6))
    T_dh = forward_kinematics(table, q)
    T_mj = np.array([sm.flange_pose(qi) for qi in q])
    assert np.max(se3.translation_distance(T_mj, T_dh)) < POS_TOL_M
    assert np.max(se3.rotation_angle(T_mj, T_dh)) < ROT_TOL_RAD


def test_perturbation_changes_the_arm(rng):
    """Sanity check that the comparison above can fail: deltas move the flange by mm."""
    table = perturbed_table(rng)
    q = rng.uniform(-np.pi, np.pi, (100, 6))
    d = se3.translation_distance(
        forward_kinematics(table, q), forward_kinematics(NOMINAL_TABLES["ur3"], q)
    )
    assert np.median(d) > 1e-3


# Published UR3 kinematics: at zero joint angles tool0 sits at (a2 + a3, -(d4 + d6), d1 - d5)
# with rotation Rx(90°); straight up (q2 = q4 = -90°) at height d1 - a2 - a3 + d5.
PUBLISHED_UR3 = [
    (np.zeros(6), [-0.45690, -0.19425, 0.06655], [[1, 0, 0], [0, 0, -1], [0, 1, 0]]),
    (
        np.radians([0, -90, 0, -90, 0, 0]),
        [0.0, -0.19425, 0.69415],
        [[-1, 0, 0], [0, 0, -1], [0, -1, 0]],
    ),
]


@pytest.mark.parametrize("q,p,R", PUBLISHED_UR3)
def test_dh_fk_reproduces_published_ur3(q, p, R):
    T = forward_kinematics(NOMINAL_TABLES["ur3"], q)
    np.testing.assert_allclose(T[:3, 3], p, atol=1e-12)
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-12)


def test_exported_mjcf_reproduces_published_ur3(tmp_path, rng):
    files = export_scene(scene_for(NOMINAL_TABLES["ur3"]), tmp_path)
    assert "scene.xml" in files and any(f.endswith(".stl") for f in files)
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "scene.xml"))
    data = mujoco.MjData(model)
    # The six arm hinges are the first six joints, in order from the base.
    assert [model.joint(i).name for i in range(6)] == [f"joint{i}" for i in range(1, 7)]
    assert all(model.jnt_type[i] == mujoco.mjtJoint.mjJNT_HINGE for i in range(6))
    ee = model.site("ee").id
    for q, p, R in PUBLISHED_UR3:
        data.qpos[:6] = q
        mujoco.mj_kinematics(model, data)
        np.testing.assert_allclose(data.site_xpos[ee], p, atol=1e-9)
        np.testing.assert_allclose(data.site_xmat[ee].reshape(3, 3), R, atol=1e-9)
    # And everywhere else: the exported model is the DH model.
    for q in rng.uniform(-np.pi, np.pi, (200, 6)):
        data.qpos[:6] = q
        mujoco.mj_kinematics(model, data)
        T = forward_kinematics(NOMINAL_TABLES["ur3"], q)
        np.testing.assert_allclose(data.site_xpos[ee], T[:3, 3], atol=1e-9)


def test_dh_deltas_rms_and_round_trip(rng):
    arr = rng.normal(size=(6, 4))
    deltas = DHDeltas.from_array(arr)
    np.testing.assert_allclose(deltas.as_array(), arr)
    np.testing.assert_allclose(deltas.rms(), np.sqrt(np.mean(arr**2, axis=0)))
    table = NOMINAL_TABLES["ur3"].with_deltas(deltas)
    np.testing.assert_allclose(table.as_array() - NOMINAL_TABLES["ur3"].as_array(), arr)
