"""The error hierarchy: every failure a user can cause or meet is a :class:`UscalError`.

The CLI turns these into one line on stderr and exit code 2 (``--debug`` shows the
traceback). Anything else escaping is a bug in uscal, not a user mistake.
"""

from __future__ import annotations

__all__ = [
    "CalibrationError",
    "CollisionError",
    "DatasetError",
    "FrameGrabberError",
    "LocalizationError",
    "RobotConnectionError",
    "RobotSetupError",
    "RobotStoppedError",
    "ScenarioError",
    "TransformError",
    "UnreachablePoseError",
    "UscalError",
]


class UscalError(Exception):
    """Root of all errors uscal raises on purpose."""


class ScenarioError(UscalError):
    """A scenario (or hw config, or sweep) file or override is invalid.

    The message names the file, the key path, the offending value and what is allowed.
    """

    def __init__(
        self,
        message: str,
        *,
        source: str | None = None,
        key: str | None = None,
        value: object = None,
        allowed: str | None = None,
        line: int | None = None,
    ) -> None:
        self.source, self.key, self.value, self.allowed, self.line = (
            source,
            key,
            value,
            allowed,
            line,
        )
        where = source or "<scenario>"
        if line is not None:
            where += f":{line}"
        parts = [where]
        if key is not None:
            parts.append(f"{key} = {value!r}" if value is not None else key)
        text = ": ".join([*parts, message])
        if allowed:
            text += f" (allowed: {allowed})"
        super().__init__(text)


class UnreachablePoseError(UscalError):
    """No joint configuration reaches the requested pose (or all violate joint limits)."""


class CollisionError(UscalError):
    """A planned configuration puts the tool or arm into the phantom or the tank."""


class LocalizationError(UscalError):
    """A sphere could not be localized in a sweep."""


class CalibrationError(UscalError):
    """The calibration problem is ill-posed or did not converge."""


class DatasetError(UscalError):
    """A dataset on disk is missing, malformed or inconsistent."""


class TransformError(UscalError):
    """A matrix that must be a rigid transform is not one (shape, non-finite entries,
    last row, a rotation block that is not a proper rotation)."""


class RobotConnectionError(UscalError):
    """The robot controller cannot be reached, or the connection was lost."""


class RobotSetupError(UscalError):
    """The controller is set up in a way the method cannot use (e.g. a non-zero TCP
    offset, which makes every reported pose the TCP's instead of the flange's)."""


class RobotStoppedError(UscalError):
    """The robot stopped on its own: a protective or emergency stop, or its program ended."""


class FrameGrabberError(UscalError):
    """The frame grabber cannot be opened or delivers no frames."""
