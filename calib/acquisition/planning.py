"""Pose planning: which sweeps to acquire so that ``T_ee_us`` is best determined for the
robot time spent (the paper's closing open problem: "reduce the number of required
acquisition poses while maintaining calibration accuracy and conditioning").

A sweep is placed relative to the taught nominal pose (:class:`SweepPose`): turned about
the target by three angles about the image axes, then shifted in its image plane, as the
paper's plan does with its 9 orientations × 5 positions (:func:`paper_poses`). Each sweep
yields one localized centre; its information about θ = (ω rad, t mm) of ``T_ee_us`` is
that of :mod:`calib.acquisition.observability`, whitened by the localizer's noise in the image frame
(anisotropic: laterally under a hundredth of a millimetre, axially one or two, in elevation
about five hundredths, :class:`NoiseModel`).

The target's own position is unknown (one sphere: its centre; several spheres with the
CAD layout: the phantom's pose), so the information of a set of sweeps is the Schur
complement of the nuisance block,

    H = Σ AᵀA − (Σ AᵀB)(Σ BᵀB)⁻¹(Σ BᵀA),

with A the whitened Jacobians of the observations with respect to θ and B those with
respect to the nuisance parameters. Sweeps of several spheres therefore inform each
other through the shared phantom pose: a multi-sphere plan is chosen for the joint
problem, not sphere by sphere.

The selection (:func:`select_sweeps`) is a greedy start followed by Fedorov exchange
(swap a chosen sweep for a candidate while the criterion improves), on a finite set of
candidates that the caller has checked for reach, collisions and the target's place in
the image. A convex relaxation (weights on the candidates, then rounding) would bound
the optimum, but needs rounding to N whole sweeps all the same and loses the nuisance
coupling's sparsity; the exchange reaches a local optimum that, on this problem, sits
within a few percent of the greedy-with-restarts best (the paper's plan is far from
both, see ``benchmarks/planning.py``). Criteria, all in the image-error metric (mm at
the image's points, so that rotation and translation are weighed by what a user sees):

- ``D``: maximize log det H (the volume of the confidence ellipsoid; unit-free);
- ``A``: minimize the predicted mean squared image error, trace(M H⁻¹);
- ``E``: minimize its worst direction, λ_max(M^½ H⁻¹ M^½).

The prediction (:func:`predict`) is the spread of the fit :mod:`calib.calibration.markers` makes,
which weighs every axis alike: the sandwich N⁻¹ (Σ Jᵀ S J) N⁻¹ of that least squares
under the anisotropic noise S, a little above H⁻¹ (the noise-weighted fit's); the noise
is the localizer's and the arm's pose noise, added.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .. import se3
from .observability import jacobians

__all__ = [
    "CRITERIA",
    "Candidates",
    "NoiseModel",
    "PlanPrediction",
    "PlanningConfig",
    "SweepPose",
    "bias_covariance",
    "candidate_poses",
    "image_metric",
    "next_sweep",
    "paper_poses",
    "predict",
    "select_sweeps",
    "sweep_commands",
    "sweep_scores",
]

Array = NDArray[np.float64]
Criterion = Literal["D", "A", "E"]
CRITERIA: tuple[Criterion, ...] = ("D", "A", "E")
_MM = 1e3


@dataclass(frozen=True)
class PlanningConfig:
    """Pose planning (``uscal plan --optimize``): the candidate sweeps a plan is chosen
    from and the localization noise it is chosen for."""

    max_rotation_deg: float = field(
        default=30.0,
        metadata={
            "doc": "Candidates turn about the target by up to ± this about each image axis.",
            "ge": 0,
            "le": 45,
        },
    )
    rotation_step_deg: float = field(
        default=10.0,
        metadata={"doc": "Step of the candidates' angles.", "gt": 0, "le": 45},
    )
    max_lateral_mm: float = field(
        default=10.0,
        metadata={
            "doc": "Candidates shift the image laterally by up to ± this.",
            "ge": 0,
            "le": 30,
        },
    )
    max_axial_mm: float = field(
        default=6.0,
        metadata={"doc": "Candidates shift the image axially by up to ± this.", "ge": 0, "le": 30},
    )
    shift_step_mm: float = field(
        default=2.0,
        metadata={"doc": "Step of the candidates' in-plane shifts.", "gt": 0, "le": 30},
    )
    image_margin_mm: float = field(
        default=3.0,
        metadata={
            "doc": "The sphere stays this far inside the image (beyond its radius) as the "
            "coarse T_ee_us predicts it: room for the coarse mount's error, which moves "
            "the sphere by up to 3 mm at a 20° turn (the twin's ± 10°, ± 3 mm mount).",
            "ge": 0,
            "le": 30,
        },
    )
    clearance_mm: float = field(
        default=5.0,
        metadata={
            "doc": "Every frame and transit of a chosen sweep keeps the arm and probe this "
            "far from the tank and the phantom, in this session and in each of "
            "session_draws others.",
            "ge": 0,
            "le": 100,
        },
    )
    session_draws: int = field(
        default=24,
        metadata={
            "doc": "A plan is made to be reused: its sweeps are checked in this many other "
            "sessions, each with its own taught pose (protocol.teaching_error_mm) and "
            "coarse mount (calibration.initial_error_mm / _deg), drawn as another "
            "session's would be; a sweep that does not clear in every one is replaced. "
            "0: this session only.",
            "ge": 0,
            "le": 1000,
        },
    )
    spares: int = field(
        default=10,
        metadata={
            "doc": "Spare sweeps per sphere the plan file keeps, best first, each clear "
            "in the same sessions: at acquisition a sweep that does not clear is "
            "replaced by the first spare that does.",
            "ge": 0,
            "le": 100,
        },
    )
    localization_noise_mm: tuple[float, float, float] = field(
        default=(0.03, 0.027, 0.083),
        metadata={
            "doc": "1 σ of a localized centre along the image's lateral, axial and "
            "elevational axes, independent between sweeps, which a plan is chosen for "
            "(the twin's refined localizer on quick.yaml's sphere 1, textured print, the "
            "paper's plan: scatter within a session over 18 random draws of seed, gain and "
            "temperature, 0.028–0.032, 0.026–0.027, 0.082–0.083 mm; "
            "`benchmarks/target_noise.py --target sphere`).",
            "len": 3,
            "gt": 0,
            "le": 5,
        },
    )
    pose_noise_mm: float = field(
        default=0.007,
        metadata={
            "doc": "1 σ per axis of where a sweep's reported flange pose puts the sphere, "
            "independent between sweeps, added to the localization noise: joint "
            "repeatability and encoder noise through the arm (the twin's 0.002° and "
            "0.001°: 0.007 mm, measured; scale it with a rig's repeatability).",
            "ge": 0,
            "le": 5,
        },
    )
    localization_bias_mm: tuple[float, float, float] = field(
        default=(0.016, 0.057, 0.027),
        metadata={
            "doc": "1 σ of an offset shared by every centre of a session, along the image's "
            "lateral, axial and elevational axes (where in the cap's echo the centre lands): "
            "it moves T_ee_us by as much, whatever the plan (the twin on quick.yaml's "
            "sphere 1, RMS over the same 18 draws: 0.016, 0.057, 0.027 mm).",
            "len": 3,
            "ge": 0,
            "le": 5,
        },
    )

    dot_noise_mm: tuple[float, float] = field(
        default=(0.01, 0.02),
        metadata={
            "doc": "Wire and N-wire plans: 1 σ of a wire's dot in one frame along the "
            "image's lateral and axial axes, independent between frames "
            "(benchmarks/target_noise.py --seed 5, the twin's wire over three random "
            "draws of seed, gain and temperature: medians 0.009, 0.020 mm).",
            "len": 2,
            "ge": 0,
            "le": 5,
        },
    )
    dot_sweep_noise_mm: tuple[float, float] = field(
        default=(0.003, 0.15),
        metadata={
            "doc": "Wire and N-wire plans: 1 σ of an offset every dot of one sweep shares "
            "(lateral, axial; where in the wire's echo its dot lands depends on the view), "
            "independent between sweeps: it makes a sweep's many frames worth less than "
            "as many sweeps (benchmarks/target_noise.py --seed 5: medians 0.003, 0.14 mm, "
            "the axial 0.13–0.17 mm over the draws).",
            "len": 2,
            "ge": 0,
            "le": 5,
        },
    )
    cone_tip_noise_mm: tuple[float, float, float] = field(
        default=(0.2, 0.25, 0.25),
        metadata={
            "doc": "Cone-tip plans: 1 σ of a sweep's tip along the image's lateral, axial "
            "and elevational axes, independent between sweeps "
            "(benchmarks/target_noise.py --seed 5, the twin's cone over three random "
            "draws: medians 0.18, 0.24, 0.22 mm).",
            "len": 3,
            "ge": 0,
            "le": 5,
        },
    )

    def noise(self) -> NoiseModel:
        """Each sweep's centre noise in the image frame: the localizer's and the arm's
        (isotropic, so the same in every frame)."""
        return NoiseModel(*np.hypot(self.localization_noise_mm, self.pose_noise_mm))

    def candidates(self) -> list[SweepPose]:
        """The dense candidate set: every angle, lateral and axial shift of the grid."""

        def grid(limit: float, step: float) -> Array:
            k = int(np.floor(limit / step + 1e-9))
            return step * np.arange(-k, k + 1)

        return candidate_poses(
            grid(self.max_rotation_deg, self.rotation_step_deg),
            grid(self.max_lateral_mm, self.shift_step_mm),
            grid(self.max_axial_mm, self.shift_step_mm),
        )


@dataclass(frozen=True)
class SweepPose:
    """One sweep relative to the taught nominal pose: turned about the target by the
    extrinsic x-y-z Euler angles ``rotation_deg`` about the image axes (lateral, axial,
    elevational), then shifted in the image plane by ``lateral_mm`` and ``axial_mm``
    (the target then appears at (−lateral, depth − axial) in the image)."""

    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lateral_mm: float = 0.0
    axial_mm: float = 0.0

    def rotation(self) -> Array:
        return se3.matrix_from_euler(np.radians(np.asarray(self.rotation_deg, dtype=float)))

    def target_in_image(self, depth: float) -> Array:
        """Where the target appears (us frame, metres) if the taught pose were exact."""
        return np.array([-self.lateral_mm * 1e-3, depth - self.axial_mm * 1e-3, 0.0])


def paper_poses(
    rotation_deg: float, translation_mm: float, tilt_deg: float | None = None
) -> list[SweepPose]:
    """The paper's 45 sweeps about one sphere: the nominal orientation and the eight
    (±r, ±r, ±r) corners, each at the nominal position and the four (±t, ±t) in-plane
    corners (the order of :func:`calib.acquisition.protocol.plan_sweeps`). ``tilt_deg``: the corners
    about the image's lateral axis at ± this instead (None: ± r)."""
    r, t = float(rotation_deg), float(translation_mm)
    tx = r if tilt_deg is None else float(tilt_deg)
    corners = [(0.0, 0.0, 0.0)] + [
        (sx * tx, sy * r, sz * r) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)
    ]
    shifts = [(0.0, 0.0)] + [(sx * t, sy * t) for sx in (-1, 1) for sy in (-1, 1)]
    return [SweepPose(c, dx, dy) for c in corners for dx, dy in shifts]


