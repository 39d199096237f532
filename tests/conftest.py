"""Shared fixtures: seeded generators and small builders."""

from __future__ import annotations

import numpy as np
import pytest

from calib.dh import NOMINAL_TABLES, DHDeltas, DHTable

# Paper-like DH error magnitudes (RMS): 2.51°, 0.24 mm, 1.51 mm, 0.27°.
PAPER_RMS = (np.radians(2.51), 0.24e-3, 1.51e-3, np.radians(0.27))


def perturbed_table(rng: np.random.Generator, name: str = "ur3") -> DHTable:
    """The nominal table plus DH errors of paper-like size."""
    deltas = np.column_stack([rng.normal(0.0, s, 6) for s in PAPER_RMS])
    return NOMINAL_TABLES[name].with_deltas(DHDeltas.from_array(deltas))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261122)
