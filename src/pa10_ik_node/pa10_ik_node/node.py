"""pa10_ik_node: follow /curve/waypoints with the arm's tool tip, pressing with a set force.

Closed loop at ``rate`` on /joint_states and /tool/pressure; joint commands out on
/pa10_controller/joint_trajectory (one point, positions and velocities, a short
time_from_start: the joint_trajectory_controller convention), the measured tool pose on
/tool_pose. The task (approach, contact, tracking, done; stopped, failed) is
``tracking.TrackingController``; the velocity IK is ``ik.RateSolver``. This file only
declares parameters, converts messages and calls them.
"""

import time
from collections import deque

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import PoseStamped, WrenchStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from pa10_ik_node.ik import METHODS, RateSolver
from pa10_ik_node.path import validate_waypoints
from pa10_ik_node.thesis import fixed_step_matrix
from pa10_ik_node.tracking import (
    ACTIVE_PHASES,
    FORCE_LAWS,
    TrackingConfig,
    TrackingController,
    Unreachable,
)
from vgm_common.conversions import matrix_to_pose_stamped, path_to_matrices
from vgm_common.diagnostics import CountingPublisher, guarded
from vgm_common.errors import InvalidInput, VgmError
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams, Param
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.robot_model import load_robot, own_tool_length
from vgm_common.subscriber_gate import SubscriberGate, subscriber_gate_params
from vgm_common.topics import (
    BASE_FRAME,
    JOINT_STATES_TOPIC,
    JOINT_TRAJECTORY_TOPIC,
    PRESSURE_TOPIC,
    TOOL_POSE_TOPIC,
    WAYPOINTS_TOPIC,
)

MAX_FORCE_N = 1e4  # a pressure reading beyond this is a broken sensor, not a contact
JOINT_LIMIT_SLACK_RAD = 0.1  # a measured joint this far outside its limits is no reading
THESIS_WEIGHTS = [1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0]  # §6.6
# The controller's settings that are parameters (the rest keep TrackingConfig's defaults).
TRACKING = ConfigParams(TrackingConfig, renamed={'stiffness': 'contact_stiffness'})


OWN_TOOL = -1.0  # tool_length: the model's own


def _check_tool_length(value):
    if value < 0 and value != OWN_TOOL:
        return f"a length >= 0 [m], or {OWN_TOOL:g} for the model's own"
    return None


def _check_weights(values):
    if not values or any(not np.isfinite(v) or v == 0 for v in values):
        return 'every weight must be finite and non-zero'
    return None


