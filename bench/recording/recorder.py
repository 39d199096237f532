"""Rerun recordings of a run: where the robot went, what each frame showed, what the
localizer found, how the calibration converged, where the reconstruction is wrong.

With :mod:`~bench.recording.logs` (what each job logs, the merge of the workers'
parts), the only module that imports rerun. One recording per run; each acquisition
session (``run`` for a single acquisition, the datasets ``A``, ``B``… of the paper's
experiment) is a subtree, in metres and in the robot base frame::

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

import importlib.util
import logging
import sys
from collections.abc import Mapping, Sequence
from types import ModuleType

import mujoco
import numpy as np
import trimesh
from numpy.typing import NDArray

from calib import se3
from calib.calibration.alternation import AlternationResult
from calib.image import pixel_to_us, sphere_section, us_to_pixel

from .options import RecordingOptions


def lazy_module(name: str) -> ModuleType:
    """``import name``, run at the first use of one of its attributes (the standard
    library's :class:`importlib.util.LazyLoader`): rerun takes ≈ 0.8 s to import and every
    run's job imports this module, while most runs, and every pool worker that records
    nothing, never log."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    assert spec is not None and spec.loader is not None, name
    loader = importlib.util.LazyLoader(spec.loader)
    spec.loader = loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    loader.exec_module(module)
    return module


rr = lazy_module("rerun")

__all__ = ["GREEN", "RED", "Recorder"]

Array = NDArray[np.float64]
log = logging.getLogger(__name__)

#: The colours of what the pipeline found (red) and of the truth (green).
RED, GREEN = (230, 40, 40), (40, 200, 80)
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
                rr.LineStrips3D([se3.apply(T_base_us_estimated, corners)], colors=[RED]),
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
        for name, value, colour in (("detected", detected, RED), ("true", true, GREEN)):
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
            f"/{session}/bmode/boundary", rr.Points2D(samples, colors=[RED], radii=[1.0])
        )

    def lines(self, path: str, strips: Sequence[Array], colour=RED, radius=0.0002) -> None:
        """Line strips (each (k, 3)), static (a phantom's wires)."""
        self.stream.reset_time()
        self.stream.log(
            path, rr.LineStrips3D(list(strips), colors=[colour], radii=[radius]), static=True
        )

    def points(self, path: str, P: Array, colour=RED, radius: float = 0.0005) -> None:
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
                colors=[RED],
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
