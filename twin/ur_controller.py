"""A loopback UR controller whose arm is the twin (``uscal twin serve``).

It speaks the controller's side of the protocols a UR3 offers on its network port, so
the unmodified ``ur_rtde`` client — ``hw.URRobot``, or a user's own RTDE code — drives the
twin as it would drive the real arm:

- **RTDE** (port 30004): protocol version, controller version, output and input
  recipes, start/pause, and the data packages both ways. Outputs are streamed at the
  requested frequency (capped, see ``_MAX_STREAM_HZ``), each value packed with its real
  type (the client decodes with its own table).
- **Dashboard** (29999): the line protocol the client uses at connection
  (``PolyscopeVersion``, ``get serial number``, ``is in remote control``) and the usual
  status queries.
- **Script port** (30003): accepts the URScript program the control interface uploads;
  once received the "program" runs (``runtime_state`` PLAYING).

Motion commands follow ``ur_rtde``'s register handshake (``ur-rtde.md``): the program
signals ready (``output_int_register_0 = 1``), the client writes a command code and its
arguments into the input registers, the controller executes it and signals done (2),
and returns to ready once the client clears the command. moveJ goes to joint angles,
moveL to a flange pose through the controller's *nominal* kinematics — exactly what
:class:`twin.robot.SimRobot` does; the true arm then settles with its repeatability, and
the reported ``actual_q`` / ``actual_TCP_pose`` (metres + rotation vector) are what the
controller believes.

After each settled move the controller renders the B-mode frame the probe sees at the
true pose (``sim_us``) and writes it, atomically, to a frame file (binary PGM) that a
frame grabber's file source reads: the scanner of this loopback rig.

Faults, for tests of the client side: a network outage when a given move starts, or a
protective stop in the middle of one. The dashboard also takes the loopback rig's own
commands (``twin mount stylus|probe``, ``twin touch <vertex> <index>``): an emulated
operator hand-guiding the arm, as :mod:`twin.touch` does in simulation.

Only one controller may listen per address (the ports are fixed): run several on
127.0.0.2, 127.0.0.3, …
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import socketserver
import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from calib import se3
from calib.errors import UscalError

__all__ = ["ControllerFaults", "LoopbackController", "write_pgm"]

log = logging.getLogger(__name__)
Array = NDArray[np.float64]

RTDE_PORT, DASHBOARD_PORT, SCRIPT_PORT = 30004, 29999, 30003
_MAX_STREAM_HZ = 500.0
_CONTROLLER_VERSION = (5, 11, 0, 0)  # major > 3: the client runs at 500 Hz
_POLYSCOPE = "URSoftware 5.11.0.108249 (Mar 21 2022)"

# RTDE packet types.
_V, _v, _O, _I, _S, _P, _U, _M = 86, 118, 79, 73, 83, 80, 85, 77

# Command codes of ur_rtde's control script (lower register range).
_NO_CMD, _MOVEJ, _MOVEL, _STOP_SCRIPT = 0, 1, 3, 255
# ur_rtde's setTcp / getTCPOffset (its control script: set_tcp(pose); get_tcp_offset()
# written to output_double_register_0..5).
_SET_TCP, _GET_TCP_OFFSET = 29, 40
_STOPL, _STOPJ, _WATCHDOG = 33, 34, 99

_RUNTIME_STOPPED, _RUNTIME_PLAYING = 1, 2
_SAFETY_NORMAL, _SAFETY_PROTECTIVE_STOP = 1, 1 << 2
_ROBOT_POWER_ON, _ROBOT_PROGRAM_RUNNING = 1, 1 << 1


def _rtde_type(name: str) -> str:
    """The RTDE type of a variable, as the controller's type table has it."""
    vec6d = {
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment",
        "actual_q", "actual_qd", "actual_current", "joint_control_output",
        "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose",
        "target_TCP_speed", "joint_temperatures", "actual_joint_voltage", "tcp_offset",
        "ft_raw_wrench", "actual_current_window", "actual_current_as_torque",
        "payload_inertia", "actual_target_q",
    }  # fmt: skip
    vec3d = {"actual_tool_accelerometer", "elbow_position", "elbow_velocity", "payload_cog"}
    int32 = {"robot_mode", "safety_mode", "safety_status", "tool_output_voltage"}
    uint64 = {"actual_digital_input_bits", "actual_digital_output_bits"}
    uint32 = {
        "runtime_state", "robot_status_bits", "safety_status_bits", "analog_io_types",
        "euromap67_input_bits", "euromap67_output_bits", "tool_mode",
        "tool_analog_input_types", "output_bit_registers0_to_31",
        "output_bit_registers32_to_63", "input_bit_registers0_to_31",
        "input_bit_registers32_to_63", "script_control_line", "speed_slider_mask",
        "standard_analog_output_mask",
    }  # fmt: skip
    uint8 = {
        "standard_digital_output_mask", "standard_digital_output",
        "configurable_digital_output_mask", "configurable_digital_output",
        "tool_digital_output_mask", "tool_digital_output", "standard_analog_output_type",
        "tool_digital_output0_mode", "tool_digital_output1_mode", "tool_output_mode",
    }  # fmt: skip
    if name in vec6d:
        return "VECTOR6D"
    if name in vec3d:
        return "VECTOR3D"
    if name == "joint_mode":
        return "VECTOR6INT32"
    if name in int32 or "int_register" in name:
        return "INT32"
    if name in uint64:
        return "UINT64"
    if name in uint32:
        return "UINT32"
    if name in uint8:
        return "UINT8"
    if "bit_register_" in name:
        return "BOOL"
    return "DOUBLE"  # timestamp, voltages, currents, analog values, double registers, ...


