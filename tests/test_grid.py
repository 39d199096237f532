"""The grid executor (:mod:`bench.grid`): points of one batch run as one call of the
batch task, cached points are left out of their batch, and what a batch's points share
failing is recorded for each of them."""

from __future__ import annotations

import json
import os

from bench.grid import GridPoint, run_grid
from calib.errors import CollisionError


def _one(overrides, seed):
    return {"value": dict(overrides)["x"] + seed, "pid": os.getpid(), "batch": 1}


def _many(overrides, seed):
    """A batch: x < 0 stands for a plan refused before anything moved, x ≥ 100 for an
    acquisition that failed; both are the whole batch's."""
    xs = [dict(o)["x"] for o in overrides]
    if min(xs) < 0:
        raise CollisionError("the probe would touch sphere 2")
    if max(xs) >= 100:
        raise ValueError("the acquisition failed")
    return [{"value": x + seed, "pid": os.getpid(), "batch": len(xs)} for x in xs]


def _points(xs, seed=0, batch="b"):
    return [GridPoint((("x", x),), seed, f"k{x}_{seed}", batch) for x in xs]


def test_grid_batches_run_together_cached_points_stay_out_and_shared_failures_are_each_points(
    tmp_path,
):
    points = [
        *_points([1, 2, 3]),
        *_points([1, 2], seed=5),
        GridPoint((("x", 9),), 0, "k9"),
        *_points([100, 101], batch="c"),
        *_points([-1, -2], batch="d"),
    ]
    out = run_grid(_one, points, tmp_path, workers=1, batch_task=_many)
    docs = {p.key: d for p, d in zip(points, out.documents, strict=True)}
    assert [d.get("value") for d in out.documents[:6]] == [1, 2, 3, 6, 7, 9]
    # One call per (batch, seed); the point without a batch runs the single task.
    assert [d["batch"] for d in out.documents[:6]] == [3, 3, 3, 2, 2, 1]
    assert len({docs[k]["pid"] for k in ("k1_0", "k2_0", "k3_0")}) == 1
    assert json.loads((tmp_path / "points" / "k2_5.json").read_text())["seed"] == 5
    # What a batch shares failing is each of its points' record.
    assert (out.failed, out.refused) == (2, 2)
    for d in out.documents[6:8]:
        assert d["error"] == "ValueError: the acquisition failed" and "Traceback" in d["traceback"]
    for d in out.documents[8:]:
        assert d["refused"] == "CollisionError: the probe would touch sphere 2"
    # Grown by one point of the first batch: it runs alone, the rest is read back.
    grown = [*points, *_points([4])]
    again = run_grid(_one, grown, tmp_path, workers=1, batch_task=_many)
    assert (again.computed, again.cached) == (1, len(points))
    assert again.documents[-1]["value"] == 4 and again.documents[-1]["batch"] == 1
    assert again.documents[:-1] == out.documents
