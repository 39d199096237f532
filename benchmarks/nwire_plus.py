"""uscal's threshold-free N-wire detection (calib/nwire.py) against PLUS's own
segmentation, on PLUS's real fCal 2.0 calibration sweep (``../shared/data/plus``):
frames found by each, the distance from uscal's points to PLUS's (pixels, same wire
name), the time per frame; and a figure of the frames where the two disagree most (PLUS's
points as circles, uscal's as crosses), written to ``docs/figures/nwire_vs_plus.png``.

Then an experiment ahead of the pipeline (issue 37, item 3): ``ImageToProbe`` fitted
from uscal's own points — each frame's diagonal-wire points (:func:`calib.nwire.
middle_wire_point`) mapped to the Reference frame through PLUS's ``Phantom`` →
``Reference`` definition, against the image points through the tracked
``ProbeToReference`` (composed per frame) and the unknown ``ImageToProbe`` with the
pixel scale free (robust least squares) — beside PLUS's answer: the 3-D error (the
distance between the wire point and the image point mapped through the calibration and
the tracking, mm) of each transform on each set of points, and the two transforms'
distance over the image; the 3-D error also as PLUS states it (mean and SD of the errors
below the 95th percentile, as its source computes it). Last line:
``found=<uscal>/<frames> plus=<PLUS> median_px=<median> image_vs_plus_mm=<max over the
image corners>``.

Run: python benchmarks/nwire_plus.py [--data ../shared/data/plus] [--figure PATH]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from calib import se3  # noqa: E402
from calib.metafile import read_metafile  # noqa: E402
from calib.nwire import detect_nwires, middle_wire_point  # noqa: E402
from calib.plus_config import read_plus_config, read_plus_results  # noqa: E402
from calib.plus_import import plus_frames  # noqa: E402

CONFIG = "PlusDeviceSet_fCal_Sim_SpatialCalibration_2.0.xml"
RESULTS = "FreehandCalibration3NWires_fCal2.0.results.xml"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "plus"))
    ap.add_argument("--figure", default=str(ROOT / "docs" / "figures" / "nwire_vs_plus.png"))
    args = ap.parse_args()
    data = Path(args.data)
    config, results = read_plus_config(data / CONFIG), read_plus_results(data / RESULTS)
    frames = read_metafile(data / config.sequence_file).images
    spacing = config.pixel_spacing_mm()
    t0 = time.perf_counter()
    found = [detect_nwires(f, config.patterns, spacing) for f in frames]
    per_frame_ms = 1e3 * (time.perf_counter() - t0) / len(frames)
    plus = results.calibration
    worst: list[tuple[float, int]] = []
    distances = []
    for k, (ours, theirs) in enumerate(zip(found, plus, strict=True)):
        if ours.ok and theirs.ok:
            d = [np.hypot(*np.subtract(p, theirs.points[n])) for n, p in ours.points.items()]
            distances += d
            worst.append((max(d), k))
    d = np.array(distances)
    n_ours, n_plus = sum(f.ok for f in found), sum(p.ok for p in plus)
    only_ours = [k for k, (a, b) in enumerate(zip(found, plus, strict=True)) if a.ok and not b.ok]
    print(f"{len(frames)} frames, pixel spacing {spacing[0]:.4f} × {spacing[1]:.4f} mm")
    print(f"found: uscal {n_ours}, PLUS {n_plus}; uscal only: frames {only_ours}")
    print(
        f"distance to PLUS's point of the same wire: median {np.median(d):.2f} px, p90 "
        f"{np.percentile(d, 90):.2f}, max {d.max():.2f} ({np.median(d) * spacing[0]:.3f} mm)"
    )
    print(f"{per_frame_ms:.1f} ms per frame")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [k for _, k in sorted(worst, reverse=True)[:3]] + only_ours[:1]
    fig, axes = plt.subplots(1, len(shown), figsize=(4.2 * len(shown), 3.6))
    for ax, k in zip(np.atleast_1d(axes), shown, strict=True):
        ax.imshow(frames[k], cmap="gray", vmax=max(int(frames[k].max()), 1))
        if plus[k].ok:
            px = np.array(list(plus[k].points.values()))
            ax.scatter(px[:, 0], px[:, 1], s=70, facecolors="none", edgecolors="tab:red")
        if found[k].ok:
            ux = np.array(list(found[k].points.values()))
            ax.scatter(ux[:, 0], ux[:, 1], s=40, marker="+", color="tab:cyan")
        title = f"frame {k}" + ("" if plus[k].ok else " (PLUS: failed)")
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle("PLUS's segmentation (red circles) and uscal's (cyan crosses)", fontsize=10)
    fig.tight_layout()
    Path(args.figure).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.figure, dpi=90)
    print(f"wrote {args.figure}")
    away = calibrate_against_plus(data, config, results, found)
    print(
        f"found={n_ours}/{len(frames)} plus={n_plus} median_px={np.median(d):.3f} "
        f"image_vs_plus_mm={away:.3f}"
    )


def _wire_points(config, segmentations, spacing):
    """(frame, column, row, Reference-frame point in m) of every diagonal wire."""
    T_ref_phantom = config.transform("Phantom", "Reference")
    out = []
    for k, seg in segmentations:
        for pattern in config.patterns:
            pa, pm, pb = (np.array(seg.points[w.name]) * spacing for w in pattern.wires)
            P = se3.apply(T_ref_phantom, middle_wire_point(pattern, pa, pm, pb))
            out.append((k, *seg.points[pattern.wires[1].name], P))
    return out


def calibrate_against_plus(data: Path, config, results, found) -> float:
    """The experiment of the module doc; returns the largest distance (mm) between
    uscal's and PLUS's transform over the image's corners and centre."""
    tracked = plus_frames(data / config.sequence_file, "ProbeToReference").T_base_probe
    spacing = np.array(config.pixel_spacing_mm())
    ours = _wire_points(config, [(k, f) for k, f in enumerate(found) if f.ok], spacing)
    plus = _wire_points(config, [(s.index, s) for s in results.calibration if s.ok], spacing)

    def mapped(x, rows):
        k = np.array([r[0] for r in rows])
        uv = np.array([[r[1], r[2]] for r in rows])
        R = se3.matrix_from_rotvec(x[:3])
        p_probe = np.column_stack([uv * x[6:8], np.zeros(len(uv))]) @ R.T + x[3:6]
        T = tracked[k]
        return np.einsum("nij,nj->ni", T[:, :3, :3], p_probe) + T[:, :3, 3]

    def errors_mm(x, rows):
        return 1e3 * np.linalg.norm(mapped(x, rows) - np.array([r[3] for r in rows]), axis=1)

    A = results.image_to_probe[:3, :3]
    scale = np.linalg.norm(A, axis=0)
    U, _, Vt = np.linalg.svd(A / scale)
    origin = results.image_to_probe[:3, 3]
    x_plus = np.concatenate([se3.rotvec_from_matrix(U @ Vt), origin, scale[:2]])
    fit = least_squares(
        lambda x: (mapped(x, ours) - np.array([r[3] for r in ours])).ravel() * 1e3,
        x_plus,
        loss="soft_l1",
    )
    x_ours = fit.x
    print(f"\nImageToProbe from uscal's own points ({len(ours)} diagonal-wire points):")
    print(f"  pixel spacing fitted {x_ours[6] * 1e3:.5f} × {x_ours[7] * 1e3:.5f} mm")

    def trimmed(e):
        """PLUS's statistic: mean and SD of the errors below the 95th percentile (its
        ``ErrorConfidenceLevel``, vtkProbeCalibrationAlgo's ComputePercentile)."""
        kept = e[e <= np.percentile(e, 95)]
        return kept.mean(), kept.std()

    for name, x in (("uscal's", x_ours), ("PLUS's", x_plus)):
        e_o, e_p = errors_mm(x, ours), errors_mm(x, plus)
        print(
            f"  {name:8s} transform: 3-D error on uscal's points {e_o.mean():.3f} ± "
            f"{e_o.std():.3f} mm, on PLUS's points {e_p.mean():.3f} ± {e_p.std():.3f} mm; "
            "as PLUS states it (below the 95th percentile): %.3f ± %.3f, %.3f ± %.3f"
            % (*trimmed(e_o), *trimmed(e_p))
        )
    stated = results.reprojection_3d_mm
    print(
        f"  (PLUS reports {stated['calibration_mean_mm']:.3f} ± "
        f"{stated['calibration_sd_mm']:.3f} mm on its calibration frames)"
    )
    H, W = 616, 820
    corners = np.array([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1], [W / 2, H / 2]])

    def in_probe(x):
        R = se3.matrix_from_rotvec(x[:3])
        return np.column_stack([corners * x[6:8], np.zeros(len(corners))]) @ R.T + x[3:6]

    away = 1e3 * np.linalg.norm(in_probe(x_ours) - in_probe(x_plus), axis=1)
    turn = np.degrees(np.linalg.norm(se3.rotvec_from_matrix(
        se3.matrix_from_rotvec(x_ours[:3]).T @ se3.matrix_from_rotvec(x_plus[:3])
    )))  # fmt: skip
    print(f"  uscal's vs PLUS's over the image: {np.round(away, 3)} mm; rotation {turn:.3f}°")
    return float(away.max())


if __name__ == "__main__":
    main()
