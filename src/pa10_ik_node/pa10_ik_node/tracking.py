"""Force- and path-tracking control core of the PA-10 (ALGORITHMS.md §6.1, §6.3, §6.4). No ROS.

Waypoints are (N, 4, 4) poses in base_link (INTERFACES.md /curve/waypoints): origin on
the surface, x along the curve's tangent, z the approach direction into the surface.
Each ``TrackingController.step`` drives the tool tip towards the next waypoint ahead,
pressed along its approach axis by a depth from an integral (admittance) force law, with a
feed-forward along the path, and solves the redundant IK with W = I (KKT, or damped least
squares near singularities), the joint velocity scaled into its limits.
"""
import numpy as np

from pa10_ik_node.ik import dls_velocity, kkt_velocity, pose_error
from vgm_common.errors import InvalidInput


def _unit(v, key):
    v = np.asarray(v, dtype=float)
    norm = np.linalg.norm(v)
    if v.shape != (3,) or not np.isfinite(norm) or norm < 1e-12:
        raise InvalidInput(f'{key} must be a finite non-zero (3,) vector', key, v)
    return v / norm


def next_target_on_tangent_plane(P, normal, Q):
    """Next target Q' on the tangent plane at P and the tool frame E there (§6.4 steps 1-4).

    Simplification of step 3: Q is projected orthogonally onto the plane
    n.(x - P) = 0, not along the camera ray through Q (the same point when the ray is
    along the normal; it needs no camera pose).

    Args:
        P: (3,) contact point [m]; normal: (3,) surface normal (outward, any length);
        Q: (3,) next marker [m].

    Returns:
        (Q', T_E): Q' (3,) and the (4, 4) pose of E at P with z_E = -normal (approach into
        the surface), x_E = (Q' - P)/|Q' - P| (A7.10) and y_E = z_E x x_E.

    Raises:
        InvalidInput: on a zero normal, or Q' at P (no direction).
    """
    n = _unit(normal, 'normal')
    P, Q = np.asarray(P, dtype=float), np.asarray(Q, dtype=float)
    Q_plane = Q - n * np.dot(n, Q - P)
    z = -n
    x = _unit(Q_plane - P, 'Q - P')
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = P
    return Q_plane, T


def force_tilt_angle(measured_force, desired_force):
    """The thesis's tilt phi = pi (lambda_n - lambda_d) / (2 lambda_d) [rad] (7.3.15, A7.9)."""
    if not desired_force > 0:
        raise InvalidInput('desired_force must be > 0', 'desired_force', desired_force)
    return np.pi * (measured_force - desired_force) / (2.0 * desired_force)


def approach_correction(integral, measured_force, desired_force, stiffness, dt, gain=5.0,
                        max_depth=0.01):
    """Commanded depth [m] beyond the surface along the approach axis (PI force law).

    depth = desired_force / stiffness (feed-forward from the stiffness estimate) + integral,
    where the integral of gain * (desired - measured) / stiffness [m] runs only in contact
    (no wind-up during the approach) and is bounded to +-max_depth; depth is clipped to
    [0, max_depth]. With a linear spring contact the force settles at desired_force
    whatever the estimate's error.

    Returns:
        (depth, integral): the depth and the new integral state.
    """
    if not (desired_force > 0 and stiffness > 0 and dt >= 0 and max_depth > 0):
        raise InvalidInput('desired_force, stiffness, max_depth must be > 0 and dt >= 0')
    if measured_force > 0:
        integral += gain * dt * (desired_force - measured_force) / stiffness
        integral = float(np.clip(integral, -max_depth, max_depth))
    depth = float(np.clip(desired_force / stiffness + integral, 0.0, max_depth))
    return depth, integral


