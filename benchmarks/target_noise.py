"""How far each target's detection lies from the truth, frame by frame and sweep by sweep:
the noise the planner chooses sweeps for (``planning.localization_noise_mm`` and
``localization_bias_mm`` for spheres, ``planning.dot_noise_mm``,
``planning.dot_sweep_noise_mm``, ``planning.cone_tip_noise_mm``), measured on the twin.

Per run: the scenario (``wire`` or ``cone_tip``) on a random seed, gain and water
temperature (the speed of sound corrected as the pipeline corrects it); the twin's
acquisition, every detection put in its image against where the truth puts the target
there (the true flange pose of that frame, the true mount, the printed wire or apex):

- wire: each frame's dot against the true wire's crossing of that frame's image plane,
  along the image's lateral and axial axes — the session's mean removed (a shared offset
  is the planner's ``localization_bias_mm``), then split into what a sweep's dots share
  (the spread of the sweeps' means) and what each frame adds (the spread about its
  sweep's mean);
- cone tip: each sweep's tip against the true apex in the image at the pose the sweep
  passes over it, along lateral, axial and elevational axes, the session's mean removed;
- sphere: quick.yaml's sphere 1 (no kinematic error), the paper's 45 sweeps acquired and
  calibrated single-marker with the refined localizer; each centre the calibration kept
  against the true centre in its sweep's true reference frame, along lateral, axial and
  elevation: the RMS about the session's mean (what the least-squares fit sees: the
  calibration has already dropped its outliers) and the session's mean itself (the
  shared offset, ``localization_bias_mm``: RMS over runs).

Last line: ``runs=<n> dot_frame_mm=<lat>,<ax> dot_sweep_mm=<lat>,<ax>
tip_sweep_mm=<lat>,<ax>,<el> sphere_sweep_mm=<lat>,<ax>,<el> sphere_bias_mm=<lat>,<ax>,<el>``
(medians over runs of the 1 σ; the bias an RMS over runs), the targets not measured left
out.

Run: python benchmarks/target_noise.py [--runs 4] [--seed 0] [--target all|wire|cone|sphere]
"""

from __future__ import annotations

import os
import sys

# benchmarks/sim_us.py shares its name with the package: keep this folder off the path.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import argparse  # noqa: E402

import numpy as np  # noqa: E402

from bench.acquire_sim import make_imager, make_twin, simulate_acquisition  # noqa: E402
from bench.config.scenario import load_scenario  # noqa: E402
from calib import se3  # noqa: E402
from calib.image import pixel_to_us  # noqa: E402
from calib.localize.cone_tip import locate_cone_tip  # noqa: E402
from calib.localize.nwire import detect_wire  # noqa: E402

ROOT = os.path.dirname(_HERE)


def _robust_sd(x: np.ndarray) -> np.ndarray:
    return 1.4826 * np.median(np.abs(x - np.median(x, axis=0)), axis=0)


def _draw(rng: np.random.Generator, kind: str, k: int) -> list[str]:
    seed = int(rng.integers(1000, 10**6))
    return [
        f"seed={seed}",
        f"imaging.gain_db={rng.uniform(-6, 6):.1f}",
        f"medium.temperature_c={rng.uniform(18, 30):.1f}",
        "imaging.sound_speed_correction=true",
        f"output.dir=/tmp/target_noise_{kind}_{k}",
    ]


def _spacing(scenario) -> tuple[float, float]:
    sx, sy = scenario.imaging.spacing_m
    return sx, sy


