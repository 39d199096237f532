"""The ``uscal`` command line: the parser, and each command as the job it runs
(:mod:`bench.jobs`), what it writes (:mod:`bench.outputs`) and what it prints
(:mod:`bench.console`).

Every :class:`~calib.errors.UscalError` becomes one line on stderr and exit code 2;
``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from rich.console import Console

from calib.errors import UscalError

from .cli_parser import parser

if TYPE_CHECKING:
    from .sequential import StopRule
    from .summaries.calibration import Calibrations

# Each command imports what it runs when it runs: the simulator, the twin, the recorder
# and their libraries take seconds to import, which ``uscal --help``, ``uscal check`` or a
# mistyped option should not wait for.

__all__ = ["main"]

EXIT_USER_ERROR = 2
EXIT_NOT_ACCEPTED = 3  # a requirement was given and the calibration is not accepted within it


def _with_requirements(args: argparse.Namespace) -> list[str]:
    """The scenario overrides with ``--require-image-mm`` / ``--require-rotation-deg``
    added as the keys they stand for."""
    extra = []
    if args.require_image_mm is not None:
        extra.append(f"calibration.require_image_mm={args.require_image_mm}")
    if args.require_rotation_deg is not None:
        extra.append(f"calibration.require_rotation_deg={args.require_rotation_deg}")
    return [*args.overrides, *extra]


def _check_rrd_frames(args: argparse.Namespace, frames_per_sweep: int) -> None:
    """``--rrd-frames`` that records at least one whole sweep, or none (0): a smaller
    number recorded no B-mode frame and said nothing."""
    n = args.rrd_frames
    if not args.no_rrd and 0 < n < frames_per_sweep:
        raise UscalError(
            f"--rrd-frames {n}: fewer than one sweep's {frames_per_sweep} frames (the "
            f"recording logs whole sweeps); give 0 for none, or {frames_per_sweep} or more"
        )


def _gate(scenario, calibrations: Calibrations, console: Console) -> int:
    """Exit code 3 when the scenario states requirements and the calibration to use is
    not accepted within them (the verdict says why); 0 otherwise."""
    from .config.method import requirements

    if not requirements(scenario).any:
        return 0
    chosen = calibrations.chosen if calibrations.single or calibrations.three else None
    status = "not judged" if chosen is None or chosen.verdict is None else chosen.verdict.status
    what = "no calibration" if chosen is None else f"the {chosen.method}-marker calibration"
    return _gate_status(scenario, what, status, console)


def _gate_status(scenario, what: str, status: str, console: Console) -> int:
    """:func:`_gate` of one calibration's verdict status, named ``what``."""
    from .config.method import requirements

    if not requirements(scenario).any or status == "accepted":
        return 0
    console.print(
        f"{what} is {status}, not accepted within the requirements: exit code {EXIT_NOT_ACCEPTED}",
        highlight=False,
    )
    return EXIT_NOT_ACCEPTED


def _cmd_check(args: argparse.Namespace, console: Console) -> int:
    from .config.scenario import load_scenario
    from .console import print_scenario_summary

    print_scenario_summary(load_scenario(args.scenario, args.overrides), console)
    return 0


def _cmd_plan(args: argparse.Namespace, console: Console) -> int:
    from .config.plan_file import write_plan
    from .config.scenario import load_scenario
    from .console import print_plan, print_plan_comparison
    from .jobs.plan import plan_report
    from .jobs.plan_optimize import optimize_plan, plan_about

    scenario = load_scenario(args.scenario, args.overrides)
    if not args.optimize:
        print_plan(scenario, plan_report(scenario, args.noise_mm), args.noise_mm, console)
        return 0
    with console.status("choosing the sweeps"):
        comparison = optimize_plan(scenario, args.sweeps, args.criterion, args.markers)
    print_plan_comparison(comparison, scenario, console)
    if args.out:
        write_plan(
            args.out,
            comparison.optimized.poses,
            plan_about(comparison, scenario),
            comparison.optimized.spares,
        )
        console.print(f"wrote {args.out}; use it with --set protocol.plan={args.out}")
    return 0


