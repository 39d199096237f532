"""Robustness sweeps: a grid of scenario overrides × seeds, each point simulated,
localized (and calibrated) with every localizer named, on a local process pool or a
Dask cluster; results cached per point so that an interrupted sweep resumes (the grid
executor, :mod:`bench.grid`).

A sweep file::

    base: quick.yaml                 # the base scenario, relative to this file
    grid:                            # key path (as for --set) -> values; full product
      imaging.gain_db: [-20, -10, 0, 10, 20]
      imaging.depth_mm: [30, 50, 70]
      # linked keys, set together (one grid axis):
      # protocol.target_depth_mm, imaging.depth_mm: [[10, 25], [20, 35]]
    seeds: [0, 1, 2]
    stages: [localize]               # or [localize, calibrate]
    methods: [refined, fixed_threshold]

Or points drawn at random instead of a grid, each with a twin seed of its own (the
claims a grid supports, checked on conditions it did not list)::

    base: quick.yaml
    draws:
      points: 40                     # how many
      seed: 2026                     # the draws' own random stream
      keys:                          # key path (or linked keys) -> how it is drawn
        imaging.gain_db: {uniform: [-20, 20], step: 0.1}
        phantom.sphere_radius_mm: {choice: [3, 4, 5]}
        protocol.target_depth_mm, imaging.depth_mm: {choice: [[15, 30], [25, 45]]}
    stages: [localize, calibrate]

Each point is a pure function of (base scenario, overrides, seed): the tasks return
metrics, never frames, and the main process writes ``DIR/points/<key>.json`` as each
finishes. Points that differ in the display gain alone (a gain axis) are acquired once
and each frame's echoes simulated once, then shown at every gain
(:func:`bench.acquire_sim.simulate_acquisition_at_gains`): the acquisition is most of a
point's time. Such a point's frames are the ones it makes alone but for echoes beneath
its display's black level that the highest gain's trace reaches (one grey level in a few
pixels per million), so the cache holds it under its own key.
"""

from __future__ import annotations

import functools
import itertools
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from calib.calibration.alternation import AlternationSettings, alternate
from calib.calibration.uncertainty import alternation_bound
from calib.calibration.verdict import judge, sweep_geometry
from calib.errors import UscalError
from calib.localize import localize_sphere

from .. import progress as progress_report
from ..acquire_sim import (
    SimulatedAcquisition,
    make_imager,
    make_twin,
    simulate_acquisition,
    simulate_acquisition_at_gains,
)
from ..config.geometry import TARGET_PHANTOMS
from ..config.method import (
    axial_scale,
    image_points,
    requirements,
    scenario_uncertainty,
    stated_radius,
)
from ..config.scenario import acquisition_pixels, load_scenario, validate_overrides
from ..config.schema import read_yaml
from ..grid import GridPoint, cache_key, guarded, run_grid
from ..parallel import release_memory
from ..truth import image_error_mm, localization_errors

__all__ = [
    "LOCALIZATION_METRICS",
    "Draws",
    "KeyDraw",
    "SweepError",
    "SweepPoint",
    "SweepResult",
    "SweepRow",
    "SweepSpec",
    "load_sweep",
    "point_key",
    "run_point",
    "run_sweep",
]

STAGES = ("localize", "calibrate")
#: The override a sweep's points share one acquisition across (the display gain).
SHARED_ACROSS = "imaging.gain_db"
#: Gains one acquisition serves at most: it holds every gain's frames until its points
#: are localized (five times a point's frames), so a fine gain axis is split in runs of
#: this many neighbouring values.
MAX_GAINS_PER_ACQUISITION = 5
#: Frame pixels one worker simulates and localizes (both methods) per second, for the
#: time a sweep announces; the ``calibrate`` stage adds half. On this 2-core machine,
#: robustness.yaml (75 points, 15 acquisitions): 1 040 worker-seconds.
PIXELS_PER_SECOND = 2.4e6
#: The share of a point's time that is its own where points share their acquisition (a
#: gain axis: :func:`run_points_at_gains`): its localization (and calibration). quick.yaml,
#: spheres 1-2, both methods, one core: 3.3 s of 10.6 s; the acquisition is the rest.
OWN_SHARE = 0.3
LOCALIZER_METHODS = ("paper", "refined", "fixed_threshold")
CSV_COLUMNS = ("seed", "method", "localization_median_error_mm", "rejected_fraction")


