"""The ``ur_rtde`` client in a process of its own.

After a lost connection the client library keeps a reconnect thread running and, in
version 1.6, crashes the interpreter at exit (a segmentation fault, measured in about
half of the runs whatever the order of ``disconnect`` calls). Its constructors also hold
the GIL while they block. So the interfaces live in a child process: the adapter sends
it calls through a pipe, and when the connection is lost the child is simply ended —
whatever the library does there cannot take the acquisition (or its error message)
down with it.
"""

from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from calib.errors import RobotConnectionError

__all__ = ["RtdeProcess"]

_CALL_TIMEOUT_S = 600.0  # a move at the slowest speed over the largest step


def _serve(conn: Connection, host: str) -> None:  # pragma: no cover - child process
    import rtde_control
    import rtde_receive

    try:
        receive = rtde_receive.RTDEReceiveInterface(host)
        control = rtde_control.RTDEControlInterface(host)
    except RuntimeError as e:
        conn.send(("error", str(e)))
        return
    conn.send(("ok", None))
    interfaces = {"control": control, "receive": receive}
    while True:
        try:
            target, method, args = conn.recv()
        except EOFError:
            return
        if target == "close":
            for iface in (control, receive):
                try:
                    if iface is control and iface.isConnected():
                        iface.stopScript()
                    iface.disconnect()
                except RuntimeError:
                    pass
            conn.send(("ok", None))
            return
        try:
            conn.send(("ok", getattr(interfaces[target], method)(*args)))
        except RuntimeError as e:
            conn.send(("error", str(e)))


class RtdeProcess:
    """``RTDEReceiveInterface`` and ``RTDEControlInterface`` of one controller, in a
    child process; :meth:`call` forwards a method call and returns its result."""

    def __init__(self, host: str) -> None:
        self.host = host
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, host), daemon=True)
        self._proc.start()
        child.close()
        status, detail = self._receive(60.0, "connecting")
        if status != "ok":
            self.kill()
            raise RobotConnectionError(f"robot controller {host}: {detail}")

    def call(
        self,
        target: str,
        method: str,
        *args: Any,
        alive: Callable[[], bool] | None = None,
        grace_s: float = 3.0,
        timeout_s: float = _CALL_TIMEOUT_S,
    ) -> Any:
        """``target`` "control" or "receive"; raises :class:`RobotConnectionError` when
        the client fails or its process is gone. While waiting, ``alive()`` is asked
        about once a second (e.g. whether the controller still answers on the network):
        false for ``grace_s`` ends the call — the client library itself may wait forever
        for a controller that is gone. No reply within ``timeout_s`` ends it too."""
        try:
            self._conn.send((target, method, args))
        except (OSError, EOFError):
            self.kill()
            raise RobotConnectionError(f"robot controller {self.host}: client gone") from None
        deadline = time.monotonic() + timeout_s
        if alive is not None:
            down_since = None
            while not self._conn.poll(1.0) and time.monotonic() < deadline:
                if alive():
                    down_since = None
                    continue
                down_since = down_since or time.monotonic()
                if time.monotonic() - down_since >= grace_s:
                    self.kill()
                    raise RobotConnectionError(
                        f"robot controller {self.host}: no answer on the network for "
                        f"{grace_s:g} s while {method}"
                    )
        status, value = self._receive(max(deadline - time.monotonic(), 0.0), method)
        if status != "ok":
            raise RobotConnectionError(f"robot controller {self.host}: {value}")
        return value

    def close(self) -> None:
        """Stop the script and disconnect politely; end the process in any case."""
        if self._proc.is_alive():
            try:
                self._conn.send(("close", "", ()))
                if self._conn.poll(5.0):
                    self._conn.recv()
            except (OSError, EOFError):
                pass
        self.kill()

    def kill(self) -> None:
        if self._proc.is_alive():
            self._proc.kill()
        self._proc.join(5.0)
        self._conn.close()

    def _receive(self, timeout: float, what: str) -> tuple[str, Any]:
        try:
            if not self._conn.poll(timeout):
                self.kill()
                raise RobotConnectionError(
                    f"robot controller {self.host}: connection lost (no reply to {what} in time)"
                )
            return self._conn.recv()
        except (OSError, EOFError):
            self.kill()
            raise RobotConnectionError(
                f"robot controller {self.host}: the client stopped while {what}"
            ) from None
