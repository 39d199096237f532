"""What the ``uscal`` commands print: the scenario's summary, progress bars, and the
result tables of a run, the paper's experiment, the reconstruction and a recorded
dataset's calibration (rich). The commands themselves are in :mod:`bench.cli`."""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.progress import Progress as RichProgress
from rich.table import Table

from calib import se3
from calib.evaluate import PaperTable, table_iii, tables_i_ii
from calib.plus_import import ImportSummary

from .config.scenario import Scenario

__all__ = [
    "Bars",
    "paper_table",
    "print_cached_run",
    "print_evaluation",
    "print_plan",
    "print_plan_comparison",
    "print_reconstruction",
    "print_recorded",
    "print_run",
    "print_scenario_summary",
    "print_truth",
    "print_workload",
    "print_written",
    "progress_bars",
    "spawn_viewer",
]


def print_scenario_summary(s: Scenario, console: Console) -> None:
    table = Table(title=f"scenario {s.source}", show_header=True)
    table.add_column("section")
    table.add_column("summary")
    r, p, t = s.robot, s.phantom, s.tools
    rows = [
        ("seed", str(s.seed)),
        (
            "robot",
            f"{r.model}, DH error ×{r.dh_error_scale:g} (RMS θ {r.dh_rms_theta_deg:g}°, "
            f"d {r.dh_rms_d_mm:g} mm, a {r.dh_rms_a_mm:g} mm, α {r.dh_rms_alpha_deg:g}°), "
            f"repeatability {r.joint_repeatability_deg:g}°, encoder {r.encoder_noise_deg:g}°",
        ),
        (
            "tools",
            f"{t.mounted} mounted; probe at {list(t.probe_mount_position_mm)} mm / "
            f"{list(t.probe_mount_rotation_deg)}°; stylus tip {list(t.stylus_tip_mm)} mm",
        ),
        (
            "phantom",
            f"{p.kind} at {list(p.position_mm)} mm, {list(p.rotation_deg)}°; tank "
            f"{list(p.tank_inner_mm)} mm, water {p.water_level_mm:g} mm",
        ),
        ("medium", f"{s.medium.kind} at {s.medium.temperature_c:g} °C"),
        (
            "imaging",
            f"{s.imaging.width_mm:g} × {s.imaging.depth_mm:g} mm at "
            f"{list(s.imaging.pixel_spacing_mm)} mm/px, {s.imaging.f_mhz:g} MHz, "
            f"gain {s.imaging.gain_db:g} dB",
        ),
        (
            "protocol",
            f"9 orientations (±{s.protocol.rotation_deg:g}°) × 5 positions "
            f"(±{s.protocol.translation_mm:g} mm), sweeps ±"
            f"{s.protocol.sweep_half_length_mm:g} mm × {s.protocol.frames_per_sweep} "
            "frames",
        ),
        ("output", s.output.dir),
    ]
    for name, text in rows:
        table.add_row(name, text)
    console.print(table)
    console.print(
        "[green]ok[/green]: scenario is valid; every target is reachable at all "
        "nine orientations and the probe clears phantom and tank."
    )


def print_recorded(m: dict, console: Console) -> None:
    d, loc = m["dataset"], m["localization"]
    console.print(
        f"dataset {d['name']} ({d['source']}): {d['n_sweeps']} sweeps of "
        f"{', '.join(d['targets'])}; {loc['n_sweeps']} localized, {loc['n_rejected']} rejected"
    )

    def cells(c: dict) -> list[str]:
        t = np.array(c["T_ee_us"])[:3, 3] * 1e3
        b = c.get("bound95") or {}
        return [
            *(f"{v:.2f}" for v in t),
            f"{b['rotation_deg']:.3f}" if b else "-",
            f"{b['translation_mm']:.3f}" if b else "-",
            f"{c['precision_mm']:.3f}",
            str(c["n_retained"]),
        ]

    # The 95 % error bounds (calib.uncertainty): what the estimate can be off by.
    columns = ("x mm", "y mm", "z mm", "≤95% rot °", "≤95% mm", "prec mm", "kept")
    console.print(_calibration_table(m, "calibration (no ground truth)", columns, cells))
    both = m["calibration"].get("single_vs_three")
    if both:
        console.print(
            f"single vs three-marker: {both['rotation_deg']:.3f} °, "
            f"{both['translation_mm']:.3f} mm apart"
        )
    ev = m.get("evaluation")
    if ev:
        console.print(
            f"touches: {ev['touches']}, DH refined from {ev['dh_from']}, touch residual "
            f"RMS {ev['touch_residual_rms_mm']:.3f} mm"
        )
        for kind, v in ev.get("summary", {}).items():
            a, p = v["accuracy_mm"], v["precision_mm"]
            console.print(
                f"{kind}-marker folds: accuracy {a['mean']:.3f} ± {a['sd']:.3f} mm, "
                f"precision {p['mean']:.3f} ± {p['sd']:.3f} mm (against the touch reference)"
            )