class SweepError(UscalError):
    """A sweep file that cannot be run."""


#: A drawn point's twin seed is drawn from this range: away from the few seeds grid files
#: name, so that no drawn point repeats a grid's twin.
DRAWN_SEEDS = (1000, 1_000_000)
#: A uniform draw's default rounding (the key's own unit): fine enough that no two
#: points share a value by chance, coarse enough to read in a table.
DEFAULT_STEP = 0.01


@dataclass(frozen=True)
class KeyDraw:
    """How one entry of ``draws.keys`` is drawn: uniformly over ``[lo, hi]`` rounded to
    ``step`` (``kind`` "uniform", ``values`` (lo, hi)), or one of ``values`` with equal
    probability ("choice"; for linked keys each value a list, one per key)."""

    kind: str
    values: tuple[Any, ...]
    step: float = DEFAULT_STEP

    def draw(self, rng: np.random.Generator) -> Any:
        if self.kind == "choice":
            return self.values[int(rng.integers(len(self.values)))]
        lo, hi = self.values
        x = round(round(float(rng.uniform(lo, hi)) / self.step) * self.step, 9)
        whole = all(isinstance(v, int) for v in (lo, hi)) and float(self.step).is_integer()
        return int(x) if whole else x


@dataclass(frozen=True)
class Draws:
    """A sweep's points drawn at random (``draws:`` in the file): ``points`` of them,
    from the stream seeded by ``seed``, each key as its :class:`KeyDraw` says and each
    point with a twin seed of its own (:data:`DRAWN_SEEDS`)."""

    points: int
    seed: int
    keys: dict[str, KeyDraw]

    @functools.cached_property
    def drawn(self) -> tuple[tuple[tuple[tuple[str, Any], ...], int], ...]:
        """(overrides, twin seed) of every point, the same for the same file (drawn once)."""
        rng = np.random.default_rng(self.seed)
        out = []
        for _ in range(self.points):
            overrides = tuple(
                pair
                for key, how in self.keys.items()
                for pair in zip(linked_keys(key), _linked_values(key, how.draw(rng)), strict=True)
            )
            out.append((overrides, int(rng.integers(*DRAWN_SEEDS))))
        return tuple(out)

    def values(self) -> dict[str, list[Any]]:
        """Each entry's values over the points, as drawn (linked keys: a list per point)."""
        out: dict[str, list[Any]] = {}
        for key in self.keys:
            ks = linked_keys(key)
            values = ([dict(o)[k] for k in ks] for o, _ in self.drawn)
            out[key] = [v if len(ks) > 1 else v[0] for v in values]
        return out


