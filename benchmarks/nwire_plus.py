"""uscal's threshold-free N-wire detection (calib/localize/nwire.py) against PLUS's own
segmentation, on PLUS's real fCal 2.0 calibration sweep (``../shared/data/plus``):
frames found by each, the distance from uscal's points to PLUS's (pixels, same wire
name), the time per frame; and a figure of the frames where the two disagree most (PLUS's
points as circles, uscal's as crosses), written to ``docs/figures/nwire_vs_plus.png``.

Then the calibration (issue 37, item 3; :func:`calib.calibration.nwire.calibrate_nwire`
from uscal's own detection, as ``uscal calibrate`` runs it) beside PLUS's answer: the
3-D reprojection error as PLUS states it (mean and SD below the 95th percentile, as its
source computes it) of each transform on uscal's points, on PLUS's points, and on PLUS's
separate validation sweep (its segmented points and tracked poses from the results file:
its images are not published); the two transforms' distance over the image and their
rotation; each half of the frames calibrated and measured on the other (what a bound
must cover); and the same frames with the phantom's pose left to the fit (a robot rig's
case). Last line: ``found=<uscal>/<frames> plus=<PLUS> median_px=<median>
reprojection_mm=… plus_reprojection_mm=… validation_mm=… plus_validation_mm=…
image_vs_plus_mm=<max over the image corners> rotation_vs_plus_deg=…``.

Run: python benchmarks/nwire_plus.py [--data ../shared/data/plus] [--figure PATH]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from calib.calibration.nwire import (  # noqa: E402
    NWireObservations,
    calibrate_nwire,
    observations_of,
    observe_nwires,
    plus_error_mm,
    reprojection_errors_mm,
)
from calib.calibration.targets import judge_targets  # noqa: E402
from calib.errors import CalibrationError  # noqa: E402
from calib.files.metafile import read_metafile  # noqa: E402
from calib.files.plus_config import read_plus_config, read_plus_results  # noqa: E402
from calib.files.plus_import import plus_frames  # noqa: E402
from calib.localize.nwire import NWireDetection, detect_nwires  # noqa: E402

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
    fig = calibrate_against_plus(data, config, results, frames)
    print(
        f"found={n_ours}/{len(frames)} plus={n_plus} median_px={np.median(d):.3f} "
        + " ".join(f"{k}={v:.3f}" for k, v in fig.items())
    )


def _plus_observations(config, frames, spacing) -> NWireObservations:
    """PLUS's segmentation of ``frames`` (in frame order) read as uscal reads its own
    detections: the diagonal-wire point of each pattern from PLUS's three dots."""
    detections = [NWireDetection(f.ok, f.points) for f in frames]
    return observations_of(detections, config.patterns, tuple(spacing))


