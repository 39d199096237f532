"""Which phantom should I print? The paper's comparison of calibration targets as an
experiment (issue "N-wire and wire targets", item 5): a printed sphere, a single wire,
the field's N-wire phantom (PLUS's fCal 2.0 geometry, nylon wire; the single wire
through its centre, between the same plates) and the paper's printed cone's tip on the
same twin rig — the same
arm, probe (a 50 × 50 mm image), water, and the same error sources drawn at random for
each run: gain, water temperature, teaching error, the phantom's print tolerance, the
scenario's seed (arm noise, coarse mount, speckle). Each target runs its own protocol
for the same number of sweeps and frames (the paper's 45 sweeps of 21 frames; the
wires' tilt about the lateral axis kept to 3°, as their echoes need; the cone's sweeps
±5 mm over its apex, a point), and the robot time of each is reported.

Per run (``uscal run`` on the twin, :func:`bench.jobs.single.run`): the true rotation,
translation and mean image error of ``T_ee_us`` (the N-wire's with its fitted pixel
scale), the 95 % bound over the image and whether it covers the truth, the verdict, the
conditioning of the information the data hold about the mount (its condition number:
the sphere's centres with their sphere's position unknown, the wires' points with the
phantom's pose and the scale unknown), and what was not used (sweeps rejected by the
localizer, frames without every wire, sweeps whose apex was not found).

``--plan N``: each target's sweeps chosen by ``uscal plan --optimize`` (N sweeps, made
once per target in a session of its own, on a seed and conditions no run shares) and that
plan reused by every run, as a lab reuses a plan day after day: its robot time and errors
beside the paper's plan's. A plan a run cannot use (a sweep that no longer clears, no
spare left) is a failure of the plan and is counted.

Last line: ``runs=<n>`` then, per target, ``<target>_image_mm``,
``<target>_rotation_deg`` (medians) and ``<target>_covered`` (share); the targets
``sphere``, ``wire``, ``nwire``, ``cone_tip``.

Run: python benchmarks/targets.py [--runs 6] [--seed 0] [--workers 2] [--plan N] [--json FILE]
"""

from __future__ import annotations

import os
import sys

# benchmarks/sim_us.py shares its name with the package: keep this folder off the path.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import argparse  # noqa: E402
import concurrent.futures as cf  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SPHERE = ROOT / "scenarios" / "quick.yaml"
NWIRE = ROOT / "scenarios" / "nwire.yaml"
WIRE = ROOT / "scenarios" / "wire.yaml"
CONE_TIP = ROOT / "scenarios" / "cone_tip.yaml"
TARGETS = ("sphere", "wire", "nwire", "cone_tip")
SCENARIO = {"sphere": SPHERE, "wire": WIRE, "nwire": NWIRE, "cone_tip": CONE_TIP}
#: The same probe for both targets: wide enough for the N-wire patterns.
PROBE = {"imaging.width_mm": 50.0, "imaging.depth_mm": 50.0, "imaging.pixel_spacing_mm": [0.2, 0.2]}


def draw(rng: np.random.Generator, k: int) -> dict[str, Any]:
    """One run's rig and error sources (shared by both targets)."""
    return {
        "seed": int(rng.integers(1, 10**6)),
        "imaging.gain_db": round(float(rng.uniform(-6, 6)), 1),
        "medium.temperature_c": round(float(rng.uniform(18, 26)), 1),
        "protocol.teaching_error_mm": round(float(rng.uniform(1, 3)), 2),
        "phantom.tolerance_position_mm": round(float(rng.uniform(0.05, 0.15)), 3),
    }


def _overrides(target: str, conditions: dict[str, Any]) -> list[str]:
    overrides = [f"{k}={json.dumps(v)}" for k, v in {**conditions, **PROBE}.items()]
    if target == "sphere":
        overrides += ["protocol.spheres=[1]"]
    return overrides


