"""The real UR3 behind the :class:`calib.acquisition.protocol.Robot` protocol, through ``ur_rtde``.

Poses cross this boundary as UR controllers speak them ([x, y, z, rx, ry, rz]: metres and
a rotation vector) and become (4, 4) ``T_base_ee`` here. The controller reports and moves
its TCP, so its active TCP offset must be zero (the flange is the tool frame): it is read
on connecting, and a non-zero one is refused before anything moves, or set to zero when
asked (``set_tcp_zero``). Every move is checked first against the
configured workspace box and maximum step, blocks until the controller reports it done,
then waits ``settle_s`` before the pose is read. A protective or emergency stop, the
controller's program ending, or a lost connection raise one clear error; the caller
decides what to keep (the acquisition keeps every finished sweep).
"""

from __future__ import annotations

import socket
import time

import numpy as np
from numpy.typing import ArrayLike, NDArray

from calib import se3
from calib.errors import (
    RobotConnectionError,
    RobotSetupError,
    RobotStoppedError,
    UnreachablePoseError,
)
from calib.records import RobotReading

from .config import URRobotConfig
from .rtde_process import RtdeProcess

__all__ = ["URRobot", "check_reachable", "describe_tcp"]

Array = NDArray[np.float64]
_RTDE_PORT = 30004
_SAFETY_WAIT_S = 0.5
#: After a move the arm is within a few hundredths of a millimetre of the commanded pose;
#: a reading farther than this is read again (see ``URRobot._settled``), for up to
#: this long.
_FRESH_TOLERANCE_M = 0.5e-3
_FRESH_TOLERANCE_RAD = 1e-3
_FRESH_TIMEOUT_S = 0.5
# A TCP offset below 1 µm and 1 µrad is zero (the controller stores what was typed).
_TCP_ZERO_TOL = 1e-6


def describe_tcp(tcp: ArrayLike) -> str:
    """A TCP offset [x, y, z, rx, ry, rz] (m, rotation vector) as a user reads it."""
    tcp = np.asarray(tcp, dtype=float)
    return (
        f"{np.round(tcp[:3] * 1e3, 3).tolist()} mm, rotation vector "
        f"{np.round(np.degrees(tcp[3:]), 3).tolist()}°"
    )


def check_reachable(host: str, timeout_s: float) -> None:
    """Raise :class:`RobotConnectionError` unless the controller's RTDE port accepts a
    connection within ``timeout_s`` (the client library itself can block for minutes on
    an address that does not answer)."""
    try:
        with socket.create_connection((host, _RTDE_PORT), timeout=timeout_s):
            pass
    except OSError as e:
        reason = "no answer" if isinstance(e, TimeoutError) else (e.strerror or str(e))
        raise RobotConnectionError(
            f"robot controller {host}:{_RTDE_PORT} unreachable within {timeout_s:g} s "
            f"({reason}); check the address, the cable and that the robot is powered on"
        ) from None


def _answers(host: str, timeout_s: float) -> bool:
    try:
        check_reachable(host, timeout_s)
    except RobotConnectionError:
        return False
    return True