_FORMATS = {
    "VECTOR6D": "6d",
    "VECTOR3D": "3d",
    "VECTOR6INT32": "6i",
    "INT32": "i",
    "UINT64": "Q",
    "UINT32": "I",
    "UINT8": "B",
    "BOOL": "?",
    "DOUBLE": "d",
}


@dataclass(frozen=True)
class ControllerFaults:
    """Faults to inject (moves counted from 1 over the controller's life; 0: never).

    ``drop_at_move``: a network outage of ``outage_s`` when that move command arrives
    (every connection drops, none is accepted meanwhile); ``protective_stop_at_move``:
    that move stops halfway with a protective stop (the safety bits say so; the program
    stops)."""

    drop_at_move: int = 0
    protective_stop_at_move: int = 0
    outage_s: float = 3.0


def write_pgm(path: str | os.PathLike[str], image: NDArray[np.uint8]) -> None:
    """Write a grey frame as binary PGM, atomically (a reader never sees half a frame)."""
    path = Path(path)
    H, W = image.shape
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        f.write(f"P5\n{W} {H}\n255\n".encode("ascii"))
        f.write(np.ascontiguousarray(image, dtype=np.uint8).tobytes())
    os.replace(tmp, path)


class _Server(socketserver.ThreadingTCPServer):
    allow_reuse_address = True
    daemon_threads = True