def candidate_poses(
    rotation_deg: Sequence[float],
    lateral_mm: Sequence[float],
    axial_mm: Sequence[float],
) -> list[SweepPose]:
    """Every combination of the angles (each about each image axis), lateral and axial
    shifts: the dense set a plan is chosen from."""
    return [
        SweepPose((float(a), float(b), float(c)), float(x), float(y))
        for a in rotation_deg
        for b in rotation_deg
        for c in rotation_deg
        for x in lateral_mm
        for y in axial_mm
    ]


def sweep_commands(
    T_base_ee_taught: ArrayLike,
    T_ee_us_coarse: ArrayLike,
    depth: float,
    pose: SweepPose,
    *,
    half_length: float,
    n_frames: int,
) -> Array:
    """Flange commands (n_frames, 4, 4) of one sweep: the image turned about the target
    at ``depth`` and shifted in plane as ``pose`` says (with the coarse ``T_ee_us``),
    then run ± ``half_length`` along its elevational axis."""
    T_ee_us = np.asarray(T_ee_us_coarse, dtype=float)
    T_face = np.asarray(T_base_ee_taught, dtype=float) @ T_ee_us
    T_target = se3.make(np.eye(3), [0.0, depth, 0.0])
    T_rot = T_face @ T_target @ se3.make(pose.rotation(), np.zeros(3)) @ se3.invert(T_target)
    T_us = T_rot @ se3.make(np.eye(3), [pose.lateral_mm * 1e-3, pose.axial_mm * 1e-3, 0.0])
    steps = np.linspace(-half_length, half_length, n_frames)
    frame_shifts = se3.make(np.eye(3), np.column_stack([0 * steps, 0 * steps, steps]))
    return T_us @ frame_shifts @ se3.invert(T_ee_us)