def _plan(target: str, conditions: dict[str, Any], n_sweeps: int, path: str) -> str:
    """``uscal plan --optimize`` of ``target`` in a session of ``conditions``: the plan
    file at ``path``."""
    sys.path.insert(0, str(ROOT))
    from bench.config.plan_file import write_plan
    from bench.config.scenario import load_scenario
    from bench.jobs.plan_optimize import optimize_plan, plan_about

    scenario = load_scenario(str(SCENARIO[target]), _overrides(target, conditions))
    comparison = optimize_plan(scenario, n_sweeps, "D", 1)
    o = comparison.optimized
    write_plan(path, o.poses, plan_about(comparison, scenario), o.spares)
    return path


def _run(target: str, conditions: dict[str, Any], plan: str | None = None) -> dict[str, Any]:
    sys.path.insert(0, str(ROOT))
    from bench.config.scenario import load_scenario
    from bench.jobs.single import run
    from bench.outputs.figures import observability_eigenvalues
    from calib.errors import UscalError

    overrides = _overrides(target, conditions)
    if plan is not None:
        overrides += [f"protocol.plan={plan}"]
    scenario = load_scenario(str(SCENARIO[target]), overrides)
    t0 = time.perf_counter()
    try:
        result = run(scenario)
    except UscalError as e:  # the plan no longer fits this session
        return {"target": target, "plan": plan, "failed": str(e)}
    m = result.metrics
    out: dict[str, Any] = {
        "target": target,
        "plan": plan,
        "robot_time_s": m["acquisition"]["robot_time_s"],
        "frames": m["acquisition"]["frames"],
        "seconds": time.perf_counter() - t0,
    }
    if target == "sphere":
        cal = m["calibration"]["single"]
        eig = observability_eigenvalues(result.single)
        out |= {
            "true_error": cal["true_error"],
            "bound_image_mm": cal["bound95"]["image_mm"],
            "verdict": cal["verdict"]["status"],
            "condition_number": float(eig[0] / eig[-1]) if eig[-1] > 0 else float("inf"),
            "not_used": f"{m['localization']['n_rejected']} of "
            f"{m['localization']['n_sweeps']} sweeps",
        }
    else:
        cal = m["calibration"][target]
        out |= {
            "true_error": cal["true_error"],
            "bound_image_mm": cal["bound95"]["image_mm"],
            "verdict": cal["verdict"]["status"],
            "condition_number": cal["information"]["condition_number"],
            "not_used": f"{m['dataset']['n_sequences'] - m['detection']['sweeps_found']} of "
            f"{m['dataset']['n_sequences']} sweeps"
            if target == "cone_tip"
            else f"{m['dataset']['n_frames'] - m['detection']['frames_found']} of "
            f"{m['dataset']['n_frames']} frames",
        }
    out["covered"] = out["true_error"]["image_mm"] <= out["bound_image_mm"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0, help="draw of the runs' conditions")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--plan", type=int, metavar="N", help="also run each target's N-sweep plan")
    ap.add_argument("--json", help="write every run's figures here")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    conditions = [draw(rng, k) for k in range(args.runs)]
    jobs: list[tuple[str, dict[str, Any], str | None]] = [
        (t, c, None) for c in conditions for t in TARGETS
    ]
    t0 = time.perf_counter()
    ctx = multiprocessing.get_context("spawn")
    with cf.ProcessPoolExecutor(args.workers, mp_context=ctx) as pool:
        if args.plan:
            # Each plan made in a session of its own: conditions drawn apart from the runs'.
            tmp = Path(tempfile.mkdtemp(prefix="uscal_target_plans_"))
            session = draw(np.random.default_rng(args.seed + 10**6), 0)
            plans = dict(zip(TARGETS, pool.map(
                _plan, TARGETS, [session] * len(TARGETS), [args.plan] * len(TARGETS),
                [str(tmp / f"{t}.yaml") for t in TARGETS],
            ), strict=True))  # fmt: skip
            print(f"plans of {args.plan} sweeps made in a session of their own ({session})")
            jobs += [(t, c, plans[t]) for c in conditions for t in TARGETS]
        everything = list(pool.map(_run, *zip(*jobs, strict=True)))
    failed = [r for r in everything if "failed" in r]
    for r in failed:
        print(f"PLAN FAILED for {r['target']}: {r['failed']}")
    results = [r for r in everything if "failed" not in r and r["plan"] is None]
    planned = [r for r in everything if "failed" not in r and r["plan"] is not None]
    print(f"{args.runs} rigs drawn (seed {args.seed}), {len(jobs)} runs in "
          f"{time.perf_counter() - t0:.0f} s")  # fmt: skip
    head = (f"{'target':7s} {'rig':>3s} {'robot s':>8s} {'rot °':>7s} {'trans mm':>8s} "
            f"{'image mm':>8s} {'bound':>6s} {'cov':>4s} {'cond':>8s} {'verdict':>9s}")  # fmt: skip
    head += "  not used"
    print(head)
    for k, r in enumerate(results):
        e = r["true_error"]
        print(
            f"{r['target']:7s} {k // len(TARGETS):3d} {r['robot_time_s']:8.0f} "
            f"{e['rotation_deg']:7.3f} {e['translation_mm']:8.3f} {e['image_mm']:8.3f} "
            f"{r['bound_image_mm']:6.2f} "
            f"{'yes' if r['covered'] else 'NO':>4s} {r['condition_number']:8.1f} "
            f"{r['verdict']:>9s}  {r['not_used']}"
        )
    summary: dict[str, float] = {}
    print("\nmedian (spread) over the rigs:")
    for target in TARGETS:
        mine = [r for r in results if r["target"] == target]
        for key in ("rotation_deg", "translation_mm", "image_mm"):
            v = np.array([r["true_error"][key] for r in mine])
            summary[f"{target}_{key}"] = float(np.median(v))
            print(f"  {target:6s} {key:15s} {np.median(v):.3f} ({v.min():.3f}–{v.max():.3f})")
        summary[f"{target}_covered"] = float(np.mean([r["covered"] for r in mine]))
        summary[f"{target}_condition"] = float(np.median([r["condition_number"] for r in mine]))
    if planned:
        print(f"\nthe {args.plan}-sweep plans reused, median (spread) over the rigs:")
        print(f"  {'target':6s} {'robot s':>8s} {'rot °':>17s} {'image mm':>17s} {'covered':>8s}")
        for target in TARGETS:
            mine = [r for r in planned if r["target"] == target]
            if not mine:
                continue
            rot = np.array([r["true_error"]["rotation_deg"] for r in mine])
            img = np.array([r["true_error"]["image_mm"] for r in mine])
            paper_t = np.median([r["robot_time_s"] for r in results if r["target"] == target])
            plan_t = np.median([r["robot_time_s"] for r in mine])
            print(
                f"  {target:6s} {plan_t:8.0f} {np.median(rot):6.3f} ({rot.min():.3f}–"
                f"{rot.max():.3f}) {np.median(img):6.3f} ({img.min():.3f}–{img.max():.3f}) "
                f"{np.mean([r['covered'] for r in mine]):8.2f}   (paper's plan {paper_t:.0f} s)"
            )
            summary[f"{target}_planned_image_mm"] = float(np.median(img))
            summary[f"{target}_planned_covered"] = float(np.mean([r["covered"] for r in mine]))
    if args.json:
        Path(args.json).write_text(
            json.dumps({"conditions": conditions, "runs": everything}, indent=2)
        )
    print(
        f"runs={len(results)} "
        + " ".join(
            f"{t}_image_mm={summary[f'{t}_image_mm']:.3f} "
            f"{t}_rotation_deg={summary[f'{t}_rotation_deg']:.3f} "
            f"{t}_covered={summary[f'{t}_covered']:.2f}"
            for t in TARGETS
        )
        + (f" plan_failures={len(failed)}" if args.plan else "")
    )


if __name__ == "__main__":
    main()