class LoopbackController:
    """The controller: a twin's robot (and imager) behind UR's network protocols.

    Parameters
    ----------
    robot : twin.robot.SimRobot
    imager : twin.imager.SimImager or None
        Renders the frame after each settled move into ``frame_path``.
    host : str
        Address to listen on (127.0.0.x for tests).
    tcp_offset : (6,) [x, y, z, rx, ry, rz], metres and a rotation vector
        The active TCP offset, as a controller's installation sets it: the reported
        ``actual_TCP_pose`` and a ``moveL`` target are of the TCP, not of the flange.
    """

    def __init__(
        self,
        robot,
        imager=None,
        frame_path: str | os.PathLike[str] | None = None,
        host: str = "127.0.0.1",
        faults: ControllerFaults = ControllerFaults(),
        operator: Callable[[list[str]], str] | None = None,
        tcp_offset: Sequence[float] = (0.0,) * 6,
    ) -> None:
        self.robot = robot
        self.tcp_offset = tuple(float(v) for v in tcp_offset)
        self.operator = operator
        self.imager = imager
        self.frame_path = Path(frame_path) if frame_path else None
        self.host = host
        self.faults = faults
        self._lock = threading.Lock()
        self._inputs: dict[str, Any] = {}
        self._out_int = [0] * 48
        self._out_double = [0.0] * 48
        self._runtime = _RUNTIME_STOPPED
        self._safety = _SAFETY_NORMAL
        self._moves = 0
        self._busy = False
        self._t0 = time.monotonic()
        self._servers: list[_Server] = []
        self._connections: set[socket.socket] = set()
        self._stop = threading.Event()
        self.frames_written = 0
        self._update_reading()
        if self.frame_path is not None and imager is not None:
            self._render()

    # ------------------------------------------------------------------ lifecycle

    def start(self, executor: bool = True) -> None:
        """Listen on the three ports (raises :class:`UscalError` if one is taken)."""
        handlers = {
            RTDE_PORT: self._rtde_handler(),
            DASHBOARD_PORT: self._dashboard_handler(),
            SCRIPT_PORT: self._script_handler(),
        }
        for port, handler in handlers.items():
            try:
                server = _Server((self.host, port), handler)
            except OSError as e:
                self.close()
                raise UscalError(
                    f"cannot listen on {self.host}:{port} ({e.strerror}); is another "
                    "controller running there? Use another 127.0.0.x address"
                ) from None
            self._servers.append(server)
            # A short poll interval: an outage closes the ports within 50 ms.
            threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
        if executor:
            threading.Thread(target=self._execute_loop, daemon=True).start()

    def close(self) -> None:
        self._stop.set()
        self._drop_connections()
        for s in self._servers:
            s.shutdown()
            s.server_close()
        self._servers.clear()

    def serve_forever(self) -> None:
        """Serve until :meth:`close` (starting first if :meth:`start` was not called)."""
        if not self._servers:
            self.start()
        try:
            while not self._stop.wait(0.5):
                pass
        finally:
            self.close()

    def _outage(self) -> None:
        """A network outage: every connection drops and none is accepted for
        ``faults.outage_s`` (the client's reconnection attempts fail, as on a pulled
        cable); then the controller listens again."""
        for s in self._servers:
            s.shutdown()
            s.server_close()
        self._servers.clear()
        self._drop_connections()

        def back() -> None:
            if not self._stop.wait(self.faults.outage_s):
                self.start(executor=False)

        threading.Thread(target=back, daemon=True).start()

    def _drop_connections(self) -> None:
        with self._lock:
            conns = list(self._connections)
            self._connections.clear()
        for c in conns:
            with contextlib.suppress(OSError):
                c.shutdown(socket.SHUT_RDWR)
            c.close()

    def _track(self, conn: socket.socket) -> None:
        # Every packet leaves at once, as the controller's do: with Nagle's algorithm a
        # 500 Hz stream of small packets waits for the client's delayed acknowledgements,
        # and the state it carries arrives 20-40 ms late.
        with contextlib.suppress(OSError):
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            self._connections.add(conn)

    # ------------------------------------------------------------------ state

    def _update_reading(self) -> None:
        """What the controller reports, refreshed after each motion (the arm is still in
        between; the stream packs these cached tuples hundreds of times a second)."""
        r = self.robot.read()
        T_ee_tcp = se3.matrix_from_pose6(self.tcp_offset)
        q, pose = (
            tuple(float(v) for v in r.q),
            tuple(float(v) for v in se3.pose6_from_matrix(r.T_base_ee @ T_ee_tcp)),
        )
        with self._lock:
            self._q, self._pose = q, pose

    def _getter(self, name: str) -> Callable[[], Any]:
        """How to read an output variable's current value. Resolved once per output
        recipe, not per packet: two sessions stream dozens of variables at 500 Hz, and
        the name lookups per packet were most of the controller's CPU."""
        if name in ("actual_q", "target_q", "actual_target_q"):
            return lambda: self._q
        if name in ("actual_TCP_pose", "target_TCP_pose"):
            return lambda: self._pose
        if name == "timestamp":
            return lambda: time.monotonic() - self._t0
        if name == "runtime_state":
            return lambda: self._runtime
        if name == "robot_status_bits":
            return lambda: (
                _ROBOT_POWER_ON
                | (_ROBOT_PROGRAM_RUNNING if self._runtime == _RUNTIME_PLAYING else 0)
            )
        if name == "safety_status_bits":
            return lambda: self._safety
        if name == "safety_mode":
            return lambda: 3 if self._safety & _SAFETY_PROTECTIVE_STOP else 1
        if name.startswith("output_int_register_"):
            i = int(name.rsplit("_", 1)[1])
            return lambda: self._out_int[i]
        if name.startswith("output_double_register_"):
            i = int(name.rsplit("_", 1)[1])
            return lambda: self._out_double[i]
        if name == "robot_mode":
            constant: Any = 7  # RUNNING
        elif name == "joint_mode":
            constant = (253,) * 6  # RUNNING
        elif name == "speed_scaling" or name == "target_speed_fraction":
            constant = 1.0
        else:
            kind = _rtde_type(name)
            constant = (0,) * int(_FORMATS[kind][0]) if kind.startswith("VECTOR") else 0
        return lambda: constant

    def _register(self, kind: str, i: int, default: Any = 0) -> Any:
        """An input register as the client last wrote it (either register range)."""
        for base in (0, 24):
            key = f"input_{kind}_register_{i + base}"
            if key in self._inputs:
                return self._inputs[key]
        return default

    # --------------------------------------------------------------- executor

    def _render(self) -> None:
        if self.imager is None or self.frame_path is None:
            return
        write_pgm(self.frame_path, self.imager.grab().image)
        self.frames_written += 1

    def _execute_loop(self) -> None:
        """The "program": waits for commands in the input registers and runs them."""
        while not self._stop.wait(0.002):
            with self._lock:
                playing = self._runtime == _RUNTIME_PLAYING
                cmd = int(self._register("int", 0)) if playing else _NO_CMD
                state = self._out_int[0]
            if not playing:
                continue
            if cmd == _NO_CMD:
                if state != 1:
                    with self._lock:
                        self._out_int[0] = 1  # ready
                continue
            if state != 1:
                continue  # done; waiting for the client to clear the command
            self._run(cmd)

    def _run(self, cmd: int) -> None:
        t_cmd = time.monotonic()
        with self._lock:
            self._out_int[0] = 0  # busy
            args = [float(self._register("double", i, 0.0)) for i in range(8)]
        if cmd in (_MOVEJ, _MOVEL):
            self._moves += 1
            if self.faults.drop_at_move and self._moves == self.faults.drop_at_move:
                log.warning(
                    "fault: network outage of %g s at move %d", self.faults.outage_s, self._moves
                )
                self._outage()
                return
            if self.faults.protective_stop_at_move == self._moves:
                log.warning("fault: protective stop at move %d", self._moves)
                self._protective_stop()
                return
            try:
                if cmd == _MOVEJ:
                    self.robot.move_joints(np.array(args[:6]))
                else:  # the target is the TCP's pose
                    T_tcp_ee = se3.invert(se3.matrix_from_pose6(self.tcp_offset))
                    self.robot.move_to(se3.matrix_from_pose6(args[:6]) @ T_tcp_ee)
            except UscalError as e:  # unreachable or a collision: the arm stops
                log.warning("move %d refused: %s", self._moves, e)
                self._protective_stop()
                return
            self._update_reading()
            self._render()
            # Signal done only once every stream has carried the settled pose: a client
            # reading actual_q right after the move (another RTDE session) gets the new one.
            time.sleep(3.0 / _MAX_STREAM_HZ)
        elif cmd == _SET_TCP:
            log.warning("TCP offset set to %s", np.round(args[:6], 6).tolist())
            self.tcp_offset = tuple(args[:6])
            self._update_reading()
        elif cmd == _GET_TCP_OFFSET:
            with self._lock:
                self._out_double[:6] = list(self.tcp_offset)
        elif cmd == _STOP_SCRIPT:
            with self._lock:
                self._runtime = _RUNTIME_STOPPED
                self._out_int[0] = 2
            return
        with self._lock:
            self._out_int[0] = 2  # done
        log.debug("command %d took %.1f ms", cmd, 1e3 * (time.monotonic() - t_cmd))

    def _protective_stop(self) -> None:
        with self._lock:
            self._safety = _SAFETY_PROTECTIVE_STOP
            self._runtime = _RUNTIME_STOPPED

    # --------------------------------------------------------------- handlers

    def _dashboard_handler(self):
        ctl = self

        class Dashboard(socketserver.StreamRequestHandler):
            def handle(self) -> None:
                ctl._track(self.request)
                self.wfile.write(b"Connected: Universal Robots Dashboard Server\n")
                for raw in self.rfile:
                    line = raw.decode("utf-8", "replace").strip()
                    self.wfile.write((ctl._dashboard(line) + "\n").encode())

        return Dashboard

    def _dashboard(self, line: str) -> str:
        cmd = line.lower()
        protective = bool(self._safety & _SAFETY_PROTECTIVE_STOP)
        answers = {
            "polyscopeversion": _POLYSCOPE,
            "get serial number": "20235500001",
            "is in remote control": "true",
            "robotmode": "Robotmode: RUNNING",
            "safetymode": "Safetymode: " + ("PROTECTIVE_STOP" if protective else "NORMAL"),
            "safetystatus": "Safetystatus: " + ("PROTECTIVE_STOP" if protective else "NORMAL"),
            "programstate": (
                "PLAYING urscript" if self._runtime == _RUNTIME_PLAYING else "STOPPED urscript"
            ),
            "running": "Program running: "
            + ("true" if self._runtime == _RUNTIME_PLAYING else "false"),
            "power on": "Powering on",
            "brake release": "Brake releasing",
            "get robot model": "UR3",
        }
        if cmd == "unlock protective stop":
            with self._lock:
                self._safety = _SAFETY_NORMAL
            return "Protective stop releasing"
        if cmd.startswith("twin ") and self.operator is not None:
            # The emulated operator (hand-guiding, tool changes) of the loopback rig.
            with self._lock:
                busy = self._out_int[0] == 0 and self._runtime == _RUNTIME_PLAYING
            if busy:
                return "twin: the arm is moving"
            try:
                answer = self.operator(line.split()[1:])
            except (UscalError, ValueError, KeyError, IndexError) as e:
                return f"twin: error: {e}"
            self._update_reading()
            # Answer once the streams have carried the new pose (a person holding the
            # stylus still before pressing Enter gives the same).
            time.sleep(5.0 / _MAX_STREAM_HZ)
            return answer
        if cmd == "close safety popup":
            return "closing safety popup"
        if cmd == "stop":
            with self._lock:
                self._runtime = _RUNTIME_STOPPED
            return "Stopped"
        return answers.get(cmd, f"could not understand: '{line}'")

    def _script_handler(self):
        ctl = self

        class Script(socketserver.BaseRequestHandler):
            def handle(self) -> None:
                ctl._track(self.request)
                self.request.settimeout(0.1)
                buffer = b""
                while not ctl._stop.is_set():
                    try:
                        chunk = self.request.recv(65536)
                    except TimeoutError:
                        if buffer:
                            ctl._program_received(buffer)
                            buffer = b""
                        continue
                    except OSError:
                        return
                    if not chunk:
                        if buffer:
                            ctl._program_received(buffer)
                        return
                    buffer += chunk

        return Script

    def _program_received(self, program: bytes) -> None:
        log.info("program received (%d bytes): running", len(program))
        with self._lock:
            if self._safety & _SAFETY_PROTECTIVE_STOP:
                return  # a stopped arm does not start programs
            self._out_int[0] = 0
            self._inputs.clear()  # a new program: no command of an earlier session is pending
            self._runtime = _RUNTIME_PLAYING

    def _rtde_handler(self):
        ctl = self

        class Rtde(socketserver.BaseRequestHandler):
            def handle(self) -> None:
                ctl._track(self.request)
                _RtdeSession(ctl, self.request).run()

        return Rtde