@dataclass(frozen=True)
class SweepSpec:
    """A validated sweep file: a grid × seeds, or points drawn at random (``draws``; then
    ``grid`` is empty and ``seeds`` the points' own)."""

    source: Path
    base: Path
    base_text: str  # as validated: the cache key's, even if the file changes later
    grid: dict[str, list[Any]]
    seeds: tuple[int, ...]
    stages: tuple[str, ...]
    methods: tuple[str, ...]
    draws: Draws | None = None

    def points(self) -> list[tuple[tuple[tuple[str, Any], ...], int]]:
        """(overrides, seed) of every point: the grid's full product × the seeds; a
        linked entry (``"a, b": [[a1, b1], ...]``) sets its keys together. Drawn: the
        points as drawn (:meth:`Draws.drawn`)."""
        if self.draws is not None:
            return list(self.draws.drawn)
        keys = list(self.grid)
        combos = itertools.product(*(self.grid[k] for k in keys)) if keys else [()]
        return [
            (
                tuple(
                    pair
                    for key, value in zip(keys, values, strict=True)
                    for pair in zip(linked_keys(key), _linked_values(key, value), strict=True)
                ),
                seed,
            )
            for values in combos
            for seed in self.seeds
        ]

    def count(self) -> int:
        """Points (grid product × seeds, or drawn), without building them."""
        if self.draws is not None:
            return self.draws.points
        n = len(self.seeds)
        for values in self.grid.values():
            n *= len(values)
        return n

    def estimated_seconds(self) -> float:
        """Rough time of the whole sweep on one worker: each point simulates and
        localizes the base scenario's sweeps (grid keys that change the image size
        change it too) at ≈ :data:`PIXELS_PER_SECOND`; points that share an acquisition
        (a gain axis) cost it once (:data:`OWN_SHARE`)."""
        pixels = acquisition_pixels(load_scenario(self.base, check_reach=False))
        stages = 1.0 if self.stages == ("localize",) else 1.5
        work = self.acquisitions() * (1.0 - OWN_SHARE) + self.count() * OWN_SHARE
        return work * stages * pixels / PIXELS_PER_SECOND

    def acquisitions(self) -> int:
        """The acquisitions the points take: one each, but one for the points that
        differ in the gain alone (:func:`run_points_at_gains`)."""
        points = self.points()
        return len(
            {(b or json.dumps(o), s) for (o, s), b in zip(points, _batches(self), strict=True)}
        )

    def varied(self) -> dict[str, list[Any]]:
        """Each entry the sweep varies (grid or drawn: linked keys as one) and its values
        over the points, in the file's order (a drawn entry's values as drawn)."""
        return dict(self.grid) if self.draws is None else self.draws.values()

    def describe(self) -> str:
        """The points in words: "25 grid points × 3 seed(s) = 75 points", or drawn."""
        if self.draws is not None:
            return (
                f"{self.draws.points:,} points drawn at random (draw seed {self.draws.seed}; "
                f"{', '.join(self.draws.keys)}), each with a twin seed of its own"
            )
        return (
            f"{self.count() // len(self.seeds):,} grid points × {len(self.seeds)} seed(s) = "
            f"{self.count():,} points"
        )

    def override_keys(self) -> list[str]:
        """Every key path the sweep sets, linked entries' keys one by one."""
        entries = self.draws.keys if self.draws is not None else self.grid
        return [k for key in entries for k in linked_keys(key)]


def linked_keys(key: str) -> list[str]:
    """The key paths of a grid entry: ``"a, b"`` sets a and b together."""
    return [k.strip() for k in key.split(",")]


def _linked_values(key: str, value: Any) -> list[Any]:
    return list(value) if len(linked_keys(key)) > 1 else [value]


def _fail(source: Path, where: str, what: str) -> SweepError:
    return SweepError(f"{source}: {where}: {what}")


