"""Stereo + aux camera calibration from a chart (LX-PM genetic algorithm, neural refinement,
Levenberg-Marquardt)."""

import os

# Measured here (2 shared cores): OpenBLAS's threads make the small SVDs / QRs of the
# least-squares solvers 30x slower (62 ms instead of 2 ms for a 2048 x 22 SVD). Takes
# effect when this package is imported before numpy (the node, the bench); a user's
# setting wins.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
