"""Command line, model registry and stage orchestration of the precompute."""