def load_sweep(path: str | os.PathLike[str]) -> SweepSpec:
    """Read and validate a sweep file: the base scenario must load, and the base with
    each grid value applied too (so a typo fails now, not an hour into the sweep)."""
    source = Path(path)
    if not source.is_file():
        raise SweepError(f"{source}: no such file")
    # As settings files are read (DESIGN §3): safe loader, duplicate keys refused, a
    # syntax error named by file and line.
    data = read_yaml(str(source))
    if not isinstance(data, dict):
        raise _fail(source, "top level", "expected a mapping with base, grid, seeds, stages")
    allowed = {"base", "grid", "seeds", "stages", "methods", "draws"}
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise _fail(source, ", ".join(unknown), f"unknown key(s); allowed: {sorted(allowed)}")
    if not isinstance(data.get("base"), str):
        raise _fail(source, "base", "the base scenario's path (relative to the sweep file)")
    base = (source.parent / data["base"]).resolve()
    grid = data.get("grid") or {}
    if not isinstance(grid, dict) or not all(
        isinstance(v, list) and v and isinstance(k, str) for k, v in grid.items()
    ):
        raise _fail(source, "grid", "a mapping of key path -> non-empty list of values")
    draws = None
    if "draws" in data:
        if "grid" in data or "seeds" in data:
            raise _fail(
                source, "draws", "drawn points vary their keys and seeds themselves: give "
                "either draws, or grid and seeds",
            )  # fmt: skip
        draws = _load_draws(source, data["draws"])
    seeds = data.get("seeds", [0])
    if not (isinstance(seeds, list) and seeds and all(type(s) is int for s in seeds)):
        raise _fail(source, "seeds", "a non-empty list of whole numbers")
    stages = data.get("stages", ["localize"])
    if stages not in (["localize"], ["localize", "calibrate"]):
        raise _fail(source, "stages", "[localize] or [localize, calibrate]")
    methods = data.get("methods", ["refined", "fixed_threshold"])
    if not (isinstance(methods, list) and methods and set(methods) <= set(LOCALIZER_METHODS)):
        raise _fail(source, "methods", f"a non-empty list from {list(LOCALIZER_METHODS)}")
    for key, values in grid.items():
        n = len(linked_keys(key))
        if n > 1 and not all(isinstance(v, list) and len(v) == n for v in values):
            raise _fail(source, f"grid: {key}", f"linked keys: each value a list of {n} values")
    # Fail now on a bad base or value (the scenario's validation names the key and what is
    # allowed): the base whole, each grid value by its keys and values (the file read
    # once, ≈ 1 ms a value). Reach and collisions depend on the whole point: a point that
    # cannot be reached fails alone in the sweep, with its reason.
    base_scenario = load_scenario(base)
    base_kind = base_scenario.phantom.kind
    if draws is not None:
        # Every drawn point's values, each key by itself (a point as a whole may still be
        # out of reach: it fails alone, as a grid's does).
        grid = draws.values()
        seeds = [s_ for _, s_ in draws.drawn]
    if base_scenario.protocol.second_pass or any(
        "protocol.second_pass" in linked_keys(k) for k in grid
    ):
        raise _fail(
            source, "protocol.second_pass", "a sweep scans each point once; a second scan "
            "along the calibrated normal is uscal run's (protocol.second_pass: false here)",
        )  # fmt: skip
    if any(
        k == "phantom.kind"
        and any((w in TARGET_PHANTOMS) != (base_kind in TARGET_PHANTOMS) for w in v)
        for k, v in grid.items()
    ):
        raise _fail(
            source, "grid", "phantom.kind: spheres and the other targets (wires, the cone's "
            "tip) are measured differently; sweep them in separate files",
        )  # fmt: skip
    if base_kind in TARGET_PHANTOMS:
        # A wire, N-wire or cone point finds and calibrates its own target (one row
        # named after it): no sphere localizer to choose.
        stages, methods = ["localize", "calibrate"], [base_kind]
    validate_overrides(
        base,
        (
            [_override(k, x) for k, x in zip(linked_keys(key), _linked_values(key, v), strict=True)]
            for key, values in grid.items()
            for v in values
        ),
    )
    if draws is not None:
        grid = {}  # the drawn values were validated; the points are the draws'
    return SweepSpec(
        source, base, base.read_text(encoding="utf-8"), {k: list(v) for k, v in grid.items()},
        tuple(seeds), tuple(stages), tuple(methods), draws,
    )  # fmt: skip


def _load_draws(source: Path, data: Any) -> Draws:
    """``draws:`` validated: ``points`` (a whole number ≥ 1), ``seed`` (a whole number),
    ``keys`` (key path -> ``{uniform: [lo, hi], step: s}`` or ``{choice: [v, ...]}``)."""
    where = "draws"
    if not isinstance(data, dict) or set(data) - {"points", "seed", "keys"}:
        raise _fail(source, where, "a mapping with points, seed and keys")
    points, seed, keys = data.get("points"), data.get("seed"), data.get("keys")
    if type(points) is not int or points < 1:
        raise _fail(source, f"{where}: points", "how many points to draw: a whole number ≥ 1")
    if type(seed) is not int:
        raise _fail(source, f"{where}: seed", "the draws' random seed: a whole number")
    if not isinstance(keys, dict) or not keys:
        raise _fail(source, f"{where}: keys", "a mapping of key path -> how it is drawn")
    out: dict[str, KeyDraw] = {}
    for key, how in keys.items():
        at = f"{where}: keys: {key}"
        n = len(linked_keys(str(key)))
        allowed = "{uniform: [lo, hi], step: s} or {choice: [value, ...]}"
        if not isinstance(how, dict) or len(set(how) & {"uniform", "choice"}) != 1:
            raise _fail(source, at, allowed)
        if "choice" in how:
            values = how["choice"]
            if set(how) != {"choice"} or not (isinstance(values, list) and values):
                raise _fail(source, at, "choice: a non-empty list of values")
            if n > 1 and not all(isinstance(v, list) and len(v) == n for v in values):
                raise _fail(source, at, f"linked keys: each choice a list of {n} values")
            out[str(key)] = KeyDraw("choice", tuple(values))
            continue
        bounds, step = how["uniform"], how.get("step", DEFAULT_STEP)
        if set(how) - {"uniform", "step"} or n > 1:
            raise _fail(source, at, f"{allowed} (linked keys: choice only)")
        number = (int, float)
        if not (
            isinstance(bounds, list)
            and len(bounds) == 2
            and all(isinstance(b, number) and not isinstance(b, bool) for b in bounds)
            and bounds[0] < bounds[1]
        ):
            raise _fail(source, at, "uniform: [lo, hi], two numbers with lo < hi")
        if not (isinstance(step, number) and not isinstance(step, bool) and step > 0):
            raise _fail(source, f"{at}: step", "the values' rounding: a number > 0")
        out[str(key)] = KeyDraw("uniform", tuple(bounds), float(step))
    return Draws(points, seed, out)