@dataclass(frozen=True)
class NoiseModel:
    """1 σ (mm) of a localized centre along the image's lateral, axial and elevational
    axes, independent between sweeps."""

    lateral_mm: float
    axial_mm: float
    elevation_mm: float

    def covariance(self, R_base_us: Array) -> Array:
        """(n, 3, 3) covariance (mm²) of a centre in the base frame, for images at
        orientations ``R_base_us`` (n, 3, 3)."""
        var = np.square([self.lateral_mm, self.axial_mm, self.elevation_mm])
        return np.einsum("nij,j,nkj->nik", R_base_us, var, R_base_us)

    def whitening(self, R_base_us: Array) -> Array:
        """W (n, 3, 3) with WᵀW the inverse covariance of a centre in the base frame,
        for images at orientations ``R_base_us`` (n, 3, 3)."""
        inv_sigma = 1.0 / np.array([self.lateral_mm, self.axial_mm, self.elevation_mm])
        return inv_sigma[None, :, None] * np.swapaxes(R_base_us, 1, 2)


@dataclass(frozen=True, eq=False)
class Candidates:
    """Sweeps to choose from, as observations: the whitened Jacobians ``A`` (n, 3, 6)
    with respect to θ and ``B`` (n, 3, m) with respect to the nuisance parameters (the
    targets' positions, or the phantom's pose), and each sweep's target. ``G``, ``D`` are
    the same Jacobians unwhitened (mm) and ``S`` (n, 3, 3) each centre's noise
    covariance in the base frame (mm²): what :func:`predict` needs for the spread of
    the fit :mod:`calib.calibration.markers` makes, which weighs every axis alike."""

    A: Array
    B: Array
    target: NDArray[np.int_]
    prior: Array | None = None  # (m, m) prior information on the nuisance parameters
    G: Array | None = None
    D: Array | None = None
    S: Array | None = None

    def __len__(self) -> int:
        return len(self.A)

    def contributions(self) -> tuple[Array, Array, Array]:
        """Each candidate's AᵀA (n, 6, 6), AᵀB (n, 6, m) and BᵀB (n, m, m)."""
        return (
            np.einsum("nij,nik->njk", self.A, self.A),
            np.einsum("nij,nik->njk", self.A, self.B),
            np.einsum("nij,nik->njk", self.B, self.B),
        )

    def sums(self, chosen: Sequence[int]) -> list[Array]:
        """ΣAᵀA, ΣAᵀB and ΣBᵀB (with the nuisance prior) over the sweeps ``chosen``
        (repeats count twice)."""
        k = np.asarray(chosen, dtype=int)
        A, B = self.A[k], self.B[k]
        S_BB = np.einsum("nij,nik->jk", B, B)
        if self.prior is not None:
            S_BB = S_BB + self.prior
        return [np.einsum("nij,nik->jk", A, A), np.einsum("nij,nik->jk", A, B), S_BB]

    @classmethod
    def build(
        cls,
        T_ref_base_ee: ArrayLike,
        T_ee_us: ArrayLike,
        p_us: ArrayLike,
        target: ArrayLike,
        noise: NoiseModel,
        *,
        layout: Mapping[int, ArrayLike] | None = None,
        layout_sigma_mm: float = 0.0,
    ) -> Candidates:
        """Candidates observed at flange poses ``T_ref_base_ee`` (n, 4, 4; each sweep's
        reference frame), the target at ``p_us`` (n, 3, metres) in its image; ``target``
        (n,) indexes the sphere each one sees. ``layout``: {target: its centre (metres)}
        — the CAD layout, whose one unknown pose the spheres share, each centre printed
        off it by ``layout_sigma_mm`` (1 σ per axis; 0: exact, as the fit that takes the
        CAD as exact); without it each target's position is unknown on its own."""
        T = np.asarray(T_ref_base_ee, dtype=float)
        X = np.asarray(T_ee_us, dtype=float)
        G = jacobians(T, X, p_us)
        R = T[:, :3, :3] @ X[:3, :3]
        W = noise.whitening(R)
        A = W @ G
        S = noise.covariance(R)
        idx = np.asarray(target, dtype=int)
        if layout is None:
            names = np.unique(idx)
            D = np.zeros((len(T), 3, 3 * len(names)))
            for j, name in enumerate(names):
                D[idx == name, :, 3 * j : 3 * j + 3] = -np.eye(3)
            return cls(A, W @ D, idx, None, G, D, S)
        # c_s = R_φ c_s⁰ + t_φ: ∂c_s/∂(ω_φ rad, t_φ mm) = [−[c_s]_× · 1000 | I] (mm).
        # Each centre's print error δ_s (mm) adds to it, with its prior.
        names = list(layout)
        free = 3 * len(names) if layout_sigma_mm > 0 else 0
        D = np.zeros((len(T), 3, 6 + free))
        for j, name in enumerate(names):
            rows = idx == name
            D[rows, :, :3] = -se3.hat(np.asarray(layout[name], dtype=float)) * _MM
            D[rows, :, 3:6] = np.eye(3)
            if free:
                D[rows, :, 6 + 3 * j : 9 + 3 * j] = np.eye(3)
        prior = None
        if free:
            prior = np.zeros((6 + free, 6 + free))
            prior[6:, 6:] = np.eye(free) / layout_sigma_mm**2
        return cls(A, -W @ D, idx, prior, G, -D, S)

    @classmethod
    def from_rows(
        cls,
        J_theta: ArrayLike,
        J_nuisance: ArrayLike,
        target: ArrayLike,
        *,
        shared: ArrayLike | None = None,
    ) -> Candidates:
        """Candidates that each give many observations (a sweep's frames of wires, each
        with its constraint rows): ``J_theta`` (n, R, 6) and ``J_nuisance`` (n, R, m) the
        whitened rows of every observation of each sweep (unit variance, independent
        between observations; zero rows pad a sweep with fewer); ``shared`` (n, R, s)
        the rows' response to errors every observation of a sweep shares, one column per
        error at its 1 σ (what makes a sweep's many frames worth less than as many
        sweeps). Each sweep's information is
        JᵀJ − JᵀK (I + KᵀK)⁻¹ KᵀJ (J = [J_theta | J_nuisance], K = ``shared``: the
        Woodbury form of JᵀΣ⁻¹J, Σ = I + KKᵀ), kept as its square root (6 + m rows
        per sweep, not R): the sums are the same."""
        J = np.concatenate(
            [np.asarray(J_theta, dtype=float), np.asarray(J_nuisance, dtype=float)], axis=2
        )
        H = np.einsum("nri,nrj->nij", J, J)
        if shared is not None:
            K = np.asarray(shared, dtype=float)
            KtJ = np.einsum("nrs,nrj->nsj", K, J)
            inner = np.eye(K.shape[2]) + np.einsum("nrs,nrt->nst", K, K)
            H = H - np.einsum("nsi,nst,ntj->nij", KtJ, np.linalg.inv(inner), KtJ)
        w, V = np.linalg.eigh(0.5 * (H + np.swapaxes(H, 1, 2)))
        L = np.sqrt(np.clip(w, 0.0, None))[:, :, None] * np.swapaxes(V, 1, 2)  # LᵀL = H
        return cls(L[:, :, :6], L[:, :, 6:], np.asarray(target, dtype=int))