class _RtdeSession:
    """One RTDE connection: its recipes and its output stream."""

    def __init__(self, ctl: LoopbackController, sock: socket.socket) -> None:
        self.ctl = ctl
        self.sock = sock
        self.send_lock = threading.Lock()
        self.outputs: list[str] = []
        self.output_fmt = ""
        self.getters: list[Callable[[], Any]] = []
        self.period = 1.0 / _MAX_STREAM_HZ
        self.inputs: dict[int, tuple[list[str], str]] = {}
        self.streaming = threading.Event()
        self.closed = threading.Event()

    def send(self, kind: int, payload: bytes = b"") -> None:
        with self.send_lock:
            self.sock.sendall(struct.pack(">HB", len(payload) + 3, kind) + payload)

    def recv_exact(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise ConnectionError
            data += chunk
        return data

    def run(self) -> None:
        threading.Thread(target=self.stream, daemon=True).start()
        try:
            while True:
                size, kind = struct.unpack(">HB", self.recv_exact(3))
                self.handle(kind, self.recv_exact(size - 3))
        except (ConnectionError, OSError):
            pass
        except (struct.error, UnicodeDecodeError, ValueError) as e:
            log.warning("malformed RTDE packet (%s): connection closed", e)
        finally:
            self.closed.set()

    def handle(self, kind: int, payload: bytes) -> None:
        if kind == _V:
            self.send(_V, struct.pack(">B", 1))
        elif kind == _v:
            self.send(_v, struct.pack(">IIII", *_CONTROLLER_VERSION))
        elif kind == _O:
            (hz,) = struct.unpack(">d", payload[:8])
            self.outputs = [n for n in payload[8:].decode().split(",") if n]
            types = [_rtde_type(n) for n in self.outputs]
            self.output_fmt = ">B" + "".join(_FORMATS[t] for t in types)
            self.getters = [self.ctl._getter(n) for n in self.outputs]
            self.period = 1.0 / min(max(hz, 1.0), _MAX_STREAM_HZ)
            self.send(_O, struct.pack(">B", 1) + ",".join(types).encode())
        elif kind == _I:
            names = [n for n in payload.decode().split(",") if n]
            types = [_rtde_type(n) for n in names]
            recipe = len(self.inputs) + 1
            self.inputs[recipe] = (names, ">" + "".join(_FORMATS[t] for t in types))
            self.send(_I, struct.pack(">B", recipe) + ",".join(types).encode())
        elif kind == _S:
            self.streaming.set()
            self.send(_S, struct.pack(">B", 1))
        elif kind == _P:
            self.streaming.clear()
            self.send(_P, struct.pack(">B", 1))
        elif kind == _U:
            recipe = payload[0]
            if recipe not in self.inputs:
                return
            names, fmt = self.inputs[recipe]
            if struct.calcsize(fmt) != len(payload) - 1:
                log.warning(
                    "input recipe %d: %d bytes, expected %d",
                    recipe,
                    len(payload) - 1,
                    struct.calcsize(fmt),
                )
                return
            values = struct.unpack(fmt, payload[1:])
            with self.ctl._lock:
                self.ctl._inputs.update(zip(names, values, strict=True))

    def stream(self) -> None:
        while not self.closed.is_set() and not self.ctl._stop.is_set():
            if not self.streaming.wait(0.05) or not self.getters:
                continue
            t = time.monotonic()
            values: list[Any] = []
            with self.ctl._lock:
                for get in self.getters:
                    v = get()
                    values.extend(v if isinstance(v, tuple) else (v,))
            try:
                self.send(_U, struct.pack(self.output_fmt, 1, *values))
            except OSError:
                return
            time.sleep(max(0.0, self.period - (time.monotonic() - t)))
