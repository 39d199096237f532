"""The ``uscal`` command line.

Every :class:`~calib.errors.UscalError` becomes one line on stderr and exit code 2;
``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import traceback
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import yaml
from rich.console import Console
from rich.logging import RichHandler
from rich.table import Table

from calib import se3
from calib.errors import UscalError

from .console import (
    print_evaluation,
    print_reconstruction,
    print_recorded,
    print_run,
    print_scenario_summary,
    progress_bars,
    spawn_viewer,
)
from .progress import reporting
from .scenario import load_scenario, scenarios_markdown

__all__ = ["main"]

EXIT_USER_ERROR = 2


def _add_scenario_args(p: argparse.ArgumentParser, optional: bool = False) -> None:
    p.add_argument(
        "scenario",
        nargs="?" if optional else None,
        default=None,
        help="scenario YAML file" + (" (default: the built-in paper setup)" if optional else ""),
    )
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY.PATH=VALUE",
        help="override a scenario key (value in YAML syntax); repeatable",
    )


def _positive_mm(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of millimetres")
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number ≥ 0")
    return value


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="uscal",
        description="Tracker-free robotic ultrasound calibration: digital twin and test bench.",
    )
    for target in (parser, common := argparse.ArgumentParser(add_help=False)):
        # Accepted before and after the command; the command's copy must not reset the
        # global one, hence SUPPRESS there.
        default = False if target is parser else argparse.SUPPRESS
        target.add_argument(
            "--debug",
            action="store_true",
            default=default,
            help="show tracebacks of errors and verbose logs",
        )
        target.add_argument(
            "--quiet",
            "-q",
            action="store_true",
            default=default,
            help="print nothing but errors (for scripts)",
        )
    sub = parser.add_subparsers(dest="command", required=True)
    add_parser = sub.add_parser

    def sub_add_parser(name: str, **kwargs):
        return add_parser(name, parents=[common], **kwargs)

    sub.add_parser = sub_add_parser  # every command accepts --debug and --quiet

    run = sub.add_parser(
        "run", help="simulate the acquisition, localize, calibrate and score against truth"
    )
    _add_scenario_args(run, optional=True)
    run.add_argument("--out", help="output directory (default: the scenario's output.dir)")
    run.add_argument("--force", action="store_true", help="replace an existing directory")
    rrd = run.add_mutually_exclusive_group()
    rrd.add_argument("--rrd", metavar="FILE", help="rerun recording (default: OUT/recording.rrd)")
    rrd.add_argument("--no-rrd", action="store_true", help="write no rerun recording")
    run.add_argument(
        "--rrd-frames",
        type=_non_negative_int,
        default=420,
        metavar="N",
        help="B-mode frames recorded per acquisition session at most, as whole sweeps "
        "spread over it (default 420; 0 records none)",
    )
    run.add_argument(
        "--spawn", action="store_true", help="open the recording in the rerun viewer at the end"
    )
    run.add_argument(
        "--save-dataset",
        metavar="DATASET",
        help="also write the acquisition as dataset files (PLUS .mha per sweep + "
        "dataset.yaml) for `uscal calibrate`; the paper's experiment writes one per "
        "dataset, with its touches, as DATASET/<name>",
    )

    acquire = sub.add_parser(
        "acquire",
        help="run the sphere protocol on a real rig (UR via RTDE + frame grabber) into a dataset",
    )
    acquire.add_argument(
        "hw_config", help="hw config YAML (robot, grabber, rig, phantom, protocol)"
    )
    acquire.add_argument("--out", required=True, help="dataset directory to write")
    acquire.add_argument(
        "--resume", action="store_true", help="continue an interrupted acquisition in --out"
    )
    acquire.add_argument(
        "--dry-run", action="store_true", help="plan and check every pose; move nothing"
    )
    acquire.add_argument(
        "--yes", action="store_true", help="do not ask for confirmation before the first motion"
    )
    acquire.add_argument(
        "--touches",
        nargs="?",
        const="console",
        choices=["console", "loopback"],
        help="after the sweeps, touch every cone vertex with the stylus (for the DH "
        "refinement): hand-guided, confirmed at the terminal; 'loopback': by the loopback "
        "rig's emulated operator (uscal twin serve)",
    )
    acquire.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY.PATH=VALUE",
        help="override a hw config key, e.g. protocol.spheres=[1]; repeatable",
    )

    calibrate = sub.add_parser(
        "calibrate",
        help="localize and calibrate a recorded dataset (hardware or twin), offline",
    )
    calibrate.add_argument("dataset", help="dataset directory (dataset.yaml + sweeps/*.mha)")
    calibrate.add_argument(
        "--markers",
        choices=["1", "3"],
        help="single-marker (first sphere) or three-marker (first three) only; default both",
    )
    calibrate.add_argument("--out", help="output directory (default: DATASET-calibration)")
    calibrate.add_argument(
        "--dh-from",
        metavar="DATASET",
        action="append",
        default=[],
        help="refine the DH model from these datasets' touches (the paper's leave-one-out); "
        "default: the dataset's own touches, when it has any; repeatable",
    )
    calibrate.add_argument("--force", action="store_true", help="replace an existing directory")
    calibrate.add_argument(
        "--settings",
        metavar="SCENARIO",
        help="scenario whose localization and calibration settings to use (default: built-in)",
    )
    calibrate.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY.PATH=VALUE",
        help="override a settings key, e.g. localization.min_score=0.2; repeatable",
    )
    crrd = calibrate.add_mutually_exclusive_group()
    crrd.add_argument("--rrd", metavar="FILE", help="rerun recording (default: OUT/recording.rrd)")
    crrd.add_argument("--no-rrd", action="store_true", help="write no rerun recording")
    calibrate.add_argument(
        "--rrd-frames",
        type=_non_negative_int,
        default=420,
        metavar="N",
        help="B-mode frames recorded at most, as whole sweeps spread over the dataset",
    )

    sweep = sub.add_parser(
        "sweep",
        help="robustness sweep: a grid of scenario overrides × seeds, localized (and "
        "calibrated) with each localizer; local processes or a Dask cluster",
    )
    sweep.add_argument("sweep_file", help="sweep YAML (base, grid, seeds, stages, methods)")
    sweep.add_argument(
        "--out", help="output directory (default: out/<sweep file name>); rerunning resumes"
    )
    sweep.add_argument(
        "--scheduler", metavar="ADDRESS", help="run on this Dask scheduler (tcp://host:8786)"
    )
    sweep.add_argument(
        "--workers", type=_non_negative_int, default=0, help="local processes (default: cores)"
    )

    budget = sub.add_parser(
        "budget",
        help="error budget: each error source alone on an error-free rig and left out of "
        "the full scenario, over seeds; tornado charts of what limits the rig",
    )
    _add_scenario_args(budget)
    budget.add_argument("--out", help="output directory (default: out/<scenario>-budget)")
    budget.add_argument(
        "--sources",
        metavar="NAME,...",
        help="only these sources, comma-separated (default: all; an unknown name lists them)",
    )
    budget.add_argument(
        "--seeds", type=_non_negative_int, default=3, help="seeds per run (default 3)"
    )
    budget.add_argument(
        "--scheduler", metavar="ADDRESS", help="run on this Dask scheduler (tcp://host:8786)"
    )
    budget.add_argument(
        "--workers", type=_non_negative_int, default=0, help="local processes (default: cores)"
    )

    check = sub.add_parser("check", help="validate a scenario and print a summary")
    _add_scenario_args(check, optional=True)

    plan = sub.add_parser(
        "plan",
        help="check every planned pose (reach, collisions) and score the plan's "
        "observability of T_ee_us, sphere vs wire, without acquiring anything",
    )
    _add_scenario_args(plan, optional=True)
    plan.add_argument(
        "--noise-mm",
        type=_positive_mm,
        default=0.1,
        help="localization noise (1 σ per axis, mm) for the predicted spread (default 0.1)",
    )

    twin = sub.add_parser("twin", help="the digital twin")
    twin_sub = twin.add_subparsers(dest="twin_command", required=True)
    serve = twin_sub.add_parser(
        "serve",
        help="a loopback UR controller whose arm is the twin: RTDE (30004), dashboard "
        "(29999), script port (30003); frames of the simulated scanner to a file",
    )
    _add_scenario_args(serve, optional=True)
    serve.add_argument("--host", default="127.0.0.1", help="address to listen on (127.0.0.x)")
    serve.add_argument(
        "--frames",
        metavar="FILE",
        help="write the B-mode frame after each move here (PGM; a frame grabber's source)",
    )
    serve.add_argument(
        "--hw-config",
        metavar="FILE",
        help="also write a hw config for `uscal acquire` against this controller",
    )
    serve.add_argument("--fault-drop-at-move", type=_non_negative_int, default=0, metavar="N")
    serve.add_argument(
        "--fault-protective-stop-at-move", type=_non_negative_int, default=0, metavar="N"
    )
    export = twin_sub.add_parser(
        "export", help="write the scene as MJCF + STL meshes and print the true landmarks"
    )
    _add_scenario_args(export)
    export.add_argument("outdir", help="output directory (created atomically)")
    export.add_argument("--force", action="store_true", help="replace an existing OUTDIR")

    image = sub.add_parser(
        "image", help="render a gallery of B-mode frames at the paper's representative poses"
    )
    _add_scenario_args(image)
    image.add_argument("--out", required=True, help="output directory (created atomically)")
    image.add_argument("--force", action="store_true", help="replace an existing directory")

    docs = sub.add_parser("docs", help="generate documentation")
    docs.add_argument("topic", choices=["scenarios"])
    docs.add_argument("--output", "-o", help="write to this file instead of stdout")
    return parser


def _cmd_check(args: argparse.Namespace, console: Console) -> int:
    scenario = load_scenario(args.scenario, args.overrides)
    print_scenario_summary(scenario, console)
    return 0


def _cmd_plan(args: argparse.Namespace, console: Console) -> int:
    from .plan import plan_report

    scenario = load_scenario(args.scenario, args.overrides)
    reports = plan_report(scenario, args.noise_mm)
    p = scenario.protocol
    console.print(
        f"plan: {len(reports)} sphere(s) × {reports[0].n_sweeps} sweeps "
        f"(±{p.rotation_deg:g}° corners, ±{p.translation_mm:g} mm in-plane), "
        f"{sum(r.n_poses for r in reports)} frame poses: all reachable and collision-free"
    )
    table = Table(title=f"observability of T_ee_us (localization noise {args.noise_mm:g} mm)")
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
    return 0


def _cmd_twin_serve(args: argparse.Namespace, console: Console) -> int:
    from twin.ur_controller import ControllerFaults, LoopbackController

    from .experiment import make_imager, make_twin

    scenario = load_scenario(args.scenario, args.overrides)
    twin = make_twin(scenario)
    imager = make_imager(scenario, twin) if args.frames else None
    from .hw_config import emulated_operator

    controller = LoopbackController(
        twin.robot,
        imager,
        args.frames,
        args.host,
        ControllerFaults(args.fault_drop_at_move, args.fault_protective_stop_at_move),
        emulated_operator(scenario, twin),
    )
    controller.start()
    if args.hw_config:
        from .hw_config import loopback_hw_config

        loopback_hw_config(args.hw_config, scenario, twin, args.host, args.frames)
    console.print(
        f"loopback UR controller (the twin of {scenario.source}) on {args.host}: RTDE 30004, "
        f"dashboard 29999, script 30003"
        + (f"; frames to {args.frames}" if args.frames else "")
        + (f"; hw config {args.hw_config}" if args.hw_config else "")
        + ". Ctrl-C stops it."
    )
    sys.stdout.flush()
    try:
        controller.serve_forever()
    except KeyboardInterrupt:
        controller.close()
    return 0


def _cmd_twin_export(args: argparse.Namespace, console: Console) -> int:
    from twin.scene import export_scene

    from .experiment import make_twin
    from .output import atomic_output_dir

    scenario = load_scenario(args.scenario, args.overrides)
    twin = make_twin(scenario)
    truth = twin.truth
    landmarks = {k: [round(1e3 * float(v), 4) for v in p] for k, p in truth.landmarks_base.items()}
    with atomic_output_dir(args.outdir, force=args.force) as tmp:
        files = export_scene(twin.scene.scene, tmp)
        truth_doc = {
            "scenario": scenario.source,
            "seed": scenario.seed,
            "landmarks_base_mm": landmarks,
            "sphere_radii_mm": {k: round(1e3 * v, 4) for k, v in truth.sphere_radii.items()},
            "T_ee_us": np.round(truth.T_ee_us, 9).tolist(),
            "stylus_tip_ee_mm": np.round(1e3 * truth.p_ee_tip, 4).tolist(),
            "dh_true": {
                k: list(v)
                for k, v in zip(
                    ("theta_rad", "d_m", "a_m", "alpha_rad"),
                    (
                        truth.dh_table.theta,
                        truth.dh_table.d,
                        truth.dh_table.a,
                        truth.dh_table.alpha,
                    ),
                    strict=True,
                )
            },
        }
        (tmp / "truth.yaml").write_text(yaml.safe_dump(truth_doc, sort_keys=False))
        files.append("truth.yaml")
    table = Table(title="true landmarks (base frame, mm)")
    for col in ("landmark", "x", "y", "z"):
        table.add_column(col, justify="right" if col != "landmark" else "left")
    for name, (x, y, z) in landmarks.items():
        table.add_row(name, f"{x:.3f}", f"{y:.3f}", f"{z:.3f}")
    console.print(table)
    rot = np.degrees(se3.euler_from_matrix(truth.T_ee_us[:3, :3]))
    console.print(
        f"true T_ee_us: position {np.round(1e3 * truth.T_ee_us[:3, 3], 3).tolist()} mm, "
        f"rotation (xyz) {np.round(rot, 3).tolist()}°"
    )
    console.print(
        f"wrote {len(files)} files to {args.outdir} (open {Path(args.outdir) / 'scene.xml'}"
        " in MuJoCo's viewer)"
    )
    return 0


def _cmd_image(args: argparse.Namespace, console: Console) -> int:
    from .gallery import write_gallery
    from .output import atomic_output_dir

    scenario = load_scenario(args.scenario, args.overrides)
    with atomic_output_dir(args.out, force=args.force) as tmp:
        files = write_gallery(scenario, tmp)
    console.print(
        f"wrote {len(files)} files to {args.out} (contact sheet: {Path(args.out) / 'gallery.png'})"
    )
    return 0


def _cmd_run(args: argparse.Namespace, console: Console) -> int:
    import json

    from .output import atomic_output_dir, make_directory
    from .recording_options import RecordingOptions
    from .report import write_report
    from .run import run

    scenario = load_scenario(args.scenario, args.overrides)
    out = args.out or scenario.output.dir
    if args.save_dataset:
        _check_new_directory(args.save_dataset, "--save-dataset")
    rrd_target = None
    if not args.no_rrd:
        rrd_target = Path(args.rrd) if args.rrd else Path(out) / "recording.rrd"
    if args.rrd and Path(args.rrd).is_dir():
        raise UscalError(f"--rrd {args.rrd}: is a directory; give a file name (e.g. run.rrd)")
    if args.rrd:
        make_directory(Path(args.rrd).parent)  # fail now, not after the run
    # Fail early (before minutes of simulation) if the output would be refused.
    with atomic_output_dir(out, force=args.force) as tmp:
        recording = None
        if rrd_target is not None:
            # Written inside the new output directory; moved to --rrd FILE once complete.
            recording = RecordingOptions.new(tmp / "recording.rrd", args.rrd_frames)
        with progress_bars(console) as bars, reporting(bars.update):
            result = run(
                scenario,
                progress=lambda msg: bars.console.print(f"[dim]{msg}[/dim]"),
                recording=recording,
                save_dataset=args.save_dataset,
            )
        (tmp / "metrics.json").write_text(json.dumps(result.metrics, indent=2) + "\n")
        written = ["metrics.json"] + (["recording.rrd"] if args.rrd is None and recording else [])
        if result.evaluation is not None:
            (tmp / "tables.md").write_text(result.evaluation.tables_markdown, encoding="utf-8")
            (tmp / "tables.csv").write_text(result.evaluation.tables_csv, encoding="utf-8")
            written += ["tables.md", "tables.csv"]
        written += write_report(tmp, scenario, result)
    if args.rrd and recording is not None:
        target = Path(args.rrd)
        make_directory(target.parent)
        # The finished file leaves the (now final) output directory in one rename.
        os.replace(Path(out) / "recording.rrd", target)
        written.append(str(target.resolve()))
    print_run(result.metrics, console)
    if result.evaluation is not None:
        print_evaluation(result.metrics, console)
        if "reconstruction" in result.metrics:
            print_reconstruction(result.metrics, console)
    figures = [f for f in written if f.startswith("figures/")]
    files = [f for f in written if not f.startswith("figures/")]
    console.print(
        f"wrote {', '.join(str(Path(out) / f) for f in files)} and {len(figures)} figures in "
        f"{Path(out) / 'figures'} (open {Path(out) / 'report.html'})"
    )
    if args.save_dataset:
        what = "datasets in" if result.evaluation is not None else "the dataset"
        console.print(f"wrote {what} {args.save_dataset} (uscal calibrate reads them)")
    if args.spawn and rrd_target is not None:
        spawn_viewer(rrd_target, console)
    return 0


def _check_new_directory(path: str, option: str) -> None:
    p = Path(path)
    if p.exists() and (not p.is_dir() or any(p.iterdir())):
        raise UscalError(f"{option} {path}: exists and is not an empty directory")


def _cmd_acquire(args: argparse.Namespace, console: Console) -> int:
    from .acquire import acquire_dataset, console_operator, dashboard_operator
    from .hw_config import load_hw_config

    cfg = load_hw_config(args.hw_config, args.overrides)
    out = Path(args.out)
    if not args.resume and not args.dry_run:
        _check_new_directory(args.out, "--out")

    def confirm(message: str) -> bool:
        if not sys.stdin.isatty():
            raise UscalError(
                "the first motion needs a confirmation and there is no terminal to ask; "
                "pass --yes once the workspace is clear"
            )
        return console.input(f"{message} [y/N] ").strip().lower() in ("y", "yes")

    operator = None
    if args.touches == "loopback":
        operator = dashboard_operator(cfg.robot.host)
    elif args.touches == "console":
        if not sys.stdin.isatty() and not args.dry_run:
            raise UscalError(
                "--touches: hand-guided touches are confirmed at a terminal, and there is "
                "none ('--touches loopback' rehearses them on the loopback rig)"
            )
        operator = console_operator(lambda message: console.input(message + " "))
    with progress_bars(console) as bars, reporting(bars.update):
        summary = acquire_dataset(
            cfg,
            out,
            resume=args.resume,
            dry_run=args.dry_run,
            confirm=None if args.yes or args.dry_run else confirm,
            say=lambda msg: bars.console.print(f"[dim]{msg}[/dim]"),
            operator=operator,
        )
    if summary.dry_run:
        console.print(f"dry run: {summary.planned} sweeps planned and checked; nothing moved")
    else:
        console.print(
            f"acquired {summary.acquired} sweeps ({summary.skipped} from before) into {out} "
            f"in {summary.seconds:.0f} s; calibrate with `uscal calibrate {out}`"
        )
    return 0


def _cmd_calibrate(args: argparse.Namespace, console: Console) -> int:
    import json

    from .offline import calibrate_recorded, record_recorded
    from .output import atomic_output_dir, make_directory
    from .recording_options import RecordingOptions
    from .report import write_report
    from .run import recorded_run_result

    settings = load_scenario(args.settings, args.overrides)
    dataset_dir = Path(args.dataset)
    out = Path(args.out) if args.out else dataset_dir.with_name(dataset_dir.name + "-calibration")
    if args.rrd and Path(args.rrd).is_dir():
        raise UscalError(f"--rrd {args.rrd}: is a directory; give a file name (e.g. run.rrd)")
    if args.rrd and not args.no_rrd:
        make_directory(Path(args.rrd).parent)  # fail now, not after the calibration
    markers = (int(args.markers),) if args.markers else (1, 3)
    with atomic_output_dir(out, force=args.force) as tmp:
        with progress_bars(console) as bars, reporting(bars.update):
            result = calibrate_recorded(dataset_dir, settings, markers, tuple(args.dh_from))
        (tmp / "metrics.json").write_text(json.dumps(result.metrics, indent=2) + "\n")
        written = ["metrics.json"]
        if not args.no_rrd:
            recording = RecordingOptions.new(tmp / "recording.rrd", args.rrd_frames)
            record_recorded(recording, settings, result)
            if args.rrd is None:
                written.append("recording.rrd")
        written += write_report(tmp, settings, recorded_run_result(result, settings))
    if args.rrd and not args.no_rrd:
        target = Path(args.rrd)
        make_directory(target.parent)
        os.replace(out / "recording.rrd", target)
        written.append(str(target.resolve()))
    print_recorded(result.metrics, console)
    files = [f for f in written if not f.startswith("figures/")]
    console.print(f"wrote {', '.join(str(out / f) for f in files)} (open {out / 'report.html'})")
    return 0


def _cmd_sweep(args: argparse.Namespace, console: Console) -> int:
    from .sweep import load_sweep, run_sweep

    with console.status(f"validating {args.sweep_file}"):
        spec = load_sweep(args.sweep_file)
    workers = args.workers or os.cpu_count() or 1
    hours = spec.estimated_seconds() / 3600
    console.print(
        f"{spec.count() // len(spec.seeds):,} grid points × {len(spec.seeds)} seed(s) = "
        f"{spec.count():,} acquisitions; "
        + (
            f"≈ {hours / workers:.1f} h on {workers} local worker(s)"
            if not args.scheduler
            else f"≈ {hours:.1f} worker-hours on the cluster"
        )
        + " (cached points are not recomputed)"
    )
    out = Path(args.out or Path("out") / Path(args.sweep_file).stem)
    with progress_bars(console) as bars, reporting(bars.update):
        result = run_sweep(spec, out, args.scheduler, args.workers or None)
    console.print(
        f"{len(result.points)} points: {result.computed} computed, {result.cached} from "
        f"the cache, {result.failed} failed, in {result.seconds:.0f} s"
    )
    console.print(f"wrote {out / 'results.csv'} and {out / 'sweep.html'}")
    return 1 if result.failed else 0


def _cmd_budget(args: argparse.Namespace, console: Console) -> int:
    from .budget import plan_budget, run_budget

    sources = [n.strip() for n in args.sources.split(",") if n.strip()] if args.sources else None
    spec = plan_budget(args.scenario, args.overrides, sources, args.seeds)
    out = Path(args.out or Path("out") / f"{Path(args.scenario).stem}-budget")
    with progress_bars(console) as bars, reporting(bars.update):
        result = run_budget(spec, out, args.scheduler, args.workers or None)
    console.print(
        f"{len(result.runs)} runs: {result.computed} computed, {result.cached} from the "
        f"cache, {result.failed} failed, in {result.seconds:.0f} s"
    )
    console.print(f"wrote {out / 'budget.csv'}, {out / 'budget.md'} and {out / 'budget.html'}")
    return 1 if result.failed else 0


def _cmd_docs(args: argparse.Namespace, console: Console) -> int:
    text = scenarios_markdown()
    if args.output:
        Path(args.output).write_text(text, encoding="utf-8")
    else:
        sys.stdout.write(text)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``uscal`` console script; returns the exit code."""
    args = _parser().parse_args(argv)
    console = Console(quiet=args.quiet)
    if args.debug:
        # Verbose logs of this project's packages only (libraries stay at warnings).
        logging.basicConfig(
            level=logging.WARNING,
            format="%(name)s: %(message)s",
            handlers=[RichHandler(console=Console(stderr=True), show_path=False)],
        )
        for package in ("bench", "calib", "twin", "sim_us", "hw"):
            logging.getLogger(package).setLevel(logging.DEBUG)
    handlers = {
        "acquire": _cmd_acquire,
        "budget": _cmd_budget,
        "calibrate": _cmd_calibrate,
        "check": _cmd_check,
        "docs": _cmd_docs,
        "image": _cmd_image,
        "plan": _cmd_plan,
        "run": _cmd_run,
        "sweep": _cmd_sweep,
    }
    try:
        if args.command == "twin":
            if args.twin_command == "serve":
                return _cmd_twin_serve(args, console)
            return _cmd_twin_export(args, console)
        return handlers[args.command](args, console)
    except UscalError as exc:
        if args.debug:
            traceback.print_exc()
        print(f"uscal: error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print("uscal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