def image_metric(T_ee_us: ArrayLike, points_us: ArrayLike) -> Array:
    """M (6, 6): the mean over image points of JᵀJ, J the change of a point mapped
    through ``T_ee_us`` (flange frame, mm) with θ; δθᵀ M δθ is the mean squared
    image error (mm²) of an error δθ of ``T_ee_us``."""
    X = np.asarray(T_ee_us, dtype=float)
    G = jacobians(np.eye(4)[None], X, np.asarray(points_us, dtype=float))
    return np.einsum("nij,nik->jk", G, G) / len(G)


def _information(S_AA: Array, S_AB: Array, S_BB: Array) -> Array:
    """H (…, 6, 6): the Schur complement of the nuisance block (a pseudo-inverse where
    the sweeps do not yet fix every nuisance parameter)."""
    return S_AA - S_AB @ np.linalg.pinv(S_BB, hermitian=True) @ np.swapaxes(S_AB, -1, -2)


def _score(H: Array, criterion: Criterion, M: Array, ridge: float) -> Array:
    """The criterion of information matrices H (…, 6, 6), larger is better."""
    H = H + ridge * np.eye(6)
    if criterion == "D":
        sign, logdet = np.linalg.slogdet(H)
        return np.where(sign > 0, logdet, -np.inf)
    cov = np.linalg.inv(H)
    if criterion == "A":
        return -np.einsum("ij,...ji->...", M, cov)
    L = np.linalg.cholesky(M)
    return -np.linalg.eigvalsh(L.T @ cov @ L)[..., -1]


