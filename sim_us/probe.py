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
    bandwidth_pct: float = field(
        default=65.0,
        metadata={
            "doc": "Pulse-echo -6 dB fractional bandwidth (datasheet): sets the pulse, "
            "hence the axial resolution.",
            "gt": 5,
            "lt": 200,
        },
    )
    pulse_cycles: float = field(
        default=1.0,
        metadata={"doc": "Cycles of the transmit excitation (a sine at f_mhz).", "gt": 0, "le": 20},
    )
    pitch_mm: float = field(
        default=0.2,
        metadata={"doc": "Element pitch (datasheet).", "gt": 0.01, "le": 2},
    )
    kerf_mm: float = field(
        default=0.02,
        metadata={
            "doc": "Gap between elements; the element width is pitch - kerf (its "
            "directivity sets the f-number).",
            "ge": 0,
            "lt": 1,
        },
    )
    active_elements: int = field(
        default=64,
        metadata={
            "doc": "Elements that fire and receive for one scanline at most (the "
            "scanner's channel count): caps the aperture, hence the lateral resolution "
            "at depth.",
            "ge": 2,
            "le": 1024,
        },
    )
    f_number: float | None = field(
        default=None,
        metadata={
            "doc": "Transmit/receive f-number (depth / aperture) of the scanner; null = "
            "where the element's directivity falls to 0.71 (2.3 for 0.18 mm elements at "
            "13 MHz).",
            "gt": 0.3,
            "le": 20,
        },
    )
    plane_waves_deg: tuple[float, ...] = field(
        default=(),
        metadata={
            "doc": "Plane-wave imaging: the steering angles of the plane waves every "
            "frame is compounded from (coherently, each fired by all active_elements; "
            "e.g. [-8, 0, 8]), symmetric about 0. [] = a scanner that focuses its "
            "transmit at every depth, line by line (the clinical default). Each angle's "
            "transmit is unfocused: the lateral beam is wider and its compounding tails "
            "stand beside an echo (sim_us.transducer).",
            "ge": -30,
            "le": 30,
        },
    )
    apodization: Literal["rect", "hann"] = field(
        default="rect",
        metadata={
            "doc": "Weighting of the apertures, transmit and receive: 'rect' uniform (the "
            "focused scanner's), 'hann' a Hann window across each (the receive aperture's "
            "f-number width; a plane wave's whole active aperture): lower side lobes, a "
            "wider main lobe; plane-wave sequences use it to keep the edge waves of the "
            "transmit aperture and a specular echo's line out of the image."
        },
    )
    lateral_fwhm_mm: float | None = field(
        default=None,
        metadata={
            "doc": "Stated lateral resolution (two-way PSF FWHM) for a probe measured on "
            "a wire: a Gaussian beam of this width at every depth. null = the array's "
            "own beam from the transducer figures above (depth-dependent, side lobes "
            "included; sim_us.transducer).",
            "gt": 0,
            "le": 10,
        },
    )
    axial_fwhm_mm: float | None = field(
        default=None,
        metadata={
            "doc": "Stated axial resolution (PSF FWHM); null = the pulse's envelope from "
            "f_mhz, bandwidth_pct and pulse_cycles.",
            "gt": 0,
            "le": 10,
        },
    )
    elevation_aperture_mm: float = field(
        default=4.0,
        metadata={
            "doc": "Elevation aperture height (element height, datasheet).",
            "gt": 0.1,
            "le": 30,
        },
    )
    elevation_focus_mm: float = field(
        default=18.0, metadata={"doc": "Depth of the elevation (lens) focus.", "gt": 1, "le": 200}
    )
    slice_thickness_mm: float | None = field(
        default=None,
        metadata={
            "doc": "Stated slice thickness (elevation FWHM) at the lens focus: a geometric "
            "beam, sqrt(ST² + (H |y - F| / F)²). null = the lensed aperture's diffraction "
            "(thinnest in front of the focus for a weak lens; sim_us.transducer).",
            "gt": 0.05,
            "le": 10,
        },
    )
    scanline_spacing_mm: float | None = field(
        default=None,
        metadata={
            "doc": "Spacing of the scanlines (rounded to whole pixels; the display "
            "interpolates between them). null = half the narrowest lateral FWHM in the "
            "image, down to whole pixels (the beam's Nyquist spacing: a line every 0.1 mm "
            "for the paper probe at 0.1 mm pixels).",
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
            "speed of sound (from medium.temperature_c) over the assumed one (the tool's "
            "recommended practice). Off, water at 20 °C (1482 m/s) reads 3.9 % deep at "
            "the scanner's 1540 m/s; the paper does not say it corrects it."
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
        default=-90.0,
        metadata={
            "doc": "Electronic noise (rms) at the receiver input, before gain and TGC, "
            "relative to the echo of a perfect reflector at the elevation focus. -90: a "
            "13 MHz probe shows "
            "tissue speckle (-38 dB) through 0.5 dB/cm/MHz to ≈ 4 cm, as real ones do "
            "(4-6 cm); in water it lies below the display unless the gain is raised.",
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
    continuous_elevation: bool = field(
        default=True,
        metadata={
            "doc": "Integrate the echo continuously over the elevation beam: each sub-plane "
            "stands for a slab of elevation over which the surface's depth changes along "
            "its tangent plane (slope from the hit normal), so its echo is spread over that "
            "depth interval with the beam profile (piecewise-linear in elevation). false: "
            "point echoes per sub-plane (discrete arcs past the elevation focus)."
        },
    )
    surface_speckle: bool = field(
        default=True,
        metadata={
            "doc": "Draw the incoherent share of each surface echo (what a rough or "
            "obliquely met surface returns besides its specular reflection) as speckle: "
            "random-phase scatterers on the surface, summed as waves and blurred by the "
            "PSF, so an oblique face shows a granular, broken line as on a real scanner; the "
            "mirror part of the echo stays smooth. Its mean brightness is the smooth "
            "model's. On by default: the phantoms are printed (layer lines, roughness); "
            "off draws every surface echo smooth, a lathe-turned part's."
        },
    )
    side_lobe_db: float | Literal["array"] | None = field(
        default="array",
        metadata={
            "doc": "Lateral side lobes. 'array': the array's own (the derived beam's "
            "profile; with a stated lateral_fwhm_mm, copies at the level the array gives). "
            "A number: copies of every echo at the first side lobe's offset (1.61 × the "
            "lateral FWHM of a two-way sinc² beam) at this two-way level relative to the "
            "main lobe (dB): -26.5 for a narrow-band rectangular aperture, ≈ -33 "
            "broadband (the reference), below -40 apodized. null = none (the main lobe "
            "alone).",
            "ge": -100,
            "le": -6,
        },
    )
    ring_down_cycles: float = field(
        default=0.0,
        metadata={
            "doc": "Transducer ring-down below echoes: the envelope behind the main pulse "
            "decays as exp(-f t / N), N this value in cycles of the centre frequency "
            "(Q = π N), N c / (2 f) of displayed depth per e-fold (0.12 mm at 13 MHz for "
            "N = 2); it shows where it exceeds the PSF's trailing edge. 0 = off. "
            "Plausible 1-3 (broadband imaging arrays, Q ≈ 3-10: 2-3 visible cycles, "
            "≈ 0.1-0.3 mm at 13 MHz; transducer design references).",
            "ge": 0,
            "le": 10,
        },
    )
    pixel_scale_error_pct: tuple[float, float] = field(
        default=(0.0, 0.0),
        metadata={
            "doc": "Scale error of the reported pixel spacing (lateral, axial), percent, "
            "as a caliper error: distances read off a frame with its reported spacing are "
            "e % too long (the true spacing is spacing / (1 + e / 100)), so with e > 0 "
            "things look e % larger and deeper. 0 = off. Caliper tolerances in vendor "
            "manuals ±2-5 % (±2-3 % axial, ±5 % lateral); est. σ ≈ 0.5 % per axis for "
            "one scanner.",
            "ge": -10,
            "le": 10,
        },
    )
    image_origin_offset_mm: float = field(
        default=0.0,
        metadata={
            "doc": "Depth of the image's row 0 below the transducer face (lens delay or "
            "stand-off not compensated, or a frame-grabber crop): echoes appear this much "
            "shallower; the pipeline takes row 0 at the face. 0 = off. Est. ±0.5 mm "
            "(lens ≈ 1 mm of silicone at ≈ 1000 m/s, mostly compensated by the scanner; "
            "a grabber crop off by a few pixels).",
            "ge": -5,
            "le": 5,
        },
    )
    lateral_offset_mm: float = field(
        default=0.0,
        metadata={
            "doc": "Lateral position (along +x, increasing column) of the image's centre "
            "column off the centre of the transducer face (array placement in the "
            "housing, grabber crop): echoes appear this much further toward column 0; "
            "the pipeline takes it at the centre. 0 = off. Est. ±0.5 mm (a few element "
            "pitches of 0.1-0.2 mm, or grabber pixels).",
            "ge": -5,
            "le": 5,
        },
    )

    @property
    def plane_waves_symmetric(self) -> bool:
        """Whether the plane waves' steering angles come in ± pairs (the beam tables are
        symmetric about the scanline; no plane waves is symmetric)."""
        return sorted(self.plane_waves_deg) == sorted(-a for a in self.plane_waves_deg)

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
    temperature_drift_c_per_h: float = field(
        default=0.0,
        metadata={
            "doc": "Drift of the true water temperature during the session (°C per hour, "
            "negative = cooling): T(t) = temperature_c + rate · t, t the session clock, "
            "the first-order part of the water relaxing toward room temperature "
            "(evaporative cooling keeps it 1-2 °C below). The speed of sound and "
            "attenuation follow T(t); the pipeline keeps correcting with temperature_c. "
            "0 = off. Est. ±0.2-1 °C/h (no published figure).",
            "ge": -5,
            "le": 5,
        },
    )

    def temperature_at(self, clock_s: float) -> float:
        """True medium temperature (°C) ``clock_s`` seconds into the session."""
        if self.temperature_drift_c_per_h == 0.0:
            return self.temperature_c
        return self.temperature_c + self.temperature_drift_c_per_h * clock_s / 3600.0
