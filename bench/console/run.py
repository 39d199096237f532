"""What ``uscal run`` prints of one acquisition: the localization, the calibrations
against the ground truth with their 95 % bounds, the timing; and the files a run or
calibration wrote."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from rich.console import Console
from rich.table import Table

__all__ = ["calibration_table", "print_run", "print_written"]


def calibration_table(m: dict, title: str, columns: Sequence[str], cells) -> Table:
    """One row per calibration method of ``metrics.json`` (``cells(entry)`` → texts)."""
    table = Table(title=title)
    table.add_column("method", justify="left")
    for col in columns:
        table.add_column(col, justify="right")
    for name in ("single", "three"):
        c = m["calibration"].get(name)
        if c is not None:
            table.add_row(name, *cells(c))
    return table


def print_run(m: dict, console: Console) -> None:
    loc = m["localization"]
    console.print(
        f"localization ({loc['method']}): {loc['n_sweeps']} sweeps, {loc['n_rejected']} "
        f"rejected; error vs truth median {loc['error_mm']['median']:.3f} mm, "
        f"p95 {loc['error_mm']['p95']:.3f} mm, max {loc['error_mm']['max']:.3f} mm"
    )

    def cells(c: dict) -> list[str]:
        e = c["true_error"]
        return [
            f"{e['rotation_deg']:.3f}",
            f"{e['translation_mm']:.3f}",
            f"{e['image_mm']:.3f}",
            f"{c['precision_mm']:.3f}",
            f"{c['accuracy_mm']:.3f}",
            str(c["n_retained"]),
            str(c["iterations"]),
        ]

    # Short headers: the table must fit an 80-column terminal.
    columns = ("rot °", "trans mm", "image mm", "prec mm", "acc mm", "kept", "iter")
    console.print(calibration_table(m, "calibration against ground truth", columns, cells))
    for name in ("single", "three"):
        c = m["calibration"].get(name)
        if c is None or "bound95" not in c:
            continue
        b, e = c["bound95"], c.get("true_error_equivalent", c["true_error"])
        inside = all(e[k] <= b[k] for k in ("rotation_deg", "translation_mm", "image_mm"))
        console.print(
            f"{name}: 95 % error bounds (from the data alone) rotation {b['rotation_deg']:.3f}°, "
            f"translation {b['translation_mm']:.3f} mm, image {b['image_mm']:.3f} mm; "
            f"the truth is {'inside' if inside else 'OUTSIDE'}"
        )
    t = m["timing_s"]
    summed = f" (summed over {t['workers']} workers)" if "workers" in t else ""
    console.print(
        f"time: simulate {t['simulate']:.1f} s, localize {t['localize']:.1f} s, "
        f"calibrate {t['calibrate']:.1f} s{summed}, total {t['total']:.1f} s"
    )


def print_written(out: Path, written: Sequence[str], console: Console) -> None:
    """The files a run or calibration wrote (figures counted, not listed)."""
    figures = [f for f in written if f.startswith("figures/")]
    files = [f for f in written if not f.startswith("figures/")]
    console.print(
        f"wrote {', '.join(str(out / f) for f in files)} and {len(figures)} figures in "
        f"{out / 'figures'} (open {out / 'report.html'})"
    )
