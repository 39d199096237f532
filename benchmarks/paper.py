"""The whole paper experiment on the twin: wall time, split by stage, and peak memory.

Runs ``scenarios/paper.yaml`` (3 datasets × 4 spheres × 45 sweeps × 21 frames of
401 × 381 px, touches, 24 folds) as ``uscal run`` does, while a thread samples the
memory (proportional set size) of this process and all its children (the dataset
workers) every 0.2 s.
Targets: ≤ 180 s wall on 2 cores, ≤ 3 GB peak. The last line is ``total_s=<value>``.

Run: python benchmarks/paper.py [--workers N]
"""

from __future__ import annotations

import os
import sys

# benchmarks/sim_us.py shares its name with the package: keep this folder off the path.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import argparse  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from bench.run import run  # noqa: E402
from bench.scenario import load_scenario  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _tree_pss_bytes(pid: int) -> int:
    """Memory of a process and all its descendants (Linux /proc): the proportional set
    size, which counts pages shared between them (libraries) once, not once per process
    as summing resident sizes would."""
    total = 0
    stack = [pid]
    while stack:
        p = stack.pop()
        try:
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Pss:"):
                    total += int(line.split()[1]) * 1024
            children = Path(f"/proc/{p}/task/{p}/children").read_text().split()
        except (FileNotFoundError, ProcessLookupError, PermissionError):
            continue
        stack += [int(c) for c in children]
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--workers", type=int, default=0, help="0: the scenario's default")
    args = parser.parse_args()
    overrides = [f"evaluation.workers={args.workers}"] if args.workers else []
    scenario = load_scenario(ROOT / "scenarios" / "paper.yaml", overrides)
    peak = 0
    done = threading.Event()

    def sample() -> None:
        nonlocal peak
        while not done.is_set():
            peak = max(peak, _tree_pss_bytes(os.getpid()))
            time.sleep(0.2)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t0 = time.perf_counter()
    result = run(scenario)
    wall = time.perf_counter() - t0
    done.set()
    sampler.join()
    t = result.metrics["timing_s"]
    print(f"cores={os.cpu_count()} workers={t['workers']}")
    print(f"touches_and_dh_s={t['touches_and_dh']:.1f} datasets_wall_s={t['datasets_wall']:.1f}")
    for name, d in t["per_dataset"].items():
        print(
            f"dataset {name}: simulate_s={d['simulate']:.1f} "
            f"localize_initial_s={d['localize_initial']:.1f} folds_s={d['folds']:.1f} "
            f"(alternation localization {d['localize_folds']:.1f}) truth_s={d['truth']:.1f}"
        )
    print(f"peak_pss_mb={peak / 2**20:.0f}")
    print(f"total_s={wall:.1f}")


if __name__ == "__main__":
    main()