class Bars:
    """Rich progress bars, one per reported task, with counts, elapsed time and ETA."""

    def __init__(self, console: Console) -> None:
        self.progress = RichProgress(
            TextColumn("{task.description:<28}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TextColumn("eta"),
            TimeRemainingColumn(),
            console=console,
            disable=console.quiet,
        )
        self.console = self.progress.console
        self._tasks: dict[str, TaskID] = {}

    def update(self, task: str, done: int, total: int) -> None:
        if task not in self._tasks:
            self._tasks[task] = self.progress.add_task(task, total=total)
        self.progress.update(self._tasks[task], completed=done, total=total)


@contextlib.contextmanager
def progress_bars(console: Console):
    bars = Bars(console)
    with bars.progress:
        yield bars


def spawn_viewer(path: Path, console: Console) -> None:
    """Open a recording in the rerun viewer, if one is installed (a separate process)."""
    import shutil
    import subprocess

    viewer = shutil.which("rerun")
    if viewer is None:
        console.print(f"no rerun viewer found on PATH: open {path} with `rerun {path}`")
        return
    subprocess.Popen([viewer, str(path)], start_new_session=True)
    console.print(f"opened {path} in the rerun viewer")


def paper_table(t: PaperTable, columns: Sequence[str] | None = None) -> Table:
    """One of the paper's tables (:class:`calib.evaluate.PaperTable`) for the console;
    ``columns`` replaces its column names (shorter ones for a narrow terminal)."""
    table = Table(title=t.title)
    for i, col in enumerate(columns or t.columns):
        table.add_column(col, justify="left" if i < 2 else "right", no_wrap=i < 2)
    for row in t.rows:
        table.add_row(*row)
    return table


def print_evaluation(m: dict, console: Console) -> None:
    names = m["evaluation"]["datasets"]
    for t in tables_i_ii(m["evaluation"]):
        console.print(paper_table(t))
    kin = m["kinematics"]
    table = Table(title="against ground truth (beyond the paper)")
    for col in (
        "set",
        "kin. err nominal",
        "kin. err refined",
        "ref. err",
        "1: image",
        "1: acc",
        "3: image",
        "3: acc",
    ):
        table.add_column(col, justify="right" if col != "set" else "left")
    for n in names:
        k = kin["datasets"][n]
        folds = [f for f in m["evaluation"]["folds"] if f["dataset"] == n]

        def mean(kind: str, key: str, folds=folds) -> float:
            return float(np.mean([f["true"][key] for f in folds if f["kind"] == kind]))

        table.add_row(
            n,
            f"{k['true_error']['nominal_rms']:.2f}",
            f"{k['true_error']['refined_rms']:.3f}",
            f"{np.mean(list(k['reference_error_mm'].values())):.2f}",
            f"{mean('single', 'image_mm'):.2f}",
            f"{mean('single', 'accuracy_true_mm'):.2f}",
            f"{mean('three', 'image_mm'):.2f}",
            f"{mean('three', 'accuracy_true_mm'):.2f}",
        )
    console.print(table)
    console.print(
        "mm; kin. err: RMS error of the kinematic model at the image over the scanned "
        "configurations (after the base/flange frames touches cannot see); ref. err: touch "
        "reference centres vs true centres; image/acc: per-fold mean true image error of "
        "T_ee_us and accuracy against the true centres (1: single-, 3: three-marker)."
    )
    hidden = [k for k, v in kin["unobservable_share"].items() if v >= 0.5]
    console.print(
        "touches cannot identify (≥ half in directions they cannot see; the regulariser "
        f"keeps these at nominal): {', '.join(hidden)}"
    )
    rms = kin["rms_change_mean"]
    console.print(
        "DH change from nominal, RMS over the leave-one-out models: "
        f"θ {rms['theta_deg']:.2f}°, d {rms['d_mm']:.2f} mm, a {rms['a_mm']:.2f} mm, "
        f"α {rms['alpha_deg']:.2f}°"
    )


def print_reconstruction(m: dict, console: Console) -> None:
    names = m["evaluation"]["datasets"]
    rec = m["reconstruction"]
    kinds = [k for k in ("cone", "prism") if k in rec]
    after_icp = table_iii({k: rec[k] for k in kinds}, names)[0]
    short = ("", "set", "1: MAE±SD", "RMSE", "max", "3: MAE±SD", "RMSE", "max")
    console.print(paper_table(after_icp, short))
    console.print(
        "1: single-marker (sphere 1), 3: three-marker (spheres 1–3), re-calibrated after the "
        "remount with each set's DH model. Without ICP, through the true phantom placement "
        "(beyond the paper), overall MAE: "
        + "; ".join(
            f"{kind} {rec[kind]['single']['overall']['without_icp']['mae']:.2f} (1), "
            f"{rec[kind]['three']['overall']['without_icp']['mae']:.2f} (3)"
            for kind in kinds
        )
        + " mm."
    )


def _calibration_table(m: dict, title: str, columns: Sequence[str], cells) -> Table:
    """One row per calibration method of ``metrics.json`` (``cells(entry)`` → texts)."""
    table = Table(title=title)
    table.add_column("method", justify="left")
    for col in columns:
        table.add_column(col, justify="right")
    for name in ("single", "three"):
        c = m["calibration"].get(name)
        if c is not None:
            table.add_row(name, *cells(c))
    return table


def print_run(m: dict, console: Console) -> None:
    loc = m["localization"]
    console.print(
        f"localization ({loc['method']}): {loc['n_sweeps']} sweeps, {loc['n_rejected']} "
        f"rejected; error vs truth median {loc['error_mm']['median']:.3f} mm, "
        f"p95 {loc['error_mm']['p95']:.3f} mm, max {loc['error_mm']['max']:.3f} mm"
    )

    def cells(c: dict) -> list[str]:
        e = c["true_error"]
        return [
            f"{e['rotation_deg']:.3f}",
            f"{e['translation_mm']:.3f}",
            f"{e['image_mm']:.3f}",
            f"{c['precision_mm']:.3f}",
            f"{c['accuracy_mm']:.3f}",
            str(c["n_retained"]),
            str(c["iterations"]),
        ]

    # Short headers: the table must fit an 80-column terminal.
    columns = ("rot °", "trans mm", "image mm", "prec mm", "acc mm", "kept", "iter")
    console.print(_calibration_table(m, "calibration against ground truth", columns, cells))
    for name in ("single", "three"):
        c = m["calibration"].get(name)
        if c is None or "bound95" not in c:
            continue
        b, e = c["bound95"], c.get("true_error_equivalent", c["true_error"])
        inside = all(e[k] <= b[k] for k in ("rotation_deg", "translation_mm", "image_mm"))
        console.print(
            f"{name}: 95 % error bounds (from the data alone) rotation {b['rotation_deg']:.3f}°, "
            f"translation {b['translation_mm']:.3f} mm, image {b['image_mm']:.3f} mm; "
            f"the truth is {'inside' if inside else 'OUTSIDE'}"
        )
    t = m["timing_s"]
    summed = f" (summed over {t['workers']} workers)" if "workers" in t else ""
    console.print(
        f"time: simulate {t['simulate']:.1f} s, localize {t['localize']:.1f} s, "
        f"calibrate {t['calibrate']:.1f} s{summed}, total {t['total']:.1f} s"
    )


# ---------------------------------------------------------------- the other commands


def print_plan(scenario: Scenario, reports: Sequence, noise_mm: float, console: Console) -> None:
    """``uscal plan``: the plan checked, and the observability of ``T_ee_us`` per sphere
    (sphere vs wire target)."""
    p = scenario.protocol
    console.print(
        f"plan: {len(reports)} sphere(s) × {reports[0].n_sweeps} sweeps "
        f"(±{p.rotation_deg:g}° corners, ±{p.translation_mm:g} mm in-plane), "
        f"{sum(r.n_poses for r in reports)} frame poses: all reachable and collision-free"
    )
    table = Table(title=f"observability of T_ee_us (localization noise {noise_mm:g} mm)")
    for col in ("sphere", "target", "λ min", "cond.", "σ min", "NAI", "rot° 1σ", "mm 1σ"):
        table.add_column(col, justify="left" if col in ("sphere", "target") else "right")
    for r in reports:
        for label, o in (("sphere", r.point), ("wire", r.wire)):
            table.add_row(
                r.sphere.removeprefix("sphere_") if label == "sphere" else "",
                label,
                f"{o.eigenvalues[-1]:.3g}",
                f"{o.condition_number:.2g}",
                f"{o.min_singular_value:.3g}",
                f"{o.noise_amplification:.2g}",
                f"{o.std_rotation_deg.max():.3f}",
                f"{o.std_translation_mm.max():.3f}",
            )
    console.print(table)
    console.print(
        "θ = (rotation vector in rad, translation in mm), points in mm; λ: eigenvalues of the "
        "information matrix; NAI: noise amplification index λmin/√λmax; 1σ: largest "
        "predicted standard deviation over the three axes. The wire runs perpendicular to "
        "the nominal image plane; it slides along itself, so it never informs more than "
        "the sphere."
    )


def print_plan_comparison(c, scenario: Scenario, console: Console) -> None:
    """``uscal plan --optimize``: the chosen plan beside the paper's."""
    o = c.optimized
    per_sphere = ", ".join(f"{k}: {len(v)}" for k, v in o.poses.items())
    left = ", ".join(f"{n} {k}" for k, n in (o.left_out or {}).items())
    kind = "three-marker" if len(c.spheres) >= 3 else "single-marker"
    console.print(
        f"chose {o.n_sweeps} sweeps ({per_sphere}) from {o.candidates} candidates ({left}), "
        f"criterion {c.criterion}, for {kind} calibration"
    )
    noise = scenario.planning.localization_noise_mm
    table = Table(
        title="predicted for localization noise "
        f"{noise[0]:g} / {noise[1]:g} / {noise[2]:g} mm (lateral / axial / elevation, 1 σ) "
        f"and the arm's {scenario.planning.pose_noise_mm:g} mm, fitted as calib.calibrate fits"
    )
    for col in ("plan", "sweeps", "rot° 1σ", "mm 1σ", "image mm", "cond.", "robot time"):
        table.add_column(col, justify="left" if col == "plan" else "right")
    for name, p in (("paper", c.paper), ("optimized", o)):
        pr = p.prediction
        table.add_row(
            name,
            str(p.n_sweeps),
            f"{pr.rotation_deg:.3f}",
            f"{pr.translation_mm:.3f}",
            f"{pr.image_mm:.3f}",
            f"{pr.condition_number:.3g}",
            f"{p.robot_time_s:.0f} s",
        )
    console.print(table)


def print_truth(landmarks_mm: dict[str, list[float]], T_ee_us, console: Console) -> None:
    """``uscal twin export``: the true landmarks and mount."""
    table = Table(title="true landmarks (base frame, mm)")
    for col in ("landmark", "x", "y", "z"):
        table.add_column(col, justify="right" if col != "landmark" else "left")
    for name, (x, y, z) in landmarks_mm.items():
        table.add_row(name, f"{x:.3f}", f"{y:.3f}", f"{z:.3f}")
    console.print(table)
    rot = np.degrees(se3.euler_from_matrix(T_ee_us[:3, :3]))
    console.print(
        f"true T_ee_us: position {np.round(1e3 * T_ee_us[:3, 3], 3).tolist()} mm, "
        f"rotation (xyz) {np.round(rot, 3).tolist()}°"
    )


def print_written(out: Path, written: Sequence[str], console: Console) -> None:
    """The files a run or calibration wrote (figures counted, not listed)."""
    figures = [f for f in written if f.startswith("figures/")]
    files = [f for f in written if not f.startswith("figures/")]
    console.print(
        f"wrote {', '.join(str(out / f) for f in files)} and {len(figures)} figures in "
        f"{out / 'figures'} (open {out / 'report.html'})"
    )


def print_workload(count: int, seeds: int, hours: float, workers: int, cluster: bool, console):
    """What a sweep is about to run, before it runs."""
    where = (
        f"≈ {hours:.1f} worker-hours on the cluster"
        if cluster
        else f"≈ {hours / workers:.1f} h on {workers} local worker(s)"
    )
    console.print(
        f"{count // seeds:,} grid points × {seeds} seed(s) = {count:,} acquisitions; "
        f"{where} (cached points are not recomputed)"
    )


def print_cached_run(what: str, n: int, result, files: Sequence[Path], console) -> None:
    """How a sweep's or budget's points went, and its files."""
    console.print(
        f"{n} {what}: {result.computed} computed, {result.cached} from the cache, "
        f"{result.failed} failed, in {result.seconds:.0f} s"
    )
    console.print(f"wrote {', '.join(str(f) for f in files[:-1])} and {files[-1]}")


def print_import(summary: ImportSummary, console: Console) -> None:
    """What ``uscal import plus`` wrote: each sweep, the frames skipped and why."""
    for line in summary.sweep_lines:
        console.print(line)
    skipped = sum(summary.skipped.values())
    why = ", ".join(f"{n} with {reason}" for reason, n in sorted(summary.skipped.items()))
    console.print(
        f"wrote {summary.directory}: {summary.sweeps} sweeps, {summary.frames} frames; "
        + (f"skipped {skipped} frames ({why})" if skipped else "no frame skipped")
        + f". Next: uscal calibrate {summary.directory} --markers 1"
    )
