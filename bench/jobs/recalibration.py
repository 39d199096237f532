"""The probe taken off and put back before the reconstruction (paper, "Volumetric
Reconstruction of Different Phantoms"): a new true ``T_ee_us``, re-calibrated from a
separate scan of the four-sphere phantom — single-marker on sphere 1 and three-marker on
spheres 1-3 — with each of the three frozen leave-one-out DH models (sets A-C). Process-
pool tasks: one :func:`run_remount_scan` per sphere (its frames to a scratch file), then
one :func:`run_recalibration` per method once its spheres are scanned."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from calib import se3
from calib.calibration.alternation import AlternationSettings, alternate
from calib.dh import DHTable
from calib.evaluation.cross_validation import TABLE_III_METHODS
from calib.kinematics import kinematic_gauge, with_kinematics
from calib.localize import localize_sphere

from ..acquire_sim import make_imager, make_twin, simulate_acquisition
from ..config.method import axial_scale, image_points, stated_radius
from ..config.scenario import Scenario, layout_sigma_mm
from ..files import frames_to_file, without_frames
from ..parallel import release_memory
from ..progress import report
from ..results import Recalibration, RemountScan
from ..sessions import REMOUNT_KEY, SESSIONS, dataset_rngs, stream
from ..truth import mount_error

__all__ = ["recalibration_scenario", "remounted", "run_recalibration", "run_remount_scan"]


def remounted(scenario: Scenario) -> Scenario:
    """The probe taken off and put back: its true mount moves by the configured amounts."""
    rc = scenario.reconstruction
    rng = stream(scenario.seed, REMOUNT_KEY)
    t = scenario.tools
    pos = np.add(t.probe_mount_position_mm, rng.normal(0.0, rc.remount_position_mm, 3))
    rot = np.add(t.probe_mount_rotation_deg, rng.normal(0.0, rc.remount_rotation_deg, 3))
    tools = replace(
        t,
        probe_mount_position_mm=tuple(float(v) for v in pos),
        probe_mount_rotation_deg=tuple(float(v) for v in rot),
    )
    return replace(scenario, tools=tools)


def recalibration_scenario(scenario: Scenario) -> Scenario:
    """The separate four-sphere scan after the remount, of the spheres Table III's
    methods use (sphere 4 is used by neither, so it is not scanned)."""
    sc = remounted(scenario)
    used = sorted({t for spheres in TABLE_III_METHODS.values() for t in spheres})
    spheres = tuple(int(t.split("_")[1]) for t in used)
    return replace(sc, protocol=replace(sc.protocol, spheres=spheres))


def run_remount_scan(scenario: Scenario, index: int, scratch: Path) -> RemountScan:
    """Scan sphere ``index`` with the remounted probe (the re-calibration's protocol), save
    its frames to ``scratch`` and localize it once under the coarse ``T_ee_us`` (a
    process-pool task: one per sphere, so the scan spreads over the workers)."""
    t0 = time.perf_counter()
    sc = recalibration_scenario(scenario)
    sc = replace(sc, protocol=replace(sc.protocol, spheres=(index,)))
    rngs = dataset_rngs(scenario, SESSIONS["recalibration"] + index)
    twin = make_twin(sc, rngs["joints"])
    imager = make_imager(sc, twin, rngs["imaging"])
    target = f"sphere_{index}"
    acq = simulate_acquisition(
        sc, twin, imager, "remount", rngs["protocol"], progress=f"remount: scan {target}"
    )
    truth, coarse = twin.truth, acq.T_ee_us_coarse
    cad_centre = twin.phantom_cad.landmarks[target]
    del imager, twin
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    sweeps = acq.dataset.of(target)
    # The first localization (under the coarse T_ee_us) is done once, on the poses the
    # controller recorded: it depends only on the flange's motion within each 20 mm
    # sweep, on which the DH models differ by a turn of the flange frame of a degree or
    # two (≈ 0.3 mm over 10 mm) — well inside the coarse T_ee_us's own error (up to
    # 10°), and absorbed by the calibration. Every model's alternation starts from it and
    # re-localizes with its own poses.
    first = localize_sphere(
        sweeps,
        None,
        stated_radius(sc),
        sc.localization,
        axial_scale=axial_scale(sc),
    )
    path = scratch / f"remount_{target}.npy"
    frames_to_file(sweeps, path)
    scan = RemountScan(
        target,
        without_frames(sweeps),
        path,
        tuple(first),
        cad_centre,
        coarse,
        truth.T_ee_us,
        truth.dh_table,
        {"simulate": t_sim, "localize": time.perf_counter() - t0},
    )
    del acq, sweeps
    release_memory()
    return scan


def run_recalibration(
    scenario: Scenario,
    method: str,
    tables: dict[str, DHTable],
    scans: list[RemountScan],
    threads: int = 1,
) -> Recalibration:
    """Calibrate with ``method`` (of :data:`TABLE_III_METHODS`) from the re-calibration scan of its
    spheres, with each DH model of ``tables`` (a process-pool task, mapping the scans'
    frames). ``threads`` > 1 localizes the spheres side by side (the localizer's kernels
    release the GIL): the three-marker task is the last of the run, mostly alone."""
    t0 = time.perf_counter()
    sc = recalibration_scenario(scenario)
    by_target = {s.target: s for s in scans}
    spheres = TABLE_III_METHODS[method]
    missing = [t for t in spheres if t not in by_target]
    assert not missing, f"re-calibration scan lacks {missing}"
    frames = {t: by_target[t].sweeps_with_frames() for t in spheres}
    truth = by_target[spheres[0]]
    cad = {t: by_target[t].cad_centre for t in spheres} if len(spheres) > 1 else None
    # The truth in each model's gauge: over the frames this calibration used.
    q_frames = np.concatenate([s.q[::10] for t in spheres for s in frames[t]])
    tool_points = se3.apply(truth.T_ee_us_true, image_points(sc, 3))
    T_ee_us, n_retained, errors = {}, {}, {}
    # Every model's alternation would reach its estimate from the first localizations;
    # each later model's starts from the previous model's final ones instead and gets
    # there (within 0.02 mm over the image, measured) in fewer re-localizations, which
    # is why one task calibrates with every model.
    start = {t: by_target[t].first for t in spheres}
    label = f"remount: {method}-marker calibrations"
    report(label, 0, len(tables))
    settings = AlternationSettings(
        sc.localization,
        axial_scale=axial_scale(sc),
        max_iterations=sc.calibration.max_alternations,
        layout_sigma_mm=layout_sigma_mm(sc),
        threads=threads,
    )
    for name, table in tables.items():
        X_equiv = (
            kinematic_gauge(table, truth.dh_true, q_frames, tool_points).G @ truth.T_ee_us_true
        )
        alt = alternate(
            {t: with_kinematics(frames[t], table) for t in spheres},
            stated_radius(sc),
            settings,
            cad_centres=cad,
            T_coarse=truth.T_ee_us_coarse,
            initial=start,
        )
        start = alt.localizations
        X = alt.result.T_ee_us
        T_ee_us[(name, method)] = X
        n_retained[(name, method)] = int(alt.result.retained.sum())
        errors[(name, method)] = mount_error(sc, X, X_equiv)
        report(label, len(errors), len(tables))
    return Recalibration(T_ee_us, n_retained, errors, {"calibrate": time.perf_counter() - t0})
