"""rerun recordings of a run: the options (:mod:`~bench.recording.options`), the
recorder and its entities (:mod:`~bench.recording.recorder`), and what each job logs
and how the workers' parts merge (:mod:`~bench.recording.logs`). Jobs and their pool
workers log while they run, so this sits beside the pipeline, below the jobs. The only
package that imports rerun."""