def select_sweeps(
    cands: Candidates,
    n: int,
    *,
    criterion: Criterion = "D",
    M: Array | None = None,
    max_passes: int = 10,
    repeats: bool = False,
    min_per_target: int = 0,
    admissible: Callable[[int], bool] | None = None,
) -> list[int]:
    """``n`` of the candidates (indices, in the order chosen) maximizing the criterion:
    greedy (each next sweep the one that adds most), then exchange passes (swap a chosen
    sweep for the candidate that improves the criterion most) until none improves.
    Without ``repeats`` every sweep is at its own pose: the optimum of a linear model
    repeats its few extreme poses, but a sweep repeated shares its view's localization
    bias (which the model does not hold), and distinct views are what the bounds'
    jackknife needs. ``min_per_target``: each target gets at least that many sweeps (a
    multi-marker fit needs every sphere seen). ``admissible(k)``: asked of a candidate
    only when it would be taken (a check too dear for every candidate, e.g. the arm's
    clearance in other sessions); one it refuses is never taken."""
    if criterion not in CRITERIA:
        raise ValueError(f"criterion {criterion!r}: one of {', '.join(CRITERIA)}")
    if n < 1:
        raise ValueError(f"n = {n}: a plan needs at least one sweep")
    M = np.eye(6) if M is None else np.asarray(M, dtype=float)
    # Per candidate: its contributions to the three sums.
    cAA, cAB, cBB = cands.contributions()
    ridge = 1e-9 * float(np.trace(cAA.mean(axis=0)))  # the first picks: never singular
    sums = cands.sums([])
    targets = np.unique(cands.target)
    if min_per_target * len(targets) > n:
        raise ValueError(f"{n} sweeps cannot give {len(targets)} targets {min_per_target} each")
    chosen: list[int] = []

    def scores(base: list[Array]) -> Array:
        H = _information(base[0] + cAA, base[1] + cAB, base[2] + cBB)
        # The greedy start ranks by D (defined from the first sweep on); the exchange
        # by the criterion asked for.
        return _score(H, crit, M, ridge)

    if not repeats and n > len(cands):
        raise ValueError(f"{n} sweeps from {len(cands)} candidates: too few candidates")
    taken = np.zeros(len(cands), dtype=bool)
    barred = np.zeros(len(cands), dtype=bool)

    def masked(s: Array) -> Array:
        s = np.where(barred, -np.inf, s)
        return s if repeats else np.where(taken, -np.inf, s)

    def best_of(s: Array) -> int:
        """The best candidate by ``s`` that is admissible (the others barred)."""
        s = s.copy()
        while True:
            k = int(np.argmax(s))
            if admissible is None or not np.isfinite(s[k]) or barred[k] or admissible(k):
                return k
            barred[k] = True
            s[k] = -np.inf

    def counts(ks: list[int]) -> dict[int, int]:
        return {int(g): sum(1 for k in ks if cands.target[k] == g) for g in targets}

    crit: Criterion = "D"
    for step in range(n):
        s = masked(scores(sums))
        # The targets still short of their minimum when no more sweeps can be spared.
        have = counts(chosen)
        short = [g for g in targets if have[g] < min_per_target]
        if short and sum(min_per_target - have[g] for g in short) >= n - step:
            s = np.where(np.isin(cands.target, short), s, -np.inf)
        k = best_of(s)
        if not np.isfinite(s[k]) or barred[k]:
            raise ValueError(f"only {step} of the {n} sweeps can be admitted")
        taken[k] = True
        chosen.append(k)
        sums = [sums[0] + cAA[k], sums[1] + cAB[k], sums[2] + cBB[k]]
    crit = criterion
    best = float(_score(_information(*sums), crit, M, ridge))
    for _ in range(max_passes):
        improved = False
        for i in range(len(chosen)):
            k = chosen[i]
            without = [sums[0] - cAA[k], sums[1] - cAB[k], sums[2] - cBB[k]]
            s = masked(scores(without))
            if min_per_target and counts(chosen)[int(cands.target[k])] <= min_per_target:
                # Only a sweep of the same target may take its place.
                s = np.where(cands.target == cands.target[k], s, -np.inf)
            # Only a candidate that would improve is asked whether it is admissible.
            better = np.where(s > best + 1e-9 * abs(best), s, -np.inf)
            j = best_of(better) if np.isfinite(better).any() else k
            if np.isfinite(better[j]) and not barred[j] and j != k:
                chosen[i], best, improved = j, float(s[j]), True
                taken[k], taken[j] = False, True
                sums = [without[0] + cAA[j], without[1] + cAB[j], without[2] + cBB[j]]
        if not improved:
            break
    return chosen


