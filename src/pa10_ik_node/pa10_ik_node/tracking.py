"""Force- and path-tracking control core of the PA-10 (ALGORITHMS.md §6.1, §6.3, §6.4). No ROS.

Waypoints are (N, 4, 4) poses in base_link (INTERFACES.md /curve/waypoints): origin on
the surface, x along the curve's tangent, z the approach direction into the surface.
``TrackingController`` runs the whole task as phases: approach (free-space move to a
pre-contact pose above the first waypoint, then descent along its approach axis until the
measured force reaches the desired one), contact (the force settles), tracking (a
reference runs along the path by arc length at ``speed``; the tool frame E comes from the
tangent-plane construction of §6.4; the depth along the approach axis from the force law
``force_law``: ``integral`` (ours) or ``tilt`` (the thesis's 7.3.15 rule, see
``tilted_motion``)), done (lift-off and hold); stop or any failure holds still. Each step turns the
reference pose and its feed-forward twist into joint velocities through ``RateSolver``
(pose feedback, so no drift accumulates).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from pa10_ik_node.ik import RateSolver, cross, pose_error, spin_free_task, tilt_error
from pa10_ik_node.path import WaypointPath
from pa10_ik_node.reach import first_unreachable, spaced_indices
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray
from vgm_common.robot_model import RobotModel, workspace_reach
from vgm_common.settings import setting


def _unit(v: npt.ArrayLike, key: str) -> FloatArray:
    v = np.asarray(v, dtype=float)
    norm = np.linalg.norm(v)
    if v.shape != (3,) or not np.isfinite(norm) or norm < 1e-12:
        raise InvalidInput(f'{key} must be a finite non-zero (3,) vector', key, v)
    return v / norm


def perpendicular(v: npt.ArrayLike) -> FloatArray:
    """A unit vector (3,) orthogonal to the non-zero (3,) ``v``."""
    v = _unit(v, 'v')
    other = np.eye(3)[int(np.argmin(np.abs(v)))]
    return _unit(cross(v, other), 'v x e')


def next_target_on_tangent_plane(
    P: npt.ArrayLike, normal: npt.ArrayLike, Q: npt.ArrayLike
) -> tuple[FloatArray, FloatArray]:
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
    T[:3, :3] = np.column_stack([x, cross(z, x), z])
    T[:3, 3] = P
    return Q_plane, T


def force_tilt_angle(measured_force: float, desired_force: float) -> float:
    """The thesis's tilt phi = pi (lambda_n - lambda_d) / (2 lambda_d) [rad] (7.3.15, A7.9)."""
    if not desired_force > 0:
        raise InvalidInput('desired_force must be > 0', 'desired_force', desired_force)
    return np.pi * (measured_force - desired_force) / (2.0 * desired_force)


def approach_correction(
    integral: float,
    measured_force: float,
    desired_force: float,
    stiffness: float,
    dt: float,
    gain: float = 5.0,
    max_depth: float = 0.01,
) -> tuple[float, float]:
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


def tilted_motion(
    measured_force: float, desired_force: float, advance: float
) -> tuple[float, float, float]:
    """The thesis's force rule (7.3.15, §6.4 step 7) applied to one step of the motion PQ'.

    At each new contact point the thesis rotates the tool frame E about its y axis by
    phi = pi (lambda_n - lambda_d) / (2 lambda_d) and takes the rotated z as the approach
    axis (the normal) for the next tangent plane, so the next motion along PQ' runs in
    the rotated x direction x' = cos(phi) x_E - sin(phi) z_E (z_E points into the
    surface). Only that part of Rot(y, phi) moves the tip: rotating the approach axis about
    the contact point leaves the tip, and so a frictionless point contact's normal force,
    unchanged. Here the next marker Q is the reference one control step ahead, so a step
    of ``advance`` [m] along the path becomes ``advance cos(phi)`` along the tangent x_E
    and ``-advance sin(phi)`` deeper along z_E: too little force (phi < 0) tilts the motion
    into the surface, too much (phi > 0) out of it; no contact at all (phi = -pi/2) goes
    straight in. phi is clipped to [-pi/2, pi/2] (lambda_n > 2 lambda_d: straight out).

    Returns:
        (phi [rad], tangential advance [m], depth change [m] along z_E).
    """
    phi = float(np.clip(force_tilt_angle(measured_force, desired_force), -np.pi / 2, np.pi / 2))
    return phi, advance * np.cos(phi), -advance * np.sin(phi)


FORCE_LAWS = ('integral', 'tilt')
MIN_RESPONSE = 0.4  # commands are scaled up at most 2.5 times (_compensated)
# The pose feedback's loop gain times the arm's uncovered lag the response scaling may
# reach: a loop whose only lag is a delay tau stays stable for gain x tau < pi / 2; at 0.5
# it keeps 61 degrees of phase margin (1 rang at 2-2.5 Hz over topics). A delayed arm
# also looks slow (it makes less of a changing command in time), and scaling up for that
# made a loop that had run at 10 / s x 0.1 s oscillate and stall (the full graph on a
# loaded machine, in process with commands 0.15 s late: failed, done without scaling).
MAX_GAIN_LAG = 0.5
# [s] The lag the gains are set for falls with this time constant after the measured one
# (it rises at once): the estimate dips while the arm's motion turns, and each dip let the
# full gains back in (over topics, force swings of 1.5-10 N within 2 s of each).
LAG_HOLD_S = 60.0
RESPONSE_WINDOW = 1.0  # [s] forgetting time of the response estimate
# [s] the commands kept to compare the arm's motion with: command_latency's range and
# the measured arm lag's (commands.MAX_LAG_S)
SENT_HISTORY_S = 0.6
MAX_INTEGRAL_SPEEDS = 1.0  # see TrackingConfig.pose_integral_gain
REACH_CHECK_SPACING_M = 0.002  # waypoints walked through before the arm moves
# [m] the descent reference runs at max_tip_speed until it is this far short of the first
# waypoint (judged on the reference, which the governor keeps at most governor_distance
# ahead of the measured tip), then at descent_speed: the contact is met slowly wherever the
# surface really is within the waypoints' depth error.
DESCENT_SLOW_DISTANCE_M = 0.005
# A start touching the surface within governor_distance of the first waypoint across its
# approach axis and this close to its orientation presses on from there (no lift-off).
IN_CONTACT_MAX_TILT_RAD = np.radians(5.0)
CURVATURE_LOOKAHEAD_M = 0.01  # [m] see TrackingConfig.max_lateral_acceleration
PHASES = ('idle', 'approach', 'contact', 'tracking', 'done', 'stopped', 'failed')
ACTIVE_PHASES = ('approach', 'contact', 'tracking')

