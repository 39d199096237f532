"""Settings files: the schema engine (:mod:`~bench.config.schema`), scenario files
(:mod:`~bench.config.scenario`) with the checks of their world
(:mod:`~bench.config.geometry`) and their generated documentation
(:mod:`~bench.config.docs`), the hw config of a real rig (:mod:`~bench.config.hw`) and
the registry of the twin's error sources (:mod:`~bench.config.error_sources`). The bottom
layer of :mod:`bench`: it imports no other part of it."""