def _cmd_twin_serve(args: argparse.Namespace, console: Console) -> int:
    import numpy as np

    from twin.ur_controller import ControllerFaults

    from .config.scenario import load_scenario
    from .jobs.twin_serve import serve_twin

    scenario = load_scenario(args.scenario, args.overrides)
    faults = ControllerFaults(args.fault_drop_at_move, args.fault_protective_stop_at_move)
    tcp = [*(v * 1e-3 for v in args.tcp_offset[:3]), *np.radians(args.tcp_offset[3:])]
    controller = serve_twin(scenario, args.host, args.frames, args.hw_config, faults, tcp)
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
    from .config.scenario import load_scenario
    from .console import print_truth
    from .jobs.twin_serve import export_twin, landmarks_mm

    scenario = load_scenario(args.scenario, args.overrides)
    files, truth = export_twin(scenario, args.outdir, args.force)
    print_truth(landmarks_mm(truth), truth.T_ee_us, console)
    scene = Path(args.outdir) / "scene.xml"
    console.print(f"wrote {len(files)} files to {args.outdir} (open {scene} in MuJoCo's viewer)")
    return 0


def _cmd_image(args: argparse.Namespace, console: Console) -> int:
    from .config.scenario import load_scenario
    from .files import atomic_output_dir
    from .jobs.gallery import write_gallery

    scenario = load_scenario(args.scenario, args.overrides)
    with atomic_output_dir(args.out, force=args.force) as tmp:
        files = write_gallery(scenario, tmp)
    sheet = Path(args.out) / "gallery.png"
    console.print(f"wrote {len(files)} files to {args.out} (contact sheet: {sheet})")
    return 0


def _cmd_run(args: argparse.Namespace, console: Console) -> int:
    from .config.geometry import TARGET_PHANTOMS
    from .config.scenario import load_scenario
    from .console import (
        print_evaluation,
        print_reconstruction,
        print_run,
        print_written,
        progress_bars,
        spawn_viewer,
    )
    from .files import check_new_directory
    from .jobs.single import run
    from .outputs.run_files import run_directory
    from .progress import reporting
    from .summaries import RunSummary

    scenario = load_scenario(args.scenario, _with_requirements(args))
    _check_rrd_frames(args, scenario.protocol.frames_per_sweep)
    out = Path(args.out or scenario.output.dir)
    if args.save_dataset:
        check_new_directory(args.save_dataset, "--save-dataset")
    if scenario.phantom.kind in TARGET_PHANTOMS:
        return _run_target(args, scenario, out, console)
    with run_directory(out, args.force, args.rrd, args.no_rrd, args.rrd_frames) as directory:
        with progress_bars(console) as bars, reporting(bars.update):
            say = lambda msg: bars.console.print(f"[dim]{msg}[/dim]")  # noqa: E731
            result = run(scenario, say, directory.recording, args.save_dataset, _until(args))
        directory.write(scenario, result)
    summary = RunSummary.from_metrics(result.metrics)
    print_run(summary, console)
    if summary.evaluation is not None:
        print_evaluation(summary.evaluation, console)
    if summary.reconstruction is not None:
        print_reconstruction(summary.reconstruction, console)
    print_written(out, directory.written, console)
    if args.save_dataset:
        what = "datasets in" if result.evaluation is not None else "the dataset"
        console.print(f"wrote {what} {args.save_dataset} (uscal calibrate reads them)")
    if args.spawn and directory.recording_path is not None:
        spawn_viewer(directory.recording_path, console)
    return _gate(scenario, summary.calibrations, console)


