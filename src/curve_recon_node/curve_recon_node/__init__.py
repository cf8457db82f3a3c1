"""Reconstructs a 3D curve from its images in two or three views by intersecting cones of fitted
algebraic curves."""
