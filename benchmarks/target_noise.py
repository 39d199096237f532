"""How far each target's detection lies from the truth, frame by frame and sweep by sweep:
the noise the planner chooses wire and cone-tip sweeps for (``planning.dot_noise_mm``,
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
  passes over it, along lateral, axial and elevational axes, the session's mean removed.

Last line: ``runs=<n> dot_frame_mm=<lat>,<ax> dot_sweep_mm=<lat>,<ax>
tip_sweep_mm=<lat>,<ax>,<el>`` (medians over runs of the robust 1 σ).

Run: python benchmarks/target_noise.py [--runs 4] [--seed 0]
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    frame, sweep, tip = [], [], []
    print(f"{'run':>4} {'target':>8}  robust 1 σ (mm)")
    for k in range(args.runs):
        over = _draw(rng, "wire", k)
        f, s = wire_errors(over)
        frame.append(f)
        sweep.append(s)
        print(
            f"{k:4d} {'wire':>8}  frame {f.round(4)}  sweep {s.round(4)}   ({' '.join(over[:3])})"
        )
        over = _draw(rng, "cone", k)
        t = tip_errors(over)
        tip.append(t)
        print(f"{k:4d} {'cone tip':>8}  sweep {t.round(4)}   ({' '.join(over[:3])})")

    def fmt(x: list[np.ndarray]) -> str:
        return ",".join(f"{v:.4f}" for v in np.median(np.array(x), axis=0))

    print(
        f"runs={args.runs} dot_frame_mm={fmt(frame)} dot_sweep_mm={fmt(sweep)} "
        f"tip_sweep_mm={fmt(tip)}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