def _run_target(args: argparse.Namespace, scenario, out: Path, console: Console) -> int:
    """``uscal run`` of a wire, N-wire or cone-tip scenario: the acquisition, the
    calibration from its target and its errors against the twin's truth
    (:func:`bench.jobs.targets.run_target`), with its rerun recording."""
    from .console import print_target, print_written, progress_bars, spawn_viewer
    from .jobs.single import run
    from .outputs.run_files import run_directory
    from .outputs.target_files import write_target
    from .progress import reporting

    if _until(args) is not None:
        raise UscalError(
            "--until-rotation-deg / --until-translation-mm: the sequential acquisition "
            f"plans sphere sweeps; a {scenario.phantom.kind} scenario runs its protocol"
        )
    with run_directory(out, args.force, args.rrd, args.no_rrd, args.rrd_frames) as directory:
        with progress_bars(console) as bars, reporting(bars.update):
            result = run(scenario, None, directory.recording, args.save_dataset)
        written = write_target(directory.tmp, result.nwire)
        if directory.recording is not None and directory.rrd is None:
            written.append("recording.rrd")
    print_target(result.nwire, console)
    cal = result.metrics["calibration"][result.metrics["dataset"]["target"]]
    e, covers = cal["true_error"], cal["bound_covers"]
    outside = [k for k, v in covers.items() if not v]
    console.print(
        f"against the twin's truth: {e['rotation_deg']:.3f}°, {e['translation_mm']:.3f} mm, "
        f"{e['image_mm']:.3f} mm over the image; inside the 95 % bounds: "
        + ", ".join(k for k, v in covers.items() if v)
        + ("" if all(covers.values()) else "; OUTSIDE: " + ", ".join(outside)),
        highlight=False,
    )
    print_written(out, written, console)
    if args.save_dataset:
        console.print(f"wrote the dataset {args.save_dataset} (uscal calibrate reads it)")
    if args.spawn and directory.recording_path is not None:
        spawn_viewer(directory.recording_path, console)
    what = {"nwire": "the N-wire", "wire": "the single-wire", "cone_tip": "the cone-tip"}
    label = what[result.metrics["dataset"]["target"]] + " calibration"
    return _gate_status(scenario, label, result.nwire.verdict.status, console)


def _until(args: argparse.Namespace) -> StopRule | None:
    """The sequential acquisition's stop rule, when a limit is given."""
    from .sequential import StopRule

    if args.until_rotation_deg is None and args.until_translation_mm is None:
        return None
    inf = float("inf")
    return StopRule(
        args.until_rotation_deg or inf, args.until_translation_mm or inf, args.max_sweeps
    )


def _confirm_at_terminal(console: Console):
    def confirm(message: str) -> bool:
        if not sys.stdin.isatty():
            raise UscalError(
                "the first motion needs a confirmation and there is no terminal to ask; "
                "pass --yes once the workspace is clear"
            )
        return console.input(f"{message} [y/N] ").strip().lower() in ("y", "yes")

    return confirm


def _operator(args: argparse.Namespace, host: str, console: Console):
    """Who makes the stylus touches: the loopback rig's emulated operator, or a person
    at this terminal."""
    from .acquire_rig import console_operator, dashboard_operator

    if args.touches == "loopback":
        return dashboard_operator(host)
    if args.touches == "console":
        if not sys.stdin.isatty() and not args.dry_run:
            raise UscalError(
                "--touches: hand-guided touches are confirmed at a terminal, and there is "
                "none ('--touches loopback' rehearses them on the loopback rig)"
            )
        return console_operator(lambda message: console.input(message + " "))
    return None


def _cmd_acquire(args: argparse.Namespace, console: Console) -> int:
    from .acquire_rig import acquire_dataset
    from .config.hw import load_hw_config
    from .config.scenario import load_scenario
    from .console import progress_bars
    from .files import check_new_directory
    from .progress import reporting

    cfg = load_hw_config(args.hw_config, args.overrides)
    if not args.resume and not args.dry_run:
        check_new_directory(args.out, "--out")
    required = args.require_image_mm is not None or args.require_rotation_deg is not None
    if required and not args.dry_run:
        # What the calibration after the acquisition needs, checked before anything moves.
        as_calibrate = argparse.Namespace(**{**vars(args), "overrides": []})
        load_scenario(args.settings, _with_requirements(as_calibrate))
        check_new_directory(f"{Path(args.out)}-calibration", "the calibration's directory")
    operator = _operator(args, cfg.robot.host, console)
    confirm = None if args.yes or args.dry_run else _confirm_at_terminal(console)
    with progress_bars(console) as bars, reporting(bars.update):
        say = lambda msg: bars.console.print(f"[dim]{msg}[/dim]")  # noqa: E731
        summary = acquire_dataset(
            cfg, Path(args.out), args.resume, args.dry_run, confirm, say, operator, _until(args),
            args.set_tcp_zero,
        )  # fmt: skip
    if summary.dry_run:
        console.print(f"dry run: {summary.planned} sweeps planned and checked; nothing moved")
        return 0
    console.print(
        f"acquired {summary.acquired} sweeps ({summary.skipped} from before) into "
        f"{args.out} in {summary.seconds:.0f} s"
        + ("; calibrating it" if required else f"; calibrate with `uscal calibrate {args.out}`")
    )
    if not required:
        return 0
    # A lab script gates on the acquisition itself: calibrate it as `uscal calibrate`
    # would (no recording), and exit 3 unless accepted within the requirements.
    calibrate = argparse.Namespace(
        dataset=str(Path(args.out)),
        out=None,
        markers=args.markers,
        dh_from=[],
        settings=args.settings,
        overrides=[],
        require_image_mm=args.require_image_mm,
        require_rotation_deg=args.require_rotation_deg,
        force=False,
        rrd=None,
        no_rrd=True,
        rrd_frames=0,
    )
    return _cmd_calibrate(calibrate, console)


