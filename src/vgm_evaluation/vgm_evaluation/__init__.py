"""Evaluation only: seeded generators of the setups a user may have (rigs and lenses,
curves, shaded scenes, arms and their tasks) with their ground truth, for benches, tests
and the demo's report. The node packages never import it."""
