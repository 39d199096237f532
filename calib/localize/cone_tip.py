"""A cone's tip in a sweep, threshold-free (the paper's "Geometric Analysis of Calibration
Targets": a cone tip is a point target, read where the image plane passes over the
apex; issue "N-wire and wire targets", item 5).

A vertical image plane at elevation ``e`` from a cone's axis (apex up, half-angle α)
cuts its surface along a hyperbola: at lateral ``x`` the surface lies at depth

    d(x, e) = d₀ + c · √((x − x₀)² + (e − e₀)²),      c = cot α,

with the apex at (x₀, d₀, e₀). The sweep's frames are planes at known elevations (the
robot's own positions along the image normal), so one fit over every frame gives the
apex in three dimensions:

1. **Adaptive brightness** (the paper's, §III-E-1): a pixel is bright when it is above
   its own frame's mean grey level; no level is chosen.
2. **Upper envelope.** In every frame, each column's surface echo: the peak of its
   first bright run in the frame's largest bright region (the cone's section: one
   connected ∧).
3. **Fit.** Robust least squares (soft-L1 at the envelope's own MAD scale) of the
   envelope depths over the whole sweep for (x₀, d₀, e₀, c) and the slice's half
   thickness ``w``: within ``w`` of the apex's elevation the slice still holds the
   apex, the hyperbola's vertex is the apex's depth (``|e − e₀|`` becomes
   ``max(|e − e₀| − w, 0)``).

A sweep is refused, with its reason, when too few frames show the cone, when the fit's
apex lies outside the sweep or the image, or when the envelope does not follow a cone
(its scatter about the fit more than a few pixels).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.optimize import least_squares

__all__ = ["ConeTip", "locate_cone_tip"]

Array = NDArray[np.float64]
#: Frames showing the cone's section needed for a fit of five unknowns, with margin.
MIN_FRAMES = 7
#: The envelope scatters about a cone by a few pixels (speckle on its surface); more
#: than this many pixels (rms, robust) is not a cone's section.
_MAX_SCATTER_PX = 4.0


@dataclass(frozen=True)
class ConeTip:
    """One sweep's result: ``ok``; the apex's lateral ``x_m`` and ``depth_m`` in the
    image frame and its elevation ``elevation_m`` along the sweep (the same axis as the
    elevations given); ``half_angle_deg`` the cone's as fitted; ``scatter_px`` the
    envelope's robust scatter about the fit; ``frames`` the frames it rests on; the
    ``reason`` when not ok; ``slice_half_m`` the slice's half thickness at the apex as
    fitted (the apex's elevation is not resolved within it: a view-dependent bias)."""

    ok: bool
    x_m: float = float("nan")
    depth_m: float = float("nan")
    elevation_m: float = float("nan")
    half_angle_deg: float = float("nan")
    scatter_px: float = float("nan")
    frames: int = 0
    reason: str = ""
    slice_half_m: float = float("nan")


def _envelope(frame: NDArray[np.uint8]) -> tuple[Array, Array]:
    """(columns, rows) of each column's surface echo in the frame's largest bright region
    (bright: above the frame's mean): the peak of the column's first bright run, where
    the surface's echo is drawn (its leading edge lies half a pulse above the surface,
    its grey-weighted centre below it where speckle trails; measured on the twin's cone
    against its truth: depth 0.23 mm off at the peak, −0.59 at the edge, 0.38 at the
    centre)."""
    smooth = ndimage.uniform_filter(frame.astype(np.float32), 3)
    bright = smooth > float(frame.mean())
    labels, n = ndimage.label(bright)
    if n == 0:
        return np.zeros(0), np.zeros(0)
    sizes = ndimage.sum_labels(np.ones_like(labels), labels, index=np.arange(1, n + 1))
    region = labels == int(np.argmax(sizes)) + 1
    cols = np.flatnonzero(region.any(axis=0))
    first = np.argmax(region[:, cols], axis=0)
    rows = np.empty(len(cols))
    H = frame.shape[0]
    for i, (c, r0) in enumerate(zip(cols, first, strict=True)):
        r1 = r0
        while r1 + 1 < H and region[r1 + 1, c]:
            r1 += 1
        w = smooth[r0 : r1 + 1, c]
        rows[i] = r0 + float(np.argmax(w))
    return cols.astype(float), rows


def locate_cone_tip(
    images: NDArray[np.uint8],
    elevations_m: NDArray[np.float64],
    spacing_m: tuple[float, float],
    width_px: int,
) -> ConeTip:
    """The apex of a cone swept by ``images`` (n, H, W) at elevations ``elevations_m``
    (n,) along the image normal; see the module doc. Lateral ``x`` about the image's
    centre column, as the image frame has it."""
    sx, sy = spacing_m
    xs, ds, es = [], [], []
    seen = 0
    for frame, e in zip(images, elevations_m, strict=True):
        cols, rows = _envelope(frame)
        if len(cols) < 5:
            continue
        seen += 1
        xs.append((cols - (width_px - 1) / 2) * sx)
        ds.append(rows * sy)
        es.append(np.full(len(cols), e))
    if seen < MIN_FRAMES:
        return ConeTip(False, frames=seen, reason=f"the cone in {seen} frames; {MIN_FRAMES} needed")
    x, d, e = np.concatenate(xs), np.concatenate(ds), np.concatenate(es)
    top = int(np.argmin(d))
    # (x₀, d₀, e₀) the apex; (a_x, a_z) the axis's tilt (it points up, −depth, tilted by
    # the frames' own turn and the cone's mount); c = cot α; w the slice's half thickness.
    start = np.array([x[top], d[top], e[top], 0.0, 0.0, 1.0, 0.0])
    scale = np.array([sx, sy, sx, 0.1, 0.1, 1.0, sx])

    def residual(p: Array) -> Array:
        x0, d0, e0, ax, az, c, w = p
        axis = np.array([ax, -1.0, az]) / np.sqrt(1.0 + ax * ax + az * az)
        # Within the slice's half thickness of the apex the slice still holds it.
        de = e - e0
        de = np.sign(de) * np.maximum(np.abs(de) - abs(w), 0.0)
        v = np.column_stack([x - x0, d - d0, de])
        along = -(v @ axis)  # below the apex, along the axis
        radial = np.linalg.norm(v + along[:, None] * axis, axis=1)
        s = 1.0 / np.sqrt(1.0 + c * c)  # sin α
        return (radial * c * s - along * s) / sy  # distance to the surface, pixels

    first = least_squares(residual, start, loss="soft_l1", f_scale=3.0, x_scale=scale)
    sigma = max(1.4826 * float(np.median(np.abs(first.fun))), 0.5)
    fit = least_squares(residual, first.x, loss="soft_l1", f_scale=sigma, x_scale=scale)
    x0, d0, e0, _, _, c, w = fit.x
    scatter = 1.4826 * float(np.median(np.abs(fit.fun)))
    half_angle = float(np.degrees(np.arctan2(1.0, c)))
    if scatter > _MAX_SCATTER_PX or c <= 0:
        return ConeTip(
            False, frames=seen, scatter_px=scatter,
            reason=f"the echoes do not follow a cone (scatter {scatter:.1f} px about the fit)",
        )  # fmt: skip
    if not (elevations_m.min() <= e0 <= elevations_m.max()):
        return ConeTip(
            False, frames=seen, reason="the apex lies outside the sweep: sweep across the tip"
        )
    if not (abs(x0) <= (width_px - 1) / 2 * sx and d0 >= 0):
        return ConeTip(False, frames=seen, reason="the apex lies outside the image")
    return ConeTip(
        True,
        float(x0),
        float(d0),
        float(e0),
        half_angle,
        scatter,
        seen,
        "",
        float(abs(w)),
    )
