"""The ``uscal`` command line's parser: every command, its arguments and their help
(the commands themselves are in :mod:`bench.cli`)."""

from __future__ import annotations

import argparse

import numpy as np

__all__ = ["parser"]


def _add_scenario_args(p: argparse.ArgumentParser, optional: bool = False) -> None:
    p.add_argument(
        "scenario",
        nargs="?" if optional else None,
        default=None,
        help="scenario YAML file" + (" (default: the built-in paper setup)" if optional else ""),
    )
    _add_set(p, "scenario", "robot.dh_error_scale=0 (value in YAML syntax)")


def _add_set(p: argparse.ArgumentParser, what: str, example: str) -> None:
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY.PATH=VALUE",
        help=f"override a {what} key, e.g. {example}; repeatable",
    )


def _add_settings(p: argparse.ArgumentParser, which: str, example: str) -> None:
    """``--settings SCENARIO`` and its ``--set`` overrides: the method's settings of a
    command on recorded data."""
    p.add_argument(
        "--settings",
        metavar="SCENARIO",
        help=f"scenario whose {which} settings to use (default: built-in)",
    )
    _add_set(p, "settings", example)


def _add_output(p: argparse.ArgumentParser, out_help: str, required: bool = False) -> None:
    p.add_argument("--out", required=required, help=out_help)
    p.add_argument("--force", action="store_true", help="replace an existing directory")


def _add_recording(p: argparse.ArgumentParser, frames_help: str) -> None:
    group = p.add_mutually_exclusive_group()
    group.add_argument("--rrd", metavar="FILE", help="rerun recording (default: OUT/recording.rrd)")
    group.add_argument("--no-rrd", action="store_true", help="write no rerun recording")
    p.add_argument(
        "--rrd-frames", type=_non_negative_int, default=420, metavar="N", help=frames_help
    )


def _add_until(p: argparse.ArgumentParser) -> None:
    until = p.add_argument_group(
        "sequential acquisition: each next sweep the most informative, until the "
        "predicted 1 σ of T_ee_us is within the limits"
    )
    until.add_argument("--until-rotation-deg", type=_positive_mm, metavar="DEG")
    until.add_argument("--until-translation-mm", type=_positive_mm, metavar="MM")
    until.add_argument(
        "--max-sweeps", type=_positive_int, default=45, metavar="N",
        help="sweeps of a sphere at most (default 45)",
    )  # fmt: skip


def _add_requirements(p: argparse.ArgumentParser, first: str = "") -> None:
    req = p.add_argument_group(
        f"requirements: {first}exit with code 3 unless the calibration used (three-marker "
        "when it ran, else single-marker) is accepted with its 95 % bounds within them"
    )
    req.add_argument(
        "--require-image-mm",
        type=_positive_mm,
        metavar="MM",
        help="the 95 %% bound over the image at most this (calibration.require_image_mm)",
    )
    req.add_argument(
        "--require-rotation-deg",
        type=_positive_mm,
        metavar="DEG",
        help="the 95 %% rotation bound at most this (calibration.require_rotation_deg)",
    )


