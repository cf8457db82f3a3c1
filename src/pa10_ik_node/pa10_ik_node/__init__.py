"""Follows curve waypoints with force feedback; redundant inverse kinematics of the PA-10 (primal-
dual network, KKT, damped least squares)."""
