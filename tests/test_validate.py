"""``uscal validate`` on a sphere dataset of the twin: the run's own calibration gives the
localizer's scatter; the same calibration turned by a few degrees scatters the centres
(the check can fail); files that are no calibration, or one made for other pixels, are
one line."""

from __future__ import annotations

import re

import numpy as np
import pytest
import yaml

from calib import se3
from calib.files.plus_config import image_to_probe_mm, us_of_image_to_probe

from .test_cli import uscal_here


def _write(path, A):
    path.write_text(yaml.safe_dump({"plus_ImageToProbe": {"matrix": A.tolist()}}))
    return path


@pytest.mark.slow  # localizes the run's 45 sweeps twice
def test_a_calibration_is_checked_by_the_scatter_it_gives(quick_run, capsys, tmp_path):
    out = quick_run[0]
    dataset = out.parent / "dataset"
    r = uscal_here(capsys, "validate", str(dataset), "--calibration", str(out / "calibration.yaml"))
    assert r.returncode == 0, r.stderr
    good = re.fullmatch(r"precision_mm=(\d+\.\d+)", r.stdout.strip().splitlines()[-1])
    assert good is not None and float(good.group(1)) < 0.3
    # The same mount turned by 3° about the image's lateral axis.
    doc = yaml.safe_load((out / "calibration.yaml").read_text())
    A = np.array(doc["plus_ImageToProbe"]["matrix"])
    width = doc["image"]["width_px"]
    T, spacing = us_of_image_to_probe(A, width)
    turned = T @ se3.make(se3.matrix_from_rotvec([np.radians(3.0), 0, 0]), [0, 0, 0])
    bad_file = _write(tmp_path / "turned.yaml", image_to_probe_mm(turned, width, spacing))
    r = uscal_here(capsys, "validate", str(dataset), "--calibration", str(bad_file))
    assert r.returncode == 0, r.stderr
    bad = float(r.stdout.strip().splitlines()[-1].split("=")[1])
    assert bad > 2 * float(good.group(1))


def test_what_is_not_a_calibration_for_this_dataset_is_one_line(quick_run, capsys, tmp_path):
    dataset = quick_run[0].parent / "dataset"
    for path, message in (
        (dataset / "dataset.yaml", "not a uscal calibration.yaml"),
        (tmp_path / "none.yaml", "no such file"),
        (_write(tmp_path / "wide.yaml", image_to_probe_mm(np.eye(4), 10, (1e-3, 1e-3))),
         "made for a pixel spacing of 1.00000 × 1.00000 mm"),
    ):  # fmt: skip
        r = uscal_here(capsys, "validate", str(dataset), "--calibration", str(path))
        assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
        assert message in r.stderr
