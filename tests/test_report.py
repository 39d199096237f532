"""The report of `uscal run`: every figure the HTML links exists, the numbers agree
with metrics.json, calibration.yaml's transforms (metres, mm, PLUS ImageToProbe) are
one and the same, and the page renders in a headless browser."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest
import yaml

from bench.config.scenario import load_scenario
from calib import se3
from calib.image import pixel_to_us

from .conftest import QUICK


def test_every_figure_the_html_references_exists(quick_run):
    out, *_ = quick_run
    page = (out / "report.html").read_text(encoding="utf-8")
    sources = re.findall(r'<img src="([^"]+)"', page)
    assert {"figures/localization_overlay.png", "figures/radial_profile.png"} <= set(sources)
    assert {"figures/convergence.png", "figures/observability.png"} <= set(sources)
    for src in sources:
        png = out / src
        assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", src
    assert (out / "report.md").read_text(encoding="utf-8").count("](figures/") == len(sources)


def test_report_states_the_calibration_of_the_metrics(quick_run):
    out, _, m, _ = quick_run
    md = (out / "report.md").read_text(encoding="utf-8")
    c = m["calibration"]["single"]
    T = np.array(c["T_ee_us"])
    assert f"{T[2, 3] * 1e3:.4f}" in md  # the translation row, in mm
    assert f"{c['true_error']['image_mm']:.3f} mm" in md
    assert "<table>" in (out / "report.html").read_text(encoding="utf-8")


def test_calibration_yaml_transforms_agree(quick_run):
    out, _, m, _ = quick_run
    doc = yaml.safe_load((out / "calibration.yaml").read_text(encoding="utf-8"))
    T = np.array(doc["T_ee_us"]["matrix_m"])
    assert np.allclose(T, m["calibration"]["single"]["T_ee_us"], atol=1e-9)
    T_mm = np.array(doc["T_ee_us"]["matrix_mm"])
    assert np.allclose(T_mm[:3, 3], T[:3, 3] * 1e3, atol=1e-5)
    assert np.allclose(se3.matrix_from_rotvec(doc["T_ee_us"]["rotation_vector_rad"]), T[:3, :3])
    # PLUS ImageToProbe: pixel (column i, row j) → flange mm, pixel spacing included.
    img = doc["image"]
    W, spacing = img["width_px"], tuple(s * 1e-3 for s in img["pixel_spacing_mm"])
    M = np.array(doc["plus_ImageToProbe"]["matrix"])
    for i, j in ((0, 0), ((W - 1) / 2, 0), (17, 93), (W - 1, img["height_px"] - 1)):
        expected = se3.apply(T, pixel_to_us(j, i, W, spacing)) * 1e3
        assert np.allclose((M @ [i, j, 0, 1])[:3], expected, atol=1e-4)
    sc = load_scenario(QUICK)
    assert (img["height_px"], W) == sc.imaging.image_shape
    assert doc["dh_table"]["source"].startswith("nominal")
    assert np.allclose(doc["dh_table"]["d_m"], sc.robot.nominal_table.d)
    std = doc["uncertainty_1sigma"]
    assert all(0 < v < 1 for v in std["rotation_deg"] + std["translation_mm"])


def _browser() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


@pytest.mark.skipif(_browser() is None, reason="no headless chromium installed")
def test_report_renders_in_a_headless_browser(quick_run, tmp_path):
    out, *_ = quick_run
    browser = _browser()
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--allow-file-access-from-files"]
    url = (out / "report.html").resolve().as_uri()
    dom = subprocess.run(
        [browser, *flags, "--dump-dom", url], capture_output=True, text=True, timeout=120
    )
    assert dom.returncode == 0, dom.stderr[-2000:]
    assert "<h1>uscal report</h1>" in dom.stdout
    shot = tmp_path / "report.png"
    r = subprocess.run(
        [browser, *flags, f"--screenshot={shot}", "--window-size=1200,1600", url],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert shot.is_file() and shot.stat().st_size > 10_000
