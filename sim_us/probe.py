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
    elevation_aperture_mm: float = field(
        default=4.0,
        metadata={
            "doc": "Elevation aperture height: the slice thickness at the face.",
            "gt": 0.1,
            "le": 30,
        },
    )
    elevation_focus_mm: float = field(
        default=18.0, metadata={"doc": "Depth of the elevation (lens) focus.", "gt": 1, "le": 200}
    )
    slice_thickness_mm: float = field(
        default=0.7,
        metadata={"doc": "Slice thickness (elevation FWHM) at the focus.", "gt": 0.05, "le": 10},
    )
    scanline_spacing_mm: float = field(
        default=0.2,
        metadata={
            "doc": "Spacing of the simulated scanlines (rounded to whole pixels; the "
            "lateral PSF fills in between).",
            "gt": 0.005,
            "le": 2,
        },
    )
    elevation_planes: int = field(
        default=9,
        metadata={
            "doc": "Elevation sub-planes rays are cast in (partial-volume sum).",
            "ge": 1,
            "le": 101,
        },
    )
    sound_speed_correction: bool = field(
        default=True,
        metadata={
            "doc": "Pipeline: rescale the displayed axial spacing by the medium's true "
            "speed of sound (from medium.temperature_c) over the assumed one."
        },
    )
    assumed_speed_m_s: float = field(
        default=1540.0,
        metadata={"doc": "Speed of sound the scanner assumes for display.", "ge": 1000, "le": 2000},
    )
    gain_db: float = field(
        default=0.0, metadata={"doc": "Overall receive gain.", "ge": -60, "le": 60}
    )
    tgc_db_per_cm: float = field(
        default=0.0,
        metadata={
            "doc": "Time-gain compensation slope (gain added per cm of depth).",
            "ge": 0,
            "le": 20,
        },
    )
    noise_db: float = field(
        default=-55.0,
        metadata={
            "doc": "Electronic noise (rms) relative to the echo of a perfect reflector.",
            "ge": -200,
            "le": 0,
        },
    )
    reverberation: bool = field(
        default=True,
        metadata={"doc": "Add the probe-face reverberation of strong flat echoes (floor)."},
    )
    dynamic_range_db: float = field(
        default=60.0, metadata={"doc": "Log-compression dynamic range.", "ge": 10, "le": 120}
    )

    @property
    def spacing_m(self) -> tuple[float, float]:
        """(sx, sy) in metres."""
        sx, sy = self.pixel_spacing_mm
        return sx * 1e-3, sy * 1e-3

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
