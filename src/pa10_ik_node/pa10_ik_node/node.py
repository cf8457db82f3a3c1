"""pa10_ik_node: follow /curve/waypoints with the arm's tool tip, pressing with a set force.

Closed loop at ``rate`` on /joint_states and /tool/pressure; joint commands out on
/pa10_controller/joint_trajectory (positions and velocities at a short time_from_start,
after the set point continued at time 0 if ``send_set_point``: the
joint_trajectory_controller convention), the measured tool pose on /tool_pose. The task
(approach, contact, tracking, done; stopped, failed) is ``tracking.TrackingController``,
run by ``session.TrackingSession`` between messages; the parameters are the fields of
``settings.ArmSettings``, ``SolverSettings``, ``LoopSettings`` and
``tracking.TrackingConfig``. This file only declares parameters, converts messages and wires them.
"""

from builtin_interfaces.msg import Duration
from geometry_msgs.msg import PoseStamped, WrenchStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from pa10_ik_node.session import JointCommand, TrackingSession
from pa10_ik_node.settings import ArmSettings, LoopSettings, SolverSettings, weights_per_joint
from pa10_ik_node.tracking import TrackingConfig
from vgm_common.conversions import matrix_to_pose_stamped, path_to_matrices
from vgm_common.diagnostics import CountingPublisher, guarded
from vgm_common.errors import InvalidInput
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.subscriber_gate import SubscriberGate, subscriber_gate_params
from vgm_common.topics import (
    BASE_FRAME,
    JOINT_STATES_TOPIC,
    JOINT_TRAJECTORY_TOPIC,
    PRESSURE_TOPIC,
    TOOL_POSE_TOPIC,
    WAYPOINTS_TOPIC,
)

# The settings that are parameters (each dataclass says which and how).
ARM = ConfigParams(ArmSettings)
SOLVER = ConfigParams(SolverSettings)
TRACKING = ConfigParams(TrackingConfig)
LOOP = ConfigParams(LoopSettings)
PARAMETERS = [
    *ARM.declarations(),
    *SOLVER.declarations(),
    *TRACKING.declarations(),
    *LOOP.declarations(),
    *subscriber_gate_params('Run the loop (and publish /tool_pose) only once /tool_pose has'),
]


def _names(settings: ConfigParams) -> tuple[str, ...]:
    return tuple(settings.param_names(p.name for p in PARAMETERS).values())


def _seconds_to_duration(seconds: float) -> Duration:
    whole = int(seconds)
    return Duration(sec=whole, nanosec=int((seconds - whole) * 1e9))


