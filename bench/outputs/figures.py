"""Figures of a run, as PNG files (matplotlib, no display needed)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from calib.acquisition.observability import information, jacobians
from calib.calibration.alternation import AlternationResult
from calib.evaluation.cross_validation import METHOD_TITLES, PHANTOM_TITLES, TABLE_III_METHODS

from ..results import PhantomReconstruction
from ..snapshot import LocalizationSnapshot
from ..summaries import PhantomStats

__all__ = [
    "convergence_figure",
    "observability_eigenvalues",
    "observability_figure",
    "overlay_figure",
    "profile_figure",
    "reconstruction_heatmaps",
]

Array = NDArray[np.float64]


def _figure(**kwargs):
    """A matplotlib ``Figure``, imported here: the pool's workers import this module
    (for its snapshot types) and never draw; matplotlib costs ≈ 0.25 s to import."""
    from matplotlib.figure import Figure

    return Figure(**kwargs)


def _circle(*args, **kwargs):
    """A matplotlib ``Circle`` patch (imported here, as :func:`_figure`)."""
    from matplotlib.patches import Circle

    return Circle(*args, **kwargs)


def overlay_figure(snap: LocalizationSnapshot, path: str | Path) -> Path:
    """The paper's figure of sphere cross-sections: frames across the sphere, the found
    section in red (the true one in green where the twin knows it)."""
    path = Path(path)
    k = len(snap.frames)
    cols = min(k, 4)
    rows = -(-k // cols)
    H, W = snap.frames.shape[1:]
    fig = _figure(figsize=(2.4 * cols, 2.4 * rows * H / W + 0.5), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    for ax, img, z, det, tru in zip(
        axes, snap.frames, snap.elevation_mm, snap.detected, snap.true, strict=False
    ):
        ax.imshow(img, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        for circle, colour in ((tru, "#30c050"), (det, "#e02020")):
            if circle is not None:
                c, r, rad = circle
                ax.add_patch(_circle((c, r), rad, fill=False, color=colour, lw=1.0))
        ax.set_title(f"{z:+.1f} mm", fontsize=8)
        ax.set_axis_off()
    for ax in axes[k:]:
        ax.set_axis_off()
    fig.suptitle(f"{snap.title}: found section (red), true (green)", fontsize=9)
    fig.savefig(path, dpi=100)
    return path


def profile_figure(snap: LocalizationSnapshot, path: str | Path) -> Path:
    """The radial brightness profile about the found centres, with the 0.25 / 0.75
    crossings that set the interior and shell bands (paper, threshold-free localization)."""
    path = Path(path)
    prof = snap.profile
    fig = _figure(figsize=(5.0, 3.0), layout="constrained")
    ax = fig.subplots()
    ax.plot(prof.radii * 1e3, prof.profile, color="#2060c0")
    for x, y, label, crossed in zip(
        (prof.interior, *prof.shell),
        (0.25, 0.75, 0.75),
        ("interior", "shell", None),
        prof.crossed,
        strict=True,
    ):
        # A missing crossing: the band's fall-back (a share of the CAD radius), hollow.
        ax.plot([x * 1e3], [y], "o", color="#e02020", mfc="#e02020" if crossed else "none")
        ax.axvline(x * 1e3, color="#e02020", lw=0.6, ls=":")
        if label:
            text = label if crossed else f"{label} (no crossing: fall-back)"
            ax.annotate(text, (x * 1e3, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.axvline(snap.radius * 1e3, color="0.5", lw=0.8, ls="--", label="CAD radius")
    ax.set_xlabel("distance from the found centre (mm)")
    ax.set_ylabel("bright share (of the peak)")
    sphere = snap.title.split(",")[0]
    ax.set_title(f"{sphere}: radial profile over {prof.n_sweeps} sweeps", fontsize=9)
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    return path


def convergence_figure(alternations: Mapping[str, AlternationResult], path: str | Path) -> Path:
    """Loss and estimate change per localize/calibrate alternation."""
    path = Path(path)
    fig = _figure(figsize=(7.5, 2.8), layout="constrained")
    ax_loss, ax_change = fig.subplots(1, 2)
    for name, alt in alternations.items():
        it = [h["iteration"] for h in alt.history]
        ax_loss.plot(it, [h["cost_mm2"] for h in alt.history], "o-", label=name)
        ch = [(h["iteration"], h["change_mm"], h["change_deg"]) for h in alt.history]
        ch = [c for c in ch if np.isfinite(c[1])]
        if ch:
            ax_change.semilogy([c[0] for c in ch], [c[1] for c in ch], "o-", label=f"{name}: mm")
            ax_change.semilogy([c[0] for c in ch], [c[2] for c in ch], "s--", label=f"{name}: °")
    ax_loss.set_xlabel("iteration")
    ax_loss.set_ylabel("loss (mm²)")
    ax_change.set_xlabel("iteration")
    ax_change.set_ylabel("change of T_ee_us")
    for ax in (ax_loss, ax_change):
        ax.legend(fontsize=7)
        ax.tick_params(labelsize=7)
    fig.savefig(path, dpi=110)
    return path


def observability_eigenvalues(alt: AlternationResult) -> Array:
    """Eigenvalues (descending) of the information matrix of the retained observations
    about the estimate: each sphere's point constraint, summed (calib.acquisition.observability)."""
    obs = [o for o, keep in zip(alt.observations, alt.result.retained, strict=True) if keep]
    H = np.zeros((6, 6))
    for target in sorted({o.target for o in obs}):
        mine = [o for o in obs if o.target == target]
        G = jacobians(
            np.array([o.T_base_ee for o in mine]),
            alt.result.T_ee_us,
            np.array([o.p_us for o in mine]),
        )
        H += information(G)
    return np.sort(np.linalg.eigvalsh(0.5 * (H + H.T)))[::-1]