def wire_errors(overrides: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(per-frame, per-sweep) robust 1 σ (mm) of the dots along lateral and axial."""
    scenario = load_scenario(os.path.join(ROOT, "scenarios/wire.yaml"), overrides)
    twin = make_twin(scenario)
    acq = simulate_acquisition(scenario, twin, make_imager(scenario, twin))
    front = twin.truth.landmarks_base["wire_front"]
    back = twin.truth.landmarks_base["wire_back"]
    spacing = _spacing(scenario)
    spacing_mm = (spacing[0] * 1e3, spacing[1] * 1e3)
    errors, sweep_of = [], []
    for j, s in enumerate(acq.dataset.sweeps):
        W = s.images.shape[2]
        true_poses = acq.T_base_ee_true[(s.target, s.pose_id)]
        for k, frame in enumerate(s.images):
            d = detect_wire(frame, spacing_mm)
            if not d.ok:
                continue
            col, row = d.points["wire"]
            seen = pixel_to_us(row, col, W, spacing)
            T_us = se3.invert(true_poses[k] @ twin.truth.T_ee_us)
            a, b = se3.apply(T_us, front), se3.apply(T_us, back)
            u = -a[2] / (b[2] - a[2])
            crossing = a + u * (b - a)
            errors.append((seen - crossing)[:2] * 1e3)
            sweep_of.append(j)
    e = np.array(errors)
    e -= np.median(e, axis=0)
    g = np.array(sweep_of)
    means = np.array([np.median(e[g == j], axis=0) for j in np.unique(g)])
    within = e - means[np.searchsorted(np.unique(g), g)]
    return _robust_sd(within), _robust_sd(means)


def tip_errors(overrides: list[str]) -> np.ndarray:
    """Robust 1 σ (mm) of the sweeps' tips along lateral, axial and elevation."""
    scenario = load_scenario(os.path.join(ROOT, "scenarios/cone_tip.yaml"), overrides)
    twin = make_twin(scenario)
    acq = simulate_acquisition(scenario, twin, make_imager(scenario, twin))
    apex = twin.truth.landmarks_base["apex"]
    spacing = _spacing(scenario)
    X0 = acq.T_ee_us_coarse
    errors = []
    for s in acq.dataset.sweeps:
        W = s.images.shape[2]
        normal = (s.T_base_ee[s.reference_index] @ X0)[:3, 2]
        e = (s.T_base_ee[:, :3, 3] - s.T_base_ee[s.reference_index, :3, 3]) @ normal
        tip = locate_cone_tip(s.images, e, spacing, W)
        if not tip.ok:
            continue
        true_poses = acq.T_base_ee_true[(s.target, s.pose_id)]
        ref = true_poses[s.reference_index] @ twin.truth.T_ee_us
        true_tip = se3.apply(se3.invert(ref), apex)
        seen = np.array([tip.x_m, tip.depth_m, tip.elevation_m])
        errors.append((seen - true_tip) * 1e3)
    e = np.array(errors)
    return _robust_sd(e - np.median(e, axis=0))


def sphere_errors(overrides: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(RMS about the session's mean, the session's mean) of the kept centres (mm) along
    lateral, axial and elevation."""
    from bench.jobs.single import run
    from bench.progress import reporting
    from bench.truth import true_centre_in_sweep

    sets = [*overrides, "protocol.spheres=[1]", "robot.dh_error_scale=0"]
    scenario = load_scenario(os.path.join(ROOT, "scenarios/quick.yaml"), sets)
    with reporting(None):
        result = run(scenario)
    acq, truth = result.acquisition, make_twin(scenario).truth
    kept = {
        (loc.target, loc.pose_id): loc.centre
        for locs in result.single.retained_localizations().values()
        for loc in locs
        if loc.accepted
    }
    e = np.array(
        [
            (kept[(s.target, s.pose_id)] - true_centre_in_sweep(acq, truth, s.target, s)) * 1e3
            for s in acq.dataset.sweeps
            if (s.target, s.pose_id) in kept
        ]
    )
    mean = e.mean(axis=0)
    return np.sqrt(np.sum((e - mean) ** 2, axis=0) / (len(e) - 1)), mean


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--target", choices=["all", "wire", "cone", "sphere"], default="all")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    frame, sweep, tip, sphere, bias = [], [], [], [], []
    want = {"wire", "cone", "sphere"} if args.target == "all" else {args.target}
    print(f"{'run':>4} {'target':>8}  1 σ (mm; wire and cone tip robust)")
    for k in range(args.runs):
        if "wire" in want:
            over = _draw(rng, "wire", k)
            f, s = wire_errors(over)
            frame.append(f)
            sweep.append(s)
            print(
                f"{k:4d} {'wire':>8}  frame {f.round(4)}  sweep {s.round(4)}   "
                f"({' '.join(over[:3])})"
            )
        if "cone" in want:
            over = _draw(rng, "cone", k)
            t = tip_errors(over)
            tip.append(t)
            print(f"{k:4d} {'cone tip':>8}  sweep {t.round(4)}   ({' '.join(over[:3])})")
        if "sphere" in want:
            over = _draw(rng, "sphere", k)
            sd, mean = sphere_errors(over)
            sphere.append(sd)
            bias.append(mean)
            print(
                f"{k:4d} {'sphere':>8}  sweep {sd.round(4)}  session mean {mean.round(4)}   "
                f"({' '.join(over[:3])})"
            )

    def fmt(x: list[np.ndarray]) -> str:
        return ",".join(f"{v:.4f}" for v in np.median(np.array(x), axis=0))

    figures = [f"runs={args.runs}"]
    if frame:
        figures += [f"dot_frame_mm={fmt(frame)}", f"dot_sweep_mm={fmt(sweep)}"]
    if tip:
        figures.append(f"tip_sweep_mm={fmt(tip)}")
    if sphere:
        rms = np.sqrt(np.mean(np.square(bias), axis=0))
        figures += [
            f"sphere_sweep_mm={fmt(sphere)}",
            "sphere_bias_mm=" + ",".join(f"{v:.4f}" for v in rms),
        ]
    print(" ".join(figures))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
