"""The paper experiment's ``metrics.json`` from its parts: the first dataset's
localization and calibrations (with their errors against the truth), every fold, the
leave-one-out kinematics and what of the DH model the touches can observe, and Tables I
and II as summaries (:class:`calib.evaluation.cross_validation.Summary`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from calib.calibration.verdict import BoundFigures, ImageScale, SweepGeometry, judge
from calib.evaluation.cross_validation import (
    FoldResult,
    Summary,
    summarize,
)
from calib.kinematics import (
    TouchReference,
    identifiability,
)

from ..acquire_sim import coarse_estimate
from ..config.method import requirements
from ..config.scenario import Scenario
from ..results import DatasetOutcome
from ..results import calibration_entry as pipeline_entry
from ..sessions import stage_rngs
from ..truth import transform_difference

__all__ = ["coarse_error", "evaluation_metrics", "summary_tables", "tables_json"]
_MM = 1e3


def summary_tables(
    names: list[str], references: dict[str, TouchReference], outcomes: list[DatasetOutcome]
) -> dict[str, dict[str, dict[str, Summary]]]:
    by_name = {o.name: o for o in outcomes}
    tool = {n: list(references[n].tool_precision_mm.values()) for n in names}
    out: dict[str, dict[str, dict[str, Summary]]] = {}
    for kind in ("single", "three"):
        prec = {n: [r.precision for r in by_name[n].folds if r.fold.kind == kind] for n in names}
        acc = {n: [r.accuracy for r in by_name[n].folds if r.fold.kind == kind] for n in names}
        table = {"sphere_precision_mm": summarize(prec), "sphere_accuracy_mm": summarize(acc)}
        if kind == "single":
            table = {"tool_precision_mm": summarize(tool), **table}
        out[kind] = table
    return out


def tables_json(table: dict[str, dict[str, Summary]]) -> dict[str, Any]:
    return {metric: {s: v.as_dict() for s, v in by_set.items()} for metric, by_set in table.items()}


def evaluation_metrics(
    scenario, names, touches, refinements, references, outcomes, truth, cad_vertices
) -> dict[str, Any]:
    first = outcomes[0]
    single = next(r for r in first.folds if r.fold.kind == "single")
    three = next((r for r in first.folds if r.fold.kind == "three"), None)
    errors = first.localization_errors_mm
    if len(errors) == 0:
        errors = np.array([np.nan])
    fold_truth = {f["fold"]: f for o in outcomes for f in o.truth["folds"]}
    fold_bounds = {k: v for o in outcomes for k, v in o.uncertainty.items()}
    # Every fold's verdict, once (the first folds' also go into ``calibration``).
    verdicts = {}
    for o in outcomes:
        for r in o.folds:
            figures = fold_bounds.get(r.fold.name, {}).get("bound95")
            bound = None if figures is None else BoundFigures.from_dict(figures)
            g = fold_bounds.get(r.fold.name, {}).get("sweep_geometry")
            geometry = None if g is None else SweepGeometry.from_dict(g)
            # The image scale as the dataset task read it (with the arm model's modes).
            s = fold_bounds.get(r.fold.name, {}).get("image_scale")
            verdicts[r.fold.name] = judge(
                r.alternation,
                bound,
                requirements(scenario),
                geometry=geometry,
                scale=None if s is None else ImageScale.from_dict(s),
            )

    def calibration_entry(r: FoldResult) -> dict[str, Any]:
        """A fold's calibration (:func:`bench.results.calibration_entry`, its bounds
        from the dataset task) with its errors against the truth."""
        t = fold_truth[r.fold.name]
        bounds = fold_bounds.get(r.fold.name, {})
        entry = pipeline_entry(
            r.alternation, r.fold.train, r.fold.test, verdict=verdicts[r.fold.name]
        )
        true_error = {k: t[k] for k in ("rotation_deg", "translation_mm", "image_mm")}
        return {
            "fold": r.fold.name,
            "true_error": true_error,
            "accuracy_mm": r.accuracy,
            "accuracy_true_mm": t["accuracy_true_mm"],
            **entry,
            **bounds,
        }

    folds_doc = []
    for o in outcomes:
        for r in o.folds:
            t = fold_truth[r.fold.name]
            folds_doc.append(
                {
                    "fold": r.fold.name,
                    "dataset": r.fold.dataset,
                    "kind": r.fold.kind,
                    "train": list(r.fold.train),
                    "test": list(r.fold.test),
                    "sphere_precision_mm": r.precision,
                    "sphere_accuracy_mm": r.accuracy,
                    "per_sphere": {
                        s: {"precision_mm": r.precision_mm[s], "accuracy_mm": r.accuracy_mm[s]}
                        for s in r.fold.test
                    },
                    "n_retained": int(r.alternation.result.retained.sum()),
                    "iterations": len(r.alternation.history),
                    "verdict": {
                        "status": verdicts[r.fold.name].status,
                        "reasons": list(verdicts[r.fold.name].reasons),
                    },
                    "true": {k: v for k, v in t.items() if k != "fold"},
                    **(
                        {"bound95": fold_bounds[r.fold.name]["bound95"]}
                        if r.fold.name in fold_bounds
                        else {}
                    ),
                }
            )
    kin = {}
    for n in names:
        ref = refinements[n]
        kin[n] = {
            "trained_on": [m for m in names if m != n],
            "rms_change": dict(
                zip(("theta_deg", "d_mm", "a_mm", "alpha_deg"), ref.rms_change, strict=True)
            ),
            "z": ref.z.round(6).tolist(),
            "training_loss_mm2": ref.loss,
            "start_losses_mm2": ref.start_losses.round(6).tolist(),
            "touch_residual_rms_mm": float(np.sqrt(np.mean(ref.residuals_mm**2))),
            "reference_residual_rms_mm": float(np.sqrt(np.mean(references[n].residuals_mm ** 2))),
            "tip_mm": (references[n].tip * _MM).round(4).tolist(),
        }
        o = next(o for o in outcomes if o.name == n)
        kin[n]["true_error"] = o.truth["kinematic_error_mm"]
        kin[n]["reference_error_mm"] = o.truth["reference_error_mm"]
    # The paper's figure: RMS over the three leave-one-out models and the six joints.
    rms = np.sqrt(np.mean(np.array([r.rms_change for r in refinements.values()]) ** 2, axis=0))
    true_rms = np.array(truth.dh_deltas.rms()) * [180 / np.pi, _MM, _MM, 180 / np.pi]
    ident = identifiability(
        refinements[names[0]], [touches[n] for n in names if n != names[0]], cad_vertices
    )
    return {
        "scenario": {"name": scenario.source, "seed": scenario.seed},
        "localization": {
            "method": scenario.localization.method,
            "n_sweeps": first.n_sweeps,
            "n_rejected": first.n_rejected,
            "error_mm": {
                "median": float(np.median(errors)),
                "p95": float(np.percentile(errors, 95)),
                "max": float(np.max(errors)),
            },
        },
        "calibration": {
            "coarse_error": coarse_error(scenario, truth),
            "single": calibration_entry(single),
            **({"three": calibration_entry(three)} if three is not None else {}),
        },
        "kinematics": {
            "datasets": kin,
            "rms_change_mean": dict(
                zip(("theta_deg", "d_mm", "a_mm", "alpha_deg"), rms.tolist(), strict=True)
            ),
            "true_dh_error_rms": dict(
                zip(("theta_deg", "d_mm", "a_mm", "alpha_deg"), true_rms.tolist(), strict=True)
            ),
            "unobservable_share": {k: round(v, 4) for k, v in ident.unobservable.items()},
            "weak_directions": [
                {"singular_value": w.singular_value, "dh": w.dh} for w in ident.weak
            ],
        },
        "evaluation": {"datasets": names, "folds": folds_doc},
    }


def coarse_error(scenario: Scenario, truth) -> dict[str, float]:
    coarse = coarse_estimate(
        truth.T_ee_us, scenario.calibration, stage_rngs(scenario)["calibration"]
    )
    return transform_difference(coarse, truth.T_ee_us)
