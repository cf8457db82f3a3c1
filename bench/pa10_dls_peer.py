"""The damped-least-squares peer of bench_pa10_ik.py (``--pace``, in process) and of
pa10_dls_peer_node.py (``--over-topics``): a conventional contact-tracking controller,
no product code."""

import numpy as np

from pa10_ik_node.ik import RateSolver, pose_error, spin_free_task, tilt_error
from pa10_ik_node.path import WaypointPath

PEER_SPEED = 0.03  # [m/s] the peer: a 0.8 m lemniscate in 27.6 s


class DlsPeer:
    """A conventional damped-least-squares contact-tracking controller (the issue's
    peer), with its own phases and no governor: free move (pose feedback, 0.05 m/s) to
    ``standoff`` above the first waypoint, descent at ``descent_speed`` until the force
    reaches the desired one (from a start already touching: straight to the descent),
    the reference on the clock at ``speed`` along the path at the depth
    desired / stiffness + an integral of the force error, lift-off. Same spin-free task,
    joint-limit clamping and velocity limits as ours (``RateSolver('dls')``)."""

    def __init__(self, robot, waypoints, desired, stiffness, speed=PEER_SPEED):
        self.robot, self.path = robot, WaypointPath(waypoints)
        self.desired, self.stiffness, self.speed = desired, stiffness, speed
        self.solver = RateSolver('dls', np.ones(robot.n_joints))
        self.velocity_limits = np.minimum(robot.velocity_limits, 1.0)
        self.phase, self.stage, self.progress, self.reason = 'approach', 'free', 0.0, ''
        self.s = self.reference_depth = self.integral = self.lifted = 0.0

    def stop(self, reason='stop requested'):
        self.phase, self.reason = 'stopped', reason

    def _target(self, s, depth):
        P, z, tangent = self.path.sample(s % self.path.length if self.path.closed else s)
        x = tangent - z * np.dot(z, tangent)
        x /= np.linalg.norm(x)
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        T[:3, 3] = P + depth * z
        return T, z, x

    def step(self, q, force, dt):
        T = self.robot.forward_kinematics(q)
        standoff, descent_speed, lift_height = 0.03, 0.01, 0.03
        feed_forward, free = np.zeros(6), False
        P0, z0, _ = self.path.sample(0.0)
        if self.stage == 'free' and force >= 0.05 * self.desired:
            offset = T[:3, 3] - P0
            if np.linalg.norm(offset - z0 * np.dot(offset, z0)) < 0.002:  # touching at P0
                self.stage, self.reference_depth = 'descend', float(np.dot(offset, z0))
        if self.phase == 'approach' and self.stage == 'free':
            T_d, _, _ = self._target(0.0, -standoff)
            free = True
            if np.linalg.norm(T_d[:3, 3] - T[:3, 3]) < 0.001:
                self.stage, self.reference_depth = 'descend', -standoff
        elif self.phase == 'approach':
            if force >= self.desired:
                self.phase, self.s = 'tracking', 0.0
                self.integral = self.reference_depth - self.desired / self.stiffness
            else:
                self.reference_depth += descent_speed * dt
                feed_forward[:3] = descent_speed * self.path.sample(0.0)[1]
            T_d, _, _ = self._target(0.0, self.reference_depth)
        if self.phase == 'tracking':
            self.integral += 5.0 * (self.desired - force) / self.stiffness * dt
            self.s = min(self.s + self.speed * dt, self.path.length)
            self.progress = self.s / self.path.length
            T_d, _, x = self._target(self.s, self.desired / self.stiffness + self.integral)
            feed_forward[:3] = self.speed * x if self.s < self.path.length else 0.0
            if self.s >= self.path.length:
                self.phase, self.stage, self.T_end = 'done', 'lifting', T_d
        if self.phase == 'done':
            self.lifted = min(self.lifted + descent_speed * dt, lift_height)
            T_d = self.T_end.copy()
            T_d[:3, 3] -= self.lifted * T_d[:3, 2]
            lifted = float(np.dot(self.T_end[:3, 3] - T[:3, 3], T_d[:3, 2]))
            if lifted >= lift_height - 0.0005:
                self.stage = 'lifted'
        error = pose_error(T, T_d)
        error[3:] = tilt_error(T[:3, :3], T_d[:3, 2])
        twist = feed_forward + 10.0 * error
        if free and np.linalg.norm(twist[:3]) > 0.05:
            twist[:3] *= 0.05 / np.linalg.norm(twist[:3])
        J, task = spin_free_task(self.robot.jacobian(q), twist, T_d)
        qdot, _ = self.solver.solve_limited(
            J, task, q, self.robot.lower_limits, self.robot.upper_limits, self.velocity_limits
        )
        return qdot, {'phase': self.phase}
