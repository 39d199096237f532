"""Touch measurements and the touch-based DH refinement (calib/kinematics.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.acquire_sim import make_twin, simulate_touches
from bench.config.error_sources import ERROR_SOURCES
from bench.config.scenario import load_scenario
from bench.sessions import dataset_rngs, dataset_scenario
from calib import se3
from calib.acquisition.protocol import touch_plan
from calib.calibration.markers import Observation
from calib.calibration.uncertainty import _gauge_free_displacements
from calib.dh import NOMINAL_TABLES, forward_kinematics
from calib.kinematics import (
    _set_jacobian,
    _set_residuals,
    _touch_set,
    deltas_from_z,
    fit_reference,
    identifiability,
    kinematic_gauge,
    kinematic_modes,
    refine_dh,
    tip_positions,
)
from calib.records import Sweep, Touch

MM = 1e-3
TIP_CAD = np.array([0.0, 0.0, 0.165])
# Every declared error source off but the arm's DH errors (what the refinement recovers).
NOISE_FREE = [
    f"{key}={json.dumps(value)}"
    for s in ERROR_SOURCES
    if s.name != "kinematics"
    for key, value in s.off
]


def touches_of(overrides):
    """Touches of three datasets (new placement each) of the paper scenario's robot."""
    scenario = load_scenario("scenarios/paper.yaml", overrides, check_reach=False)
    sets, twins = [], []
    for i in range(3):
        sc = dataset_scenario(scenario, i)
        rngs = dataset_rngs(scenario, i)
        twin = make_twin(sc, rngs["touch_joints"])
        sets.append(simulate_touches(sc, twin, rngs["touch_contact"]))
        twins.append(twin)
    cad = {k: v for k, v in twins[0].phantom_cad.landmarks.items() if k.startswith("vertex_")}
    return scenario, sets, twins, cad


@pytest.fixture(scope="module")
def noise_free():
    return touches_of(NOISE_FREE)


def test_touch_plan_tilts_and_spreads_orientations():
    scenario = load_scenario("scenarios/paper.yaml", [], check_reach=False)
    lean = {"vertex_1": [1.0, 0.0, 0.0]}
    plan = touch_plan(["vertex_1", "vertex_2"], scenario.protocol, lean=lean)
    assert len(plan) == 2 * scenario.protocol.touches_per_vertex
    for p in plan:
        axis = p.R_base_ee[:, 2]  # the stylus runs along the flange z axis
        tilt = np.degrees(np.arccos(-axis[2]))
        assert tilt == pytest.approx(scenario.protocol.touch_tilt_deg, abs=1e-9)
    # Leaning towards +x: the flange sits on the +x side of the tip for every touch.
    for p in plan[: scenario.protocol.touches_per_vertex]:
        assert -p.R_base_ee[0, 2] > 0
    # Six distinct orientations per vertex.
    T = [se3.make(p.R_base_ee, np.zeros(3)) for p in plan[:6]]
    angles = [np.degrees(se3.rotation_angle(a, b)) for i, a in enumerate(T) for b in T[i + 1 :]]
    assert min(angles) > 5


def test_twin_touches_put_the_true_tip_on_the_true_vertex(noise_free):
    _, sets, twins, _ = noise_free
    truth = twins[0].truth
    for t in sets[0]:
        tip = tip_positions(truth.dh_table, t.q[None], truth.p_ee_tip)[0]
        assert np.linalg.norm(tip - truth.landmarks_base[t.vertex]) < 1e-9
        # The record holds what the controller reports: nominal kinematics of those angles.
        np.testing.assert_allclose(
            t.T_base_ee, forward_kinematics(NOMINAL_TABLES["ur3"], t.q), atol=1e-12
        )
    assert len(sets[0]) == 24 and len({t.vertex for t in sets[0]}) == 4