def calibrate_against_plus(data: Path, config, results, frames) -> dict[str, float]:
    """uscal's calibration (calib.calibration.nwire, from uscal's own detection) beside
    PLUS's answer, each measured by PLUS's 3-D error on both sets of points, on PLUS's
    separate validation sweep (its segmented points and tracked poses: the images are not
    published), and half against half."""
    tracked = plus_frames(data / config.sequence_file, "ProbeToReference").T_base_probe
    spacing = np.array(config.pixel_spacing_mm())
    T_phantom = config.transform("Phantom", "Reference")
    H, W = frames.shape[1:]
    obs = observe_nwires(frames, config.patterns, tuple(spacing))
    cal = calibrate_nwire(
        obs, tracked, width_px=W, height_px=H, spacing_m=tuple(spacing * 1e-3),
        T_base_phantom=T_phantom,
    )  # fmt: skip
    ours = cal.image_to_probe_mm()
    theirs = results.image_to_probe.copy()
    theirs[:3, :] *= 1e3
    assert [f.index for f in results.calibration] == list(range(len(tracked)))
    plus_points = _plus_observations(config, results.calibration, spacing)
    valid = [f for f in results.validation if f.ok]
    valid_points = _plus_observations(config, valid, spacing)
    valid_poses = np.array([f.transform("ProbeToReference") for f in valid])
    stated = results.reprojection_3d_mm
    print(f"\nImageToProbe from uscal's own points ({len(obs.frame)} diagonal-wire points):")
    print(
        f"  pixel spacing fitted {cal.spacing_m[0] * 1e3:.5f} × {cal.spacing_m[1] * 1e3:.5f} mm;"
        f" 95 % bound {cal.bound95['rotation_deg']:.2f}°, {cal.bound95['translation_mm']:.2f} "
        f"mm, {cal.bound95['image_mm']:.2f} mm over the image; verdict "
        f"{judge_targets(cal).line()}"
    )
    print("  3-D error as PLUS states it (mean ± SD below the 95th percentile), mm:")
    print(f"  {'transform':10s} {'uscal pts':>15s} {'PLUS pts':>15s} {'PLUS validation':>16s}")
    figures = {}
    for name, A in (("uscal", ours), ("PLUS", theirs)):
        cells = [
            plus_error_mm(reprojection_errors_mm(o, poses, A, T_phantom))
            for o, poses in ((obs, tracked), (plus_points, tracked), (valid_points, valid_poses))
        ]
        print(f"  {name:10s} " + " ".join(f"{m:8.3f} ± {s:5.3f}" for m, s in cells))
        figures[name] = cells
    print(
        f"  (PLUS states {stated['calibration_mean_mm']:.3f} ± "
        f"{stated['calibration_sd_mm']:.3f} on its calibration frames, "
        f"{stated['validation_mean_mm']:.3f} ± {stated['validation_sd_mm']:.3f} on validation)"
    )
    corners = np.array([[0, 0, 0, 1], [W - 1, 0, 0, 1], [0, H - 1, 0, 1], [W - 1, H - 1, 0, 1],
                        [W / 2, H / 2, 0, 1]])  # fmt: skip
    away = np.linalg.norm((corners @ ours.T - corners @ theirs.T)[:, :3], axis=1)
    RA, RB = (M[:3, :3] / np.linalg.norm(M[:3, :3], axis=0) for M in (ours, theirs))
    turn = float(np.degrees(np.arccos(np.clip((np.trace(RA.T @ RB) - 1) / 2, -1, 1))))
    print(f"  uscal's vs PLUS's over the image: {np.round(away, 3)} mm; rotation {turn:.3f}°")
    # Half against half: calibrate on one half of the frames, measure on the other.
    half = len(frames) // 2
    print("  half against half (calibrated on one, 3-D error on the other):")
    for train, test in (
        (obs.frame < half, obs.frame >= half),
        (obs.frame >= half, obs.frame < half),
    ):
        part = calibrate_nwire(
            obs.subset(train), tracked, width_px=W, height_px=H,
            spacing_m=tuple(spacing * 1e-3), T_base_phantom=T_phantom, n_draws=500,
        )  # fmt: skip
        e = reprojection_errors_mm(obs.subset(test), tracked, part.image_to_probe_mm(), T_phantom)
        m, sd = plus_error_mm(e)
        moved = np.linalg.norm(
            (corners @ part.image_to_probe_mm().T - corners @ ours.T)[:, :3], axis=1
        )
        print(
            f"    frames {'first' if train[0] else 'second'} half → other: {m:.3f} ± {sd:.3f} mm "
            f"(in-sample {plus_error_mm(part.errors_mm)[0]:.3f}); from the whole's answer "
            f"{moved[:4].mean():.2f} mm at the corners, {moved[4]:.2f} at the centre; its "
            f"bound over the image {part.bound95['image_mm']:.2f} mm"
        )
    # The robotic case on the same frames: the phantom's pose left to the fit.
    try:
        robot = calibrate_nwire(
            obs, tracked, width_px=W, height_px=H, spacing_m=tuple(spacing * 1e-3), n_draws=500
        )
        print(f"  phantom pose estimated too (a robot rig): {judge_targets(robot).line()}")
    except CalibrationError as e:
        print(f"  phantom pose estimated too (a robot rig): refused: {e}")
    return {
        "reprojection_mm": figures["uscal"][0][0],
        "plus_reprojection_mm": figures["PLUS"][0][0],
        "validation_mm": figures["uscal"][2][0],
        "plus_validation_mm": figures["PLUS"][2][0],
        "image_vs_plus_mm": float(away.max()),
        "rotation_vs_plus_deg": turn,
    }


if __name__ == "__main__":
    main()