#: The localization figures of a row, in the order ``results.csv`` lists them.
LOCALIZATION_METRICS = (
    "localization_median_error_mm",
    "rejected_fraction",
    "localization_max_error_mm",
    "false_acceptances",
    "sweeps",
)


def _override(key: str, value: Any) -> str:
    return f"{key}={json.dumps(value)}"


def point_key(spec: SweepSpec, overrides: Sequence[tuple[str, Any]], seed: int) -> str:
    """Cache key of a point: a hash of everything its result depends on (the code, the
    base scenario's text, the overrides, the seed, stages and methods;
    :func:`bench.grid.cache_key`)."""
    return cache_key(
        base=spec.base_text,
        overrides=[[k, v] for k, v in overrides],
        seed=seed,
        stages=list(spec.stages),
        methods=list(spec.methods),
    )


# ----------------------------------------------------------------------------- a point

#: How a sweep calibrates a target other than spheres at a point: ``uscal run``'s
#: (scenario, twin, acquisition, start time) → the run with its ``metrics``.
TargetRunner = Callable[[Any, Any, Any, float], Any]


def run_point(
    base: str,
    overrides: Sequence[tuple[str, Any]],
    seed: int,
    stages: Sequence[str],
    methods: Sequence[str],
    target_runner: TargetRunner | None = None,
) -> list[dict[str, Any]]:
    """Simulate one acquisition of ``base`` with ``overrides`` and ``seed``, localize
    every sphere with each method (the sweeps stacked with the twin's true ``T_ee_us``:
    the localizer alone) and, with the ``calibrate`` stage, calibrate single-marker on
    the first sphere from the coarse estimate; one row of metrics per method, no
    frames. A wire, N-wire or cone scenario is calibrated from its own target by
    ``target_runner`` (``uscal run``'s: :func:`bench.jobs.targets.run_target`)."""
    scenario = _point_scenario(base, overrides, seed)
    t0 = time.perf_counter()
    twin = make_twin(scenario)
    imager = make_imager(scenario, twin)
    with progress_report.reporting(None):  # the sweep counts points, not sweeps
        acq = simulate_acquisition(scenario, twin, imager, "sweep")
    del imager
    if scenario.phantom.kind in TARGET_PHANTOMS:
        if target_runner is None:
            raise SweepError(f"a {scenario.phantom.kind} scenario's point needs its runner")
        return [_target_row(target_runner, scenario, twin, acq, seed, t0)]
    release_memory()
    return _sphere_rows(scenario, twin.truth, acq, stages, methods)


def run_points_at_gains(
    base: str,
    overrides: Sequence[Sequence[tuple[str, Any]]],
    seed: int,
    stages: Sequence[str],
    methods: Sequence[str],
) -> list[dict[str, Any]]:
    """:func:`run_point`'s rows of sphere points that differ in the display gain alone,
    from one acquisition shown at every gain
    (:func:`bench.acquire_sim.simulate_acquisition_at_gains`); each point's result
    (``{"rows": ...}``, or the error its own localization or calibration raised), in
    order."""
    scenarios = [_point_scenario(base, o, seed) for o in overrides]
    with progress_report.reporting(None):
        twin, series = simulate_acquisition_at_gains(scenarios, "sweep")
    release_memory()
    return [
        guarded(lambda s=s, acq=acq: {"rows": _sphere_rows(s, twin.truth, acq, stages, methods)})
        for s, acq in zip(scenarios, series, strict=True)
    ]