POSITIVE = (1e-9, 1e9)
PARAMETERS = [
    Param(
        'robot',
        'pa10',
        "Kinematic model: 'pa10', 'pa10_thesis' or a URDF path.",
        read_only=True,
    ),
    Param(
        'tool_length',
        OWN_TOOL,
        "[m] Tool beyond tip_frame along its z axis; -1: the model's own (0.1 m for the "
        'built-in pa10 models, 0 for a URDF, whose tip frame is the tool tip). Must match '
        "the scenario's robot.tool_length.",
        range=(OWN_TOOL, 1.0),
        check=_check_tool_length,
        read_only=True,
    ),
    Param(
        'tip_frame',
        'tool0',
        'Tip frame of the URDF, any of its frames (z = approach axis); /tool/pressure '
        'must be stamped in it.',
        read_only=True,
    ),
    Param(
        'base_frame',
        '',
        "Frame of the URDF the arm's chain starts at ('': its root); joints moving it (a "
        "torso's) are locked.",
        read_only=True,
    ),
    Param(
        'base_placement',
        [0.0] * 6,
        '[m, rad] x, y, z, roll, pitch, yaw of base_frame in base_link (the frame of the '
        "waypoints and /tool_pose); = the scenario's robot.base_placement.",
        check=lambda v: None if len(v) == 6 else 'needs 6 numbers',
        read_only=True,
    ),
    Param('rate', 100.0, '[Hz] Control rate.', range=(100.0, 1000.0), read_only=True),
    Param(
        'method',
        'ours',
        'Velocity IK: ours (closed-form KKT + feedback, joint '
        'limits), primal_dual (the thesis network), dls (reference).',
        choices=METHODS,
    ),
    Param(
        'weights',
        [1.0] * 7,
        f'Diagonal of W (may be indefinite, e.g. the thesis {THESIS_WEIGHTS}).',
        check=_check_weights,
    ),
    Param(
        'K',
        100.0,
        'Penalty gain of the primal-dual network.',
        range=POSITIVE,
    ),
    Param(
        'mu',
        0.02,
        "Step size of the thesis's fixed-step rule for qdot. The node integrates the "
        'network exactly; with method primal_dual its diagnostics report the spectral '
        'radius of the fixed-step rule at mu, eta and the current joints '
        '(fixed_step_radius; > 1: the literal rule would diverge there).',
        range=POSITIVE,
    ),
    Param(
        'eta',
        0.02,
        "Step size of the thesis's fixed-step rule for lambda (see mu).",
        range=POSITIVE,
    ),
    Param(
        'damping',
        0.05,
        'DLS damping; largest adaptive damping of ours.',
        range=(0.0, 10.0),
    ),
    Param(
        'desired_force',
        TRACKING.defaults.desired_force,
        '[N] Contact force to hold.',
        range=(0.01, 200.0),
    ),
    Param(
        'contact_stiffness',
        TRACKING.defaults.stiffness,
        '[N/m] Stiffness estimate (feed-forward depth; the integral law corrects its error).',
        range=(1.0, 1e7),
    ),
    Param(
        'force_gain',
        TRACKING.defaults.force_gain,
        '[1/s] Integral gain of the force law.',
        range=(0.0, 100.0),
    ),
    Param(
        'force_law',
        TRACKING.defaults.force_law,
        "Force law: 'integral' (ours: depth = "
        "desired_force / contact_stiffness + integral of the force error) or 'tilt' "
        "(the thesis's 7.3.15: the motion PQ' tilted by phi into / out of the "
        'surface; acts only while moving along the path).',
        choices=FORCE_LAWS,
    ),
    Param(
        'max_tip_speed',
        TRACKING.defaults.max_tip_speed,
        "[m/s] The tip's top speed: along the path, in the free-space move, in the "
        'descent until 5 mm short of the first waypoint, in the lift-off.',
        range=(1e-3, 0.2),
    ),
    Param(
        'speed',
        TRACKING.defaults.speed,
        '[m/s] Speed along the path, at most max_tip_speed; 0: max_tip_speed.',
        range=(0.0, 0.2),
    ),
    Param(
        'adapt_response',
        TRACKING.defaults.adapt_response,
        'Measure how much of the commanded motion the '
        'arm makes and scale commands up for an arm slower than commanded (at most '
        '2.5 times, within the joint speed limits); the motion measured is compared with '
        'the command sent command_latency before.',
    ),
    Param(
        'command_latency',
        TRACKING.defaults.command_latency,
        "[s] The arm's delay from a command to its measured effect: the control law acts on "
        'the measured joints advanced by the commands of that time (a Smith predictor); '
        '0: none assumed.',
        range=(0.0, 0.5),
    ),
    Param(
        'pose_integral_gain',
        TRACKING.defaults.pose_integral_gain,
        "[1/s^2] Integral of the tip's error across "
        'the approach axis while tracking (a slow arm trails its reference '
        'otherwise); 0 turns it off.',
        range=(0.0, 200.0),
    ),
    Param(
        'pose_gain',
        TRACKING.defaults.pose_gain,
        '[1/s] Pose feedback gain.',
        range=(0.1, 50.0),
    ),
    Param(
        'max_joint_velocity',
        1.0,
        "[rad/s] Cap on every joint speed (on top of the model's limits).",
        range=(0.01, 10.0),
        read_only=True,
    ),
    Param(
        'track_spin',
        TRACKING.defaults.track_spin,
        'Also track the spin about the approach axis '
        '(6 constraints, as the seed); false leaves it free.',
    ),
    Param(
        'standoff',
        TRACKING.defaults.standoff,
        '[m] Pre-contact pose above the first waypoint.',
        range=(0.005, 0.2),
    ),
    Param(
        'descent_speed',
        TRACKING.defaults.descent_speed,
        '[m/s] The last 5 mm of the descent to contact (slowing as the force builds).',
        range=(1e-4, 0.1),
    ),
    Param(
        'lift_height',
        TRACKING.defaults.lift_height,
        '[m] Lift-off along the approach axis when done.',
        range=(0.0, 0.2),
    ),
    Param(
        'max_position_error',
        TRACKING.defaults.max_position_error,
        '[m] Tip farther than this from its reference for error_timeout: failure.',
        range=(1e-4, 1.0),
    ),
    Param(
        'error_timeout',
        TRACKING.defaults.error_timeout,
        '[s] See max_position_error.',
        range=(0.01, 60.0),
    ),
    Param(
        'pressure_timeout',
        1.0,
        '[s] Pressure (or joint state) older than this while active: stop.',
        range=(0.01, 60.0),
    ),
    Param(
        'command_horizon',
        0.05,
        '[s] time_from_start of the commanded point.',
        range=(0.001, 1.0),
    ),
    Param(
        'auto_start',
        False,
        'Start as soon as valid waypoints, joint states and pressure are there.',
    ),
    Param(
        'diagnostics_rate',
        2.0,
        '[Hz] Rate of the tracking diagnostics.',
        range=(0.1, 50.0),
        read_only=True,
    ),
    *subscriber_gate_params('Run the loop (and publish /tool_pose) only once /tool_pose has'),
]

