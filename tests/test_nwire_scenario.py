"""An N-wire scenario (scenarios/nwire.yaml) is a valid scenario, its protocol checks,
and the commands that measure the sphere method refuse it in one line, writing nothing."""

from __future__ import annotations

from pathlib import Path

import pytest

from .test_cli import uscal_here

ROOT = Path(__file__).resolve().parents[1]
NWIRE = str(ROOT / "scenarios" / "nwire.yaml")


def test_the_n_wire_scenario_is_valid_and_its_protocol_checks(capsys):
    r = uscal_here(capsys, "check", NWIRE)
    assert r.returncode == 0, r.stderr
    assert "nwire" in r.stdout and "scenario is valid" in r.stdout
    r = uscal_here(capsys, "plan", NWIRE)
    assert r.returncode == 0, r.stderr
    assert "nwire" in r.stdout


@pytest.mark.parametrize(
    "args, message",
    [
        (["budget", NWIRE], "the error budget is measured on the sphere method"),
        (["plan", NWIRE, "--optimize", "--sweeps", "10"], "the planner chooses sphere sweeps"),
    ],
)
def test_sphere_only_commands_refuse_it_in_one_line(capsys, tmp_path, args, message):
    r = uscal_here(capsys, *args, "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert message in r.stderr and not (tmp_path / "out").exists()


def test_a_sweep_over_it_is_refused(capsys, tmp_path):
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(f"base: {NWIRE}\ngrid:\n  imaging.gain_db: [0, 6]\n", encoding="utf-8")
    r = uscal_here(capsys, "sweep", str(sweep), "--out", str(tmp_path / "out"))
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "an N-wire scenario runs with `uscal run`" in r.stderr
