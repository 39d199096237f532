"""What each ``uscal`` command runs, one module per job, built on :mod:`calib.pipeline`
and the acquisitions (:mod:`bench.acquire_sim`, :mod:`bench.acquire_rig`):
:mod:`~bench.jobs.single` (one twin acquisition), :mod:`~bench.jobs.paper` (the paper's
experiment, with :mod:`~bench.jobs.paper_dataset` per dataset and
:mod:`~bench.jobs.paper_metrics`), :mod:`~bench.jobs.table3` (re-calibration and
reconstruction), :mod:`~bench.jobs.recorded` (``uscal calibrate``), :mod:`~bench.jobs.sweep`,
:mod:`~bench.jobs.budget`, :mod:`~bench.jobs.plan`, :mod:`~bench.jobs.gallery` and
:mod:`~bench.jobs.twin_serve`. Jobs return typed results (:mod:`bench.results`); the
files a command leaves are written by :mod:`bench.outputs`. A job imports no other job
(``uscal run`` is :mod:`~bench.jobs.single` with the paper's modules): sweeps and budgets
run their points on :mod:`bench.grid`, and a budget is handed the run it repeats."""
