"""Stereo + aux camera calibration from a chart (LX-PM genetic algorithm, neural refinement,
Levenberg-Marquardt)."""
