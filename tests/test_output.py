"""Atomic output directories."""

from __future__ import annotations

import pytest

from bench.files import OutputExistsError, atomic_output_dir


def test_success_renames_into_place(tmp_path):
    target = tmp_path / "run"
    with atomic_output_dir(target) as tmp:
        (tmp / "a.txt").write_text("x")
        assert not target.exists()
    assert (target / "a.txt").read_text() == "x"
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_failure_leaves_nothing_and_keeps_old(tmp_path):
    target = tmp_path / "run"
    target.mkdir()
    (target / "old.txt").write_text("old")
    with pytest.raises(RuntimeError), atomic_output_dir(target, force=True) as tmp:
        (tmp / "half.txt").write_text("half")
        raise RuntimeError("boom")
    assert [p.name for p in target.iterdir()] == ["old.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
    with pytest.raises(OutputExistsError, match="not empty"), atomic_output_dir(target):
        pass


def test_write_text_atomic_replaces_whole_and_leaves_no_temporary(tmp_path, monkeypatch):
    import os

    from bench.files import write_text_atomic

    target = tmp_path / "results.csv"
    write_text_atomic(target, "old\n")
    assert write_text_atomic(target, "new\n").read_text() == "new\n"

    def fail(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError):
        write_text_atomic(target, "half")
    assert target.read_text() == "new\n"
    assert [p.name for p in tmp_path.iterdir()] == ["results.csv"]