class URRobot:
    """A UR controller driven through RTDE.

    Parameters
    ----------
    cfg : URRobotConfig
    dry_run : bool
        Plan and check only: no connection, no motion (``read`` then fails).
    set_tcp_zero : bool
        A non-zero active TCP offset is set to zero (``tcp_offset_cleared`` keeps what it
        was); otherwise it is refused with :class:`RobotSetupError`.
    """

    def __init__(
        self, cfg: URRobotConfig, dry_run: bool = False, set_tcp_zero: bool = False
    ) -> None:
        self.cfg = cfg
        self.dry_run = dry_run
        self._rtde: RtdeProcess | None = None
        self._last: Array | None = None  # the last commanded (or read) flange pose
        self.tcp_offset_cleared: Array | None = None
        if dry_run:
            return
        check_reachable(cfg.host, cfg.connect_timeout_s)
        self._rtde = RtdeProcess(cfg.host)
        try:
            if self._call("receive", "isProtectiveStopped", what="connecting"):
                raise RobotStoppedError(
                    f"robot {cfg.host} is in a protective stop: release it on the teach pendant"
                )
            self._check_tcp(set_tcp_zero)
            self._last = self.read().T_base_ee
        except BaseException:
            self.close()
            raise

    def tcp_offset(self) -> Array:
        """The controller's active TCP offset [x, y, z, rx, ry, rz] (m, rotation vector)."""
        tcp = np.asarray(
            self._call("control", "getTCPOffset", what="reading the TCP offset"), dtype=float
        )
        if tcp.shape != (6,) or not np.all(np.isfinite(tcp)):
            raise RobotConnectionError(f"robot controller {self.cfg.host}: no TCP offset received")
        return tcp

    def _check_tcp(self, set_zero: bool) -> None:
        tcp = self.tcp_offset()
        if np.all(np.abs(tcp) <= _TCP_ZERO_TOL):
            return
        what = describe_tcp(tcp)
        if not set_zero:
            raise RobotSetupError(
                f"robot {self.cfg.host}: the active TCP offset is {what}; uscal reads and moves "
                "the flange, so it must be zero (every pose would be the TCP's): set it to "
                "zero in the installation, or pass --set-tcp-zero; nothing moved"
            )
        self._call("control", "setTcp", [0.0] * 6, what="setting the TCP offset to zero")
        if np.any(np.abs(self.tcp_offset()) > _TCP_ZERO_TOL):
            raise RobotSetupError(
                f"robot {self.cfg.host}: the TCP offset stays {what} after setting it to zero"
            )
        self.tcp_offset_cleared = tcp

    # ---------------------------------------------------------------- checks

    def check_pose(self, T_base_ee: ArrayLike, pose_label: str = "") -> None:
        """Raise :class:`UnreachablePoseError` if a pose leaves the workspace box."""
        p_mm = np.asarray(T_base_ee, dtype=float)[:3, 3] * 1e3
        lo, hi = np.array(self.cfg.workspace_min_mm), np.array(self.cfg.workspace_max_mm)
        if np.any(p_mm < lo) or np.any(p_mm > hi):
            raise UnreachablePoseError(
                f"pose {pose_label or ''} at {np.round(p_mm, 1).tolist()} mm lies outside the "
                f"workspace box {lo.tolist()}…{hi.tolist()} mm (hw config robot.workspace_*)"
            )

    def check_step(self, T_from: ArrayLike, T_to: ArrayLike, pose_label: str = "") -> None:
        """Raise :class:`UnreachablePoseError` if one move would exceed the max step."""
        d_mm = 1e3 * float(se3.translation_distance(T_from, T_to))
        d_deg = float(np.degrees(se3.rotation_angle(T_from, T_to)))
        if d_mm > self.cfg.max_step_mm or d_deg > self.cfg.max_step_deg:
            raise UnreachablePoseError(
                f"move to {pose_label or 'the pose'} is a step of {d_mm:.1f} mm and "
                f"{d_deg:.1f}°, more than robot.max_step_mm = {self.cfg.max_step_mm:g} / "
                f"max_step_deg = {self.cfg.max_step_deg:g}"
            )

    # ---------------------------------------------------------------- motion

    def move_to(self, T_base_ee: ArrayLike, pose_label: str = "") -> RobotReading:
        """Linear move to a flange pose; returns the settled reading."""
        T = np.asarray(T_base_ee, dtype=float)
        self.check_pose(T, pose_label)
        if self._last is not None:
            self.check_step(self._last, T, pose_label)
        if self.dry_run:
            self._last = T
            return RobotReading(np.full(6, np.nan), T)
        pose = [float(v) for v in se3.pose6_from_matrix(T)]
        v, a = self.cfg.speed_m_s, self.cfg.acceleration_m_s2
        step = float(se3.translation_distance(self._last, T)) if self._last is not None else 1.0
        ok = self._call(
            "control", "moveL", pose, v, a, what=pose_label, duration_s=step / v + v / a
        )
        self._after_move(ok, pose_label)
        self._last = T
        return self._settled(T_base_ee=T)

    def move_joints(self, q: ArrayLike, pose_label: str = "") -> RobotReading:
        """Joint move (to a taught configuration, radians); returns the settled reading."""
        q = [float(v) for v in np.asarray(q, dtype=float)]
        if self.dry_run:
            return RobotReading(np.asarray(q), np.full((4, 4), np.nan))
        w, a = self.cfg.joint_speed_rad_s, self.cfg.joint_acceleration_rad_s2
        travel = float(np.max(np.abs(np.asarray(q) - self.read().q)))
        ok = self._call("control", "moveJ", q, w, a, what=pose_label, duration_s=travel / w + w / a)
        self._after_move(ok, pose_label)
        reading = self._settled(q=np.asarray(q))
        self._last = reading.T_base_ee
        return reading

    def read(self) -> RobotReading:
        """Reported joint angles and flange pose (the controller's own kinematics)."""
        if self._rtde is None:
            raise RobotConnectionError("no robot connection (dry run, or closed)")
        q = self._call("receive", "getActualQ", what="reading the pose")
        pose = self._call("receive", "getActualTCPPose", what="reading the pose")
        if len(q) != 6 or len(pose) != 6:
            raise RobotConnectionError(f"robot controller {self.cfg.host}: no state received")
        T = se3.check(se3.matrix_from_pose6(pose), f"robot controller {self.cfg.host}: flange pose")
        return RobotReading(np.asarray(q, dtype=float), T)

    def close(self) -> None:
        """Stop the control script and disconnect (safe to call twice)."""
        rtde, self._rtde = self._rtde, None
        if rtde is not None:
            rtde.close()

    def __enter__(self) -> URRobot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- helpers

    def _call(self, target: str, method: str, *args, what: str = "", duration_s: float = 0.0):
        """Forward a call to the client; a move may take ``duration_s`` (its expected
        motion time): no reply within three times that plus 5 s means the connection is
        lost (the client library can wait forever on a pending move)."""
        if self._rtde is None:
            raise RobotConnectionError("no robot connection (dry run, or closed)")
        host, timeout = self.cfg.host, self.cfg.connect_timeout_s
        try:
            return self._rtde.call(
                target,
                method,
                *args,
                alive=lambda: _answers(host, min(timeout, 1.0)),
                grace_s=timeout,
                timeout_s=5.0 + 3.0 * duration_s,
            )
        except RobotConnectionError as e:
            self._lost()
            raise RobotConnectionError(f"{e}: connection lost while {what or 'moving'}") from None

    def _lost(self) -> None:
        """The connection is gone: end the client process without ceremony."""
        rtde, self._rtde = self._rtde, None
        if rtde is not None:
            rtde.kill()

    def _after_move(self, ok: bool, pose_label: str) -> None:
        """Turn a failed move into the reason: a stop, a lost connection, or a refusal."""
        if ok:
            return
        where = f"during the move to {pose_label or 'the pose'}"
        # The client notices a dead connection only after a while: ask the network too.
        if not self._connected() or not _answers(self.cfg.host, self.cfg.connect_timeout_s):
            self._lost()
            raise RobotConnectionError(f"robot controller {self.cfg.host}: connection lost {where}")
        # The safety bits arrive on the receive stream, which may trail the control
        # session that saw the move fail by a few packets: watch them for a moment.
        deadline = time.monotonic() + _SAFETY_WAIT_S
        while True:
            if self._call("receive", "isEmergencyStopped"):
                raise RobotStoppedError(f"emergency stop {where}")
            if self._call("receive", "isProtectiveStopped"):
                raise RobotStoppedError(
                    f"protective stop {where}: check the rig, release the stop on the teach "
                    "pendant, then resume"
                )
            if time.monotonic() > deadline:
                break
            time.sleep(0.02)
        raise RobotStoppedError(
            f"the controller did not complete the move to {pose_label or 'the pose'} "
            "(its program stopped)"
        )

    def _connected(self) -> bool:
        try:
            return bool(
                self._call("control", "isConnected") and self._call("receive", "isConnected")
            )
        except RobotConnectionError:
            return False

    def _settled(
        self, T_base_ee: NDArray[np.float64] | None = None, q: NDArray[np.float64] | None = None
    ) -> RobotReading:
        """The reading after a move (its settle time waited): read again while it is still
        off the commanded pose ``T_base_ee`` or joints ``q`` by more than the arm ever is
        after a completed move, for up to ``_FRESH_TIMEOUT_S`` — such a reading is the
        receive stream's last packet from before the move ended (a loaded host), not the
        arm. A pose the arm really missed is returned as read once the time is up."""
        if self.cfg.settle_s:
            time.sleep(self.cfg.settle_s)
        deadline = time.monotonic() + _FRESH_TIMEOUT_S
        while True:
            reading = self.read()
            near = (
                T_base_ee is None
                or se3.translation_distance(reading.T_base_ee, T_base_ee) < _FRESH_TOLERANCE_M
            ) and (q is None or float(np.max(np.abs(reading.q - q))) < _FRESH_TOLERANCE_RAD)
            if near or time.monotonic() > deadline:
                return reading
            time.sleep(0.005)