def test_analytic_jacobian_matches_numeric(rng):
    table = NOMINAL_TABLES["ur3"]
    q = rng.uniform(-2, 2, (8, 6))
    touches = [Touch(f"v{i % 4}", i, q[i], np.eye(4)) for i in range(8)]
    cad = {f"v{i}": rng.normal(size=3) * 0.05 for i in range(4)}
    ts = _touch_set(touches, cad)
    T0 = se3.make(np.eye(3), [0.3, 0.0, 0.0])
    x = np.array([1.0, 2.0, 160.0, 3.0, -2.0, 5.0, 4.0, 5.0, 6.0])
    z = rng.normal(size=24) * 0.5
    tab = table.with_deltas(deltas_from_z(z))
    Jz, Js = _set_jacobian(tab, ts, x, T0)
    h = 1e-6

    def f(dz, xs):
        return _set_residuals(table.with_deltas(deltas_from_z(z + dz)), ts, xs, T0)

    Jz_num = np.array([(f(h * e, x) - f(-h * e, x)) / (2 * h) for e in np.eye(24)]).T
    Js_num = np.array(
        [(f(0 * x[:1], x + h * e) - f(0 * x[:1], x - h * e)) / (2 * h) for e in np.eye(9)]
    ).T
    np.testing.assert_allclose(Jz, Jz_num, atol=1e-5)
    np.testing.assert_allclose(Js, Js_num, atol=1e-5)


def test_noise_free_refinement_without_regulariser_is_exact_where_touched(noise_free):
    _, sets, twins, cad = noise_free
    truth = twins[0].truth
    ref = refine_dh(
        NOMINAL_TABLES["ur3"], sets[1:], cad, TIP_CAD, regularizer=0.0, initialisations=3
    )
    assert ref.loss < 1e-10
    # Held out: dataset A's touch configurations (the touched region, another placement).
    q = np.array([t.q for t in sets[0]])
    gauge = kinematic_gauge(ref.table, truth.dh_table, q, [truth.p_ee_tip])
    assert gauge.max_mm <= 0.05
    nominal = kinematic_gauge(NOMINAL_TABLES["ur3"], truth.dh_table, q, [truth.p_ee_tip])
    assert nominal.rms_mm > 1.0  # the arm really is off without refinement
    # With the paper's regulariser the fit trades a little accuracy for staying near
    # nominal in the directions touches cannot see.
    reg = refine_dh(
        NOMINAL_TABLES["ur3"], sets[1:], cad, TIP_CAD, regularizer=0.01, initialisations=3
    )
    g_reg = kinematic_gauge(reg.table, truth.dh_table, q, [truth.p_ee_tip])
    assert g_reg.max_mm <= 0.1


def test_weak_directions_are_named_and_the_regulariser_keeps_them_put(noise_free):
    _, sets, _, cad = noise_free
    nominal = NOMINAL_TABLES["ur3"]
    reg = refine_dh(nominal, sets[1:], cad, TIP_CAD, regularizer=0.01, initialisations=1)
    ident = identifiability(reg, sets[1:], cad)
    u = ident.unobservable
    # The three parallel axes (joints 2-4): only the sum of Δd2, Δd3, Δd4 matters, so two
    # of the three directions are invisible (2/3 of each parameter).
    for name in ("Δd2", "Δd3", "Δd4"):
        assert u[name] > 0.5, u
    # A base rotation is absorbed by the phantom poses, a turn of the flange by the tip.
    assert u["Δθ1"] > 0.9 and u["Δθ6"] > 0.9, u
    # The elbow's and shoulder's joint offsets are seen.
    assert u["Δθ2"] < 0.1 and u["Δθ3"] < 0.1, u
    null = ident.null_space
    assert null.shape[0] >= 4
    # Regularised: no component along the unobservable directions.
    assert np.max(np.abs(null @ reg.z.ravel())) < 1e-3
    # Unregularised from spread starts: the fit lands wherever the start put it along
    # those directions (nothing in the data pulls it back).
    free = refine_dh(
        nominal, sets[1:], cad, TIP_CAD, regularizer=0.0, initialisations=4, start_scale=1.0
    )
    assert np.max(np.abs(null @ free.z.ravel())) > 0.05


def test_reference_fit_recovers_tip_and_phantom_pose(noise_free):
    _, sets, twins, cad = noise_free
    truth = twins[0].truth
    ref = fit_reference(truth.dh_table, sets[0], cad, TIP_CAD)
    np.testing.assert_allclose(ref.tip, truth.p_ee_tip, atol=1e-9)
    np.testing.assert_allclose(ref.T_base_phantom, truth.T_base_phantom, atol=1e-9)
    assert max(ref.tool_precision_mm.values()) < 1e-6
    assert ref.residuals_mm.max() < 1e-6


