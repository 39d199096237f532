"""Acoustic materials: impedance, speed, attenuation, backscatter, surface behaviour.

Numbers: ``notes/ultrasound-physics.md`` of the project. Water's speed of sound follows
Marczak (1997); its attenuation goes with f² (2.17e-3 f² dB/cm, f in MHz); printed solids
attenuate tens of dB/cm at 10–15 MHz, so a solid sphere throws a complete shadow.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

# Water's speed of sound is defined once, in calib (the pipeline's axial scale uses it).
from calib.sound import water_speed_m_s

__all__ = [
    "MATERIALS",
    "Material",
    "amplitude_reflection",
    "attenuation_db_per_m",
    "medium_material",
    "water",
    "water_speed_m_s",
]


@dataclass(frozen=True)
class Material:
    """Acoustic properties of a medium or solid.

    Attributes
    ----------
    name : str
    speed_m_s : float
    density_kg_m3 : float
    attenuation_db_cm_mhz : float
        One-way attenuation coefficient at 1 MHz (dB/cm), scaled by ``f ** power``.
    attenuation_power : float
        Frequency exponent (1 for tissue and solids, 2 for water).
    backscatter_db : float or None
        Mean intensity of fully developed speckle relative to a perfect reflector (dB) at
        the probe's elevation focus, before attenuation; elsewhere its ratio to a perfect
        reflector at the same depth follows the resolution cell
        (:func:`sim_us.beam.speckle_cell_gain`), and that reflector's echo the apertures
        (:func:`sim_us.beam.flat_echo_gain`). None for a medium without scatterers
        (water).
    diffuse : float
        Share (amplitude, of a mirror's) of the surface echo returned at every angle: what
        roughness finer than the wavelength and a print's fine structure (layer corners,
        extrusion seams) scatter. The specular lobe follows from the probe's apertures
        (:mod:`sim_us.propagation`); a texture coarser than the wavelength is the scene
        part's, not the material's.
    """

    name: str
    speed_m_s: float
    density_kg_m3: float
    attenuation_db_cm_mhz: float
    attenuation_power: float = 1.0
    backscatter_db: float | None = None
    diffuse: float = 0.1

    @property
    def impedance(self) -> float:
        """Acoustic impedance Z = ρ c (Rayl)."""
        return self.speed_m_s * self.density_kg_m3


def water(temperature_c: float = 20.0) -> Material:
    """Degassed water at a temperature: no scatterers, f² attenuation."""
    return Material("water", water_speed_m_s(temperature_c), 998.0, 2.17e-3, 2.0, None)


#: Materials by name. PLA and resin are printed solids (diffuse share 0.1 and 0.08: their
#: oblique faces show as granular lines), acrylic a cast or machined sheet, steel a polished
#: ball bearing (a mirror: nothing returns off its specular point), nylon a calibration
#: wire's monofilament.
MATERIALS: dict[str, Material] = {
    "water": water(20.0),
    "gel": Material("gel", 1540.0, 1030.0, 0.5, 1.0, -38.0),
    "pla": Material("pla", 2220.0, 1240.0, 4.0, 1.0, None, 0.1),
    "resin": Material("resin", 2500.0, 1180.0, 5.0, 1.0, None, 0.08),
    "acrylic": Material("acrylic", 2750.0, 1190.0, 0.8, 1.0, None, 0.02),
    "steel": Material("steel", 5900.0, 7850.0, 0.05, 1.0, None, 0.0),
    # Nylon monofilament (fishing line, the usual calibration wire): polyamide 6.
    # Diffuse share 0.05: an extruded line is smoother than a print (0.1), not a polished
    # mirror (steel, 0); a wire tilted well off the beam stays faintly visible.
    "nylon": Material("nylon", 2620.0, 1140.0, 3.0, 1.0, None, 0.05),
}


def medium_material(kind: str, temperature_c: float) -> Material:
    """The propagation medium: water at its temperature, or gel."""
    if kind == "water":
        return water(temperature_c)
    return replace(MATERIALS[kind])


def amplitude_reflection(z1: np.ndarray | float, z2: np.ndarray | float) -> np.ndarray:
    """Pressure-amplitude reflection coefficient magnitude |Z2 − Z1| / (Z2 + Z1) at normal
    incidence; its square is the intensity reflection coefficient R."""
    z1, z2 = np.asarray(z1, dtype=float), np.asarray(z2, dtype=float)
    return np.abs(z2 - z1) / (z2 + z1)


def attenuation_db_per_m(material: Material, f_mhz: float) -> float:
    """One-way attenuation (dB/m) at frequency ``f_mhz``."""
    return 100.0 * material.attenuation_db_cm_mhz * f_mhz**material.attenuation_power