class Pa10IkNode(GraphNode):
    """Follows the latched /curve/waypoints with the tool tip at ``rate``: approach,
    contact at ``desired_force``, tracking and lift-off (``tracking.TrackingController``),
    joint commands on /pa10_controller/joint_trajectory and the measured tool pose on
    /tool_pose. Services ``~/start_tracking`` and ``~/stop``."""

    node_name = 'pa10_ik_node'

    def __init__(self) -> None:
        # A change of a solver parameter builds the solver anew, of a tracking one
        # reconfigures the task, of a loop one applies at the next step.
        hooks = dict.fromkeys(_names(SOLVER), self._on_solver_change)
        hooks |= dict.fromkeys(_names(TRACKING), self._on_tracking_change)
        hooks |= dict.fromkeys(_names(LOOP), self._on_loop_change)
        super().__init__(PARAMETERS, on_change=hooks)
        p = self.params
        arm = ARM.build(p)
        self.session = TrackingSession.create(
            arm, SOLVER.build(p), TRACKING.build(p), LOOP.build(p)
        )
        self.robot = self.session.robot
        self.params.add_check(lambda v: weights_per_joint(self.robot.n_joints, v['weights']))

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
            f'robot {p.robot} (tip {p.tip_frame} + tool {arm.tool_length_m:g} m), '
            f'method {p.method}, {p.rate:g} Hz, '
            f'desired force {p.desired_force} N, speed along the path '
            f'{self.session.controller.path_speed:g} m/s (max_tip_speed {p.max_tip_speed:g}), '
            f'auto_start {p.auto_start}'
        )

    # --- parameters ------------------------------------------------------------------

    def _on_solver_change(self, _value: object) -> None:
        if hasattr(self, 'session'):
            self.session.configure_solver(SOLVER.build(self.params))

    def _on_tracking_change(self, _value: object) -> None:
        """A tracking parameter changed: the controller takes them all anew."""
        if hasattr(self, 'session'):
            self.session.controller.configure(**TRACKING.fields(self.params))

    def _on_loop_change(self, _value: object) -> None:
        if hasattr(self, 'session'):
            self.session.settings = LOOP.build(self.params)

    # --- inputs ----------------------------------------------------------------------

    @guarded(JOINT_STATES_TOPIC)
    def _on_joint_state(self, msg: JointState) -> None:
        try:
            stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            age = self.get_clock().now().nanoseconds * 1e-9 - stamp if stamp > 0 else 0.0
            self.session.take_joint_state(msg.name, msg.position, age)
        except InvalidInput as error:
            self.diagnostics.reject(JOINT_STATES_TOPIC, error)

    @guarded(PRESSURE_TOPIC)
    def _on_pressure(self, msg: WrenchStamped) -> None:
        try:
            self.session.take_pressure(msg.header.frame_id, msg.wrench.force.z)
        except InvalidInput as error:
            self.diagnostics.reject(PRESSURE_TOPIC, error)

    @guarded(WAYPOINTS_TOPIC)
    def _on_waypoints(self, msg: Path) -> None:
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
    def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message, hold = self.session.start()
        self._send(hold)
        self._log_phase_change()
        return response

    @guarded('stop')
    def _on_stop(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        self._send(self.session.stop('stop requested'))
        self._log_phase_change()
        response.success, response.message = True, 'stopped'
        return response

    # --- the loop --------------------------------------------------------------------

    @guarded('control step')
    def _control_step(self) -> None:
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

    def _send(self, command: JointCommand | None) -> None:
        if command is None:
            return
        points = [
            JointTrajectoryPoint(
                positions=positions.tolist(),
                velocities=velocities.tolist(),
                time_from_start=_seconds_to_duration(time_from_start),
            )
            for time_from_start, positions, velocities in command.points()
        ]
        # A zero stamp: start now (joint_trajectory_controller convention).
        self.command_publisher.publish(
            JointTrajectory(joint_names=list(self.robot.joint_names), points=points)
        )

    def on_internal_error(self, what: str, error: Exception) -> None:
        """An exception in a callback (a solver, a singular configuration, a bug): stop
        the arm at its measured position, report, keep serving."""
        reason = f'{what}: {type(error).__name__}: {error}'
        try:
            hold = self.session.fail(reason)
            count = self.session.internal_errors
            self.get_logger().error(
                f'internal error in {reason} ({count} so far); the arm holds',
                throttle_duration_sec=2.0,
            )
            self._send(hold)
            self.diagnostics.publish('internal error', 'error', reason, {'count': count})
            self._log_phase_change()
        except Exception as second:  # noqa: BLE001 - e.g. a publisher already destroyed
            self.get_logger().error(
                f'could not stop after the internal error: {second}', throttle_duration_sec=2.0
            )

    def _log_phase_change(self) -> None:
        change = self.session.phase_change()
        if change is None:
            return
        # rclpy ties one severity to each call site: one call per severity.
        if change.level == 'error':
            self.get_logger().error(change.message)
        elif change.level == 'warn':
            self.get_logger().warning(change.message)
        else:
            self.get_logger().info(change.message)
        if change.summary:
            self.get_logger().info(change.summary)
        self._publish_diagnostics()

    @guarded('diagnostics')
    def _publish_diagnostics(self) -> None:
        status = self.session.status()
        self.diagnostics.publish('tracking', status.level, status.message, status.values)


def main(args: list[str] | None = None) -> int:
    """Run pa10_ik_node until SIGINT/SIGTERM; exit status 2 on an unusable parameter or
    robot model at start-up (one line)."""
    return run_node(Pa10IkNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
