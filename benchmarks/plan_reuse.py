"""Does a plan made once hold in new sessions? One optimized 15-sweep plan of quick.yaml's
sphere 1 (single-marker, no kinematic error, as a user makes it with ``uscal plan
--optimize --sweeps 15 --out PLAN``), made in one session, then acquired and calibrated
in new sessions of the twin — each its own seed: its coarse mount, taught pose, print,
joint and image noise — beside the paper's 45-sweep plan in the same sessions.

The plan session and the new sessions' seeds are drawn at random from ``--seed`` (a fresh
draw for each). Prints per session the sweeps the plan replaced or left out, whether the
acquisition stopped (a collision or a refused plan) and the true single-marker errors of
both plans; then the medians and 90th percentiles. Targets (issue 36): no session stops,
none collides; the plan calibrates at least as well as the paper's (median true image
error no worse). Last line: ``sessions=<n> stopped=<n> replaced=<n> left_out=<n>
image_ratio=<median of the plan / median of the paper's>``.

Run: python benchmarks/plan_reuse.py [--sessions 20] [--seed 0] [--workers 2] [--criterion D]
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import multiprocessing
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import wilcoxon

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.config.plan_file import write_plan  # noqa: E402
from bench.config.scenario import load_scenario  # noqa: E402
from bench.jobs.plan_optimize import optimize_plan, plan_about  # noqa: E402
from bench.jobs.single import run  # noqa: E402
from bench.parallel import one_blas_thread  # noqa: E402
from bench.progress import reporting  # noqa: E402
from calib.errors import UscalError  # noqa: E402

QUICK = ROOT / "scenarios" / "quick.yaml"
BASE = ["protocol.spheres=[1]", "robot.dh_error_scale=0"]
MEASURES = ("rotation_deg", "translation_mm", "image_mm")


def session(plan: str | None, seed: int) -> dict[str, Any]:
    """One new session acquired and calibrated with ``plan`` (None: the paper's)."""
    sets = [*BASE, f"seed={seed}"] + ([f"protocol.plan={plan}"] if plan else [])
    t0 = time.perf_counter()
    try:
        with one_blas_thread(), reporting(None):
            m = run(load_scenario(QUICK, sets)).metrics
    except UscalError as e:  # a refused plan or a collision: the acquisition stopped
        return {"seed": seed, "stopped": f"{type(e).__name__}: {e}"}
    replaced = m["acquisition"]["replaced"]
    return {
        "seed": seed,
        "seconds": time.perf_counter() - t0,
        "sweeps": m["acquisition"]["sweeps"],
        "replaced": sum("replaced by spare" in r for r in replaced),
        "left_out": sum("left out" in r for r in replaced),
        "lines": replaced,
        "verdict": m["calibration"]["single"].get("verdict", {}).get("status"),
        **{k: m["calibration"]["single"]["true_error"][k] for k in MEASURES},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0, help="draws the plan's and the sessions' seeds")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--criterion", choices=["D", "A", "E"], default="D")
    args = ap.parse_args()
    rng = np.random.default_rng([args.seed, 36_3])
    seeds = [int(s) for s in rng.choice(10**6, size=args.sessions + 1, replace=False)]
    plan_seed, new = seeds[0], seeds[1:]
    with tempfile.TemporaryDirectory() as tmp, reporting(None):
        scenario = load_scenario(QUICK, [*BASE, f"seed={plan_seed}"])
        t0 = time.perf_counter()
        c = optimize_plan(scenario, 15, args.criterion, 1)
        path = str(Path(tmp) / "plan.yaml")
        write_plan(path, c.optimized.poses, plan_about(c, scenario), c.optimized.spares)
        print(
            f"plan made in session seed {plan_seed} in {time.perf_counter() - t0:.0f} s: "
            f"{c.optimized.n_sweeps} sweeps, {sum(map(len, (c.optimized.spares or {}).values()))} "
            f"spares, checked in {c.optimized.sessions} other sessions",
            flush=True,
        )
        ctx = multiprocessing.get_context("spawn")
        rows: dict[tuple[str, int], dict[str, Any]] = {}
        with cf.ProcessPoolExecutor(args.workers, mp_context=ctx) as pool:
            futures = {
                pool.submit(session, p, s): (name, s)
                for s in new
                for name, p in (("plan", path), ("paper", None))
            }
            for f in cf.as_completed(futures):
                name, s = futures[f]
                r = rows[(name, s)] = f.result()
                if "stopped" in r:
                    print(f"{name:5s} seed {s:7d}: STOPPED {r['stopped']}", flush=True)
                    continue
                print(
                    f"{name:5s} seed {s:7d} {r['seconds']:5.1f} s  {r['sweeps']:2d} sweeps "
                    f"({r['replaced']} replaced, {r['left_out']} left out)  "
                    f"image {r['image_mm']:.3f} mm  rotation {r['rotation_deg']:.3f}°  "
                    f"{r['verdict']}",
                    flush=True,
                )
                for line in r["lines"]:
                    print(f"      {line}", flush=True)
    print(f"\n{args.sessions} new sessions, single-marker calibration of sphere 1")
    print(
        f"{'plan':6s} {'stopped':>7s} {'replaced':>8s} {'left out':>8s}  "
        + "  ".join(f"{m + ' med/p90':>22s}" for m in MEASURES)
    )
    summary = {}
    for name in ("plan", "paper"):
        done = [rows[(name, s)] for s in new if "stopped" not in rows[(name, s)]]
        stopped = args.sessions - len(done)
        errs = {m: np.array([r[m] for r in done]) for m in MEASURES}
        summary[name] = {
            "stopped": stopped,
            "replaced": sum(r["replaced"] for r in done),
            "left_out": sum(r["left_out"] for r in done),
            **{m: float(np.median(errs[m])) if len(done) else float("nan") for m in MEASURES},
        }
        cells = "  ".join(
            f"{np.median(errs[m]):>10.3f} / {np.percentile(errs[m], 90):>9.3f}"
            if len(done)
            else f"{'-':>22s}"
            for m in MEASURES
        )
        s = summary[name]
        print(f"{name:6s} {stopped:>7d} {s['replaced']:>8d} {s['left_out']:>8d}  {cells}")
    p, q = summary["plan"], summary["paper"]
    # The sessions are paired (the same twin, coarse mount and noise streams): per
    # session, the plan's true image error over the paper's, and a signed-rank test.
    both = [s for s in new if "stopped" not in rows[("plan", s)] | rows[("paper", s)]]
    if len(both) >= 5:
        a = np.array([rows[("plan", s)]["image_mm"] for s in both])
        b = np.array([rows[("paper", s)]["image_mm"] for s in both])
        test = wilcoxon(a, b)
        print(
            f"paired over {len(both)} sessions: plan / paper image error median "
            f"{np.median(a / b):.2f} (p10 {np.percentile(a / b, 10):.2f}, p90 "
            f"{np.percentile(a / b, 90):.2f}); plan better in {int(np.sum(a < b))}; "
            f"signed-rank p = {test.pvalue:.2f}"
        )
    print(
        f"sessions={args.sessions} stopped={p['stopped']} replaced={p['replaced']} "
        f"left_out={p['left_out']} image_ratio={p['image_mm'] / q['image_mm']:.3f}"
    )


if __name__ == "__main__":
    main()