def sweep_scores(
    cands: Candidates,
    chosen: Sequence[int],
    *,
    criterion: Criterion = "D",
    M: Array | None = None,
) -> Array:
    """Per candidate, the criterion of the sweeps ``chosen`` with it added (higher is
    better): what :func:`next_sweep` ranks by."""
    M = np.eye(6) if M is None else np.asarray(M, dtype=float)
    S_AA, S_AB, S_BB = cands.sums(chosen)
    cAA, cAB, cBB = cands.contributions()
    H = _information(S_AA + cAA, S_AB + cAB, S_BB + cBB)
    ridge = 1e-9 * float(np.trace(cAA.mean(axis=0)))
    # With fewer than a handful of sweeps only D is defined; then the criterion asked for.
    return _score(H, criterion if len(chosen) >= 3 else "D", M, ridge)


def next_sweep(
    cands: Candidates,
    chosen: Sequence[int],
    *,
    exclude: Sequence[int] = (),
    criterion: Criterion = "D",
    M: Array | None = None,
) -> int:
    """The candidate that adds most to the sweeps ``chosen`` so far (the sequential
    mode's step: the sweeps actually localized, not the ones planned), none of
    ``exclude`` (tried already, whether they were localized or not)."""
    s = sweep_scores(cands, chosen, criterion=criterion, M=M)
    s[np.asarray(list(exclude), dtype=int)] = -np.inf
    if not np.isfinite(s).any():
        raise ValueError("every candidate has been tried")
    return int(np.argmax(s))


