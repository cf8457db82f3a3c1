"""Synthetic stereo + aux cameras, pressure sensor and simulated PA-10 arm driven by a scenario
file."""