def _cmd_calibrate(args: argparse.Namespace, console: Console) -> int:
    from calib.files.dataset import dataset_kind

    from .config.geometry import WIRED
    from .config.scenario import load_scenario
    from .console import print_recorded, print_written, progress_bars
    from .jobs.recorded import calibrate_recorded, record_recorded, recorded_run_result
    from .outputs.run_files import run_directory
    from .progress import reporting
    from .summaries import RecordedSummary

    settings = load_scenario(args.settings, _with_requirements(args))
    dataset = Path(args.dataset)
    out = Path(args.out) if args.out else dataset.with_name(dataset.name + "-calibration")
    if dataset_kind(dataset) in (*WIRED, "cone_tip"):
        return _calibrate_target(args, settings, dataset, out, console)
    markers = (int(args.markers),) if args.markers else (1, 3)
    with run_directory(out, args.force, args.rrd, args.no_rrd, args.rrd_frames) as directory:
        with progress_bars(console) as bars, reporting(bars.update):
            result = calibrate_recorded(dataset, settings, markers, tuple(args.dh_from))
        logged = None
        if directory.recording is not None:
            logged = record_recorded(directory.recording, settings, result)
        directory.write(settings, recorded_run_result(result, settings))
    recorded = RecordedSummary.from_metrics(result.metrics)
    print_recorded(recorded, console)
    print_written(out, directory.written, console)
    per_sweep = max((s.n_frames for s in result.dataset.sweeps), default=0)
    if logged == 0 and 0 < args.rrd_frames < per_sweep:
        console.print(
            f"[yellow]the recording holds no B-mode frame: --rrd-frames {args.rrd_frames} "
            f"is less than one of the dataset's sweeps ({per_sweep} frames)[/yellow]"
        )
    return _gate(settings, recorded.calibrations, console)


def _calibrate_target(args, settings, dataset: Path, out: Path, console: Console) -> int:
    """``uscal calibrate`` of an N-wire or single-wire dataset (:mod:`bench.jobs.targets`)."""
    from calib.files.dataset import read_dataset

    from .config.method import requirements
    from .console import print_target, print_written
    from .files import atomic_output_dir
    from .jobs.targets import (
        calibrate_cone_dataset,
        calibrate_nwire_dataset,
        calibrate_wire_dataset,
        echo_depth_bias_m,
        mount_error,
    )
    from .outputs.target_files import write_target

    data, info = read_dataset(dataset)
    calibrate = (
        calibrate_wire_dataset
        if info.wire is not None
        else calibrate_cone_dataset
        if info.cone_tip is not None
        else calibrate_nwire_dataset
    )
    with atomic_output_dir(out, force=args.force) as tmp:
        with console.status(f"finding the wires in {dataset}"):
            result = calibrate(
                data,
                info,
                dataset,
                requirements(settings),
                # A cone's tips alone barely move in the image: its scale is held.
                estimate_scale=not args.fixed_pixel_scale and info.cone_tip is None,
                wire_tolerance_m=settings.phantom.tolerance_position_mm * 1e-3,
                axial_bias_m=echo_depth_bias_m(settings),
                **mount_error(settings),
            )
        written = write_target(tmp, result)
    print_target(result, console)
    print_written(out, written, console)
    what = {"nwire": "the N-wire", "wire": "the single-wire", "cone_tip": "the cone-tip"}
    label = what[result.metrics["dataset"]["target"]] + " calibration"
    return _gate_status(settings, label, result.verdict.status, console)


