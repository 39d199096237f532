"""PLUS's real files (``../shared/data/plus``, BSD-3, beside the repository when present)
that the PLUS tests read: their paths, and the mark that skips a test without them."""

from __future__ import annotations

from pathlib import Path

import pytest

PLUS_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "plus"
FCAL_SEQUENCE = PLUS_DATA / "fCal_Test_Calibration_3NWires_fCal2.0.igs.mha"
FCAL_CONFIG = PLUS_DATA / "PlusDeviceSet_fCal_Sim_SpatialCalibration_2.0.xml"
FCAL_RESULTS = PLUS_DATA / "FreehandCalibration3NWires_fCal2.0.results.xml"
NWIRE_CROPPED = PLUS_DATA / "NwirePhantomFreehandCropped.igs.mha"
needs_plus_data = pytest.mark.skipif(not PLUS_DATA.is_dir(), reason="no ../shared/data/plus")
