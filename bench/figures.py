"""Figures of a run, as PNG files (matplotlib, no display needed)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from calib.evaluate import PHANTOM_TITLES

from .reconstruction import METHODS, PhantomReconstruction

__all__ = ["reconstruction_heatmaps"]

_METHOD_TITLES = {"single": "single-marker (sphere 1)", "three": "three-marker (spheres 1–3)"}


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
    columns = [(m, s) for m in METHODS for s in sets]
    fig = Figure(figsize=(2.6 * len(columns) + 1.0, 2.8 * len(parts)), layout="constrained")
    axes = fig.subplots(len(parts), len(columns), squeeze=False)
    for row, part in zip(axes, parts, strict=True):
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
            mae = part.metrics[method][s]["mae"]
            ax.set_title(
                f"{PHANTOM_TITLES[part.kind]}, set {s}\n{_METHOD_TITLES[method]}\nMAE {mae:.2f} mm",
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