def _add_executor(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--scheduler", metavar="ADDRESS", help="run on this Dask scheduler (tcp://host:8786)"
    )
    p.add_argument(
        "--workers", type=_non_negative_int, default=0, help="local processes (default: cores)"
    )


def _positive_mm(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of millimetres")
    return value


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number ≥ 1")
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number ≥ 0")
    return value


def parser() -> argparse.ArgumentParser:
    """The parser of every command and its options."""
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
    _add_output(run, "output directory (default: the scenario's output.dir)")
    _add_recording(
        run,
        "B-mode frames recorded per acquisition session at most, as whole sweeps spread "
        "over it (default 420; 0 records none)",
    )
    run.add_argument(
        "--spawn", action="store_true", help="open the recording in the rerun viewer at the end"
    )
    _add_until(run)
    _add_requirements(run)
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
        "--set-tcp-zero",
        action="store_true",
        help="if the controller's active TCP offset is not zero, set it to zero (uscal's "
        "poses are the flange's); without it such a controller is refused before any motion",
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
    _add_set(acquire, "hw config", "protocol.spheres=[1]")
    _add_until(acquire)
    _add_requirements(
        acquire,
        "then calibrate the dataset (as `uscal calibrate OUT` into OUT-calibration) and ",
    )
    acquire.add_argument(
        "--markers",
        choices=["1", "3"],
        help="with a requirement: calibrate single-marker or three-marker only",
    )
    acquire.add_argument(
        "--settings",
        metavar="SCENARIO",
        help="with a requirement: the scenario whose localization and calibration settings "
        "to calibrate with (default: built-in)",
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
    _add_output(calibrate, "output directory (default: DATASET-calibration)")
    calibrate.add_argument(
        "--dh-from",
        metavar="DATASET",
        action="append",
        default=[],
        help="refine the DH model from these datasets' touches (the paper's leave-one-out); "
        "default: the dataset's own touches, when it has any; repeatable",
    )
    calibrate.add_argument(
        "--fixed-pixel-scale",
        action="store_true",
        help="N-wire datasets: hold the dataset's pixel spacing instead of fitting it "
        "with the calibration (PLUS fits it; a robot rig with a trusted spacing may not)",
    )
    _add_settings(calibrate, "localization and calibration", "localization.min_score=0.2")
    _add_requirements(calibrate)
    _add_recording(
        calibrate, "B-mode frames recorded at most, as whole sweeps spread over the dataset"
    )

    sweep = sub.add_parser(
        "sweep",
        help="robustness sweep: a grid of scenario overrides × seeds (or points drawn at "
        "random), localized (and calibrated) with each localizer; local processes or a "
        "Dask cluster",
    )
    sweep.add_argument(
        "sweep_file",
        help="sweep YAML (base, grid and seeds or draws, stages, methods)",
    )
    sweep.add_argument(
        "--out", help="output directory (default: out/<sweep file name>); rerunning resumes"
    )
    _add_executor(sweep)

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
    _add_executor(budget)

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
    plan.add_argument(
        "--optimize",
        action="store_true",
        help="choose the sweeps that determine T_ee_us best (reachable, collision-free, "
        "the sphere in the image) and compare them with the paper's plan",
    )
    plan.add_argument(
        "--sweeps",
        type=_positive_int,
        default=15,
        metavar="N",
        help="with --optimize: sweeps in the plan, in all (default 15)",
    )
    plan.add_argument(
        "--criterion",
        choices=["D", "A", "E"],
        default="D",
        help="with --optimize: D (log det of the information), A (mean squared image "
        "error) or E (its worst direction); default D",
    )
    plan.add_argument(
        "--markers",
        type=int,
        choices=[1, 3],
        help="with --optimize: plan the first sphere alone (1) or the first three jointly "
        "(3); default 3 when the protocol scans three or more spheres",
    )
    plan.add_argument(
        "--out", metavar="PLAN", help="with --optimize: write the plan file (protocol.plan)"
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
    serve.add_argument(
        "--tcp-offset",
        type=float,
        nargs=6,
        default=[0.0] * 6,
        metavar=("X", "Y", "Z", "RX", "RY", "RZ"),
        help="the installation's active TCP offset (mm, and a rotation vector in degrees; "
        "default zero): reported poses and linear moves are then of the TCP",
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

    imports = sub.add_parser("import", help="turn other tools' recordings into a uscal dataset")
    import_sub = imports.add_subparsers(dest="import_command", required=True)
    plus = import_sub.add_parser(
        "plus",
        help="PLUS sequence metafiles (.mha, or .mhd with its .raw/.zraw, as PLUS and 3D "
        "Slicer write them): one linear "
        "sweep of a sphere per file (or per --frames-per-sweep frames), the probe's pose "
        "from a per-frame transform (a tracked probe: the tracker plays the robot base)",
    )
    plus.add_argument(
        "files", nargs="+", metavar="FILE.mha", help="PLUS sequence files (.mha or .mhd)"
    )
    plus.add_argument(
        "--config",
        metavar="PLUS_CONFIG.xml",
        help="an N-wire phantom: the PLUS device set configuration with its "
        "PhantomDefinition and Phantom→Reference (the frames are then freehand frames of "
        "the phantom; `uscal calibrate` finds the wires and fits ImageToProbe)",
    )
    plus.add_argument(
        "--pose-transform",
        metavar="NAME",
        help="per-frame transform giving the probe's pose (default with --config: "
        "ProbeToReference, as PLUS's calibration), e.g. ProbeToTrackerTransform "
        "(T_tracker_probe; the calibration is then T_probe_image), or one composed from "
        "those the file records, e.g. ProbeToReference = ReferenceToTracker⁻¹ · "
        "ProbeToTracker (as PLUS's transform repository composes it)",
    )
    plus.add_argument(
        "--target", default="sphere_1", help="what the sweeps image (default sphere_1)"
    )
    plus.add_argument("--out", required=True, help="new dataset directory")
    plus.add_argument(
        "--radius-mm", type=_positive_mm, help="spheres: the sphere's CAD radius (mm)"
    )
    speed = plus.add_mutually_exclusive_group()
    speed.add_argument(
        "--temperature-c",
        type=float,
        metavar="C",
        help="the water's temperature: the axial spacing is corrected from the scanner's "
        "assumed speed of sound to water's",
    )
    speed.add_argument(
        "--no-speed-correction",
        action="store_true",
        help="the medium's speed of sound is the scanner's: no axial correction",
    )
    plus.add_argument(
        "--assumed-speed-m-s", type=_positive_mm, default=1540.0, metavar="C",
        help="the scanner's assumed speed of sound (default 1540)",
    )  # fmt: skip
    plus.add_argument(
        "--spacing-mm",
        nargs=2,
        type=_positive_mm,
        metavar=("SX", "SY"),
        help="pixel spacing (columns, rows); needed when the files hold PLUS's default 1 1",
    )
    plus.add_argument(
        "--frames-per-sweep", type=_positive_int, metavar="N",
        help="split each file into sweeps of N frames (default: one sweep per file)",
    )  # fmt: skip
    plus.add_argument(
        "--max-turn-deg", type=_positive_mm, default=1.0, metavar="DEG",
        help="refuse a sweep whose probe turns more than this (default 1°)",
    )  # fmt: skip

    validate = sub.add_parser(
        "validate",
        help="check a calibration on another dataset with uscal's detection (N-wire: "
        "PLUS's 3-D reprojection error; spheres: the centres' scatter and layout)",
    )
    validate.add_argument("dataset", help="dataset directory (dataset.yaml + sweeps/*.mha)")
    validate.add_argument(
        "--calibration",
        required=True,
        metavar="FILE",
        help="uscal's calibration.yaml, a PLUS calibration result (.xml) or a PLUS device "
        "set configuration holding Image→Probe",
    )
    _add_settings(validate, "localization (spheres)", "localization.method=paper")
    validate.add_argument("--json", metavar="FILE", help="also write the figures to FILE")

    image = sub.add_parser(
        "image", help="render a gallery of B-mode frames at the paper's representative poses"
    )
    _add_scenario_args(image)
    _add_output(image, "output directory (created atomically)", required=True)

    docs = sub.add_parser("docs", help="generate documentation")
    docs.add_argument("topic", choices=["scenarios"])
    docs.add_argument("--output", "-o", help="write to this file instead of stdout")
    return parser
