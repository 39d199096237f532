"""Is the three-marker calibration ever worse than one marker? ``scenarios/quick.yaml``
over seeds 0-9 and print tolerances (1 σ per axis of each printed sphere centre), each
acquisition calibrated three ways on the same sweeps: single-marker (sphere 1), three
markers with the CAD layout taken as exact (the paper's loss), and three markers with the
printed layout estimated, the CAD as its prior at the print tolerance
(``calibration.layout: estimated``). Prints, per tolerance, the median and 90th percentile
of the true rotation, translation and image errors of each, and the estimated layout's
error against the printed one. Last line:
``ratio_rotation_three_vs_single=<median at the default tolerance>``.

Run: python benchmarks/layout_prior.py [--workers 2] [--seeds 10]
"""

from __future__ import annotations

import os
import sys

# benchmarks/sim_us.py shares its name with the package: keep this folder off the path.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import argparse  # noqa: E402
import concurrent.futures as cf  # noqa: E402
import multiprocessing  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

BASE = Path(__file__).resolve().parents[1] / "scenarios" / "quick.yaml"
TOLERANCES_MM = (0.1, 0.03, 0.3)  # the default first
METHODS = ("single", "three, CAD exact", "three, layout estimated")


def one(seed: int, tolerance_mm: float) -> dict:
    from dataclasses import replace

    from bench.acquire_sim import make_imager, make_twin, simulate_acquisition
    from bench.config.method import method_inputs
    from bench.config.scenario import load_scenario
    from bench.parallel import one_blas_thread
    from bench.truth import image_error_mm
    from calib import se3
    from calib.pipeline import calibrate_markers

    sc = load_scenario(
        BASE, [f"seed={seed}", f"phantom.tolerance_position_mm={tolerance_mm}"], check_reach=False
    )
    with one_blas_thread():
        twin = make_twin(sc)
        acq = simulate_acquisition(sc, twin, make_imager(sc, twin), f"layout-{seed}")
        truth = twin.truth
        cad = {k: v for k, v in twin.phantom_cad.landmarks.items() if k.startswith("sphere_")}
        inputs = method_inputs(sc, cad_centres=cad, T_coarse=acq.T_ee_us_coarse)

        def with_layout(sigma_mm: float):
            return replace(
                inputs, alternation=replace(inputs.alternation, layout_sigma_mm=sigma_mm)
            )

        exact = calibrate_markers(acq.dataset, with_layout(0.0), markers=(1, 3))
        est = calibrate_markers(acq.dataset, with_layout(tolerance_mm), markers=(3,))
    out = {}
    for name, alt in zip(METHODS, (exact.single, exact.three, est.three), strict=True):
        T = alt.result.T_ee_us
        out[name] = (
            float(np.degrees(se3.rotation_angle(T, truth.T_ee_us))),
            float(se3.translation_distance(T, truth.T_ee_us) * 1e3),
            image_error_mm(sc, T, truth.T_ee_us),
        )
    # The estimated layout against the printed one: RMS distance over the spheres after
    # the best rigid alignment (a rigid motion of the layout is the phantom pose's).
    layout = est.three.result.layout
    names = sorted(layout)
    T_phantom_base = se3.invert(truth.T_base_phantom)
    printed = np.array([se3.apply(T_phantom_base, truth.landmarks_base[t]) for t in names])

    def misfit(P: np.ndarray) -> float:
        aligned = se3.apply(se3.kabsch(P, printed), P)
        return float(np.sqrt(np.mean(np.sum((aligned - printed) ** 2, axis=1))) * 1e3)

    out["layout_mm"] = (
        misfit(np.array([cad[t] for t in names])),
        misfit(np.array([layout[t] for t in names])),
    )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seeds", type=int, default=10)
    args = ap.parse_args()
    jobs = [(s, tol) for tol in TOLERANCES_MM for s in range(args.seeds)]
    t0 = time.perf_counter()
    ctx = multiprocessing.get_context("spawn")
    with cf.ProcessPoolExecutor(args.workers, mp_context=ctx) as ex:
        results = dict(zip(jobs, ex.map(one, *zip(*jobs, strict=True)), strict=True))
    print(f"{len(jobs)} acquisitions in {time.perf_counter() - t0:.0f} s ({args.workers} workers)")
    ratio = float("nan")
    for tol in TOLERANCES_MM:
        print(f"\nprint tolerance {tol:g} mm (1 σ per axis), seeds 0-{args.seeds - 1}")
        print(f"{'':26s} {'rotation °':>16s} {'translation mm':>16s} {'image mm':>16s}")
        print(f"{'':26s} {'median / p90':>16s} {'median / p90':>16s} {'median / p90':>16s}")
        medians = {}
        for m in METHODS:
            e = np.array([results[(s, tol)][m] for s in range(args.seeds)])
            cells = [
                f"{np.median(e[:, j]):.3f} / {np.percentile(e[:, j], 90):.3f}" for j in range(3)
            ]
            medians[m] = float(np.median(e[:, 0]))
            print(f"{m:26s} " + " ".join(f"{c:>16s}" for c in cells))
        lay = np.array([results[(s, tol)]["layout_mm"] for s in range(args.seeds)])
        print(
            f"layout RMS off the printed one (median): CAD {np.median(lay[:, 0]):.3f} mm, "
            f"estimated {np.median(lay[:, 1]):.3f} mm"
        )
        if tol == TOLERANCES_MM[0]:
            ratio = medians[METHODS[2]] / medians[METHODS[0]]
    print(f"ratio_rotation_three_vs_single={ratio:.3f}")


if __name__ == "__main__":
    main()