@dataclass(frozen=True)
class PlanPrediction:
    """What a plan predicts of ``T_ee_us`` for its noise model: 1 σ (RMS over the axes)
    of the rotation (°) and translation (mm), the RMS image error (mm), the condition
    number of its information and the covariance of θ = (ω rad, t mm)."""

    rotation_deg: float
    translation_mm: float
    image_mm: float
    condition_number: float
    covariance: Array


def _fit_covariance(cands: Candidates, chosen: Sequence[int]) -> Array:
    """(6, 6) covariance of θ as :func:`calib.calibration.markers.calibrate` estimates it: least
    squares of the centres' base-frame residuals, every axis weighed alike, under the
    anisotropic noise ``S`` — the sandwich N⁻¹ (Σ Jᵀ S J) N⁻¹, N = Σ JᵀJ. It exceeds the
    inverse information (the efficient, noise-weighted fit) the more the plan turns the
    image's noisy elevation axis about. The layout prior acts as the fit applies it: at
    the weight of a typical centre's variance."""
    assert cands.G is not None and cands.D is not None and cands.S is not None
    k = np.asarray(chosen, dtype=int)
    J = np.concatenate([cands.G[k], cands.D[k]], axis=2)
    S = cands.S[k]
    N = np.einsum("nij,nik->jk", J, J)
    mid = np.einsum("nji,njk,nkl->il", J, S, J)
    if cands.prior is not None:
        s2 = float(np.mean(np.trace(S, axis1=1, axis2=2))) / 3
        P = np.zeros_like(N)
        P[6:, 6:] = cands.prior
        N, mid = N + s2 * P, mid + s2**2 * P
    Ninv = np.linalg.pinv(N, hermitian=True)
    return (Ninv @ mid @ Ninv)[:6, :6]


