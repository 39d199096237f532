"""Rerun recordings of a run: where the robot went, what each frame showed, what the
localizer found, how the calibration converged, where the reconstruction is wrong.

The only module that imports rerun. One recording per run; each acquisition session
(``run`` for a single acquisition, the datasets ``A``, ``B``… of the paper's experiment)
is a subtree, in metres and in the robot base frame::

    /<session>/world/scene/<part>          phantom and tank meshes (static)
    /<session>/world/robot/<geom>          arm and tool at the reported joint angles
    /<session>/world/image/frame           the B-mode frame, a textured quad at its true pose
                                           (recorded data: at the estimated pose)
    /<session>/world/image/estimated       outline of the image under the estimated T_ee_us
    /<session>/world/touches               stylus tip at each touch (controller's model)
    /<session>/world/centres/<method>      localized sphere centres
    /<session>/bmode/image                 the current frame
    /<session>/bmode/section/{detected,true}   sphere section: red = found, green = truth
                                           (no true sections in recorded data)
    /<session>/localization/<sphere>/{profile,crossings}   radial brightness profile
    /<session>/calibration/<method>/{loss_mm2,change_mm,change_deg}   per iteration
    /<session>/calibration/<method>/residuals_mm   per-sweep residuals (bar chart)
    /reconstruction/<phantom>/<method>/<set>   registered points coloured by error
    /reconstruction/<phantom>/cad          the CAD surface they were registered to

Timelines: ``frame`` (acquisition step) and ``iteration`` (localize/calibrate
alternation). Frames are many (the paper's run acquires 11 340), so at most
``max_frames`` per session are logged, whole sweeps spread evenly over the acquisition;
everything else is logged in full.

Worker processes write their own part files (:class:`Recorder` on a part path); the
main process merges them into the run's file (:func:`merge_parts`) and adds the
blueprint, so the viewer opens on the 3D scene, the current frame and the plots.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import mujoco
import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import trimesh
from numpy.typing import NDArray
from rerun.chunk import RrdReader

from calib import se3
from calib.calibrate import AlternationResult
from calib.image import pixel_to_us, sphere_section, us_to_pixel
from calib.localization import LocalizerConfig, SweepLocalization, frame_offsets
from calib.localize import sphere_profile
from calib.records import Sweep

from .recording_options import RecordingOptions, sweeps_to_log

__all__ = [
    "Recorder",
    "RecordingOptions",
    "blueprint",
    "log_acquisition",
    "log_sweeps",
    "merge_parts",
    "sweeps_to_log",
]

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

_RED, _GREEN = (230, 40, 40), (40, 200, 80)
_MATERIAL_COLOURS = {
    "pla": (200, 200, 190),
    "acrylic": (150, 190, 220, 90),
    "steel": (160, 160, 170),
}
_ROBOT_COLOUR = (90, 120, 170)
_TOOL_COLOUR = (200, 140, 60)


class Recorder:
    """A rerun recording stream writing to ``options.path``."""

    def __init__(self, options: RecordingOptions) -> None:
        self.options = options
        self.stream = rr.RecordingStream("uscal", recording_id=options.recording_id)
        options.path.parent.mkdir(parents=True, exist_ok=True)
        self.stream.save(options.path)
        self._frame = 0

    def close(self) -> None:
        """Flush everything to the file."""
        self.stream.flush()
        self.stream.disconnect()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ scene

    def scene(self, session: str, parts: Sequence) -> None:
        """Static meshes in the base frame, ``world/scene/<name>``: the acoustic scene's
        parts (``name``, ``material``, ``mesh`` each; phantom and tank)."""
        s = self.stream
        s.log(f"/{session}/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        for part in parts:
            mesh = part.mesh
            colour = _MATERIAL_COLOURS.get(part.material, (190, 190, 190))
            s.log(
                f"/{session}/world/scene/{part.name}",
                rr.Mesh3D(
                    vertex_positions=np.asarray(mesh.vertices, dtype=np.float32),
                    triangle_indices=np.asarray(mesh.faces, dtype=np.uint32),
                    vertex_normals=np.asarray(mesh.vertex_normals, dtype=np.float32),
                    albedo_factor=colour,
                ),
                static=True,
            )

    def robot_shapes(self, session: str, model: mujoco.MjModel) -> list[int]:
        """Log the arm's and tool's geoms (capsules, cylinders, boxes) in their own frames
        (static); returns their ids, whose poses :meth:`robot_pose` then logs."""
        ids = []
        for g in range(model.ngeom):
            body = model.body(model.geom_bodyid[g]).name
            if not (body.startswith("link") or body == "tool"):
                continue
            kind, size = model.geom_type[g], model.geom_size[g]
            colour = _TOOL_COLOUR if body == "tool" else _ROBOT_COLOUR
            path = f"/{session}/world/robot/{model.geom(g).name}"
            if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
                shape = rr.Capsules3D(
                    lengths=[2 * size[1]],
                    radii=[size[0]],
                    translations=[[0.0, 0.0, -size[1]]],
                    colors=[colour],
                )
            elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
                shape = rr.Cylinders3D(lengths=[2 * size[1]], radii=[size[0]], colors=[colour])
            elif kind == mujoco.mjtGeom.mjGEOM_BOX:
                shape = rr.Boxes3D(half_sizes=[size[:3]], colors=[colour], fill_mode="solid")
            else:
                continue
            self.stream.log(path, shape, static=True)
            ids.append(g)
        return ids

    def robot_pose(
        self, session: str, model: mujoco.MjModel, data: mujoco.MjData, q: Array, ids: list[int]
    ) -> None:
        """Poses of the robot's geoms at joint angles ``q`` (at the current time)."""
        data.qpos[:6] = q
        mujoco.mj_kinematics(model, data)
        for g in ids:
            self.stream.log(
                f"/{session}/world/robot/{model.geom(g).name}",
                rr.Transform3D(
                    translation=data.geom_xpos[g], mat3x3=data.geom_xmat[g].reshape(3, 3)
                ),
            )

    # ------------------------------------------------------------------ acquisition

    def next_frame(self) -> int:
        """Advance the ``frame`` timeline (one acquisition step) and return it."""
        self.stream.reset_time()
        self.stream.set_time("frame", sequence=self._frame)
        self._frame += 1
        return self._frame - 1

    def image_quad(self, session: str, image: NDArray[np.uint8], spacing) -> None:
        """The frame as a textured quad in the ``us`` frame of ``world/image/frame``."""
        H, W = image.shape
        corners = pixel_to_us(
            np.array([0, 0, H - 1, H - 1]), np.array([0, W - 1, W - 1, 0]), W, spacing
        )
        small = image[::2, ::2]
        self.stream.log(
            f"/{session}/world/image/frame",
            rr.Mesh3D(
                vertex_positions=corners.astype(np.float32),
                triangle_indices=[[0, 1, 2], [0, 2, 3]],
                vertex_texcoords=[[0, 0], [1, 0], [1, 1], [0, 1]],
                albedo_texture=np.repeat(small[:, :, None], 3, axis=2),
            ),
        )

    def frame(
        self,
        session: str,
        image: NDArray[np.uint8],
        spacing: tuple[float, float],
        T_base_us_true: Array | None,
        T_base_us_estimated: Array | None,
        textured: bool,
    ) -> None:
        """One B-mode frame: 2D, and in 3D at its true pose (the textured quad when
        ``textured``, else the previous texture moves along) and the estimated outline.
        Recorded data has no true pose: the quad then sits at the estimated one."""
        s = self.stream
        s.log(
            f"/{session}/bmode/image",
            rr.Image(image, color_model="L").compress(jpeg_quality=self.options.jpeg_quality),
        )
        H, W = image.shape
        if textured:
            self.image_quad(session, image, spacing)
        T_quad = T_base_us_true if T_base_us_true is not None else T_base_us_estimated
        if T_quad is not None:
            s.log(
                f"/{session}/world/image/frame",
                rr.Transform3D(translation=T_quad[:3, 3], mat3x3=T_quad[:3, :3]),
            )
        if T_base_us_estimated is not None:
            corners = pixel_to_us(
                np.array([0, 0, H - 1, H - 1, 0]), np.array([0, W - 1, W - 1, 0, 0]), W, spacing
            )
            s.log(
                f"/{session}/world/image/estimated",
                rr.LineStrips3D([se3.apply(T_base_us_estimated, corners)], colors=[_RED]),
            )

    def sections(
        self,
        session: str,
        width: int,
        spacing: tuple[float, float],
        detected: tuple[Array, float] | None,
        true: tuple[Array, float] | None,
        with_truth: bool = True,
    ) -> None:
        """Sphere sections in the current frame: (centre in the frame's ``us`` coordinates,
        radius), metres; a circle where the sphere cuts the image plane. ``with_truth``
        False (recorded data): no true section is logged at all."""
        for name, value, colour in (("detected", detected, _RED), ("true", true, _GREEN)):
            if name == "true" and not with_truth:
                continue
            path = f"/{session}/bmode/section/{name}"
            strips = []
            section = sphere_section(*value) if value is not None else None
            if section is not None:
                x, y, r = section
                a = np.linspace(0, 2 * np.pi, 65)
                P = np.column_stack([x + r * np.cos(a), y + r * np.sin(a), np.zeros_like(a)])
                rows, cols = us_to_pixel(P, width, spacing)
                strips.append(np.column_stack([cols, rows]))
            self.stream.log(path, rr.LineStrips2D(strips, colors=[colour], radii=[0.8]))

    def boundary(self, session: str, samples: Array) -> None:
        """Boundary samples (column, row) of the current frame (cone/prism scans)."""
        self.stream.log(
            f"/{session}/bmode/boundary", rr.Points2D(samples, colors=[_RED], radii=[1.0])
        )

    def points(self, path: str, P: Array, colour=_RED, radius: float = 0.0005) -> None:
        """Points (n, 3), static (touches, localized centres)."""
        self.stream.reset_time()
        self.stream.log(path, rr.Points3D(P, colors=[colour], radii=[radius]), static=True)

    # ------------------------------------------------------------------ pipeline

    def profile(self, session: str, sphere: str, prof) -> None:
        """A :class:`calib.localize.SphereProfile`: the curve (mm, share of the peak) and
        its 0.25/0.75 crossings, in a 2D view of its own."""
        base = f"/{session}/localization/{sphere}"
        self.stream.reset_time()
        if prof.n_sweeps == 0:
            return
        x = prof.radii * 1e3
        # Scaled so the curve reads in a square panel: radius (mm) × 10·share.
        curve = np.column_stack([x, -10.0 * prof.profile])
        self.stream.log(f"{base}/profile", rr.LineStrips2D([curve], colors=[(80, 160, 255)]))
        xs = [prof.interior, *prof.shell]
        ys = [0.25, 0.75, 0.75]
        self.stream.log(
            f"{base}/crossings",
            rr.Points2D(
                np.column_stack([np.array(xs) * 1e3, -10.0 * np.array(ys)]),
                colors=[_RED],
                radii=[0.15],
                labels=[
                    label if crossed else f"{label} (fall-back)"
                    for label, crossed in zip(
                        ("interior 0.25", "shell 0.75 ↑", "shell 0.75 ↓"),
                        prof.crossed,
                        strict=True,
                    )
                ],
            ),
        )

    def alternation(self, session: str, method: str, alt: AlternationResult) -> None:
        """Loss and estimate change per iteration; residuals of the final calibration."""
        s = self.stream
        base = f"/{session}/calibration/{method}"
        for h in alt.history:
            s.reset_time()
            s.set_time("iteration", sequence=int(h["iteration"]))
            s.log(f"{base}/loss_mm2", rr.Scalars(float(h["cost_mm2"])))
            for key in ("change_mm", "change_deg"):
                if np.isfinite(h[key]):
                    s.log(f"{base}/{key}", rr.Scalars(float(h[key])))
        s.reset_time()
        s.log(
            f"{base}/residuals_mm",
            rr.BarChart(np.asarray(alt.result.residuals_mm, dtype=float)),
        )

    def reconstruction(
        self,
        kind: str,
        mesh: trimesh.Trimesh,
        points: Mapping[tuple[str, str], tuple[NDArray[np.float32], NDArray[np.float32]]],
        max_points: int = 50_000,
    ) -> None:
        """Registered points (CAD frame) coloured by point-to-surface error (turbo, up to
        the 99th percentile), and the CAD surface."""
        from matplotlib import colormaps

        s = self.stream
        s.reset_time()
        s.log(
            f"/reconstruction/{kind}/cad",
            rr.Mesh3D(
                vertex_positions=np.asarray(mesh.vertices, dtype=np.float32),
                triangle_indices=np.asarray(mesh.faces, dtype=np.uint32),
                albedo_factor=(200, 200, 200, 60),
            ),
            static=True,
        )
        top = float(np.percentile(np.concatenate([d for _, d in points.values()]), 99))
        cmap = colormaps["turbo"]
        for (method, name), (P, d) in points.items():
            pick = np.random.default_rng(0).permutation(len(d))[:max_points]
            colours = (cmap(np.clip(d[pick] / max(top, 1e-9), 0, 1))[:, :3] * 255).astype(np.uint8)
            s.log(
                f"/reconstruction/{kind}/{method}/{name}",
                rr.Points3D(P[pick], colors=colours, radii=[0.00015]),
                static=True,
            )