def _cmd_validate(args: argparse.Namespace, console: Console) -> int:
    from .config.scenario import load_scenario
    from .files import write_text_atomic
    from .jobs.validate import read_calibration, validate_dataset

    settings = load_scenario(args.settings, args.overrides)
    given = read_calibration(args.calibration)
    with console.status(f"validating on {args.dataset}"):
        result = validate_dataset(args.dataset, given, settings)
    if args.json:
        write_text_atomic(Path(args.json), json.dumps(result.metrics, indent=2) + "\n")
    for line in result.lines:
        console.print(line, highlight=False, soft_wrap=True)
    return 0


def _cmd_import_plus(args: argparse.Namespace, console: Console) -> int:
    from calib.files.plus_config import read_plus_config
    from calib.files.plus_import import import_plus

    from .console import print_import

    config = read_plus_config(args.config) if args.config else None
    if config is None and args.temperature_c is None and not args.no_speed_correction:
        raise UscalError(
            "import plus: give the water's --temperature-c C, or --no-speed-correction when "
            "the medium's speed of sound is the scanner's"
        )
    with console.status(f"importing {len(args.files)} PLUS file(s)"):
        summary = import_plus(
            args.files,
            config=config,
            pose_transform=args.pose_transform,
            target=args.target,
            out=args.out,
            radius_mm=args.radius_mm,
            temperature_c=None if args.no_speed_correction else args.temperature_c,
            spacing_mm=tuple(args.spacing_mm) if args.spacing_mm else None,
            frames_per_sweep=args.frames_per_sweep,
            max_turn_deg=args.max_turn_deg,
            assumed_speed_m_s=args.assumed_speed_m_s,
        )
    print_import(summary, console)
    return 0


def _cmd_sweep(args: argparse.Namespace, console: Console) -> int:
    from .console import print_cached_run, print_workload, progress_bars
    from .jobs.sweep import load_sweep, run_sweep
    from .jobs.targets import run_target
    from .outputs.sweep_report import write_sweep
    from .progress import reporting

    with console.status(f"validating {args.sweep_file}"):
        spec = load_sweep(args.sweep_file)
    workers = args.workers or os.cpu_count() or 1
    hours = spec.estimated_seconds() / 3600
    print_workload(
        spec.describe(),
        spec.acquisitions(),
        hours,
        workers,
        bool(args.scheduler),
        console,
    )
    out = Path(args.out or Path("out") / Path(args.sweep_file).stem)
    with progress_bars(console) as bars, reporting(bars.update):
        result = run_sweep(spec, out, args.scheduler, args.workers or None, run_target)
    files = write_sweep(out, result)
    print_cached_run("points", len(result.points), result, files, console)
    return 1 if result.failed else 0


def _cmd_budget(args: argparse.Namespace, console: Console) -> int:
    from .console import print_cached_run, progress_bars
    from .jobs.budget import plan_budget, run_budget
    from .jobs.single import run
    from .outputs.budget_report import declared_mount_error, write_budget
    from .progress import reporting

    sources = [n.strip() for n in args.sources.split(",") if n.strip()] if args.sources else None
    spec = plan_budget(args.scenario, args.overrides, sources, args.seeds)
    out = Path(args.out or Path("out") / f"{Path(args.scenario).stem}-budget")
    with progress_bars(console) as bars, reporting(bars.update):
        result = run_budget(spec, out, run, args.scheduler, args.workers or None)
    files = write_budget(out, result)
    print_cached_run("runs", len(result.runs), result, files, console)
    declare = declared_mount_error(result.runs)
    if declare is not None:
        console.print(
            f"declare calibration.mount_error_mm: {declare[0]:.2f}, mount_error_deg: "
            f"{declare[1]:.2f} (the mount error this rig's sources add and no view shows, "
            "1 σ per axis; budget.md says how it is measured)"
        )
    return 1 if result.failed else 0


def _cmd_docs(args: argparse.Namespace, console: Console) -> int:
    from .config.docs import scenarios_markdown

    text = scenarios_markdown()
    if args.output:
        Path(args.output).write_text(text, encoding="utf-8")
    else:
        sys.stdout.write(text)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``uscal`` console script; returns the exit code."""
    args = parser().parse_args(argv)
    console = Console(quiet=args.quiet)
    if args.debug:
        from rich.logging import RichHandler

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
        "validate": _cmd_validate,
    }
    try:
        if args.command == "import":
            return _cmd_import_plus(args, console)
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