def test_reference_tool_precision_with_contact_noise():
    _, sets, twins, cad = touches_of([*NOISE_FREE, "tools.contact_noise_mm=0.2"])
    ref = fit_reference(twins[0].truth.dh_table, sets[0], cad, TIP_CAD)
    # Mean distance of 6 touches from their centroid with 0.2 mm per axis: ≈ 0.28 mm.
    assert 0.1 < np.mean(list(ref.tool_precision_mm.values())) < 0.45


def test_kinematic_gauge_recovers_base_and_flange_motions(rng):
    # Δθ1, Δd1 move the base frame (Rz, Tz commute to the front of the chain) and Δθ6,
    # Δd6 the flange frame: exactly the motions the gauge absorbs.
    table = NOMINAL_TABLES["ur3"]
    z = np.zeros((6, 4))
    z[0, 0], z[0, 1], z[5, 0], z[5, 1] = 2.0, 1.5, -3.0, 0.8  # °, mm, °, mm
    moved = table.with_deltas(deltas_from_z(z))
    q = rng.uniform(-1.5, 1.5, (40, 6))
    pts = np.array([[0.0, 0.0, 0.15], [0.02, 0.0, 0.15], [0.0, 0.03, 0.12]])
    g = kinematic_gauge(moved, table, q, pts)
    assert g.max_mm < 1e-6
    B = se3.make(se3.matrix_from_euler([0, 0, np.radians(2.0)]), [0, 0, 1.5e-3])
    G = se3.invert(se3.make(se3.matrix_from_euler([0, 0, np.radians(-3.0)]), [0, 0, 0.8e-3]))
    np.testing.assert_allclose(g.B, B, atol=1e-9)
    np.testing.assert_allclose(g.G, G, atol=1e-9)
    # A general DH error is not a gauge motion: something remains.
    perturbed = table.with_deltas(deltas_from_z(rng.normal(size=24) * 0.5))
    assert kinematic_gauge(perturbed, table, q, pts).rms_mm > 0.05


@pytest.mark.slow
def test_the_refinements_covariance_predicts_its_error_where_the_probe_works():
    """The refined model's own error, carried from its covariance to configurations it
    was not fitted on (another dataset's touches), is about what the model is really
    off there beyond a rigid change of base and flange — and well below the touch
    residual, which carries the stylus's seating noise the probe does not share."""
    actual, predicted, residual = [], [], []
    for seed in (1, 2, 3):
        _, sets, twins, cad = touches_of(
            [*NOISE_FREE, "tools.contact_noise_mm=0.2", f"seed={seed}"]
        )
        truth = twins[0].truth
        ref = refine_dh(NOMINAL_TABLES["ur3"], sets[1:], cad, TIP_CAD, initialisations=3)
        q = np.array([t.q for t in sets[0]])
        tip = truth.p_ee_tip
        tool = tip + np.array([[0, 0, 0], [0.02, 0, 0], [0, 0.02, 0], [0, 0, -0.03]])
        actual.append(kinematic_gauge(ref.table, truth.dh_table, q, tool).rms_mm)
        T = forward_kinematics(ref.table, q)
        sweeps = [
            Sweep("a", i, np.zeros((1, 1, 1), np.uint8), (1e-4, 1e-4), q[i : i + 1], T[i : i + 1])
            for i in range(len(q))
        ]
        modes = kinematic_modes(ref.table, ref.covariance, sweeps)
        obs = [Observation("a", i, tip, T[i]) for i in range(len(q))]
        E = _gauge_free_displacements(obs, modes, np.eye(4), tool)
        predicted.append(float(np.sqrt(np.mean(np.sum(E**2, axis=(1, 2))))) / MM)
        residual.append(float(np.sqrt(np.mean(ref.residuals_mm**2))))
    ratio = np.sqrt(np.mean(np.square(actual)) / np.mean(np.square(predicted)))
    assert 0.6 < ratio < 1.6, (actual, predicted)
    assert max(predicted) < 0.6 * min(residual), (predicted, residual)
