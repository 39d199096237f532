"""uscal's threshold-free N-wire detection (calib/nwire.py) against PLUS's own
segmentation, on PLUS's real fCal 2.0 calibration sweep (``../shared/data/plus``):
frames found by each, the distance from uscal's points to PLUS's (pixels, same wire
name), the time per frame; and a figure of the frames where the two disagree most (PLUS's
points as circles, uscal's as crosses), written to ``docs/figures/nwire_vs_plus.png``.
Last line: ``found=<uscal>/<frames> plus=<PLUS> median_px=<median> p90_px=<p90>``.

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

from calib.metafile import read_metafile  # noqa: E402
from calib.nwire import detect_nwires  # noqa: E402
from calib.plus_config import read_plus_config, read_plus_results  # noqa: E402

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
    print(
        f"found={n_ours}/{len(frames)} plus={n_plus} median_px={np.median(d):.3f} "
        f"p90_px={np.percentile(d, 90):.3f}"
    )


if __name__ == "__main__":
    main()
