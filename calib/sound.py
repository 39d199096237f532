"""The speed of sound and the images' axial scale (beyond the paper, which images at the
scanner's assumed speed).

A scanner converts echo time to depth at an assumed speed (1540 m/s); in water at room
temperature sound travels ≈ 3.5 % slower, so every depth it draws is stretched by
``c_assumed / c_water``. With the speed-of-sound correction the pipeline scales the
images' axial spacing by ``c_medium / c_assumed`` (:func:`speed_ratio`), from the water
temperature a user reads off a thermometer. The simulator draws its water from the same
formula (:func:`water_speed_m_s`), so one definition serves both sides.
"""

from __future__ import annotations

__all__ = ["SOFT_TISSUE_SPEED_M_S", "speed_ratio", "water_speed_m_s"]

# Marczak (1997), J. Acoust. Soc. Am. 102, 2776: speed of sound in pure water, 0–95 °C.
_MARCZAK = (1.402385e3, 5.038813, -5.799136e-2, 3.287156e-4, -1.398845e-6, 2.787860e-9)

#: The speed (m/s) taken for a medium other than water (tissue-mimicking gel).
SOFT_TISSUE_SPEED_M_S = 1540.0


def water_speed_m_s(temperature_c: float) -> float:
    """Speed of sound in pure water (m/s) at ``temperature_c`` (°C)."""
    return float(sum(c * temperature_c**k for k, c in enumerate(_MARCZAK)))


def speed_ratio(
    *, correction: bool, medium: str, temperature_c: float, assumed_speed_m_s: float
) -> float:
    """c_medium / c_assumed when the speed-of-sound correction is on (the pipeline knows
    the water temperature a user reads off a thermometer), else 1; a medium other than
    water is taken at :data:`SOFT_TISSUE_SPEED_M_S`.

    Examples
    --------
    >>> round(speed_ratio(correction=True, medium="water", temperature_c=20.0,
    ...                   assumed_speed_m_s=1540.0), 4)
    0.9626
    >>> speed_ratio(correction=False, medium="water", temperature_c=20.0,
    ...             assumed_speed_m_s=1540.0)
    1.0
    """
    if not correction:
        return 1.0
    c = water_speed_m_s(temperature_c) if medium == "water" else SOFT_TISSUE_SPEED_M_S
    return c / assumed_speed_m_s
