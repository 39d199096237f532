"""What the commands around a run print: ``uscal check`` (the scenario's summary),
``uscal plan [--optimize]`` (the plan's observability, the chosen plan beside the
paper's) and ``uscal twin export`` (the true landmarks and mount)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from rich.console import Console
from rich.table import Table

from calib import se3

from ..config.scenario import Scenario

__all__ = ["print_plan", "print_plan_comparison", "print_scenario_summary", "print_truth"]


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
        *(
            [("derived", "; ".join(f"{k} = {v:g} (from {src})" for k, v, src in s.derived))]
            if s.derived
            else []
        ),
    ]
    for name, text in rows:
        table.add_row(name, text)
    console.print(table)
    console.print(
        "[green]ok[/green]: scenario is valid; every target is reachable at all "
        "nine orientations and the probe clears phantom and tank."
    )


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
    per_target = ", ".join(f"{k}: {len(v)}" for k, v in o.poses.items())
    left = ", ".join(f"{n} {k}" for k, n in (o.left_out or {}).items())
    console.print(
        f"chose {o.n_sweeps} sweeps ({per_target}) from {o.candidates} candidates ({left}), "
        f"criterion {c.criterion}, for {c.calibration}"
    )
    spares = ", ".join(f"{k}: {len(v)}" for k, v in (o.spares or {}).items()) or "none"
    console.print(
        f"every frame and transit {scenario.planning.clearance_mm:g} mm clear of the tank and "
        f"phantom here and in {o.sessions} other sessions (their taught pose and coarse "
        f"mount); spares {spares}"
    )
    table = Table(title=f"predicted for {c.noise}")
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
