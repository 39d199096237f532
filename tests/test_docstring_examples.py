"""The runnable examples (``>>>``) in the docstrings of the method's entry points: the
transforms, the image frame, the localizer and the calibration."""

from __future__ import annotations

import doctest
import importlib

import pytest

MODULES = ["calib.se3", "calib.image", "calib.localize.sphere", "calib.calibration.markers"]


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.attempted > 0, f"{name} has no examples"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed"
