"""The whole paper experiment on the twin: wall time, split by stage, and peak memory.

Runs ``scenarios/paper.yaml`` (3 datasets × 4 spheres × 45 sweeps × 21 frames of
401 × 381 px, touches, 24 folds; then the reconstruction: a 3-sphere re-calibration scan,
six calibrations, 45 cone and 45 prism sweeps, 12 ICP registrations) as ``uscal run``
does, while a thread samples the memory (proportional set size) of this process and all
its children (the pool's workers) every second. ``--no-reconstruction`` leaves the
reconstruction out, to measure what it adds.
Targets: ≤ 60 s and ≤ 2 GB peak on 2 cores; the reconstruction adds ≤ 1/3 to the wall
time. The last line is ``wall_s=<value> peak_mb=<value>`` (peak: PSS over all processes).

Run: python benchmarks/paper.py [--workers N] [--no-reconstruction] [--record]
"""

from __future__ import annotations

import os
import sys

# benchmarks/sim_us.py shares its name with the package: keep this folder off the path.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import argparse  # noqa: E402
import resource  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from bench.config.scenario import load_scenario  # noqa: E402
from bench.jobs.single import run  # noqa: E402
from bench.recording.options import RecordingOptions  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _tree_pss_bytes(pid: int) -> tuple[int, int]:
    """Memory of a process and all its descendants (Linux /proc): the proportional set
    size, which counts pages shared between them (libraries) once, not once per process
    as summing resident sizes would; and the part of it that is not file-backed (the
    frames a run maps from its scratch files are clean file pages, which the kernel can
    drop and read back)."""
    total = anon = 0
    stack = [pid]
    while stack:
        p = stack.pop()
        try:
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Pss:"):
                    total += int(line.split()[1]) * 1024
                elif line.startswith(("Pss_Anon:", "Pss_Shmem:")):
                    anon += int(line.split()[1]) * 1024
            children = Path(f"/proc/{p}/task/{p}/children").read_text().split()
        except (FileNotFoundError, ProcessLookupError, PermissionError):
            continue
        stack += [int(c) for c in children]
    return total, anon


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--workers", type=int, default=0, help="0: the scenario's default")
    parser.add_argument(
        "--no-reconstruction", action="store_true", help="leave Table III's stage out"
    )
    parser.add_argument(
        "--record", action="store_true", help="also write the rerun recording (its cost)"
    )
    args = parser.parse_args()
    overrides = [f"evaluation.workers={args.workers}"] if args.workers else []
    if args.no_reconstruction:
        overrides.append("reconstruction.phantoms=[]")
    scenario = load_scenario(ROOT / "scenarios" / "paper.yaml", overrides)
    peak = peak_anon = 0
    done = threading.Event()

    def sample() -> None:
        nonlocal peak, peak_anon
        while not done.is_set():
            pss, anon = _tree_pss_bytes(os.getpid())
            peak, peak_anon = max(peak, pss), max(peak_anon, anon)
            # Reading smaps_rollup walks each process's page tables: every 0.2 s this
            # thread took a fifth of a core from the run it measures (py-spy).
            done.wait(1.0)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        recording = RecordingOptions.new(Path(tmp) / "recording.rrd") if args.record else None
        result = run(scenario, recording=recording)
        wall = time.perf_counter() - t0
        rrd_mb = recording.path.stat().st_size / 2**20 if recording else 0.0
    done.set()
    sampler.join()
    t = result.metrics["timing_s"]
    print(f"cores={os.cpu_count()} workers={t['workers']}")
    print(f"touches_and_dh_s={t['touches_and_dh']:.1f} pool_wall_s={t['pool_wall']:.1f}")
    for name, d in t["per_dataset"].items():
        print(
            f"dataset {name}: simulate_s={d['simulate']:.1f} "
            f"localize_initial_s={d['localize_initial']:.1f} folds_s={d['folds']:.1f} "
            f"(alternation localization {d['localize_folds']:.1f}) truth_s={d['truth']:.1f}"
        )
    for stage, d in t["reconstruction"].items():
        print(f"reconstruction {stage}: " + " ".join(f"{k}_s={v:.1f}" for k, v in d.items()))
    cpu = sum(
        getattr(resource.getrusage(who), f)
        for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
        for f in ("ru_utime", "ru_stime")
    )
    print(f"cpu_s={cpu:.1f} (this process and its finished workers)")
    if args.record:
        print(f"recording_s={t['recording']:.1f} (CPU, summed over processes) rrd_mb={rrd_mb:.0f}")
    print(f"peak_not_file_backed_mb={peak_anon / 2**20:.0f}")
    print(f"wall_s={wall:.1f} peak_mb={peak / 2**20:.0f}")


if __name__ == "__main__":
    main()
