"""What the ``uscal`` commands print (rich; with :mod:`bench.cli`, the only modules that
print), one module per kind of output: :mod:`~bench.console.tables` (a
:class:`bench.tables.Table` with rich), :mod:`~bench.console.terminal` (progress bars,
the rerun viewer), :mod:`~bench.console.scenario` (``check``, ``plan``, ``twin
export``), :mod:`~bench.console.run` (one acquisition's results, the files written),
:mod:`~bench.console.paper` (Tables I–III of the paper's experiment and the ground truth
beside them), :mod:`~bench.console.recorded` (``calibrate`` on recorded data, ``import
plus``) and :mod:`~bench.console.grids` (``sweep``, ``budget``). What they print of a
run comes from its typed summary (:mod:`bench.summaries`). The commands themselves are
in :mod:`bench.cli`."""

from .grids import print_cached_run, print_workload
from .paper import paper_table, print_evaluation, print_reconstruction
from .recorded import print_import, print_recorded, print_target
from .run import print_run, print_written
from .scenario import print_plan, print_plan_comparison, print_scenario_summary, print_truth
from .tables import print_table, rich_table
from .terminal import Bars, progress_bars, spawn_viewer

__all__ = [
    "Bars",
    "paper_table",
    "print_cached_run",
    "print_evaluation",
    "print_import",
    "print_plan",
    "print_plan_comparison",
    "print_reconstruction",
    "print_recorded",
    "print_run",
    "print_scenario_summary",
    "print_table",
    "print_target",
    "print_truth",
    "print_workload",
    "print_written",
    "progress_bars",
    "rich_table",
    "spawn_viewer",
]