# A change of these builds the solver anew; of the tracking ones, reconfigures the controller.
SOLVER_PARAMETERS = ('method', 'weights', 'K', 'damping')
TRACKING_PARAMETERS = tuple(TRACKING.param_names(p.name for p in PARAMETERS).values())


class Pa10IkNode(GraphNode):
    """Follows the latched /curve/waypoints with the tool tip at ``rate``: approach,
    contact at ``desired_force``, tracking and lift-off (``tracking.TrackingController``),
    joint commands on /pa10_controller/joint_trajectory and the measured tool pose on
    /tool_pose. Services ``~/start_tracking`` and ``~/stop``."""

    node_name = 'pa10_ik_node'

    def __init__(self):
        solver_hooks = dict.fromkeys(SOLVER_PARAMETERS, self._rebuild_solver)
        super().__init__(
            PARAMETERS,
            on_change=solver_hooks | dict.fromkeys(TRACKING_PARAMETERS, self._reconfigure),
        )
        p = self.params
        self.tool_length_m = own_tool_length(p.robot) if p.tool_length < 0 else p.tool_length
        try:
            self.robot = load_robot(
                p.robot,
                self.tool_length_m,
                p.tip_frame,
                base_frame=p.base_frame,
                base_placement=p.base_placement,
            )
        except InvalidInput as error:
            named = error.key in ('tip_frame', 'base_frame', 'base_placement')
            key = error.key if named else 'robot'
            raise InvalidInput(f'parameter {key}: {error}', key, error.value) from None
        self.params.add_check(self._one_weight_per_joint)
        self.controller = TrackingController(
            self.robot,
            self._make_solver(),
            TRACKING.build(self.params),
            max_joint_velocity=p.max_joint_velocity,
            tip_description=f'tip_frame {p.tip_frame!r} + tool_length {self.tool_length_m:g} m',
        )
        self.joint_index = {name: i for i, name in enumerate(self.robot.joint_names)}
        self.q = None  # measured joints, robot order [rad]
        self.force = 0.0  # [N]
        self.joint_state_time = self.pressure_time = None  # monotonic receive times [s]
        self.waypoints = None  # (N, 4, 4) base_link
        self.step_times: deque[float] = deque(maxlen=500)  # [s]
        self.last_phase = self.controller.phase
        self.last_info = {}
        self.null_space_failures = 0
        self.internal_errors = 0
        self.last_failure_condition = ''

        self.command_publisher = self.create_publisher(
            JointTrajectory, JOINT_TRAJECTORY_TOPIC, DEFAULT_QOS, publisher_class=CountingPublisher
        )
        self.pose_publisher = self.create_publisher(
            PoseStamped, TOOL_POSE_TOPIC, DEFAULT_QOS, publisher_class=CountingPublisher
        )
        self.pose_gate = SubscriberGate(
            self,
            [self.pose_publisher, self.command_publisher],
            p.min_subscribers,
            p.subscriber_timeout,
            p.wait_for_nodes,
            counted=[self.pose_publisher],
        )
        self.create_subscription(JointState, JOINT_STATES_TOPIC, self._on_joint_state, DEFAULT_QOS)
        self.create_subscription(WrenchStamped, PRESSURE_TOPIC, self._on_pressure, DEFAULT_QOS)
        self.create_subscription(Path, WAYPOINTS_TOPIC, self._on_waypoints, LATCHED_QOS)
        self.create_service(Trigger, '~/start_tracking', self._on_start)
        self.create_service(Trigger, '~/stop', self._on_stop)
        self.dt = 1.0 / p.rate
        self.last_step = None  # time.monotonic() of the previous control step
        self.create_timer(self.dt, self._control_step)
        self.create_timer(1.0 / p.diagnostics_rate, self._publish_diagnostics)
        self.get_logger().info(
            f'robot {p.robot} (tip {p.tip_frame} + tool {self.tool_length_m:g} m), '
            f'method {p.method}, {p.rate:g} Hz, '
            f'desired force {p.desired_force} N, speed along the path '
            f'{self.controller.path_speed:g} m/s (max_tip_speed {p.max_tip_speed:g}), '
            f'auto_start {p.auto_start}'
        )

    # --- parameters ------------------------------------------------------------------

    def _make_solver(self):
        p = self.params
        return RateSolver(p.method, p.weights, K=p.K, damping=p.damping)

    def _one_weight_per_joint(self, values):
        if len(values['weights']) != self.robot.n_joints:
            return f"'weights' needs {self.robot.n_joints} values, got {len(values['weights'])}"
        return None

    def _rebuild_solver(self, _value):
        if hasattr(self, 'controller'):
            self.controller.solver = self._make_solver()

    def _reconfigure(self, _value):
        """A tracking parameter changed: the controller takes them all anew."""
        if hasattr(self, 'controller'):
            self.controller.configure(**TRACKING.fields(self.params))

    # --- inputs ----------------------------------------------------------------------

    @guarded(JOINT_STATES_TOPIC)
    def _on_joint_state(self, msg):
        try:
            q = self._joint_vector(msg)
        except InvalidInput as error:
            self.diagnostics.reject(JOINT_STATES_TOPIC, error)
            return
        self.q = q
        self.joint_state_time = time.monotonic()

    def _joint_vector(self, msg):
        """The measured joints (n,) in robot order; ``InvalidInput`` for a reading that
        cannot be the arm's (unknown, duplicate or missing names, non-finite or far
        outside the joint limits)."""
        names = list(msg.name)
        duplicates = sorted({name for name in names if names.count(name) > 1})
        if duplicates:
            raise InvalidInput(f'duplicate joint names {duplicates}', 'name', duplicates)
        unknown = sorted(set(names) - set(self.joint_index))
        if unknown:
            raise InvalidInput(f'unknown joint names {unknown}', 'name', unknown)
        missing = sorted(set(self.joint_index) - set(names))
        if missing or len(names) != len(msg.position):
            raise InvalidInput(
                f'need one position for each of {self.robot.n_joints} '
                f'joints (missing {missing}, {len(msg.position)} '
                f'positions for {len(names)} names)',
                'position',
            )
        q = np.empty(self.robot.n_joints)
        for name, value in zip(names, msg.position):
            q[self.joint_index[name]] = value
        q = self.robot.check_q(q)
        lower = self.robot.lower_limits - JOINT_LIMIT_SLACK_RAD
        upper = self.robot.upper_limits + JOINT_LIMIT_SLACK_RAD
        outside = np.flatnonzero((q < lower) | (q > upper))
        if outside.size:
            i = int(outside[0])
            raise InvalidInput(
                f'{self.robot.joint_names[i]} at {q[i]:.6g} rad is more than '
                f'{JOINT_LIMIT_SLACK_RAD} rad outside its limits '
                f'[{self.robot.lower_limits[i]:.4g}, {self.robot.upper_limits[i]:.4g}]',
                'position',
                q[i],
            )
        return q

    @guarded(PRESSURE_TOPIC)
    def _on_pressure(self, msg):
        force = msg.wrench.force.z
        frame = msg.header.frame_id
        if frame != self.params.tip_frame:
            error = InvalidInput(
                f'frame {frame!r}, expected the tip frame {self.params.tip_frame!r} '
                '(parameter tip_frame)',
                'frame_id',
                frame,
            )
        elif not (np.isfinite(force) and abs(force) <= MAX_FORCE_N):
            error = InvalidInput(
                f'force.z is {force} N, beyond the sanity bound '
                f'+-{MAX_FORCE_N:g} N (a broken sensor)',
                'force.z',
                force,
            )
        else:
            self.force = float(force)
            self.pressure_time = time.monotonic()
            return
        self.diagnostics.reject(PRESSURE_TOPIC, error)

    @guarded(WAYPOINTS_TOPIC)
    def _on_waypoints(self, msg):
        try:
            if msg.header.frame_id != BASE_FRAME:
                raise InvalidInput(
                    f'frame {msg.header.frame_id!r}, expected {BASE_FRAME!r}',
                    'frame_id',
                    msg.header.frame_id,
                )
            waypoints = validate_waypoints(path_to_matrices(msg))
        except InvalidInput as error:
            self.diagnostics.reject(WAYPOINTS_TOPIC, error)
            return
        if self.controller.phase in ACTIVE_PHASES and self.q is not None:
            tip = self.robot.forward_kinematics(self.q)[:3, 3]
            try:
                self.controller.update_path(waypoints, tip)
            except InvalidInput as error:
                self.diagnostics.reject(WAYPOINTS_TOPIC, error)
                return
            self.get_logger().info(
                f'took over a new path of {len(waypoints)} waypoints at '
                f'progress {self.controller.progress:.3f}'
            )
        self.waypoints = waypoints
        self.get_logger().info(f'waypoints: {len(waypoints)} poses')

    # --- services --------------------------------------------------------------------

    def _missing_inputs(self):
        missing = []
        if self.waypoints is None:
            missing.append(WAYPOINTS_TOPIC)
        if not self._fresh(self.joint_state_time):
            missing.append(JOINT_STATES_TOPIC)
        if not self._fresh(self.pressure_time):
            missing.append(PRESSURE_TOPIC)
        return missing

    def _fresh(self, stamp):
        return stamp is not None and time.monotonic() - stamp <= self.params.pressure_timeout

    def _start(self):
        """(success, message)."""
        missing = self._missing_inputs()
        waypoints = self.waypoints
        if missing or waypoints is None:  # None: WAYPOINTS_TOPIC is among the missing
            return False, f'cannot start: no recent {", ".join(missing)}'
        try:
            self.controller.start(waypoints, self.q)
        except Unreachable as error:
            self.controller.fail(f'unreachable waypoints: {error}')
            self._hold()
            return False, self.controller.reason
        except VgmError as error:
            return False, f'cannot start: {error}'
        path = self.controller.path
        assert path is not None  # set by start()
        return True, (
            f'started on {len(waypoints)} waypoints: a {path.length * 1e3:.0f} mm path, about '
            f'{self.controller.nominal_tracking_time():.1f} s along it'
        )

    @guarded('start_tracking')
    def _on_start(self, request, response):
        response.success, response.message = self._start()
        self._log_phase_change()
        return response

    @guarded('stop')
    def _on_stop(self, request, response):
        self.controller.stop('stop requested')
        self._hold()
        self._log_phase_change()
        response.success, response.message = True, 'stopped'
        return response

    # --- the loop --------------------------------------------------------------------

    @guarded('control step')
    def _control_step(self):
        if self.q is None or not self.pose_gate.is_open():
            return
        controller = self.controller
        if self.params.auto_start and controller.phase == 'idle' and not self._missing_inputs():
            self._start()
        # The step the timer really took (a loaded machine runs it late), bounded so one
        # long stall does not become a jump: the reference then moves at the set speed.
        now = time.monotonic()
        stalled = (
            self.last_step is not None and now - self.last_step > self.params.pressure_timeout / 2
        )
        dt = self.dt if self.last_step is None else min(now - self.last_step, 3 * self.dt)
        self.last_step = now
        # After a stall of this node's own executor the sensors' newest messages are still
        # queued behind this timer: judge their freshness on the next step.
        if controller.phase in ACTIVE_PHASES and not stalled:
            if not self._fresh(self.pressure_time):
                controller.stop(
                    f'stale pressure: no /tool/pressure for more than '
                    f'{self.params.pressure_timeout} s'
                )
            elif not self._fresh(self.joint_state_time):
                controller.stop(
                    f'stale joint states: no /joint_states for more than '
                    f'{self.params.pressure_timeout} s'
                )
            if controller.phase == 'stopped':
                self._hold()
        q = self.q
        if controller.phase in (*ACTIVE_PHASES, 'done'):
            started = time.perf_counter()
            qdot, info = controller.step(q, self.force, dt)
            self.step_times.append(time.perf_counter() - started)
            self.last_info = info
            if info.get('diverged'):
                self.null_space_failures += 1
                self.last_failure_condition = (
                    'W + K J^T J not positive definite at any K (near a singularity): the '
                    'network diverges; used the KKT solution'
                )
            elif info.get('null_space_positive') is False:
                self.null_space_failures += 1
                self.last_failure_condition = (
                    f'W not positive on null(J) (min eigenvalue '
                    f'{info.get("min_null_eigenvalue", float("nan")):.3g}); fell back to |W|'
                )
            if controller.phase in ('stopped', 'failed'):
                self._hold()
            else:
                self._command(q, qdot)
            T = info['T']
        else:
            T = self.robot.forward_kinematics(q)
        self.pose_publisher.publish(
            matrix_to_pose_stamped(T, self.get_clock().now().nanoseconds, BASE_FRAME)
        )
        self._log_phase_change()

    def _command(self, q, qdot, horizon=None):
        horizon = self.params.command_horizon if horizon is None else horizon
        seconds = int(horizon)
        point = JointTrajectoryPoint(
            positions=(q + qdot * horizon).tolist(),
            velocities=qdot.tolist(),
            time_from_start=Duration(sec=seconds, nanosec=int((horizon - seconds) * 1e9)),
        )
        # A zero stamp: start now (joint_trajectory_controller convention).
        self.command_publisher.publish(
            JointTrajectory(joint_names=list(self.robot.joint_names), points=[point])
        )

    def _hold(self):
        """Zero velocity at the measured position, now (time_from_start 0: a position
        arm does not coast on to a point ahead, a velocity arm gets zero at once)."""
        if self.q is not None:
            self._command(self.q, np.zeros(self.robot.n_joints), horizon=0.0)

    def on_internal_error(self, what, error):
        """An exception in a callback (a solver, a singular configuration, a bug): stop
        the arm at its measured position, report, keep serving."""
        reason = f'{what}: {type(error).__name__}: {error}'
        self.internal_errors += 1
        self.get_logger().error(
            f'internal error in {reason} ({self.internal_errors} so far); the arm holds',
            throttle_duration_sec=2.0,
        )
        try:
            if self.controller.phase in (*ACTIVE_PHASES, 'done'):
                self.controller.fail(reason)
            self._hold()
            self.diagnostics.publish(
                'internal error', 'error', reason, {'count': self.internal_errors}
            )
            self._log_phase_change()
        except Exception as second:  # noqa: BLE001 - e.g. a publisher already destroyed
            self.get_logger().error(
                f'could not stop after the internal error: {second}', throttle_duration_sec=2.0
            )

    def _log_phase_change(self):
        controller = self.controller
        phase = controller.phase
        if phase == self.last_phase:
            return
        self.last_phase = phase
        # rclpy ties one severity to each call site: one call per severity.
        if phase == 'failed':
            self.get_logger().error(f'phase failed: {controller.reason}')
        elif phase == 'stopped':
            self.get_logger().warning(f'phase stopped: {controller.reason}')
        else:
            self.get_logger().info(f'phase {phase}')
        if phase == 'done':
            rms, force_band = controller.stats.summary()
            self.get_logger().info(
                f'tracking done: rms position error {rms * 1e3:.3f} mm, force within '
                f'+-{force_band:.3f} N of desired ({self.params.desired_force} N)'
            )
        self._publish_diagnostics()

    @guarded('diagnostics')
    def _publish_diagnostics(self):
        controller, info = self.controller, self.last_info
        phase = controller.phase
        if phase == 'approach' and controller.stage == 'descend' and self.force > 0:
            phase = 'contact'  # touching, force building up
        values = {
            'phase': phase,
            'stage': controller.stage,
            'progress': f'{controller.progress:.4f}',
            'position_error_m': f'{info.get("position_error", float("nan")):.6f}',
            'force_N': f'{self.force:.4f}',
            'force_error_N': f'{self.force - self.params.desired_force:.4f}',
            'arm_response': f'{controller.response:.3f}',
            'phi_rad': f'{info.get("phi", float("nan")):.5f}',
            'step_time_ms': f'{np.median(self.step_times) * 1e3:.4f}'
            if self.step_times
            else 'nan',
            'method': self.params.method,
            'force_law': self.params.force_law,
            'reason': controller.reason,
        }
        if self.params.method == 'primal_dual':
            values['failure_condition'] = self.last_failure_condition or 'none detected'
            values['null_space_failures'] = self.null_space_failures
            if self.q is not None:
                values['fixed_step_radius'] = f'{self._fixed_step_radius(self.q):.6g}'
        rms, force_band = controller.stats.summary()
        values.update(rms_position_error_m=f'{rms:.6f}', max_force_error_N=f'{force_band:.4f}')
        level = {'failed': 'error', 'stopped': 'warn'}.get(controller.phase, 'ok')
        message = controller.phase + (f': {controller.reason}' if controller.reason else '')
        self.diagnostics.publish('tracking', level, message, values)

    def _fixed_step_radius(self, q):
        """Spectral radius of the thesis's literal learning rules (mu, eta) on the full
        tip Jacobian at the measured joints: below 1 they converge, above they diverge."""
        p = self.params
        J = self.robot.jacobian(q)
        matrix = fixed_step_matrix(J, np.diag(p.weights), p.K, p.mu, p.eta)
        return float(np.max(np.abs(np.linalg.eigvals(matrix))))


def main(args=None):
    """Run pa10_ik_node until SIGINT/SIGTERM; exit status 2 on an unusable parameter or
    robot model at start-up (one line)."""
    return run_node(Pa10IkNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
