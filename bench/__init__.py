"""Composition root: scenario loading, experiment runner, sweeps, report, recording, CLI."""
