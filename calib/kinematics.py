"""Touch-based kinematics refinement (paper, "Reference Target Localization and
Kinematics Refinement").

**Step 1 (DH table refinement).** Over the training datasets r, with the stylus tip
offset ``u_r`` (flange frame) and phantom pose ``Y_r`` unknown per dataset and the scaled
DH corrections ``z`` shared, minimise (paper, touch loss)::

    L(z, {u_r, Y_r}) = Σ_r Σ_j Σ_k ‖p_tip(q_rjk; z, u_r) − (R_r c_j + t_r)‖² + λ ‖z‖²

with residuals in millimetres, ``z`` per joint (Δθ, Δd, Δa, Δα) in units of 1° and 1 mm,
λ = 0.01, bounded TRF, keeping the lowest training loss of 12 deterministic starts.

**Step 2 (CAD-guided reference).** With ``z`` frozen, fit the current dataset's tip
offset and phantom pose; the CAD sphere centres mapped by that pose are the accuracy
reference.

Touches constrain the kinematics only up to motions they cannot see: a rigid motion of
the base frame is absorbed by the phantom poses, a rigid motion of the flange frame by
the tip offset (about the stylus axis, and along it), and the parallel shoulder/elbow/
wrist axes make some DH combinations redundant. :func:`identifiability` names those
directions; the regulariser keeps them at the nominal values.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from . import se3
from .dh import DHDeltas, DHTable, forward_kinematics, frame_transforms
from .errors import CalibrationError
from .records import Sweep, Touch

__all__ = [
    "DH_COLUMNS",
    "DHRefinement",
    "Identifiability",
    "KinematicGauge",
    "TouchReference",
    "WeakDirection",
    "deltas_from_z",
    "fit_reference",
    "identifiability",
    "kinematic_gauge",
    "kinematic_modes",
    "refine_dh",
    "tip_positions",
    "with_kinematics",
]

Array = NDArray[np.float64]

#: Columns of the scaled corrections z (6, 4), and their units.
DH_COLUMNS = ("theta", "d", "a", "alpha")
_Z_UNITS = ("deg", "mm", "mm", "deg")
_Z_TO_SI = np.array([np.pi / 180, 1e-3, 1e-3, np.pi / 180])
_MM = 1e3


def deltas_from_z(z: ArrayLike) -> DHDeltas:
    """Scaled corrections z (6, 4) or (24,) — degrees and millimetres — to SI deltas."""
    return DHDeltas.from_array(np.asarray(z, dtype=float).reshape(6, 4) * _Z_TO_SI)


def tip_positions(table: DHTable, q: ArrayLike, p_ee_tip: ArrayLike) -> Array:
    """Base-frame tip positions (n, 3) of a tool point ``p_ee_tip`` (flange frame) at joint
    angles ``q`` (n, 6)."""
    T = forward_kinematics(table, np.asarray(q, dtype=float))
    return T[..., :3, :3] @ np.asarray(p_ee_tip, dtype=float) + T[..., :3, 3]


def with_kinematics(sweeps: Sequence[Sweep], table: DHTable) -> tuple[Sweep, ...]:
    """The sweeps with every frame's flange pose recomputed from its reported joint
    angles through ``table`` (e.g. a refined DH model); frames are shared, not copied."""
    return tuple(replace(s, T_base_ee=forward_kinematics(table, s.q)) for s in sweeps)


# ----------------------------------------------------------------------------- touch sets


@dataclass(frozen=True, eq=False)
class _TouchSet:
    """Touches of one dataset: joint angles (n, 6) and the CAD vertex of each (n, 3)."""

    q: Array
    vertex: NDArray[np.int64]
    names: tuple[str, ...]
    cad: Array  # (m, 3) metres, phantom frame, one per name


def _touch_set(touches: Sequence[Touch], cad_vertices: Mapping[str, ArrayLike]) -> _TouchSet:
    names = tuple(dict.fromkeys(t.vertex for t in touches))
    missing = [n for n in names if n not in cad_vertices]
    if missing:
        raise CalibrationError(
            f"touches name vertices {missing} that the phantom CAD does not have "
            f"(it has {sorted(cad_vertices)})"
        )
    if len(names) < 3:
        raise CalibrationError(
            f"touches cover {len(names)} vertices; the phantom pose needs at least 3"
        )
    index = {n: i for i, n in enumerate(names)}
    return _TouchSet(
        np.array([t.q for t in touches], dtype=float),
        np.array([index[t.vertex] for t in touches]),
        names,
        np.array([cad_vertices[n] for n in names], dtype=float),
    )


def _initial_pose(table: DHTable, ts: _TouchSet, tip: Array) -> Array:
    """Phantom pose from the per-vertex mean tip positions (Kabsch onto the CAD)."""
    tips = tip_positions(table, ts.q, tip)
    means = np.array([tips[ts.vertex == i].mean(axis=0) for i in range(len(ts.names))])
    return se3.kabsch(ts.cad, means)


# Per-dataset unknowns: tip offset (mm), phantom rotation increment (deg), translation (mm).
_PER_SET = 9


def _unpack_set(x: Array, T0: Array) -> tuple[Array, Array]:
    u = x[:3] / _MM
    T = T0 @ se3.make(se3.matrix_from_rotvec(np.radians(x[3:6])), np.zeros(3))
    T[:3, 3] = T0[:3, 3] + x[6:9] / _MM
    return u, T


def _set_residuals(table: DHTable, ts: _TouchSet, x: Array, T0: Array) -> Array:
    u, T = _unpack_set(x, T0)
    tips = tip_positions(table, ts.q, u)
    model = se3.apply(T, ts.cad)[ts.vertex]
    return ((tips - model) * _MM).ravel()


def _set_jacobian(table: DHTable, ts: _TouchSet, x: Array, T0: Array) -> tuple[Array, Array]:
    """Jacobians of :func:`_set_residuals` (3n,) with respect to z (3n, 24) and to the
    set's own unknowns (3n, 9).

    Analytic for the kinematics (each DH parameter moves the tip by a rotation about, or
    a translation along, one joint frame's axis), numeric for the phantom rotation: the
    numeric alternative re-runs the forward kinematics 42 times per Jacobian and made
    the 12-start fit ≈ 50× slower.
    """
    u = x[:3] / _MM
    F = frame_transforms(table, ts.q)  # (n, 7, 4, 4): frames 0..6
    R6 = F[:, 6, :3, :3]
    p = R6 @ u + F[:, 6, :3, 3]  # (n, 3) tip
    n = len(p)
    Jz = np.empty((n, 3, 6, 4))
    for i in range(6):
        z_prev, o_prev = F[:, i, :3, 2], F[:, i, :3, 3]
        x_i, o_i = F[:, i + 1, :3, 0], F[:, i + 1, :3, 3]
        Jz[:, :, i, 0] = np.cross(z_prev, p - o_prev) * _Z_TO_SI[0]
        Jz[:, :, i, 1] = z_prev * _Z_TO_SI[1]
        Jz[:, :, i, 2] = x_i * _Z_TO_SI[2]
        Jz[:, :, i, 3] = np.cross(x_i, p - o_i) * _Z_TO_SI[3]
    Js = np.zeros((n, 3, _PER_SET))
    Js[:, :, 0:3] = R6 / _MM
    Js[:, :, 6:9] = -np.eye(3) / _MM
    h = 1e-6  # degrees
    for k in range(3):
        dx = np.zeros(_PER_SET)
        dx[3 + k] = h
        _, Tp = _unpack_set(x + dx, T0)
        _, Tm = _unpack_set(x - dx, T0)
        Js[:, :, 3 + k] = -(se3.apply(Tp, ts.cad) - se3.apply(Tm, ts.cad))[ts.vertex] / (2 * h)
    return (Jz * _MM).reshape(3 * n, 24), (Js * _MM).reshape(3 * n, _PER_SET)


# ----------------------------------------------------------------------------- step 1


def _z_covariance(J: Array, r: Array, n_touch: int) -> Array:
    """:attr:`DHRefinement.covariance` from the fit's Jacobian ``J`` and residuals ``r``
    at the solution (the first ``n_touch`` rows the touches', the last 24 the
    regulariser's)."""
    J = np.asarray(J, dtype=float)
    JtJ_inv = np.linalg.pinv(J.T @ J)
    Jt = J[:n_touch]
    leverage = float(np.einsum("ij,jk,ik->", Jt, JtJ_inv, Jt))
    rt = np.asarray(r[:n_touch], dtype=float)
    s2 = float(rt @ rt) / max(n_touch - leverage, 1.0)
    return (s2 * JtJ_inv)[:24, :24]


def kinematic_modes(
    table: DHTable, covariance: ArrayLike, sweeps: Sequence[Sweep]
) -> dict[tuple[str, int], Array]:
    """How an estimated DH model's own error moves each sweep's reference flange pose:
    for each sweep (by ``(target, pose_id)``) the (k, 4, 4) derivatives of
    ``T_base_ee`` at its reference frame's joint angles along ``k`` independent
    1 σ directions of ``covariance`` (of z, :attr:`DHRefinement.covariance`). One draw
    of the model's error moves every sweep at once: an error the sweeps share, not
    noise between them (:class:`calib.calibration.uncertainty.UncertaintyInputs`)."""
    cov = np.asarray(covariance, dtype=float)
    w, V = np.linalg.eigh((cov + cov.T) / 2)
    keep = w > 1e-12 * max(float(w.max()), 1e-300)
    L = V[:, keep] * np.sqrt(w[keep])  # (24, k): cov = L Lᵀ
    q = np.array([s.q[s.reference_index] for s in sweeps], dtype=float)
    h = 1e-3  # of z: 0.001° / 0.001 mm, central differences
    dT = np.empty((24, len(q), 4, 4))
    for j, step in enumerate(h * np.eye(24)):
        hi = forward_kinematics(table.with_deltas(deltas_from_z(step)), q)
        lo = forward_kinematics(table.with_deltas(deltas_from_z(-step)), q)
        dT[j] = (hi - lo) / (2 * h)
    modes = np.einsum("jk,jnab->nkab", L, dT)
    return {(s.target, int(s.pose_id)): modes[i] for i, s in enumerate(sweeps)}


@dataclass(frozen=True, eq=False)
class DHRefinement:
    """Result of Step 1.

    Attributes
    ----------
    z : (6, 4) float
        Scaled corrections (Δθ °, Δd mm, Δa mm, Δα °) per joint.
    table : DHTable
        Nominal table plus the corrections.
    tips : (r, 3) float, metres
        Fitted tip offset of each training dataset.
    phantom_poses : (r, 4, 4) float
        Fitted phantom pose of each training dataset.
    loss : float
        Training loss (mm², regulariser included) of the kept start.
    start_losses : (k,) float
        Final loss of each deterministic start.
    residuals_mm : (n,) float
        Distance of each training touch from its model vertex.
    covariance : (24, 24) float or None
        Of z (units of 1° and 1 mm, as ``z``): the fit's first-order covariance,
        ``s² (JᵀJ)⁻¹`` with the regulariser's rows in ``J`` (its prior: z ~ N(0, s²/λ))
        and ``s²`` the touch residuals' variance per coordinate over their degrees of
        freedom (the touch rows' leverage subtracted), marginal over the tip offsets and
        phantom poses. Directions the touches cannot see keep the prior's spread;
        :func:`kinematic_modes` carries it to the probe's poses, where a rigid change of
        the base and flange frames is no error of a mount measured through the model.
    """

    z: Array
    table: DHTable
    tips: Array
    phantom_poses: Array
    loss: float
    start_losses: Array
    residuals_mm: Array
    regularizer: float = 0.0
    covariance: Array | None = None
    info: dict[str, object] = field(default_factory=dict)

    @property
    def rms_change(self) -> tuple[float, float, float, float]:
        """RMS over joints of the change from nominal in (θ °, d mm, a mm, α °), as the
        paper reports it."""
        return tuple(float(v) for v in np.sqrt(np.mean(self.z**2, axis=0)))


def _starts(n: int, scale: float, n_sets: int) -> list[Array]:
    """Deterministic starts of z (and tip offsets): the nominal one, then a scrambled-free
    Halton sequence spread over ± ``scale`` (° / mm)."""
    starts = [np.zeros(24 + 3 * n_sets)]
    if n > 1:
        from scipy.stats import qmc  # ≈ 0.25 s to import: only when there are starts

        halton = qmc.Halton(d=24 + 3 * n_sets, scramble=False).random(n)[1:]
        starts += [(2 * h - 1) * scale for h in halton]
    return starts


def refine_dh(
    nominal: DHTable,
    touch_sets: Sequence[Sequence[Touch]],
    cad_vertices: Mapping[str, ArrayLike],
    tip_guess: ArrayLike,
    *,
    regularizer: float = 0.01,
    initialisations: int = 12,
    bound: float = 10.0,
    start_scale: float = 1.0,
) -> DHRefinement:
    """Step 1: shared DH corrections from the touches of the training datasets.

    Parameters
    ----------
    nominal : the controller's (factory) DH table
    touch_sets : touches of each training dataset
    cad_vertices : CAD vertex positions (metres, phantom frame) by name
    tip_guess : (3,) metres: the stylus tip offset from its drawing (a start value)
    regularizer : λ of λ‖z‖² (the paper: 0.01)
    initialisations : deterministic starts; the lowest training loss is kept
    bound : |z| ≤ bound (° or mm) per correction
    start_scale : spread (° / mm) of the starts after the first
    """
    sets = [_touch_set(t, cad_vertices) for t in touch_sets]
    if not sets:
        raise CalibrationError("DH refinement needs the touches of at least one dataset")
    tip0 = np.asarray(tip_guess, dtype=float)
    poses0 = [_initial_pose(nominal, ts, tip0) for ts in sets]
    n_sets = len(sets)
    sqrt_reg = np.sqrt(regularizer)
    base = nominal.as_array()

    def unpack(x: Array) -> tuple[DHTable, list[Array]]:
        table = DHTable.from_array(base + x[:24].reshape(6, 4) * _Z_TO_SI, name="refined")
        return table, [x[24 + _PER_SET * r : 24 + _PER_SET * (r + 1)] for r in range(n_sets)]

    def residuals(x: Array) -> Array:
        table, per = unpack(x)
        parts = [
            _set_residuals(table, ts, p, T0) for ts, p, T0 in zip(sets, per, poses0, strict=True)
        ]
        parts.append(sqrt_reg * x[:24])
        return np.concatenate(parts)

    def jacobian(x: Array) -> Array:
        table, per = unpack(x)
        rows = []
        for r, (ts, p, T0) in enumerate(zip(sets, per, poses0, strict=True)):
            Jz, Js = _set_jacobian(table, ts, p, T0)
            block = np.zeros((len(Jz), len(x)))
            block[:, :24] = Jz
            block[:, 24 + _PER_SET * r : 24 + _PER_SET * (r + 1)] = Js
            rows.append(block)
        reg = np.zeros((24, len(x)))
        reg[:, :24] = sqrt_reg * np.eye(24)
        rows.append(reg)
        return np.vstack(rows)

    n = 24 + _PER_SET * n_sets
    lo = np.full(n, -np.inf)
    hi = np.full(n, np.inf)
    lo[:24], hi[:24] = -bound, bound
    for r in range(n_sets):
        k = 24 + _PER_SET * r
        lo[k : k + 3], hi[k : k + 3] = tip0 * _MM - 50, tip0 * _MM + 50
        lo[k + 3 : k + 6], hi[k + 3 : k + 6] = -180, 180
    best = None
    losses = []
    for start in _starts(initialisations, start_scale, n_sets):
        x0 = np.zeros(n)
        x0[:24] = start[:24]
        for r in range(n_sets):
            k = 24 + _PER_SET * r
            x0[k : k + 3] = tip0 * _MM + start[24 + 3 * r : 27 + 3 * r]
        x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)
        sol = least_squares(
            residuals,
            x0,
            jac=jacobian,
            bounds=(lo, hi),
            method="trf",
            x_scale="jac",
            xtol=1e-12,
            ftol=1e-12,
        )
        loss = float(2 * sol.cost)
        losses.append(loss)
        if best is None or loss < best[0]:
            best = (loss, sol)
    assert best is not None
    loss, sol = best
    table, per = unpack(sol.x)
    tips, poses, dists = [], [], []
    for ts, p, T0 in zip(sets, per, poses0, strict=True):
        u, T = _unpack_set(p, T0)
        tips.append(u)
        poses.append(T)
        dists.append(np.linalg.norm(_set_residuals(table, ts, p, T0).reshape(-1, 3), axis=1))
    return DHRefinement(
        z=sol.x[:24].reshape(6, 4).copy(),
        table=table,
        tips=np.array(tips),
        phantom_poses=np.array(poses),
        loss=loss,
        start_losses=np.array(losses),
        residuals_mm=np.concatenate(dists),
        regularizer=regularizer,
        covariance=_z_covariance(sol.jac, sol.fun, len(sol.fun) - 24),
        info={"n_touches": int(sum(len(ts.q) for ts in sets)), "n_datasets": n_sets},
    )


# ----------------------------------------------------------------------------- step 2


@dataclass(frozen=True, eq=False)
class TouchReference:
    """Result of Step 2 for one dataset.

    Attributes
    ----------
    tip : (3,) float, metres, flange frame
    T_base_phantom : (4, 4) float
    residuals_mm : (n,) float
        Distance of each touch from its model vertex.
    tool_precision_mm : dict of float
        Per vertex: mean distance of its touch tip positions from their centroid (the
        paper's tool precision, one sample per vertex).
    """

    tip: Array
    T_base_phantom: Array
    residuals_mm: Array
    tool_precision_mm: dict[str, float]

    def reference_points(self, cad_points: Mapping[str, ArrayLike]) -> dict[str, Array]:
        """CAD points (e.g. sphere centres) mapped into the base frame by the fitted pose."""
        return {k: se3.apply(self.T_base_phantom, np.asarray(v)) for k, v in cad_points.items()}


def fit_reference(
    table: DHTable,
    touches: Sequence[Touch],
    cad_vertices: Mapping[str, ArrayLike],
    tip_guess: ArrayLike,
) -> TouchReference:
    """Step 2: with the DH model frozen, the dataset's tip offset and phantom pose."""
    ts = _touch_set(touches, cad_vertices)
    tip0 = np.asarray(tip_guess, dtype=float)
    T0 = _initial_pose(table, ts, tip0)
    x0 = np.concatenate([tip0 * _MM, np.zeros(6)])
    sol = least_squares(
        lambda x: _set_residuals(table, ts, x, T0), x0, method="trf", xtol=1e-12, ftol=1e-12
    )
    u, T = _unpack_set(sol.x, T0)
    tips = tip_positions(table, ts.q, u)
    precision = {}
    for i, name in enumerate(ts.names):
        pts = tips[ts.vertex == i]
        precision[name] = float(np.mean(np.linalg.norm(pts - pts.mean(axis=0), axis=1)) * _MM)
    res = np.linalg.norm(_set_residuals(table, ts, sol.x, T0).reshape(-1, 3), axis=1)
    return TouchReference(u, T, res, precision)


# ----------------------------------------------------------------------------- analysis


@dataclass(frozen=True)
class WeakDirection:
    """A direction of the unknowns the touches (nearly) cannot see.

    ``singular_value`` relative to the largest; ``dh`` the direction's largest DH
    components (name → weight of the unit direction, e.g. ``{"Δd2": 0.58, ...}``).
    """

    singular_value: float
    dh: dict[str, float]


@dataclass(frozen=True, eq=False)
class Identifiability:
    """What the touches of a DH fit can and cannot tell apart.

    Attributes
    ----------
    singular_values : (24,) float
        Of the touch residuals' Jacobian with respect to the DH corrections, after the
        per-dataset tip offsets and phantom poses have absorbed what they can (relative
        to the largest, descending).
    unobservable : dict of float
        Per DH parameter (``"Δθ1"`` …): the share of it lying in the directions the
        touches cannot see at all (relative singular value below ``null_threshold``):
        1 = unidentifiable, 0 = fully determined by the touches.
    weak : list of WeakDirection
        Each direction with relative singular value below ``weak_threshold``, named by its
        largest DH components.
    """

    singular_values: Array
    unobservable: dict[str, float]
    weak: list[WeakDirection]
    null_space: Array  # (k, 24) unit rows: the directions of z touches cannot see


_DH_NAMES = [f"Δ{c}{j + 1}" for j in range(6) for c in ("θ", "d", "a", "α")]


def identifiability(
    refinement: DHRefinement,
    touch_sets: Sequence[Sequence[Touch]],
    cad_vertices: Mapping[str, ArrayLike],
    *,
    weak_threshold: float = 1e-4,
    null_threshold: float = 1e-6,
) -> Identifiability:
    """Identifiability of the DH corrections from the touches at a Step-1 solution
    (without the regulariser): see :class:`Identifiability`."""
    sets = [_touch_set(t, cad_vertices) for t in touch_sets]
    rows = []
    for r, ts in enumerate(sets):
        x = np.concatenate([refinement.tips[r] * _MM, np.zeros(6)])
        Jz, Js = _set_jacobian(refinement.table, ts, x, refinement.phantom_poses[r])
        # The phantom pose moves the model vertices rigidly. Evaluated as if the fit were
        # exact (vertices at the tips), so directions that only trade against the pose are
        # exactly degenerate rather than blurred by the fit's small residuals.
        p = tip_positions(refinement.table, ts.q, refinement.tips[r]) * _MM
        Js = Js.copy()
        for k, e in enumerate(np.eye(3)):
            Js[:, 3 + k] = -np.cross(e, p).ravel()
        # Eliminate the dataset's own unknowns: keep what they cannot explain.
        rows.append(Jz - Js @ np.linalg.lstsq(Js, Jz, rcond=None)[0])
    J = np.vstack(rows)
    _, s, Vt = np.linalg.svd(J, full_matrices=True)
    s_full = np.zeros(24)
    s_full[: len(s)] = s
    rel = s_full / s_full[0]
    null = Vt[rel < null_threshold]
    share = (null**2).sum(axis=0)
    weak = []
    for k in np.flatnonzero(rel < weak_threshold):
        v = Vt[k]
        order = np.argsort(-np.abs(v))
        # A singular vector's sign is arbitrary (rounding flips it): its largest component
        # is reported positive. (Within a null space of several dimensions the basis
        # itself is arbitrary; ``unobservable`` is the basis-free summary.)
        v = v * np.sign(v[order[0]])
        comps = {_DH_NAMES[i]: round(float(v[i]), 3) for i in order[:4] if abs(v[i]) >= 0.05}
        weak.append(WeakDirection(float(rel[k]), comps))
    return Identifiability(
        rel, {n: float(v) for n, v in zip(_DH_NAMES, share, strict=True)}, weak, null
    )


@dataclass(frozen=True, eq=False)
class KinematicGauge:
    """How one kinematic model relates to another over a set of configurations:
    ``FK_a(q) · G ≈ B · FK_b(q)`` with ``B`` a base-frame and ``G`` a flange-frame rigid
    motion (what touches cannot see), and the residual beyond them (mm, at tool points)."""

    B: Array
    G: Array
    rms_mm: float
    max_mm: float


def kinematic_gauge(
    table_a: DHTable, table_b: DHTable, q: ArrayLike, tool_points: ArrayLike
) -> KinematicGauge:
    """Fit ``B``, ``G`` of :class:`KinematicGauge` over configurations ``q`` (n, 6) at
    flange-frame ``tool_points`` (m, 3) — e.g. an image's corners through ``T_ee_us`` or a
    stylus tip — and report the remaining error at those points."""
    q = np.asarray(q, dtype=float)
    P = np.asarray(tool_points, dtype=float)
    Ta = forward_kinematics(table_a, q)
    Tb = forward_kinematics(table_b, q)

    def residuals(x: Array) -> Array:
        B = se3.exp(x[:6])
        G = se3.exp(x[6:])
        left = _apply_many(Ta @ G, P)
        right = _apply_many(B @ Tb, P)
        return ((left - right) * _MM).ravel()

    sol = least_squares(residuals, np.zeros(12), method="lm", xtol=1e-14, ftol=1e-14)
    d = np.linalg.norm(sol.fun.reshape(-1, 3), axis=1)
    return KinematicGauge(
        se3.exp(sol.x[:6]), se3.exp(sol.x[6:]), float(np.sqrt(np.mean(d**2))), float(d.max())
    )


def _apply_many(T: Array, P: Array) -> Array:
    """Points P (m, 3) through each of the transforms T (n, 4, 4): (n, m, 3)."""
    return np.einsum("nij,mj->nmi", T[:, :3, :3], P) + T[:, None, :3, 3]