def bias_covariance(T_ee_us: ArrayLike, bias_mm: Sequence[float]) -> Array:
    """(6, 6) covariance of θ from an offset shared by every centre of a session (1 σ
    per image axis, mm): the fit moves ``t_X`` by −R_X δ, whatever the plan, and leaves
    the rotation alone."""
    R = np.asarray(T_ee_us, dtype=float)[:3, :3]
    cov = np.zeros((6, 6))
    cov[3:, 3:] = R @ np.diag(np.square(np.asarray(bias_mm, dtype=float))) @ R.T
    return cov


def predict(
    cands: Candidates, chosen: Sequence[int], M: Array, *, bias: Array | None = None
) -> PlanPrediction:
    """The prediction of the sweeps ``chosen`` (indices into ``cands``, repeats
    allowed), with the covariance ``bias`` of a session's shared offset added
    (:func:`bias_covariance`)."""
    H = _information(*cands.sums(chosen))
    w = np.linalg.eigvalsh(0.5 * (H + H.T))
    cov = np.linalg.pinv(H, hermitian=True) if cands.G is None else _fit_covariance(cands, chosen)
    if bias is not None:
        cov = cov + bias
    return PlanPrediction(
        rotation_deg=float(np.degrees(np.sqrt(np.trace(cov[:3, :3])))),
        translation_mm=float(np.sqrt(np.trace(cov[3:, 3:]))),
        image_mm=float(np.sqrt(np.einsum("ij,ji->", M, cov))),
        condition_number=float(w[-1] / w[0]) if w[0] > 0 else float("inf"),
        covariance=cov,
    )