def _point_scenario(base: str, overrides: Sequence[tuple[str, Any]], seed: int):
    """The scenario of a point: ``base`` with its overrides and seed."""
    return load_scenario(Path(base), [*(_override(k, v) for k, v in overrides), f"seed={seed}"])


def _sphere_rows(
    scenario, truth, acq: SimulatedAcquisition, stages: Sequence[str], methods: Sequence[str]
) -> list[dict[str, Any]]:
    """A sphere point's rows (:func:`run_point`) from its acquisition and the truth."""
    seed = scenario.seed
    radius = stated_radius(scenario)
    scale = axial_scale(scenario)
    targets = acq.dataset.targets()
    rows = []
    for method in methods:
        cfg = replace(scenario.localization, method=method)
        # The localizer alone: the sweeps stacked with the true T_ee_us (the twin's), so
        # that no calibration error enters; centres against the true centre in each
        # sweep's true reference frame (errors of the accepted sweeps, mm).
        locs = {
            t: localize_sphere(acq.dataset.of(t), truth.T_ee_us, radius, cfg, axial_scale=scale)
            for t in targets
        }
        e, n, rejected = localization_errors(acq, truth, locs)
        row: dict[str, Any] = {
            "seed": seed,
            "method": method,
            "localization_median_error_mm": float(np.median(e)) if len(e) else float("nan"),
            "rejected_fraction": rejected / n if n else float("nan"),
            "localization_max_error_mm": float(e.max()) if len(e) else float("nan"),
            # Accepted centres more than 1 mm from the truth: wrong answers handed back
            # as good ones.
            "false_acceptances": int((e > 1.0).sum()),
            "sweeps": n,
        }
        if "calibrate" in stages:
            row["calibration_image_mm"] = float("nan")
            row["calibration_false_acceptances"] = None
            row["calibration_dropped"] = None
            try:
                alt = alternate(
                    {targets[0]: acq.dataset.of(targets[0])},
                    radius,
                    AlternationSettings(
                        cfg,
                        axial_scale=scale,
                        max_iterations=scenario.calibration.max_alternations,
                    ),
                    T_coarse=acq.T_ee_us_coarse,
                )
                row["calibration_image_mm"] = image_error_mm(
                    scenario, alt.result.T_ee_us, truth.T_ee_us
                )
                # What the pipeline itself says of it, and why: its 95 % bound (the
                # declared terms of the scenario, as `uscal run` makes it) and the verdict
                # on it against the scenario's requirements. Judged without a bound, the
                # last update was compared with a first-order 2 σ, which called sound
                # calibrations "did not converge" (26 of 58 on robustness_wide.yaml).
                bound = alternation_bound(
                    alt, image_points(scenario), inputs=scenario_uncertainty(scenario)
                )
                row["calibration_bound_image_mm"] = bound.image_mm
                verdict = judge(
                    alt,
                    bound,
                    requirements(scenario),
                    geometry=sweep_geometry(alt, acq.dataset.of(targets[0]), radius),
                )
                row["calibration_verdict"] = verdict.status
                row["calibration_verdict_reasons"] = "; ".join(verdict.reasons)
                # The localizer again, with the estimated mount (the consensus the
                # alternation builds): the centres the calibration kept that are > 1 mm
                # off, and those the localizer accepted but the calibration dropped.
                kept = alt.retained_localizations()
                e_kept, _, _ = localization_errors(acq, truth, kept)
                row["calibration_false_acceptances"] = int((e_kept > 1.0).sum())
                row["calibration_dropped"] = sum(
                    a.accepted and not b.accepted
                    for t in kept
                    for a, b in zip(alt.localizations[t], kept[t], strict=True)
                )
            except UscalError as exc:  # e.g. too few accepted sweeps to calibrate
                row["calibration_error"] = str(exc)
        rows.append(row)
    return rows


