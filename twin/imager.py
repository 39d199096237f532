"""The simulated scanner: B-mode frames at the probe's *true* pose in the twin's scene.

A :class:`SimRobot` + :class:`SimImager` pair behaves like a robot with a scanner: the
robot reports what its controller believes, the imager sees what the true arm and the
true probe mount point at.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray

from calib import se3
from calib.records import UsFrame
from sim_us import MediumConfig, ProbeConfig
from sim_us.raycast import AcousticScene, ScenePart
from sim_us.simulator import BmodeSimulator
from sim_us.wires import Wire

from .robot import SimRobot
from .scene import Scene

__all__ = ["GainSeriesImager", "SimImager", "acoustic_scene"]


def acoustic_scene(scene: Scene) -> AcousticScene:
    """The twin's true phantom and tank as meshes in the base frame, with materials, and
    the phantom's wires (an N-wire phantom) as line targets."""
    parts = []
    for phantom, T in ((scene.phantom, scene.T_base_phantom), (scene.tank, scene.T_base_tank)):
        for part in phantom.parts:
            mesh = part.mesh.copy()
            mesh.apply_transform(T)
            smooth = part.acoustic_vertices
            if smooth is not None:  # a textured part: its un-textured surface, moved alike
                smooth = trimesh.transform_points(smooth, T)
            parts.append(
                ScenePart(
                    part.name,
                    mesh,
                    part.material,
                    smooth,
                    part.texture_rms_m,
                    texture_layer_share=part.texture_layer_share,
                    layer_m=part.layer_m,
                    build_axis=T[:3, 2].copy(),  # the CAD's z: the build direction
                )
            )
    T = scene.T_base_phantom
    wires = tuple(
        Wire(w.name, se3.apply(T, w.front), se3.apply(T, w.back), w.diameter_m, w.material)
        for w in getattr(scene.phantom, "wires", ())
    )
    return AcousticScene(tuple(parts), wires)


class SimImager:
    """Grabs frames at the robot's true probe pose.

    Parameters
    ----------
    robot : SimRobot
        Its ``truth`` gives the true flange pose.
    T_ee_us : (4, 4) float
        The true probe mount.
    probe, medium : settings of the scanner and the tank's medium
    rng : numpy.random.Generator
        Electronic noise; also draws the key of the medium's speckle once.
    """

    def __init__(
        self,
        robot: SimRobot,
        T_ee_us: NDArray[np.float64],
        probe: ProbeConfig,
        medium: MediumConfig,
        rng: np.random.Generator,
    ) -> None:
        self.robot = robot
        self._T_ee_us = np.asarray(T_ee_us, dtype=float)
        self._rng = rng
        self.probe = probe
        self.medium = medium
        self.simulator = BmodeSimulator(
            acoustic_scene(robot.scene.scene),
            probe,
            medium,
            speckle_key=int(rng.integers(0, 2**63)),
        )
        self._captured: list[tuple[NDArray[np.float64], float | None]] = []

    @property
    def spacing(self) -> tuple[float, float]:
        """Pixel spacing (sx, sy) in metres."""
        return self.probe.spacing_m

    def _temperature_c(self) -> float | None:
        """The water's true temperature now (the session clock, seconds since the session
        started); None while it does not drift (renders as configured)."""
        if self.medium.temperature_drift_c_per_h == 0.0:
            return None
        return self.medium.temperature_at(getattr(self.robot, "clock_s", 0.0))

    def grab(self) -> UsFrame:
        """One frame at the current true probe pose, as a frame grabber delivers it (the
        frame reports the scanner's nominal spacing, whatever its true geometry)."""
        # The flange at the grab instant, through the loaded holder (SimRobot.frame_pose,
        # which also advances the session clock the water temperature follows).
        T_base_us = self.robot.frame_pose() @ self._T_ee_us
        return UsFrame(self._render(T_base_us[None], self._temperature_c())[0], self.spacing)

    def capture(self) -> None:
        """Note a frame at the current true probe pose and time (what :meth:`grab` would
        render now); :meth:`develop` renders the noted frames in one call."""
        T_base_us = self.robot.frame_pose() @ self._T_ee_us
        self._captured.append((T_base_us, self._temperature_c()))

    def develop(self) -> list[UsFrame]:
        """The frames noted by :meth:`capture`, rendered in one batch, in order.

        The noise and every pose are the ones :meth:`grab` would have used, so without a
        drifting water temperature the frames are identical to grabbing them one by one.
        With a drift the batch renders at its frames' mean temperature: a sweep lasts
        seconds, the water drifts by about a millikelvin meanwhile (a depth change of
        ~1e-7), which no grey level shows.
        """
        if not self._captured:
            return []
        T = np.array([t for t, _ in self._captured])
        temps = [c for _, c in self._captured]
        self._captured = []
        temperature = None if temps[0] is None else float(np.mean(temps))
        return [UsFrame(image, self.spacing) for image in self._render(T, temperature)]

    def render_at(self, T_base_us: NDArray[np.float64]) -> NDArray[np.uint8]:
        """Frames (n, H, W) at given true image poses (batched, e.g. a whole sweep)."""
        T = np.asarray(T_base_us).reshape(-1, 4, 4)
        return self._render(T, self._temperature_c())

    def _render(self, T: NDArray[np.float64], temperature_c: float | None) -> NDArray[np.uint8]:
        """Frames (n, H, W) at true image poses ``T`` and a water temperature."""
        return self.simulator.render(T, self._rng, temperature_c)


class GainSeriesImager(SimImager):
    """A :class:`SimImager` that forms every frame at several overall gains at once, from
    one simulation of its echoes (:meth:`sim_us.simulator.BmodeSimulator.render_at_gains`):
    a robustness grid's gain axis acquires once instead of once per gain.

    It delivers the frames of its configured gain, ``probe.gain_db``, which must be the
    highest of ``gains_db`` (its trace reaches every gain's echoes); :attr:`delivered`
    keeps every gain's frames (H, W), in the order delivered. Each gain's noise is drawn
    from its own copy of ``rng`` taken here, before any frame: the noise an imager of
    that gain made from the same ``rng`` would draw.
    """

    def __init__(self, *args: Any, gains_db: Sequence[float], **kwargs: Any) -> None:
        """``args``, ``kwargs``: :class:`SimImager`'s."""
        super().__init__(*args, **kwargs)
        if len(set(gains_db)) != len(gains_db):
            raise ValueError(f"gains {list(gains_db)}: each once")
        if max(gains_db) != self.probe.gain_db:
            raise ValueError(
                f"the imager's gain ({self.probe.gain_db:g} dB) must be the highest of "
                f"{list(gains_db)}"
            )
        self.gains_db = tuple(float(g) for g in gains_db)
        self._own = self.gains_db.index(float(self.probe.gain_db))
        # After the speckle key's draw (SimImager.__init__), as every gain's imager would be.
        self._rngs = [copy.deepcopy(self._rng) for _ in self.gains_db]
        self.delivered: dict[float, list[NDArray[np.uint8]]] = {g: [] for g in self.gains_db}

    def _render(self, T: NDArray[np.float64], temperature_c: float | None) -> NDArray[np.uint8]:
        series = self.simulator.render_at_gains(T, self.gains_db, self._rngs, temperature_c)
        for g, frames in zip(self.gains_db, series, strict=True):
            self.delivered[g].extend(frames)
        return series[self._own]