# (T_desired (4, 4), feed-forward twist (6,) [m/s, rad/s], free_move) of a control step
_Reference = tuple[FloatArray, FloatArray, bool]


class Unreachable(InvalidInput):
    """Waypoints outside the arm's workspace, or a reference the arm cannot follow."""


@dataclass(frozen=True)
class TrackingConfig:
    """Settings of ``TrackingController``; the fields made by ``setting`` are
    pa10_ik_node's parameters of those names (``stiffness``: ``contact_stiffness``)."""

    desired_force: float = setting(5.0, 'Contact force to hold.', unit='N', range=(0.01, 200.0))
    stiffness: float = setting(
        2000.0,
        'Stiffness estimate (feed-forward depth; the integral law corrects its error).',
        unit='N/m',
        range=(1.0, 1e7),
        name='contact_stiffness',
    )
    force_gain: float = setting(
        5.0, 'Integral gain of the force law.', unit='1/s', range=(0.0, 100.0)
    )
    force_law: str = setting(
        'integral',
        "Force law: 'integral' (ours: depth = desired_force / contact_stiffness + integral "
        "of the force error) or 'tilt' (the thesis's 7.3.15: the motion PQ' tilted by phi "
        'into / out of the surface; acts only while moving along the path).',
        choices=FORCE_LAWS,
    )
    # 0.03 m/s keeps the in-process and topic goals (README, Measured).
    max_tip_speed: float = setting(
        0.03,
        "The tip's top speed: along the path, in the free-space move, in the descent until "
        '5 mm short of the first waypoint, in the lift-off.',
        unit='m/s',
        range=(1e-3, 0.2),
    )
    speed: float = setting(
        0.0,
        'Speed along the path, at most max_tip_speed; 0: max_tip_speed.',
        unit='m/s',
        range=(0.0, 0.2),
    )
    # [m/s^2] the path speed is also held to sqrt(this / curvature) over the next
    # CURVATURE_LOOKAHEAD_M: the tip's lateral error on a bend grows with v^2 x curvature
    # (a 145 mm figure eight bending down to 6 mm radius, in process: RMS 0.099 mm at a
    # constant 0.03 m/s, 0.012 mm with this limit); a gentle path runs at max_tip_speed.
    max_lateral_acceleration: float = 0.03
    # Scale commands by the arm's measured response (at most 1 / MIN_RESPONSE): in
    # process it meets the half-speed arms; an earlier version once overshot a Panda run
    # by 21 mm over topics.
    adapt_response: bool = setting(
        True,
        'Measure how much of the commanded motion the arm makes and scale commands up for '
        'an arm slower than commanded (at most 2.5 times, within the joint speed limits); '
        'the motion measured is compared with the command sent command_latency before.',
    )
    # A Smith predictor: a delayed arm otherwise trails or overshoots its reference; every
    # phase decision stays on the measured state.
    command_latency: float = setting(
        0.0,
        "The arm's delay from a command to its measured effect: the control law acts on the "
        'measured joints advanced by the commands of that time (a Smith predictor); 0: '
        'none assumed.',
        unit='s',
        range=(0.0, 0.5),
    )
    # An arm slower than commanded (a lag, a velocity scale) would otherwise trail the
    # reference by speed / pose_gain and cut the path's curves. Bounded to add at most
    # MAX_INTEGRAL_SPEEDS x ``speed``.
    pose_integral_gain: float = setting(
        20.0,
        "Integral of the tip's error across the approach axis while tracking (a slow arm "
        'trails its reference otherwise); 0 turns it off.',
        unit='1/s^2',
        range=(0.0, 200.0),
    )
    pose_gain: float = setting(10.0, 'Pose feedback gain.', unit='1/s', range=(0.1, 50.0))
    track_spin: bool = setting(
        False,
        'Also track the spin about the approach axis (6 constraints, as the seed); false '
        'leaves it free.',
    )
    standoff: float = setting(
        0.03, 'Pre-contact pose above the first waypoint.', unit='m', range=(0.005, 0.2)
    )
    descent_speed: float = setting(
        0.01,
        'The last 5 mm of the descent to contact (slowing as the force builds).',
        unit='m/s',
        range=(1e-4, 0.1),
    )
    lift_height: float = setting(
        0.03, 'Lift-off along the approach axis when done.', unit='m', range=(0.0, 0.2)
    )
    max_position_error: float = setting(
        0.01,
        'Tip farther than this from its reference for error_timeout: failure.',
        unit='m',
        range=(1e-4, 1.0),
    )
    error_timeout: float = setting(1.0, 'See max_position_error.', unit='s', range=(0.01, 60.0))
    max_angular_speed: float = 0.5  # [rad/s] free-space moves
    max_depth: float = 0.01  # [m] deepest commanded indentation; descent beyond: failure
    force_tolerance: float = 0.05  # relative band in which the contact counts as settled
    settle_time: float = 0.3  # [s] in that band before tracking starts
    contact_timeout: float = 5.0  # [s] tracking starts after this even if not settled
    ramp_time: float = 0.5  # [s] speed ramp at the start of tracking
    lookahead: float = 0.005  # [m] next marker Q ahead of the contact point P (§6.4)
    governor_distance: float = 0.002  # [m] the reference waits while the tip lags more
    reach_margin: float = 0.02  # [m] waypoints must lie this far inside the reach
    closed_tolerance: float = 0.01  # [m] path ends closer than this: a loop


