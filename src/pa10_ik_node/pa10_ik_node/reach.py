"""Whether a whole path is reachable within the joint limits, before the arm moves. No ROS.

The sphere test of ``TrackingController.check_reachable`` misses what the joint limits
forbid inside the workspace (a wrist that cannot turn the tool onto a tilted approach
axis, an elbow at its stop). ``first_unreachable`` walks the arm's kinematic model from the
measured joints through the pre-contact pose and every waypoint in order, with the same
limit-clamping rate solver and orientation freedom as the tracking (the spin about the
approach axis free unless tracked), and reports the first target it cannot get within
tolerance of, and by how much.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from pa10_ik_node.ik import RateSolver, pose_error, spin_free_task, tilt_error
from vgm_common.geometry import FloatArray
from vgm_common.robot_model import RobotModel

POSITION_TOLERANCE_M = 0.001
ANGLE_TOLERANCE_RAD = np.radians(1.0)
MAX_JOINT_STEP_RAD = 0.2  # per iteration: keeps each linearisation honest
LINEAR_STEP_M, ANGULAR_STEP_RAD = 0.02, 0.2  # largest task step per iteration


@dataclass(frozen=True)
class ReachMiss:
    """The first target the model could not reach within the joint limits."""

    index: int  # into the targets given
    position_error_m: float  # [m] closest the tip got
    angle_error_rad: float  # [rad] the approach axis's (or whole orientation's) error there
    joints_at_limit: tuple[str, ...]  # the joints at a position limit there
    q: FloatArray  # (n,) [rad] where the walk stopped


def first_unreachable(
    robot: RobotModel,
    q_start: npt.ArrayLike,
    targets: npt.ArrayLike,
    track_spin: bool = False,
    first_iterations: int = 400,
    iterations: int = 60,
    margin_rad: float = 0.02,
) -> ReachMiss | None:
    """Walk the model through ``targets`` (K, 4, 4) (base_link poses of the tip) in order
    from ``q_start`` (n,) [rad]: None if each is reached within 1 mm and 1 deg without a
    joint closer than ``margin_rad`` to its limits, else the first ``ReachMiss``.

    ``first_iterations`` for the first target (a free-space move), ``iterations`` for each
    next one (a step along the path). Only the approach axis (z) of a target counts
    unless ``track_spin``.
    """
    solver = RateSolver('ours', np.ones(robot.n_joints))
    lower, upper = robot.lower_limits, robot.upper_limits
    steps = np.full(robot.n_joints, MAX_JOINT_STEP_RAD)
    q = robot.check_q(q_start)
    for index, T_d in enumerate(np.asarray(targets, dtype=float)):
        budget = first_iterations if index == 0 else iterations
        for _ in range(budget + 1):
            T = robot.forward_kinematics(q)
            error = pose_error(T, T_d)
            if not track_spin:
                error[3:] = tilt_error(T[:3, :3], T_d[:3, 2])
            distance, angle = float(np.linalg.norm(error[:3])), float(np.linalg.norm(error[3:]))
            if distance < POSITION_TOLERANCE_M and angle < ANGLE_TOLERANCE_RAD:
                break
            error[:3] *= min(1.0, LINEAR_STEP_M / max(distance, 1e-12))
            error[3:] *= min(1.0, ANGULAR_STEP_RAD / max(angle, 1e-12))
            J = robot.jacobian(q)
            J_task, task = (J, error) if track_spin else spin_free_task(J, error, T_d)
            # One iteration = one second of the rate solver: its limit clamping then keeps
            # the joints margin_rad inside their limits, as the tracking does.
            qdot, _ = solver.solve_limited(
                J_task, task, q, lower, upper, steps, limit_horizon=1.0, margin=margin_rad
            )
            q = q + qdot
        else:
            near = (q - lower < 1.5 * margin_rad) | (upper - q < 1.5 * margin_rad)
            at_limit = tuple(name for name, hit in zip(robot.joint_names, near) if hit)
            return ReachMiss(index, distance, angle, at_limit, q)
    return None


def spaced_indices(points: npt.ArrayLike, spacing_m: float) -> list[int]:
    """Indices of ``points`` (K, 3) [m] at least ``spacing_m`` apart along the sequence
    (the first and the last always)."""
    points = np.asarray(points, dtype=float)
    keep, last = [0], points[0]
    for i in range(1, len(points)):
        if np.linalg.norm(points[i] - last) >= spacing_m or i == len(points) - 1:
            keep.append(i)
            last = points[i]
    return keep


def joints_at(
    robot: RobotModel,
    q_start: npt.ArrayLike,
    T_desired: npt.ArrayLike,
    tolerance_m: float = 1e-6,
    iterations: int = 400,
) -> FloatArray | None:
    """Joints (n,) [rad] putting the tip at ``T_desired`` (4, 4) (its position and approach
    axis; the spin free), walked from ``q_start`` (n,) [rad] within the joint limits as
    ``first_unreachable`` walks; None if not within ``tolerance_m`` [m] and 1e-6 rad in
    ``iterations``. (Where a run left the arm, e.g. pressing at a path's first waypoint.)"""
    solver = RateSolver('ours', np.ones(robot.n_joints))
    steps = np.full(robot.n_joints, MAX_JOINT_STEP_RAD)
    T_d = np.asarray(T_desired, dtype=float)
    q = robot.check_q(q_start)
    for _ in range(iterations):
        T = robot.forward_kinematics(q)
        error = pose_error(T, T_d)
        error[3:] = tilt_error(T[:3, :3], T_d[:3, 2])
        distance, angle = float(np.linalg.norm(error[:3])), float(np.linalg.norm(error[3:]))
        if distance < tolerance_m and angle < 1e-6:
            return q
        error[:3] *= min(1.0, LINEAR_STEP_M / max(distance, 1e-12))
        error[3:] *= min(1.0, ANGULAR_STEP_RAD / max(angle, 1e-12))
        J_task, task = spin_free_task(robot.jacobian(q), error, T_d)
        qdot, _ = solver.solve_limited(
            J_task, task, q, robot.lower_limits, robot.upper_limits, steps, limit_horizon=1.0
        )
        q = q + qdot
    return None