class TrackingController:
    """Follows a waypoint path with the tool tip, pressing with ``desired_force``.

    Args:
        robot: ``RobotModel`` (tool frame = the tip, z = approach axis).
        waypoints: (N, 4, 4) poses in base_link.
        desired_force: [N]; stiffness: contact stiffness estimate [N/m].
        speed: feed-forward speed along the path [m/s]; gain: pose gain [1/s].
        track_spin: False leaves the spin about the approach axis free (5 constraints).
        max_joint_velocity: [rad/s] scalar cap on top of the robot's limits (None: none).
        advance_distance: [m] the index advances when the tip is this close to its waypoint
            (pressed to the commanded depth); stop_distance: [m] the same for the first
            one (the end of the approach, which starts the force integral) and the last.
        max_linear_speed: [m/s] bound of the commanded linear twist (approach phase).
        sigma_threshold, damping: DLS is used when J's smallest singular value is lower.
    """

    def __init__(self, robot, waypoints, desired_force=5.0, stiffness=2000.0, speed=0.01,
                 gain=10.0, track_spin=False, max_joint_velocity=None, force_gain=5.0,
                 advance_distance=0.002, stop_distance=0.0005, max_linear_speed=0.05,
                 sigma_threshold=0.02, damping=0.05):
        waypoints = np.array(waypoints, dtype=float)
        if waypoints.ndim != 3 or waypoints.shape[1:] != (4, 4) or len(waypoints) < 1 \
                or not np.all(np.isfinite(waypoints)):
            raise InvalidInput('waypoints must be a finite (N, 4, 4) array', 'waypoints',
                               waypoints)
        self.robot, self.waypoints = robot, waypoints
        self.desired_force, self.stiffness = float(desired_force), float(stiffness)
        self.speed, self.gain, self.track_spin = speed, gain, track_spin
        self.force_gain = force_gain
        self.advance_distance, self.stop_distance = advance_distance, stop_distance
        self.max_linear_speed = max_linear_speed
        self.sigma_threshold, self.damping = sigma_threshold, damping
        limits = np.array(robot.velocity_limits, dtype=float)
        if max_joint_velocity is not None:
            limits = np.minimum(limits, max_joint_velocity)
        self.velocity_limits = limits
        self.index, self.integral, self.done = 0, 0.0, False

    def _desired_pose(self, depth):
        T = self.waypoints[self.index].copy()
        T[:3, 3] += depth * T[:3, 2]
        return T

    def step(self, q, measured_force, dt):
        """One control step: joint velocity (7,) [rad/s] and an info dict.

        info: 'index', 'done', 'depth' [m], 'phi' [rad] (7.3.15, logged only),
        'twist' (6,), 'dls' (whether DLS was used), 'T_desired'.
        """
        q = self.robot.check_q(q)
        depth, self.integral = approach_correction(  # no integral before the approach ends
            self.integral, measured_force, self.desired_force, self.stiffness,
            dt if self.index > 0 else 0.0, self.force_gain)
        T = self.robot.forward_kinematics(q)
        last = len(self.waypoints) - 1
        while True:  # advance past the (pressed) waypoints within reach
            distance = np.linalg.norm(self._desired_pose(depth)[:3, 3] - T[:3, 3])
            reach = self.advance_distance if self.index > 0 else self.stop_distance
            if self.index < last and distance < reach:
                self.index += 1
                continue
            break
        T_d = self._desired_pose(depth)
        error = pose_error(T, T_d)
        if self.index == last and np.linalg.norm(error[:3]) < self.stop_distance:
            self.done = True
        info = {'index': self.index, 'done': self.done, 'depth': depth, 'T_desired': T_d,
                'phi': force_tilt_angle(measured_force, self.desired_force), 'dls': False,
                'twist': np.zeros(6)}
        if self.done:
            return np.zeros(self.robot.n_joints), info

        approach = T_d[:3, 2]
        if not self.track_spin:  # tilt only: the rotation taking the tool's z onto approach
            axis = np.cross(T[:3, 2], approach)
            angle = np.arctan2(np.linalg.norm(axis), np.dot(T[:3, 2], approach))
            norm = np.linalg.norm(axis)
            error[3:] = axis / norm * angle if norm > 1e-12 else 0.0
        if 0 < self.index < last and distance < 2 * self.advance_distance:  # on the path:
            tangent = T_d[:3, 0]  # move along it at the set speed, correct across it
            error[:3] -= tangent * np.dot(tangent, error[:3])
            twist = self.gain * error
            twist[:3] += self.speed * tangent
        else:
            twist = self.gain * error
        linear = np.linalg.norm(twist[:3])
        if linear > self.max_linear_speed:
            twist[:3] *= self.max_linear_speed / linear

        info['twist'] = twist
        J = self.robot.jacobian(q)
        if not self.track_spin:  # rotate the angular rows to (b1, b2, approach), drop the last
            basis = np.linalg.svd(approach.reshape(1, 3))[2]  # rows: approach, b1, b2
            R = np.eye(6)
            R[3:, 3:] = np.roll(basis, -1, axis=0)
            J, twist = R @ J, R @ twist
            J[5], twist[5] = 0.0, 0.0
        active = J if self.track_spin else J[:5]
        if np.linalg.svd(active, compute_uv=False)[-1] < self.sigma_threshold:
            info['dls'] = True
            qdot = dls_velocity(J, twist, self.damping)
        else:
            qdot = kkt_velocity(J, np.eye(self.robot.n_joints), twist)[0]
        scale = np.max(np.abs(qdot) / self.velocity_limits)
        return (qdot / scale if scale > 1 else qdot), info