def observability_figure(eigenvalues: Mapping[str, Array], path: str | Path) -> Path:
    """Eigenvalues of the calibrations' information matrices (θ = rotation vector in
    rad, translation in mm; points in mm), log scale: the smallest is the weakest
    direction of the pose set."""
    path = Path(path)
    fig = _figure(figsize=(5.0, 3.0), layout="constrained")
    ax = fig.subplots()
    width = 0.8 / max(len(eigenvalues), 1)
    for i, (name, w) in enumerate(eigenvalues.items()):
        ax.bar(np.arange(len(w)) + i * width, np.maximum(w, 1e-12), width, label=name, log=True)
    ax.set_xticks(np.arange(6) + 0.4 - width / 2, [f"λ{i + 1}" for i in range(6)])
    ax.set_ylabel("eigenvalue (mm² per unit θ²)")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    return path


def reconstruction_heatmaps(
    parts: Sequence[PhantomReconstruction],
    sets: Sequence[str],
    path: str | Path,
    max_points: int = 20_000,
) -> Path:
    """The paper's heatmap figure: orthographic top-down views of the registered points
    coloured by point-to-surface error, one row per phantom, one panel per method and
    set (single-marker sets first, then three-marker). One colour scale per row, up to
    the row's 99th percentile (the few larger errors saturate). At most ``max_points``
    points per panel are drawn (a random subset)."""
    path = Path(path)
    columns = [(m, s) for m in TABLE_III_METHODS for s in sets]
    fig = _figure(figsize=(2.6 * len(columns) + 1.0, 2.8 * len(parts)), layout="constrained")
    axes = fig.subplots(len(parts), len(columns), squeeze=False)
    for row, part in zip(axes, parts, strict=True):
        stats = PhantomStats.from_metrics(part.kind, part.metrics)
        top = float(np.percentile(np.concatenate([d for _, d in part.points.values()]), 99))
        scatter = None
        for ax, (method, s) in zip(row, columns, strict=True):
            P, d = part.points[(method, s)]
            # A random subset draws the same picture as 10⁵ points in a fraction of the time.
            pick = np.random.default_rng(0).permutation(len(d))[:max_points]
            order = pick[np.argsort(d[pick])]  # larger errors drawn last, on top
            scatter = ax.scatter(
                P[order, 0] * 1e3,
                P[order, 1] * 1e3,
                c=d[order],
                s=1.5,
                cmap="turbo",
                vmin=0.0,
                vmax=top,
                rasterized=True,
                linewidths=0,
            )
            mae = stats.cells[(method, s)].mae
            ax.set_title(
                f"{PHANTOM_TITLES[part.kind]}, set {s}\n{METHOD_TITLES[method]}\nMAE {mae:.2f} mm",
                fontsize=8,
            )
            ax.set_aspect("equal")
            ax.tick_params(labelsize=7)
            ax.set_xlabel("x (mm)", fontsize=7)
        row[0].set_ylabel("y (mm)", fontsize=7)
        if scatter is not None:
            fig.colorbar(scatter, ax=row.tolist(), shrink=0.9, label="point-to-surface (mm)")
    fig.savefig(path, dpi=110)
    return path