def log_sweeps(
    rec: Recorder,
    session: str,
    sweeps: Sequence[Sweep],
    model: mujoco.MjModel,
    data: mujoco.MjData,
    robot_ids: list[int],
    T_ee_us_estimated: Array | None,
    localizations: Mapping[tuple[str, int], SweepLocalization] | None = None,
    radius: float = 0.0,
    axial_scale: float = 1.0,
    true_centres: Mapping[tuple[str, int], Array] | None = None,
    T_base_us_true: Mapping[tuple[str, int], Array] | None = None,
    max_frames: int | None = None,
) -> int:
    """Log a spread of whole sweeps frame by frame: robot, frame (2D, 3D quad at the true
    pose, estimated outline) and, when given, the detected (red) and true (green) sphere
    sections. ``localizations`` and ``true_centres`` are keyed by (target, pose id), the
    centres in the sweep's reference frame (localization) or per frame (truth, (n, 3)).
    At most ``max_frames`` frames (default: the recording's). Returns the number of frames
    logged."""
    if not sweeps:
        return 0
    limit = rec.options.max_frames if max_frames is None else max_frames
    chosen = sweeps_to_log(len(sweeps), sweeps[0].n_frames, limit)
    logged = 0
    for i in chosen:
        sweep = sweeps[i]
        key = (sweep.target, sweep.pose_id)
        W = sweep.images.shape[2]
        sx, sy = sweep.spacing
        true_spacing = (sx, sy * axial_scale)
        loc = localizations.get(key) if localizations else None
        offsets = frame_offsets(sweep, T_ee_us_estimated) if loc is not None else None
        for j in range(sweep.n_frames):
            rec.next_frame()
            rec.robot_pose(session, model, data, sweep.q[j], robot_ids)
            T_true = T_base_us_true[key][j] if T_base_us_true else None
            T_est = (
                sweep.T_base_ee[j] @ T_ee_us_estimated if T_ee_us_estimated is not None else None
            )
            rec.frame(
                session,
                sweep.images[j],
                sweep.spacing,
                T_true,
                T_est,
                textured=j == sweep.reference_index or j == 0,
            )
            detected = None
            if loc is not None and loc.accepted and offsets is not None:
                detected = (loc.centre - offsets[j], radius)
            true = None
            if true_centres is not None and key in true_centres:
                true = (true_centres[key][j], radius)
            if radius > 0:
                rec.sections(
                    session, W, true_spacing, detected, true, with_truth=true_centres is not None
                )
            logged += 1
    return logged


