"""Everything a command writes from a job's result: the report and its figures
(:mod:`~bench.outputs.report`, :mod:`~bench.outputs.figures`), ``calibration.yaml``
(:mod:`~bench.outputs.calibration_doc`), a run's output directory
(:mod:`~bench.outputs.run_files`), the sweep's and the budget's tables and pages
(:mod:`~bench.outputs.sweep_report`, :mod:`~bench.outputs.budget_report`). All through
the atomic writers of :mod:`bench.files`."""
