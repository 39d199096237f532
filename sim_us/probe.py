"""Settings of the probe/scanner and of the propagation medium."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

__all__ = ["MediumConfig", "ProbeConfig"]


@dataclass(frozen=True)
class ProbeConfig:
    """Linear-array probe and scanner settings (defaults: the paper's L8-18i-D probe)."""

    width_mm: float = field(
        default=38.0, metadata={"doc": "Lateral field of view.", "gt": 1, "le": 200}
    )
    depth_mm: float = field(
        default=40.0,
        metadata={"doc": "Imaging depth from the transducer face.", "gt": 1, "le": 300},
    )
    pixel_spacing_mm: tuple[float, float] = field(
        default=(0.1, 0.1),
        metadata={"doc": "Output pixel spacing (lateral sx, axial sy).", "gt": 0.005, "le": 2},
    )
    f_mhz: float = field(default=13.0, metadata={"doc": "Centre frequency.", "gt": 0.5, "le": 60})
    lateral_fwhm_mm: float = field(
        default=0.7, metadata={"doc": "Lateral resolution (PSF FWHM).", "gt": 0, "le": 10}
    )
    axial_fwhm_mm: float = field(
        default=0.35, metadata={"doc": "Axial resolution (PSF FWHM).", "gt": 0, "le": 10}
    )
    assumed_speed_m_s: float = field(
        default=1540.0,
        metadata={"doc": "Speed of sound the scanner assumes for display.", "ge": 1000, "le": 2000},
    )
    gain_db: float = field(
        default=0.0, metadata={"doc": "Overall receive gain.", "ge": -60, "le": 60}
    )
    dynamic_range_db: float = field(
        default=60.0, metadata={"doc": "Log-compression dynamic range.", "ge": 10, "le": 120}
    )

    @property
    def image_shape(self) -> tuple[int, int]:
        """(rows, cols) of a frame: depth / sy + 1 by width / sx + 1."""
        sx, sy = self.pixel_spacing_mm
        return round(self.depth_mm / sy) + 1, round(self.width_mm / sx) + 1


@dataclass(frozen=True)
class MediumConfig:
    """The medium the probe images through (the tank's water, or gel)."""

    kind: Literal["water", "gel"] = field(
        default="water", metadata={"doc": "Propagation medium around the phantom."}
    )
    temperature_c: float = field(
        default=20.0,
        metadata={"doc": "Water temperature; sets the true speed of sound.", "ge": 0, "le": 60},
    )