def log_acquisition(
    rec: Recorder,
    session: str,
    scene_parts: Sequence,
    model: mujoco.MjModel,
    dataset,
    alternations: Mapping[str, AlternationResult],
    radius: float,
    cfg: LocalizerConfig,
    axial_scale: float,
    truth: tuple[Mapping[tuple[str, int], Array], Array, Mapping[str, Array]] | None = None,
) -> int:
    """One acquisition session: the scene (``scene_parts``: parts with ``name``,
    ``material``, ``mesh`` in the base frame), the robot (``model``'s arm and tool), a
    spread of sweeps (at most ``max_frames`` frames over all spheres) with each sphere's
    section as found by the alternation that localized it last (``alternations`` by
    method, in order) and, in simulation, the true one; each alternation's convergence,
    residuals and radial profiles; the localized centres in the base frame. ``truth`` =
    (true flange poses per (target, pose id), true ``T_ee_us``, true landmarks): the
    twin's, kept apart; None for recorded data. Returns the frames logged."""
    rec.scene(session, scene_parts)
    data = mujoco.MjData(model)
    ids = rec.robot_shapes(session, model)
    owner: dict[str, str] = {}
    for method, alt in alternations.items():
        for target in alt.localizations:
            owner.setdefault(target, method)
    targets = [t for t in dataset.targets() if t in owner]
    budget = rec.options.max_frames // max(len(targets), 1)
    logged = 0
    for target in targets:
        alt = alternations[owner[target]]
        sweeps = dataset.of(target)
        T_true = centres = None
        if truth is not None:
            T_flange_true, T_ee_us_true, landmarks = truth
            T_true = {
                (target, s.pose_id): T_flange_true[(target, s.pose_id)] @ T_ee_us_true
                for s in sweeps
            }
            centres = {k: se3.apply(se3.invert(T), landmarks[target]) for k, T in T_true.items()}
        locs = alt.localizations[target]
        logged += log_sweeps(
            rec,
            session,
            sweeps,
            model,
            data,
            ids,
            alt.result.T_ee_us,
            {(target, s.pose_id): loc for s, loc in zip(sweeps, locs, strict=True)},
            radius,
            axial_scale,
            centres,
            T_true,
            budget,
        )
    for method, alt in alternations.items():
        T_est = alt.result.T_ee_us
        for target, locs in alt.localizations.items():
            prof = sphere_profile(dataset.of(target), locs, T_est, radius, cfg, axial_scale)
            rec.profile(session, f"{method}/{target}", prof)
        rec.alternation(session, method, alt)
        centres_base = [
            se3.apply(s.T_base_ee[s.reference_index] @ T_est, loc.centre)
            for t, locs in alt.localizations.items()
            for s, loc in zip(dataset.of(t), locs, strict=True)
            if loc.accepted
        ]
        if centres_base:
            rec.points(f"/{session}/world/centres/{method}", np.array(centres_base))
    return logged