def _target_row(
    run_target: TargetRunner, scenario, twin, acq, seed: int, t0: float
) -> dict[str, Any]:
    """A wire, N-wire or cone scenario's point: its own target found and calibrated as
    ``uscal run`` does (:func:`bench.jobs.targets.run_target`); one row named after the
    target: the share of frames (cone: sweeps) not used, the calibration's true error
    over the image and its verdict (no sphere localization figures)."""
    try:
        run = run_target(scenario, twin, acq, t0)
    except UscalError as exc:  # e.g. too few frames show the target
        return {"seed": seed, "method": scenario.phantom.kind, "calibration_error": str(exc),
                "calibration_image_mm": float("nan")}  # fmt: skip
    m = run.metrics
    kind = m["dataset"]["target"]
    per_sweep = kind == "cone_tip"
    n = m["dataset"]["n_sequences"] if per_sweep else m["dataset"]["n_frames"]
    used = m["detection"]["sweeps_found" if per_sweep else "frames_found"]
    cal = m["calibration"][kind]
    return {
        "seed": seed,
        "method": kind,
        "rejected_fraction": (n - used) / n if n else float("nan"),
        "sweeps": len(acq.dataset.sweeps),
        "calibration_image_mm": cal["true_error"]["image_mm"],
        "calibration_verdict": cal["verdict"]["status"],
        "calibration_verdict_reasons": "; ".join(cal["verdict"]["reasons"]),
    }


def _sweep_point(
    base: str,
    stages: Sequence[str],
    methods: Sequence[str],
    target_runner: TargetRunner | None,
    overrides: Sequence[tuple[str, Any]],
    seed: int,
) -> dict[str, Any]:
    """A point's result as the grid records it (:func:`run_point`'s rows)."""
    return {"rows": run_point(base, overrides, seed, stages, methods, target_runner)}


def _sweep_points_at_gains(
    base: str,
    stages: Sequence[str],
    methods: Sequence[str],
    overrides: list[tuple[tuple[str, Any], ...]],
    seed: int,
) -> list[dict[str, Any]]:
    """A batch of points that differ in the gain alone, as the grid records them."""
    return run_points_at_gains(base, overrides, seed, stages, methods)


def _batches(spec: SweepSpec) -> list[str | None]:
    """The batch each point runs in, in :meth:`SweepSpec.points`' order
    (:attr:`bench.grid.GridPoint.batch`): sphere points that set the gain and agree on
    every other override share one (their seed apart), up to
    :data:`MAX_GAINS_PER_ACQUISITION` neighbouring gains; None for the rest (a wire,
    N-wire or cone point calibrates through ``uscal run``'s own path)."""
    points = spec.points()
    # A target scenario's sweep has its target's name as its one method (load_sweep);
    # drawn points share nothing (each its own seed).
    if set(spec.methods) & set(TARGET_PHANTOMS) or spec.draws is not None:
        return [None] * len(points)
    gains = sorted({float(dict(o)[SHARED_ACROSS]) for o, _ in points if SHARED_ACROSS in dict(o)})
    rank = {g: i for i, g in enumerate(gains)}
    batches: list[str | None] = []
    for overrides, _ in points:
        gain = dict(overrides).get(SHARED_ACROSS)
        if gain is None:
            batches.append(None)
            continue
        run = rank[float(gain)] // MAX_GAINS_PER_ACQUISITION
        rest = [[k, v] for k, v in overrides if k != SHARED_ACROSS]
        batches.append(json.dumps([rest, run]))
    return batches


# ----------------------------------------------------------------------------- reading a point