@dataclass
class TrackingStats:
    """Lateral position errors [m] and force errors [N] over the tracking phase."""

    position_errors: list[float] = field(default_factory=list)
    force_errors: list[float] = field(default_factory=list)

    def summary(self) -> tuple[float, float]:
        """(rms position error [m], largest |force error| [N]); NaN when empty."""
        if not self.position_errors:
            return float('nan'), float('nan')
        return (
            float(np.sqrt(np.mean(np.square(self.position_errors)))),
            float(np.max(np.abs(self.force_errors))),
        )


class TrackingController:
    """The tracking task as a phase machine; ``step`` gives joint velocities.

    Args:
        robot: ``RobotModel`` (tool frame = the tip, z = approach axis).
        solver: ``RateSolver`` (method, W, limits handling).
        config: ``TrackingConfig``.
        max_joint_velocity: [rad/s] cap on top of the robot's limits (None: none).
        tip_description: how the model's tip was made (e.g. "tip_frame 'tool0' + tool_length
            0.1 m"), named when contact comes where the model says it cannot.

    Attributes:
        phase: one of ``PHASES``; reason: why the controller stopped or failed ('' else).
        progress: 0..1 along the path (tracking); stats: ``TrackingStats``.
        arm_lag: [s] the arm's measured lag behind the commands, kept up to date by the
            caller (pa10_ik_node.commands.SetPointCommands.lag): the gains are set for
            it (``_lag_gain_scale``).
    """

    def __init__(
        self,
        robot: RobotModel,
        solver: RateSolver,
        config: TrackingConfig | None = None,
        max_joint_velocity: float | None = None,
        tip_description: str = '',
    ) -> None:
        self.robot, self.solver = robot, solver
        self.tip_description = tip_description or 'tip_frame and tool_length'
        self.config = TrackingConfig() if config is None else config
        self.configure()  # validates force_law
        limits = np.array(robot.velocity_limits, dtype=float)
        if max_joint_velocity is not None:
            limits = np.minimum(limits, max_joint_velocity)
        self.velocity_limits = limits
        self.shoulder, self.reach = workspace_reach(robot)
        self.phase, self.reason = 'idle', ''
        self.path: WaypointPath | None = None
        self.arm_lag = 0.0
        self.held_lag = 0.0  # [s] the lag the gains are set for (LAG_HOLD_S)
        self._reset_state()

    def _reset_state(self) -> None:
        self.stage = ''  # approach: 'free' or 'descend'; done: lifting
        self.integral, self.time_in_phase, self.settled_time = 0.0, 0.0, 0.0
        self.depth = 0.0  # [m] commanded indentation along the approach axis
        self.s_start = self.s_ref = self.travelled = 0.0
        self.error_time = 0.0
        self.best_distance, self.stall_time = np.inf, 0.0
        self.progress, self.stats = 0.0, TrackingStats()
        self.T_hold: FloatArray | None = None
        self.T_end: FloatArray | None = None
        self.reference_depth = 0.0  # [m] descent reference along the approach axis
        self.lift_reference, self.wait_time, self.end_time = 0.0, 0.0, 0.0
        self.pose_integral = np.zeros(3)  # [m s] in T_desired's axes: see pose_integral_gain
        self.reference_moving = False
        self.force_before_free_move: float | None = None  # [N] at the first approach step
        self.response = 1.0  # fraction of the commanded motion the arm makes (estimated)
        self.response_sums = np.zeros(2)  # [m] (made, commanded), see _update_response
        self.last_tip: FloatArray | None = None
        self.last_tip_velocity: FloatArray | None = None
        # (dt [s], qdot (n,)) of the commands within command_latency
        self.pending: list[tuple[float, FloatArray]] = []
        # (dt [s], tip velocity (3,)) of the commands of the last SENT_HISTORY_S, newest last
        self.sent_tip_velocities: deque[tuple[float, FloatArray]] = deque()
        self.solver.reset()

    def configure(self, **changes: Any) -> None:
        """Change settings (between or during runs)."""
        law = changes.get('force_law', self.config.force_law)
        if law not in FORCE_LAWS:
            raise InvalidInput(f'force_law must be one of {FORCE_LAWS}', 'force_law', law)
        config = replace(self.config, **changes)
        if not config.max_tip_speed > 0:
            raise InvalidInput('max_tip_speed must be > 0', 'max_tip_speed', config.max_tip_speed)
        self.config = config

    @property
    def path_speed(self) -> float:
        """[m/s] The reference's speed along the path: ``speed``, or ``max_tip_speed``
        when ``speed`` is 0 or faster."""
        c = self.config
        return c.max_tip_speed if c.speed <= 0 else min(c.speed, c.max_tip_speed)

    # --- commands --------------------------------------------------------------------

    def check_reachable(self, path: WaypointPath) -> None:
        """Raises ``Unreachable`` if a waypoint or the pre-contact pose is out of reach."""
        c = self.config
        points = np.vstack([path.points, path.points[:1] - c.standoff * path.approach[:1]])
        distances = np.linalg.norm(points - self.shoulder, axis=1)
        worst = int(np.argmax(distances))
        if distances[worst] > self.reach - c.reach_margin:
            raise Unreachable(
                f'waypoint {min(worst, len(path.points) - 1)} at {points[worst].round(3)} is '
                f'{distances[worst]:.3f} m from the shoulder, beyond the reach '
                f'{self.reach:.3f} m - {c.reach_margin} m margin',
                'waypoints',
                points[worst],
            )

    def check_joint_reachable(self, path: WaypointPath, q: npt.ArrayLike) -> None:
        """Raises ``Unreachable`` naming the first target (the pre-contact pose, then the
        waypoints every ``REACH_CHECK_SPACING_M``, pressed in by the feed-forward depth)
        that the model, walked from the joints ``q`` (n,) [rad], cannot reach within its
        joint limits at the task's orientation freedom (``track_spin``), and by how much."""
        c = self.config
        T = path.T.copy()
        T[:, :3, 3] += min(c.desired_force / c.stiffness, c.max_depth) * T[:, :3, 2]
        pre_contact = path.T[0].copy()
        pre_contact[:3, 3] -= c.standoff * pre_contact[:3, 2]
        indices = spaced_indices(T[:, :3, 3], REACH_CHECK_SPACING_M)
        miss = first_unreachable(
            self.robot, q, np.concatenate([pre_contact[None], T[indices]]), c.track_spin
        )
        if miss is None:
            return
        what = (
            f'the pre-contact pose {c.standoff * 1e3:.0f} mm before waypoint 0'
            if miss.index == 0
            else f'waypoint {indices[miss.index - 1]} at '
            f'{path.T[indices[miss.index - 1], :3, 3].round(3)}'
        )
        limits = ', '.join(miss.joints_at_limit) or 'none'
        axis = 'orientation' if c.track_spin else 'approach axis'
        raise Unreachable(
            f'{what} is out of reach within the joint limits: the arm gets no closer than '
            f'{miss.position_error_m * 1e3:.1f} mm and {np.degrees(miss.angle_error_rad):.1f} '
            f'deg of its {axis} (joints at a limit: {limits})',
            'waypoints',
            miss.index,
        )

    def start(self, waypoints: npt.ArrayLike, q: npt.ArrayLike | None = None) -> None:
        """Begin the task on ``waypoints`` (N, 4, 4) from the measured joints ``q`` (n,)
        [rad] (None: only the workspace sphere is checked). Raises ``InvalidInput`` /
        ``Unreachable`` and stays as it was if they cannot be followed."""
        path = WaypointPath(waypoints, self.config.closed_tolerance)
        self.check_reachable(path)
        if q is not None:
            self.check_joint_reachable(path, q)
        self.path = path
        self._reset_state()
        self._enter('approach', 'free')

    def update_path(self, waypoints: npt.ArrayLike, tip: FloatArray) -> None:
        """Take over a new path while running: continue from its point nearest to the tip
        (``tip`` (3,)), keeping the fraction of a loop already travelled."""
        path = WaypointPath(waypoints, self.config.closed_tolerance)
        self.check_reachable(path)
        old = self.path
        if self.phase != 'tracking' or old is None:
            self.path = path
            return
        fraction = self.travelled / old.length if old.length > 0 else 0.0
        around = (
            (self.s_start + fraction * path.length) % path.length
            if path.closed
            else fraction * path.length
        )
        s_near, _ = path.nearest(tip, around, window=0.25 * path.length)
        self.path = path
        self.travelled = fraction * path.length
        self.s_start = s_near - self.travelled if path.closed else 0.0
        self.s_ref = s_near if not path.closed else self.s_start + self.travelled

    def stop(self, reason: str = 'stop requested') -> None:
        """Hold still. A failed task becomes stopped (the stop acknowledges the failure;
        its reason is kept in the new one); a stopped one stays as it is."""
        if self.phase == 'stopped':
            return
        if self.phase == 'failed':
            reason = f'{reason} (after: {self.reason})'
        self.phase, self.reason = 'stopped', reason

    def fail(self, reason: str) -> None:
        """End the task as failed, for ``reason``: the arm holds still until the next
        start."""
        self.phase, self.reason = 'failed', reason

    def _enter(self, phase: str, stage: str = '') -> None:
        self.phase, self.stage, self.time_in_phase = phase, stage, 0.0
        self.best_distance, self.stall_time, self.error_time = np.inf, 0.0, 0.0
        self.pose_integral = np.zeros(3)

    # --- the control step ------------------------------------------------------------

    def _sample(self, s: float) -> tuple[FloatArray, FloatArray, FloatArray]:
        path = self.path
        assert path is not None  # set by start() before any phase that samples it
        return path.sample(s % path.length if path.closed else s)

    def _frame(self, s: float, position: FloatArray) -> FloatArray:
        """The tool frame E at arc length ``s`` (§6.4 steps 1-4): z = approach, x towards
        the next marker Q projected on the tangent plane; origin ``position``."""
        P, z, tangent = self._sample(s)
        Q = self._sample(s + self.config.lookahead)[0]
        if np.linalg.norm(Q - P) < 1e-9:
            Q = P + tangent * self.config.lookahead
        # Q' at P (Q along the approach axis): fall back to the tangent, then to any
        # direction across the approach axis.
        for ahead in (Q, P + tangent, P + perpendicular(z)):
            try:
                _, T = next_target_on_tangent_plane(P, -z, ahead)
                break
            except InvalidInput:
                continue
        T[:3, 3] = position
        return T

    def step(
        self, q: npt.ArrayLike, measured_force: float, dt: float
    ) -> tuple[FloatArray, dict[str, Any]]:
        """One control step at joints ``q`` (n,) [rad] with the measured force [N] over
        ``dt`` [s]. Returns (qdot (n,) [rad/s], info dict)."""
        q = self.robot.check_q(q)
        T = self.robot.forward_kinematics(q)
        c = self.config
        self.time_in_phase += dt
        self.last_dt = dt
        info: dict[str, Any] = {  # str, floats and (4, 4) poses, the solver's info
            'phase': self.phase,
            'phi': force_tilt_angle(measured_force, c.desired_force),
            'force_error': measured_force - c.desired_force,
            'T': T,
            'position_error': float('nan'),
        }
        if self.phase not in ACTIVE_PHASES and self.phase != 'done':
            return np.zeros(self.robot.n_joints), info
        target = self._reference(T, measured_force, dt, info)
        if target is None:  # the phase machine stopped or failed
            info['phase'] = self.phase
            return np.zeros(self.robot.n_joints), info
        T_d, feed_forward, free_move = target
        info.update(phase=self.phase, T_desired=T_d)
        self.held_lag = max(self.arm_lag, self.held_lag * float(np.exp(-dt / LAG_HOLD_S)))
        self._update_response(T[:3, 3], dt)
        q_ahead = self._predicted(q)
        T_ahead = T if q_ahead is q else self.robot.forward_kinematics(q_ahead)
        qdot, solve_info = self._solve(q_ahead, T_ahead, T_d, feed_forward, free_move)
        J_ahead = solve_info.pop('J')
        info.update(solve_info)
        qdot = self._compensated(qdot)
        # The solve's Jacobian where it was at q (no latency assumed): computed once.
        J = J_ahead if q_ahead is q else self.robot.jacobian(q)
        self.last_tip, self.last_tip_velocity = T[:3, 3].copy(), (J @ qdot)[:3]
        self._remember_command(qdot, dt)
        self.sent_tip_velocities.append((dt, self.last_tip_velocity))
        while sum(step for step, _ in self.sent_tip_velocities) > SENT_HISTORY_S:
            self.sent_tip_velocities.popleft()
        info['response'] = self.response
        return qdot, info

    def _governor_distance(self) -> float:
        """[m] How far the measured tip may trail its reference before the reference
        waits: ``governor_distance`` plus what the tip moves at max_tip_speed within the
        arm's lag (the commands on their way: ``command_latency``, or the lag measured
        if longer). Without the measured lag a reference 3 mm ahead of an arm 0.1 s late
        at 0.03 m/s stopped and went every 0.1-0.2 s (over topics: its feed-forward on
        and off, commanded joint speeds 16 <-> 35 mrad/s, force swings of +-1.3 N)."""
        c = self.config
        return c.governor_distance + c.max_tip_speed * max(c.command_latency, self.held_lag)

    def _predicted(self, q: FloatArray) -> FloatArray:
        """The measured joints ``q`` advanced by the commands still on their way (those of
        the last ``command_latency``); ``q`` itself when no latency is assumed."""
        if self.config.command_latency <= 0 or not self.pending:
            return q
        ahead = q + sum(step * qdot for step, qdot in self.pending)
        return np.clip(ahead, self.robot.lower_limits, self.robot.upper_limits)

    def _remember_command(self, qdot: FloatArray, dt: float) -> None:
        """Keep the commands of the last ``command_latency`` for ``_predicted``."""
        latency = self.config.command_latency
        if latency <= 0 or dt <= 0:
            self.pending = []
            return
        self.pending.append((dt, qdot.copy()))
        while sum(step for step, _ in self.pending) > latency + 1e-9:
            self.pending.pop(0)

    def _update_response(self, tip: FloatArray, dt: float) -> None:
        """Estimate how much of the commanded tip motion the arm makes (1: all of it; an
        arm slower than commanded less): the measured tip's displacement along the
        velocity commanded the arm's lag before, over the commanded distance, both summed with
        a forgetting time of ``RESPONSE_WINDOW`` (a delayed or jittery measurement
        averages out), counted only while the command moves the tip fast enough to
        measure."""
        c = self.config
        # The motion measured now answers the command sent the arm's lag ago (measured, or
        # command_latency): compared with the newest command instead, a delayed arm looked
        # slow wherever the command turned (over topics, 0.8 -> 0.4 within a second on a
        # bend, and scaled up it oscillated).
        v = self._tip_velocity_sent_before(max(self.arm_lag, c.command_latency))
        if self.last_tip is None or v is None or dt <= 0 or not c.adapt_response:
            return
        speed = float(np.linalg.norm(v))
        forget = np.exp(-dt / RESPONSE_WINDOW)
        self.response_sums *= forget
        if speed >= 0.3 * self.path_speed:
            self.response_sums += (float(np.dot(tip - self.last_tip, v)) / speed, speed * dt)
        made, commanded = self.response_sums
        if commanded > 0.3 * self.path_speed * RESPONSE_WINDOW / 2:  # enough motion to judge
            self.response = float(np.clip(made / commanded, MIN_RESPONSE, 1.0))

    def _lag_gain_scale(self) -> float:
        """How far the pose feedback's gain may be scaled and stay stable over the arm's
        lag the predictor does not cover: MAX_GAIN_LAG / (pose_gain x that lag); inf
        without one. Below 1 the pose and force gains are scaled down by it together (the
        force law's loop stays slower than the pose loop it acts through); above 1 it
        bounds the response scaling."""
        c = self.config
        uncovered_lag = self.held_lag - max(c.command_latency, 0.0)
        return MAX_GAIN_LAG / (c.pose_gain * uncovered_lag) if uncovered_lag > 0 else np.inf

    def _tip_velocity_sent_before(self, lag: float) -> FloatArray | None:
        """(3,) [m/s] The tip velocity of the command sent ``lag`` [s] before the newest
        (the oldest kept, if longer ago); None before any."""
        age = 0.0
        for step, velocity in reversed(self.sent_tip_velocities):
            if age >= lag - 1e-9:
                return velocity
            age += step
        return self.sent_tip_velocities[0][1] if self.sent_tip_velocities else None

    def _compensated(self, qdot: FloatArray) -> FloatArray:
        """qdot scaled up by 1 / response, no more than keeps the pose loop stable over
        the arm's lag the predictor does not cover (MAX_GAIN_LAG), within the velocity
        limits."""
        scale = min(1.0 / self.response, max(1.0, self._lag_gain_scale()))
        if scale <= 1.0:
            return qdot
        scaled = qdot * scale
        over = np.max(np.abs(scaled) / self.velocity_limits)
        return scaled / over if over > 1.0 else scaled

    def _reference(
        self, T: FloatArray, force: float, dt: float, info: dict[str, Any]
    ) -> _Reference | None:
        """(T_desired, feed-forward twist (6,), free_move) of the current phase; None
        if the phase machine stopped."""
        if self.phase == 'approach':
            return self._approach_reference(T, force, dt, info)
        if self.phase == 'contact':
            return self._contact_reference(T, force, dt)
        if self.phase == 'tracking':
            return self._tracking_reference(T, force, dt, info)
        return self._lift(T, dt)  # done: lift off along the approach axis and hold

    def _approach_reference(
        self, T: FloatArray, force: float, dt: float, info: dict[str, Any]
    ) -> _Reference | None:
        """Approach: a free-space move to the pre-contact pose ``standoff`` above the first
        waypoint, then the descent (``_descend``)."""
        c = self.config
        tip = T[:3, 3]
        P0, z0, _ = self._sample(0.0)
        if self.stage == 'free':
            if self.force_before_free_move is None:
                self.force_before_free_move = force
            if self._unexpected_contact(tip, P0, z0, force, 'moving in free space'):
                return None
            if self._touching_first_waypoint(T, P0, z0, force):
                self.stage = 'descend'  # press on from here: no lift-off and re-approach
                self.reference_depth = float(np.dot(tip - P0, z0))
                self.best_distance, self.stall_time = np.inf, 0.0
                return self._descend(T, P0, z0, force, dt, info)
            T_d = self._frame(0.0, P0 - c.standoff * z0)
            distance = float(np.linalg.norm(T_d[:3, 3] - tip))
            angle = float(np.linalg.norm(tilt_error(T[:3, :3], z0)))
            if distance < 0.001 and angle < 0.01:
                self.stage = 'descend'
                self.reference_depth = float(np.dot(tip - P0, z0))
                self.best_distance, self.stall_time = np.inf, 0.0
            elif not self._progressing(distance + 0.05 * angle, dt):
                self.fail(
                    f'cannot reach the pre-contact pose: {distance * 1e3:.1f} mm '
                    f'away, no progress for {c.error_timeout * 2:.1f} s'
                )
                return None
            else:
                return T_d, np.zeros(6), True
        return self._descend(T, P0, z0, force, dt, info)

    def _touching_first_waypoint(
        self, T: FloatArray, P0: FloatArray, z0: FloatArray, force: float
    ) -> bool:
        """Whether the measured tip (pose ``T``) already touches the surface at the first
        waypoint ``P0`` (approach axis ``z0``): some force, within governor_distance of it
        across the axis and max_depth along it, tilted less than IN_CONTACT_MAX_TILT_RAD."""
        c = self.config
        offset = T[:3, 3] - P0
        along = float(np.dot(offset, z0))
        across = float(np.linalg.norm(offset - along * z0))
        return (
            force >= c.force_tolerance * c.desired_force
            and across < c.governor_distance
            and abs(along) <= c.max_depth
            and float(np.linalg.norm(tilt_error(T[:3, :3], z0))) < IN_CONTACT_MAX_TILT_RAD
        )

    def _force_law_depth(self, force: float, dt: float) -> float:
        """[m] The integral force law's depth (``approach_correction``) after ``dt`` [s]
        at the measured ``force`` [N], its gain scaled down with the pose gain's over a
        lagging arm (``_lag_gain_scale``)."""
        c = self.config
        gain = c.force_gain * min(1.0, self._lag_gain_scale())
        depth, self.integral = approach_correction(
            self.integral, force, c.desired_force, c.stiffness, dt, gain, c.max_depth
        )
        return depth

    def _contact_reference(self, T: FloatArray, force: float, dt: float) -> _Reference | None:
        """Contact: hold the first waypoint at the force law's depth until the force has
        settled in its band (or ``contact_timeout``), then start tracking."""
        c = self.config
        depth = self._force_law_depth(force, dt)
        P0, z0, _ = self._sample(0.0)
        in_band = abs(force - c.desired_force) <= c.force_tolerance * c.desired_force
        self.settled_time = self.settled_time + dt if in_band else 0.0
        self.depth = depth  # the tilt law starts tracking from the settled depth
        if self.settled_time >= c.settle_time or self.time_in_phase > c.contact_timeout:
            self._enter('tracking')
            self.s_start = self.s_ref = self.travelled = 0.0
        T_d = self._frame(0.0, P0 + depth * z0)
        return self._checked(T, T_d, np.zeros(6), dt)

    def _tracking_reference(
        self, T: FloatArray, force: float, dt: float, info: dict[str, Any]
    ) -> _Reference | None:
        """Tracking: the reference runs along the path at the ramped ``speed`` (waiting
        for a lagging tip) at the force law's depth; done once the path is travelled."""
        c = self.config
        path = self.path
        assert path is not None  # tracking runs on the started path
        tip = T[:3, 3]
        if c.force_law != 'tilt':
            self.depth = self._force_law_depth(force, dt)
        remaining = path.length - self.travelled
        # Gains cut by the arm's lag (_lag_gain_scale) reject the waypoints' depth errors
        # along the path as much slower, so the reference slows alike: the full graph on
        # a loaded machine (lag ~0.1 s, gains halved) at 19 mm/s pressed 4.1-6.2 N over a
        # 0.5 mm depth error of the waypoints, in the +-10 % band 93-95 % of the time.
        speed = (
            min(self.path_speed, self._bend_speed())
            * min(1.0, self._lag_gain_scale())
            * min(1.0, max(self.time_in_phase / c.ramp_time, 0.05))
        )
        motion = self._advance_reference(tip, force, speed, remaining, dt)
        if motion is None:
            return None
        direction, advanced = motion
        self.progress = self.travelled / path.length
        P, z, tangent = self._sample(self.s_ref)
        T_d = self._frame(self.s_ref, P + self.depth * z)
        moving = self.travelled < path.length and advanced
        self.reference_moving = moving
        # Feed-forward no faster than the reference can still go (the path's end),
        # along the path itself: x_E points at the marker Q ahead (a chord), which
        # on a curve would push the tip inwards.
        speed = min(speed, remaining / dt) if dt > 0 else speed
        along = self._along_path(tangent, z, T_d)
        velocity = speed * (direction[0] * along + direction[1] * z)
        feed_forward = np.concatenate([velocity if moving else np.zeros(3), np.zeros(3)])
        self._record_tracking_errors(tip, force, info)
        self._finish_when_travelled(T_d, tip, dt)
        return self._checked(T, T_d, feed_forward, dt)

    def nominal_tracking_time(self) -> float:
        """[s] How long the started path takes at the path speed, slowed on its bends
        (no speed ramp, no waiting for a lagging arm)."""
        assert self.path is not None  # set by start()
        return self.path.nominal_duration(self.path_speed, self.config.max_lateral_acceleration)

    def _bend_speed(self) -> float:
        """[m/s] The fastest speed along the path that keeps the lateral acceleration
        within max_lateral_acceleration over the next CURVATURE_LOOKAHEAD_M."""
        assert self.path is not None  # tracking runs on the started path
        curvature = self.path.largest_curvature(self.s_ref, self.s_ref + CURVATURE_LOOKAHEAD_M)
        a = self.config.max_lateral_acceleration
        return float(np.sqrt(a / curvature)) if curvature > 0 and a > 0 else np.inf

    def _advance_reference(
        self, tip: FloatArray, force: float, speed: float, remaining: float, dt: float
    ) -> tuple[tuple[float, float], bool] | None:
        """Move the reference ``s_ref`` on by ``speed`` [m/s] unless the tip lags it by
        ``governor_distance`` or more; under the tilt law the step is tilted into / out of
        the surface. Returns (direction of motion in E, advanced), or None after failing
        on a tip that lagged for 2 error_timeouts."""
        c = self.config
        tilt = c.force_law == 'tilt'
        P, z, _ = self._sample(self.s_ref)
        lag = float(np.linalg.norm(P + self.depth * z - tip))
        # Direction of motion in E: (along x_E, along z_E) per unit path step.
        direction = (1.0, 0.0)
        advanced = lag < self._governor_distance()
        self.wait_time = 0.0 if advanced else self.wait_time + dt
        if self.wait_time > 2 * c.error_timeout:
            self.fail(
                f'the tool tip lags its reference by {lag * 1e3:.1f} mm (measured) '
                f'for {self.wait_time:.1f} s: the arm does not follow'
            )
            return None
        if advanced:  # the reference waits for a lagging tip
            advance = min(speed * dt, remaining)
            if tilt:  # the thesis: PQ' tilted by phi into / out of the surface
                phi, advance, deeper = tilted_motion(force, c.desired_force, advance)
                direction = (np.cos(phi), -np.sin(phi))
                self.depth = float(np.clip(self.depth + deeper, 0.0, c.max_depth))
                if remaining - advance < 1e-6:  # no endless creep towards the end
                    advance = remaining
            self.s_ref += advance
            self.travelled += advance
        return direction, advanced

    @staticmethod
    def _along_path(tangent: FloatArray, z: FloatArray, T_d: FloatArray) -> FloatArray:
        """The unit path tangent across the approach axis ``z``; x_E of ``T_d`` where the
        tangent is along z."""
        along = tangent - z * np.dot(z, tangent)
        along_norm = np.linalg.norm(along)
        return along / along_norm if along_norm > 1e-9 else T_d[:3, 0]

    def _record_tracking_errors(self, tip: FloatArray, force: float, info: dict[str, Any]) -> None:
        """The tip's lateral distance [m] to the path near the reference (into ``info``
        and the stats) and the force error [N]."""
        path = self.path
        assert path is not None  # tracking runs on the started path
        s_near, _ = path.nearest(
            tip, self.s_ref % path.length if path.closed else self.s_ref, window=0.05
        )
        lateral = path.lateral_distance(tip, s_near)
        info['position_error'] = lateral
        self.stats.position_errors.append(lateral)
        self.stats.force_errors.append(force - self.config.desired_force)

    def _finish_when_travelled(self, T_d: FloatArray, tip: FloatArray, dt: float) -> None:
        """Once the path is travelled: done (lift-off) when the tip is at the end pose, or
        a second after the end at the latest."""
        assert self.path is not None  # tracking runs on the started path
        if self.travelled >= self.path.length:
            self.end_time += dt
            if np.linalg.norm(T_d[:3, 3] - tip) < 0.0005 or self.end_time > 1.0:
                self._enter('done', 'lifting')
                self.lift_reference = 0.0
            self.T_end = T_d.copy()

    def _descend(
        self,
        T: FloatArray,
        P0: FloatArray,
        z0: FloatArray,
        force: float,
        dt: float,
        info: dict[str, Any],
    ) -> _Reference | None:
        """Descent along the first approach axis until the measured force reaches the
        desired one, judged on the measured tip: the reference runs at most
        ``governor_distance`` ahead of it (an arm slower than commanded is waited for),
        the tip may go ``max_depth`` past the first waypoint (distance budget) and must
        keep going (stall budget: 1 mm, or the force's worth of it, per 2
        error_timeouts)."""
        c = self.config
        tip = T[:3, 3]
        depth = float(np.dot(tip - P0, z0))  # [m] measured, > 0 past the first waypoint
        info['measured_depth'] = depth
        if force >= c.desired_force:
            if self._unexpected_contact(tip, P0, z0, force, 'descending'):
                return None
            self._enter('contact')
            return self._reference(T, force, 0.0, info)
        if depth > c.max_depth:
            self.fail(
                f'no contact: the tip is {depth * 1e3:.1f} mm past the first waypoint '
                f'along its approach axis (measured) with {force:.2f} N of the '
                f'desired {c.desired_force:g} N; probable cause: the real tip is shorter '
                f"than the model's ({self.tip_description}: a URDF whose tip frame is the "
                'tool tip needs tool_length 0) or the surface lies farther along the '
                'approach axis than the waypoints (its pose)'
            )
            return None
        if not self._progressing(-depth - max(force, 0.0) / c.stiffness, dt):
            self.fail(
                f'descent stalled: the tip moved less than 1 mm along the approach '
                f'axis in {2 * c.error_timeout:.1f} s (at {depth * 1e3:.1f} mm from the '
                f'first waypoint, {force:.2f} N)'
            )
            return None
        previous = self.reference_depth
        if previous < -DESCENT_SLOW_DISTANCE_M and force < c.force_tolerance * c.desired_force:
            # In free space, far from contact: at the top speed.
            step = min(c.max_tip_speed * dt, -DESCENT_SLOW_DISTANCE_M - previous)
        else:
            slow = min(c.descent_speed, c.max_tip_speed)
            step = slow * np.clip(1.0 - force / c.desired_force, 0.2, 1.0) * dt
        self.reference_depth = max(
            previous, min(previous + step, depth + self._governor_distance())
        )
        rate = (self.reference_depth - previous) / dt if dt > 0 else 0.0
        T_d = self._frame(0.0, P0 + self.reference_depth * z0)
        feed_forward = np.concatenate([rate * z0, np.zeros(3)])
        return self._checked(T, T_d, feed_forward, dt)

    def _unexpected_contact(
        self, tip: FloatArray, P0: FloatArray, z0: FloatArray, force: float, doing: str
    ) -> bool:
        """Fail (and True) on a contact the model says cannot be there: a force appearing,
        or the desired force reached, with the tip more than ``max_depth`` before the
        first waypoint along its approach axis; the real tip or the surface is then not
        where the model and the waypoints put them. (A free-space move that brushes a
        curved surface level with the waypoints goes on, as it always did.)"""
        c = self.config
        above = float(np.dot(P0 - tip, z0))  # [m] measured, > 0 before the first waypoint
        before = self.force_before_free_move or 0.0
        touching = force >= c.force_tolerance * c.desired_force and not (
            doing != 'descending' and before >= c.force_tolerance * c.desired_force
        )
        if not (touching and above > c.max_depth):
            return False
        self.fail(
            f'unexpected contact: {force:.2f} N while {doing} with the tip {above * 1e3:.1f} '
            'mm before the first waypoint along its approach axis (measured); probable '
            f"cause: the real tip reaches farther than the model's ({self.tip_description}: "
            'too short a tool_length or the wrong tip_frame) or the surface lies nearer '
            'than the waypoints (its pose)'
        )
        return True

    def _lift(self, T: FloatArray, dt: float) -> _Reference | None:
        """Lift-off along the last approach axis by ``lift_height``, on the measured tip:
        the reference leads it by at most ``governor_distance``; stage 'lifted' once the
        tip is there, a failure if it stalls."""
        c = self.config
        assert self.T_end is not None  # set by _finish_when_travelled on entering 'done'
        T_d = self.T_end.copy()
        z = T_d[:3, 2]
        lifted = float(np.dot(self.T_end[:3, 3] - T[:3, 3], z))  # [m] measured
        previous = self.lift_reference
        if self.stage == 'lifting':
            if lifted >= c.lift_height - 0.0005:
                self.stage = 'lifted'
            elif not self._progressing(c.lift_height - lifted, dt):
                self.fail(
                    f'lift-off stalled: the tip rose {lifted * 1e3:.1f} of '
                    f'{c.lift_height * 1e3:.0f} mm, no progress for '
                    f'{2 * c.error_timeout:.1f} s'
                )
                return None
            self.lift_reference = max(
                previous,
                min(
                    previous + c.max_tip_speed * dt,
                    lifted + self._governor_distance(),
                    c.lift_height,
                ),
            )
        T_d[:3, 3] -= self.lift_reference * z
        feed_forward = np.zeros(6)
        if dt > 0:
            feed_forward[:3] = -(self.lift_reference - previous) / dt * z
        return T_d, feed_forward, False

    def _progressing(self, distance: float, dt: float) -> bool:
        """False once ``distance`` has not dropped by 1 mm for 2 error_timeouts."""
        if distance < self.best_distance - 0.001:
            self.best_distance, self.stall_time = distance, 0.0
        else:
            self.stall_time += dt
        return self.stall_time < 2 * self.config.error_timeout

    def _checked(
        self, T: FloatArray, T_d: FloatArray, feed_forward: FloatArray, dt: float
    ) -> _Reference | None:
        """The reference, unless the tip has been farther than max_position_error from it
        for error_timeout (the arm cannot follow: out of reach, at its limits)."""
        error = np.linalg.norm(T_d[:3, 3] - T[:3, 3])
        self.error_time = self.error_time + dt if error > self.config.max_position_error else 0.0
        if self.error_time > self.config.error_timeout:
            self.fail(
                f'cannot follow the path: the tool tip is {error * 1e3:.1f} mm from '
                f'its reference at {T_d[:3, 3].round(3)} (out of reach or at the '
                'joint limits)'
            )
            return None
        return T_d, feed_forward, False

    def _solve(
        self,
        q: FloatArray,
        T: FloatArray,
        T_d: FloatArray,
        feed_forward: FloatArray,
        free_move: bool,
    ) -> tuple[FloatArray, dict[str, Any]]:
        c = self.config
        error = pose_error(T, T_d)
        if not c.track_spin:
            error[3:] = tilt_error(T[:3, :3], T_d[:3, 2])
        twist = feed_forward + c.pose_gain * min(1.0, self._lag_gain_scale()) * error
        if not (self.phase == 'tracking' and self.reference_moving):
            # Only while the reference moves: at the path's end or while it waits for the
            # tip, a held integral would push the tip on past its reference.
            self.pose_integral = np.zeros(3)
        elif c.pose_integral_gain > 0:
            # Kept in the reference frame's x, y (along the path, across it), so it turns
            # with the path: a base-frame sum of the trailing error, held while the path
            # bends, pushed the tip outwards (over topics, a 5 cm bend at 15 mm/s: 0.1 mm).
            R_d = T_d[:3, :3]
            error_E = R_d.T @ error[:3]
            self.pose_integral[:2] += error_E[:2] * self.last_dt  # z: the force law's
            bound = MAX_INTEGRAL_SPEEDS * self.path_speed / c.pose_integral_gain
            norm = np.linalg.norm(self.pose_integral)
            if norm > bound:
                self.pose_integral *= bound / norm
            twist[:3] += c.pose_integral_gain * (R_d @ self.pose_integral)
        if free_move:
            linear, angular = np.linalg.norm(twist[:3]), np.linalg.norm(twist[3:])
            if linear > c.max_tip_speed:
                twist[:3] *= c.max_tip_speed / linear
            if angular > c.max_angular_speed:
                twist[3:] *= c.max_angular_speed / angular
        started = time.perf_counter()  # the IK: the Jacobian, the task, the solve
        J_full = self.robot.jacobian(q)
        if not c.track_spin:
            J, task = spin_free_task(J_full, twist, T_d)
        else:
            J, task = J_full, twist
        qdot, solve_info = self.solver.solve_limited(
            J, task, q, self.robot.lower_limits, self.robot.upper_limits, self.velocity_limits
        )
        solve_info['ik_time'] = time.perf_counter() - started  # [s]
        solve_info['J'] = J_full  # (6, n) at q
        solve_info['twist'] = twist
        return qdot, solve_info
