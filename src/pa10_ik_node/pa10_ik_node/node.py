"""pa10_ik_node: follow /curve/waypoints with the arm's tool tip, pressing with a set force.

Closed loop at ``rate`` on /joint_states and /tool/pressure; joint commands out on
/pa10_controller/joint_trajectory (one point, positions and velocities, a short
time_from_start: the joint_trajectory_controller convention), the measured tool pose on
/tool_pose. The task (approach, contact, tracking, done; stopped, failed) is
``tracking.TrackingController``; the velocity IK is ``ik.RateSolver``. This file only
declares parameters, converts messages and calls them.
"""

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import PoseStamped, WrenchStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from pa10_ik_node.ik import METHODS, RateSolver
from pa10_ik_node.session import JointCommand, TrackingSession
from pa10_ik_node.thesis import fixed_step_matrix
from pa10_ik_node.tracking import TrackingConfig, TrackingController
from vgm_common.conversions import matrix_to_pose_stamped, path_to_matrices
from vgm_common.diagnostics import CountingPublisher, guarded
from vgm_common.errors import InvalidInput
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

THESIS_WEIGHTS = [1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0]  # §6.6
# The controller's settings that are parameters (TrackingConfig says which and how).
TRACKING = ConfigParams(TrackingConfig)


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
        "Tool beyond tip_frame along its z axis [m]; -1: the model's own (0.1 m for the "
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
        "must be stamped in it (the scenario's robot.tip_frame).",
        read_only=True,
    ),
    Param(
        'base_frame',
        '',
        "Frame of the URDF the arm's chain starts at ('': its root); joints moving it (a "
        "torso's, a lift's) are locked at neutral.",
        read_only=True,
    ),
    Param(
        'base_placement',
        [0.0] * 6,
        'x, y, z [m], roll, pitch, yaw [rad] of base_frame in base_link (the frame of the '
        "waypoints and /tool_pose); = the scenario's robot.base_placement.",
        check=lambda v: None if len(v) == 6 else 'needs 6 numbers',
        read_only=True,
    ),
    Param('rate', 100.0, 'Control rate [Hz].', range=(100.0, 1000.0), read_only=True),
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
        f'Diagonal of W, non-zero (may be indefinite, e.g. the thesis {THESIS_WEIGHTS}).',
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
    *TRACKING.declarations(),
    Param(
        'max_joint_velocity',
        1.0,
        "Cap on every joint speed [rad/s] (on top of the model's limits).",
        range=(0.01, 10.0),
        read_only=True,
    ),
    Param(
        'pressure_timeout',
        1.0,
        'Pressure (or joint state) older than this [s] while active: stop.',
        range=(0.01, 60.0),
    ),
    Param(
        'command_horizon',
        0.05,
        'time_from_start of the commanded point [s].',
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
        'Rate of the tracking diagnostics [Hz].',
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
        tip = f'tip_frame {p.tip_frame!r} + tool_length {self.tool_length_m:g} m'
        self.session = TrackingSession(
            TrackingController(
                self.robot,
                self._make_solver(),
                TRACKING.build(self.params),
                max_joint_velocity=p.max_joint_velocity,
                tip_description=tip,
            ),
            p.tip_frame,
            p,  # read at every step: a set_parameters change applies at once
            1.0 / p.rate,
        )
        self.controller = self.session.controller
        self.last_phase = self.controller.phase
        self.internal_errors = 0

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
        self.create_timer(1.0 / p.rate, self._control_step)
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
            self.session.take_joint_state(msg.name, msg.position)
        except InvalidInput as error:
            self.diagnostics.reject(JOINT_STATES_TOPIC, error)

    @guarded(PRESSURE_TOPIC)
    def _on_pressure(self, msg):
        try:
            self.session.take_pressure(msg.header.frame_id, msg.wrench.force.z)
        except InvalidInput as error:
            self.diagnostics.reject(PRESSURE_TOPIC, error)

    @guarded(WAYPOINTS_TOPIC)
    def _on_waypoints(self, msg):
        try:
            waypoints = path_to_matrices(msg)
            takeover = self.session.take_waypoints(msg.header.frame_id, waypoints)
        except InvalidInput as error:
            self.diagnostics.reject(WAYPOINTS_TOPIC, error)
            return
        if takeover:
            self.get_logger().info(takeover)
        self.get_logger().info(f'waypoints: {len(waypoints)} poses')

    # --- services --------------------------------------------------------------------

    @guarded('start_tracking')
    def _on_start(self, request, response):
        response.success, response.message, hold = self.session.start()
        self._send(hold)
        self._log_phase_change()
        return response

    @guarded('stop')
    def _on_stop(self, request, response):
        self._send(self.session.stop('stop requested'))
        self._log_phase_change()
        response.success, response.message = True, 'stopped'
        return response

    # --- the loop --------------------------------------------------------------------

    @guarded('control step')
    def _control_step(self):
        if not self.pose_gate.is_open():
            return
        output = self.session.control_step(self.params.auto_start)
        if output is None:  # no joint state yet
            return
        self._send(output.command)
        self.pose_publisher.publish(
            matrix_to_pose_stamped(
                output.T_base_tool, self.get_clock().now().nanoseconds, BASE_FRAME
            )
        )
        self._log_phase_change()

    def _send(self, command: JointCommand | None):
        if command is None:
            return
        seconds = int(command.horizon)
        point = JointTrajectoryPoint(
            positions=command.positions.tolist(),
            velocities=command.velocities.tolist(),
            time_from_start=Duration(sec=seconds, nanosec=int((command.horizon - seconds) * 1e9)),
        )
        # A zero stamp: start now (joint_trajectory_controller convention).
        self.command_publisher.publish(
            JointTrajectory(joint_names=list(self.robot.joint_names), points=[point])
        )

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
            self._send(self.session.fail(reason))
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
        session = self.session
        controller, info, force = self.controller, session.last_info, session.force
        phase = controller.phase
        if phase == 'approach' and controller.stage == 'descend' and force > 0:
            phase = 'contact'  # touching, force building up
        values = {
            'phase': phase,
            'stage': controller.stage,
            'progress': f'{controller.progress:.4f}',
            'position_error_m': f'{info.get("position_error", float("nan")):.6f}',
            'force_N': f'{force:.4f}',
            'force_error_N': f'{force - self.params.desired_force:.4f}',
            'arm_response': f'{controller.response:.3f}',
            'phi_rad': f'{info.get("phi", float("nan")):.5f}',
            'step_time_ms': f'{np.median(session.step_times) * 1e3:.4f}'
            if session.step_times
            else 'nan',
            'method': self.params.method,
            'force_law': self.params.force_law,
            'reason': controller.reason,
        }
        if self.params.method == 'primal_dual':
            values['failure_condition'] = session.last_failure_condition or 'none detected'
            values['null_space_failures'] = session.null_space_failures
            if session.q is not None:
                values['fixed_step_radius'] = f'{self._fixed_step_radius(session.q):.6g}'
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