def blueprint(
    sessions: Sequence[str], scans: Sequence[str] = (), reconstruction: bool = False
) -> rrb.Blueprint:
    """One tab per sphere session (3D scene | current frame over convergence, radial
    profile and residuals), one per phantom scan (3D scene | frame with its boundary
    samples), and one for the reconstruction."""
    tabs = []
    for s in sessions:
        tabs.append(
            rrb.Horizontal(
                rrb.Spatial3DView(origin=f"/{s}/world", name=f"{s}: scene"),
                rrb.Vertical(
                    rrb.Spatial2DView(origin=f"/{s}/bmode", name=f"{s}: B-mode"),
                    rrb.Tabs(
                        rrb.TimeSeriesView(origin=f"/{s}/calibration", name="convergence"),
                        rrb.Spatial2DView(origin=f"/{s}/localization", name="radial profile"),
                        rrb.BarChartView(origin=f"/{s}/calibration", name="residuals"),
                    ),
                ),
                column_shares=[3, 2],
                name=s,
            )
        )
    for s in scans:
        tabs.append(
            rrb.Horizontal(
                rrb.Spatial3DView(origin=f"/{s}/world", name=f"{s}: scene"),
                rrb.Spatial2DView(origin=f"/{s}/bmode", name=f"{s}: B-mode"),
                column_shares=[3, 2],
                name=s,
            )
        )
    if reconstruction:
        tabs.append(rrb.Spatial3DView(origin="/reconstruction", name="reconstruction"))
    return rrb.Blueprint(rrb.Tabs(*tabs), collapse_panels=True)


def merge_parts(
    options: RecordingOptions,
    parts: Sequence[Path],
    sessions: Sequence[str],
    scans: Sequence[str] = (),
    reconstruction: bool = False,
    main: Recorder | None = None,
) -> Path:
    """Write the run's recording: the main process's own logs (``main``, closed here),
    then every worker's part file, and the blueprint. The part files are removed."""
    rec = main or Recorder(options)
    t0 = time.perf_counter()
    for part in parts:
        log.debug("merging %s (%.1f MB)", part.name, part.stat().st_size / 2**20)
        rr.send_chunks(RrdReader(part).stream(), recording=rec.stream)
    rec.stream.send_blueprint(blueprint(sessions, scans, reconstruction))
    rec.close()
    log.debug(
        "recording %s: %.1f MB, merged in %.1f s",
        options.path,
        options.path.stat().st_size / 2**20,
        time.perf_counter() - t0,
    )
    for part in parts:
        part.unlink(missing_ok=True)
    if parts:
        with contextlib.suppress(OSError):  # other runs' parts may share it
            parts[0].parent.rmdir()
    return options.path