@dataclass(frozen=True)
class SweepRow:
    """One localizer's figures at one point, as :func:`run_point` made them: the
    localization's (:data:`LOCALIZATION_METRICS`) and, with the ``calibrate`` stage, the
    calibration's true image error or why it failed. A figure the row does not hold is
    None (``results.csv`` leaves it empty)."""

    method: str
    localization_median_error_mm: float | None = None
    rejected_fraction: float | None = None
    localization_max_error_mm: float | None = None
    false_acceptances: int | None = None
    sweeps: int | None = None
    calibration_image_mm: float | None = None  # the calibrate stage only
    calibration_error: str | None = None  # the calibrate stage, when it failed
    # The calibrate stage: centres the calibration kept > 1 mm off; localizer-accepted
    # centres it dropped as outliers.
    calibration_false_acceptances: int | None = None
    calibration_dropped: int | None = None
    # The calibrate stage: the calibration's verdict (calib.calibration.verdict, on its 95 %
    # bound) and its reasons ("; " between them, empty when accepted).
    calibration_verdict: str | None = None
    calibration_verdict_reasons: str | None = None
    # The calibrate stage: the 95 % bound on the image error (mm).
    calibration_bound_image_mm: float | None = None

    @classmethod
    def from_document(cls, row: dict[str, Any]) -> SweepRow:
        """A row of a point's document: its method and the figures it holds (every
        localization figure from :func:`run_point`; ``calibration_image_mm`` only with
        the ``calibrate`` stage, NaN when it failed, and ``calibration_error`` then)."""

        def number(key: str, kind: type) -> Any:
            v = row.get(key)
            return None if v is None else kind(v)

        return cls(
            row["method"],
            number("localization_median_error_mm", float),
            number("rejected_fraction", float),
            number("localization_max_error_mm", float),
            number("false_acceptances", int),
            number("sweeps", int),
            number("calibration_image_mm", float),
            row.get("calibration_error"),
            number("calibration_false_acceptances", int),
            number("calibration_dropped", int),
            row.get("calibration_verdict"),
            row.get("calibration_verdict_reasons"),
            number("calibration_bound_image_mm", float),
        )

    @property
    def calibration_bound_covers(self) -> bool | None:
        """The calibrate stage: whether the 95 % bound covers the true image error (None
        without both)."""
        if self.calibration_bound_image_mm is None or self.calibration_image_mm is None:
            return None
        return bool(self.calibration_image_mm <= self.calibration_bound_image_mm)

    def figure(self, name: str) -> float | int | None:
        """A figure by its ``results.csv`` name (None: not measured at this point)."""
        return getattr(self, name)


@dataclass(frozen=True)
class SweepPoint:
    """A point's document as the grid records it (:func:`bench.grid.run_grid`): its
    overrides and seed, and its rows, the error it failed with, or why its plan was
    refused before anything moved (a pose that collides or is out of reach)."""

    overrides: tuple[tuple[str, Any], ...]
    seed: int
    rows: tuple[SweepRow, ...] = ()
    error: str | None = None
    refused: str | None = None

    @classmethod
    def from_document(cls, doc: dict[str, Any]) -> SweepPoint:
        """``{overrides, seed, rows}``, ``{overrides, seed, error, traceback}`` for a
        point that failed, or ``{overrides, seed, refused}`` (no rows)."""
        return cls(
            tuple((k, v) for k, v in doc["overrides"]),
            int(doc["seed"]),
            tuple(SweepRow.from_document(r) for r in doc.get("rows", [])),
            doc.get("error"),
            doc.get("refused"),
        )

    def override(self, key: str) -> Any:
        """The value the point sets ``key`` to (None: it does not set it)."""
        return dict(self.overrides).get(key)


# ----------------------------------------------------------------------------- the sweep


@dataclass(frozen=True)
class SweepResult:
    """Every point's rows (or error, or refusal), in grid order, and what was computed
    anew."""

    spec: SweepSpec
    points: list[dict[str, Any]]
    computed: int
    cached: int
    failed: int
    seconds: float
    refused: int = 0


def run_sweep(
    spec: SweepSpec,
    out: str | os.PathLike[str],
    scheduler: str | None = None,
    workers: int | None = None,
    target_runner: TargetRunner | None = None,
) -> SweepResult:
    """Run every point not yet cached in ``out/points``, on a local process pool
    (``workers``, default one per core) or the Dask cluster at ``scheduler``
    (:func:`bench.grid.run_grid`). A failed point records its error, a refused one why
    its plan was refused (collision, reach), and the sweep goes on;
    :func:`bench.outputs.sweep_report.write_sweep` writes the tables. ``target_runner``:
    how a wire, N-wire or cone scenario's points are calibrated (:func:`run_point`)."""
    task = functools.partial(_sweep_point, str(spec.base), spec.stages, spec.methods, target_runner)
    at_gains = functools.partial(_sweep_points_at_gains, str(spec.base), spec.stages, spec.methods)
    points = [
        GridPoint(o, s, point_key(spec, o, s), b)
        for (o, s), b in zip(spec.points(), _batches(spec), strict=True)
    ]
    grid = run_grid(task, points, out, scheduler, workers, "sweep points", at_gains)
    return SweepResult(
        spec,
        grid.documents,
        grid.computed,
        grid.cached,
        grid.failed,
        grid.seconds,
        grid.refused,
    )
