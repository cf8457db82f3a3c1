"""sensor_sim: the synthetic rig. Three cameras (left, right, aux), the calibration
stage, the pressure sensor at the tool tip and a simulated PA-10, from a scenario file.

Timeline: with ``calibration_phase`` true the chart is shown at every stage pose of the
scenario (``captures_per_pose`` captures each, ``/calibration/target_pose`` stamped like
the images), then the scene with the curve is captured until shutdown. The arm runs
throughout at ``joint_state_rate``.
"""

import threading
import time
from collections.abc import Callable
from pathlib import Path

from geometry_msgs.msg import PoseStamped, WrenchStamped
from sensor_msgs.msg import Image, JointState
from trajectory_msgs.msg import JointTrajectory

from sensor_sim.arm_loop import ArmLoop, ArmSample, ArmSettings, TickSchedule
from sensor_sim.capture import (
    CaptureSchedule,
    SimSettings,
    capture_images,
    render_everything,
    write_ground_truth,
)
from sensor_sim.render import SceneRenderer
from sensor_sim.scenario import (
    CAMERA_NAMES,
    load_scenario,
    resolve_scenario_path,
    with_chart_motion,
)
from vgm_common.conversions import make_header, matrix_to_pose_stamped, numpy_to_image, stamp_to_ns
from vgm_common.diagnostics import guarded
from vgm_common.errors import InvalidInput
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import ConfigParams
from vgm_common.qos import DEFAULT_QOS, NEWEST_QOS
from vgm_common.robot_model import load_robot
from vgm_common.subscriber_gate import SubscriberGate, subscriber_gate_params
from vgm_common.topics import (
    BASE_FRAME,
    IMAGE_TOPICS,
    JOINT_STATES_TOPIC,
    JOINT_TRAJECTORY_TOPIC,
    OPTICAL_FRAMES,
    PRESSURE_TOPIC,
    TARGET_POSE_TOPIC,
)

SIM = ConfigParams(SimSettings)
ARM = ConfigParams(ArmSettings)
PARAMETERS = [
    *SIM.declarations(),
    *subscriber_gate_params('Publish only once every camera topic has'),
    *ARM.declarations(),
]


class SensorSim(GraphNode):
    """The synthetic rig: publishes the scenario's three camera images at the frame rate
    (the chart at every stage pose first, with its pose), and the simulated arm's joint
    states and the tool's pressure at ``joint_state_rate``, following the joint trajectories
    it receives.

    Raises:
        ParameterError: invalid parameter value.
        ScenarioError: no such scenario, or an invalid one.
    """

    node_name = 'sensor_sim'

    def __init__(self) -> None:
        super().__init__(PARAMETERS)
        settings = SIM.build(self.params)
        self.scenario = load_scenario(resolve_scenario_path(settings.scenario))
        if settings.chart_motion and self.scenario.calibration is not None:
            self.scenario = with_chart_motion(self.scenario, settings.chart_motion)
        self.get_logger().info(f'scenario {self.scenario.name} ({self.scenario.path})')
        # Publishers first: subscribers (a recorder) discover and match them while the
        # scene renders, so not even the first capture is lost.
        self._create_publishers()
        self.schedule = CaptureSchedule(self.scenario.calibration, settings.calibration_phase)
        started = time.monotonic()
        self.renderer = SceneRenderer(self.scenario)
        render_everything(self.renderer, self.scenario, self.schedule)
        self.get_logger().info(f'rendered the scene in {time.monotonic() - started:.2f} s')
        robot = self.scenario.robot
        self.arm_loop = ArmLoop(
            load_robot(
                robot.model,
                robot.tool_length,
                robot.tip_frame,
                base_frame=robot.base_frame,
                base_placement=robot.base_placement,
            ),
            self.scenario,
            ARM.build(self.params),
            1.0 / settings.joint_state_rate,
        )
        if settings.ground_truth_dir:
            write_ground_truth(Path(settings.ground_truth_dir), self.scenario, self.renderer)
            self.get_logger().info(f'ground truth written to {settings.ground_truth_dir}')
        self._init_state()
        self._start(settings)

    def _create_publishers(self) -> None:
        self.image_publishers = {
            name: self.create_publisher(Image, IMAGE_TOPICS[name], DEFAULT_QOS)
            for name in CAMERA_NAMES
        }
        self.target_pose_publisher = self.create_publisher(
            PoseStamped, TARGET_POSE_TOPIC, DEFAULT_QOS
        )
        self.joint_state_publisher = self.create_publisher(
            JointState, JOINT_STATES_TOPIC, DEFAULT_QOS
        )
        self.pressure_publisher = self.create_publisher(WrenchStamped, PRESSURE_TOPIC, DEFAULT_QOS)

    def _init_state(self) -> None:
        self.capture_lock, self.arm_lock = threading.Lock(), threading.Lock()
        self.gate = SubscriberGate(
            self,
            [
                *self.image_publishers.values(),
                self.target_pose_publisher,
                self.joint_state_publisher,
                self.pressure_publisher,
            ],
            self.params.min_subscribers,
            self.params.subscriber_timeout,
            self.params.wait_for_nodes,
            counted=self.image_publishers.values(),
        )
        self.closed = False
        self.published = dict.fromkeys(
            (*IMAGE_TOPICS.values(), TARGET_POSE_TOPIC, JOINT_STATES_TOPIC, PRESSURE_TOPIC), 0
        )

    def _start(self, settings: SimSettings) -> None:
        """Takes joint trajectories, starts the arm and the capture threads."""
        # Only the newest command: each replaces the previous, and behind a 100 Hz
        # commander on a loaded machine a backlog of ten made the arm follow 0.1 s late.
        self.create_subscription(
            JointTrajectory, JOINT_TRAJECTORY_TOPIC, self._on_joint_trajectory, NEWEST_QOS
        )
        # The arm runs in its own thread on an absolute schedule: an executor timer at
        # 200 Hz is starved by the captures (measured: 77-160 Hz instead of 200).
        self.arm_thread = threading.Thread(
            target=self._run_ticks,
            args=(1.0 / self.params.joint_state_rate, self._arm_tick, self.gate.opened),
            name='arm',
            daemon=True,
        )
        self.arm_thread.start()
        self.create_timer(1.0, self._publish_diagnostics)
        frame_rate = settings.rate or self.scenario.rate
        # The captures too: in the executor each one held up the joint commands for as
        # long as it took (the full graph on a loaded machine: the arm 0.1 s behind them).
        threading.Thread(
            target=self._run_ticks,
            args=(1.0 / frame_rate, self._capture),
            name='capture',
            daemon=True,
        ).start()
        arm = self.arm_loop.arm
        self.get_logger().info(
            f'publishing 3 cameras at {frame_rate:g} Hz ({self.schedule.chart_frames} '
            f'calibration captures first), joint states at {settings.joint_state_rate:g} Hz, '
            f'arm {self.scenario.robot.model} following {arm.mode}s x{arm.speed_scale:g}, '
            f'commands {arm.command_delay * 1e3:g} ms late'
        )

    def _run_ticks(
        self, period: float, tick: Callable[[], None], start: threading.Event | None = None
    ) -> None:
        """A thread's loop: ``tick`` every ``period`` [s] on an absolute schedule (after
        ``start`` is set, if given) until the node closes."""
        if start is not None:
            start.wait()
        ticks = TickSchedule(period)
        while not self.closed:
            tick()
            delay = ticks.wait_after_tick()
            if delay > 0:
                time.sleep(delay)

    # --- cameras ---------------------------------------------------------------------

    @guarded('capture')  # a failed capture is reported; the thread goes on with the next
    def _capture(self) -> None:
        if self.gate.is_open():  # the arm starts publishing too
            with self.capture_lock:
                if not self.closed:
                    self._publish_capture()

    def _publish_capture(self) -> None:
        stamp_ns = self.get_clock().now().nanoseconds
        capture = self.schedule.next()
        if capture.T_base_target is not None:
            self.target_pose_publisher.publish(
                matrix_to_pose_stamped(capture.T_base_target, stamp_ns, BASE_FRAME)
            )
            self.published[TARGET_POSE_TOPIC] += 1
        if capture.ends_calibration:
            self.get_logger().info('calibration phase done: showing the scene')
        for name, pixels in capture_images(self.renderer, self.scenario, capture).items():
            self.image_publishers[name].publish(
                numpy_to_image(pixels, 'mono8', stamp_ns, OPTICAL_FRAMES[name])
            )
            self.published[IMAGE_TOPICS[name]] += 1

    # --- arm and pressure sensor ---------------------------------------------------

    def _on_joint_trajectory(self, msg: JointTrajectory) -> None:
        points = msg.points
        start = stamp_to_ns(msg.header.stamp) * 1e-9 or self._now()
        try:
            with self.arm_lock:
                self.arm_loop.command(
                    msg.joint_names,
                    [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in points],
                    [list(p.positions) for p in points],
                    [list(p.velocities) for p in points],
                    start,
                )
        except (InvalidInput, ValueError) as error:
            self.diagnostics.reject(JOINT_TRAJECTORY_TOPIC, error)

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    @guarded('arm')  # a failed step is reported; the thread goes on with the next
    def _arm_tick(self) -> None:
        with self.arm_lock:
            if not self.closed:
                self._publish_arm(self.arm_loop.step(self._now()))

    def _publish_arm(self, sample: ArmSample) -> None:
        self.joint_state_publisher.publish(
            JointState(
                header=make_header(sample.stamp_ns, BASE_FRAME),
                name=list(self.arm_loop.robot.joint_names),
                position=sample.q.tolist(),
                velocity=sample.qdot.tolist(),
            )
        )
        self.published[JOINT_STATES_TOPIC] += 1
        wrench = WrenchStamped(header=make_header(sample.stamp_ns, self.scenario.robot.tip_frame))
        wrench.wrench.force.z = sample.force
        self.pressure_publisher.publish(wrench)
        self.published[PRESSURE_TOPIC] += 1

    def _publish_diagnostics(self) -> None:
        phase = self.schedule.phase
        self.diagnostics.publish(
            'simulation',
            'ok',
            f'{phase} phase',
            {
                **self.published,
                'phase': phase,
                **{f'rejected {k}': v for k, v in self.diagnostics.rejected.items()},
            },
        )

    def close(self) -> None:
        """Final counts, so a recording can be checked for lost messages
        (``parse_published_counts`` reads them back)."""
        # rclpy's executor shutdown does not wait for running callbacks: these locks do,
        # so the counts are final.
        with self.capture_lock, self.arm_lock:
            self.closed = True
        self.gate.opened.set()  # releases an arm thread still waiting for subscribers
        counts = ' '.join(f'{topic}={n}' for topic, n in self.published.items())
        self.get_logger().info(f'published: {counts}')


def main(args: list[str] | None = None) -> int:
    """Run sensor_sim until SIGINT/SIGTERM; exit status 2 on an unusable parameter or
    scenario at start-up (one line)."""
    # One executor thread beside the arm's: rclpy's MultiThreadedExecutor spun on the
    # 100 Hz command subscription and starved the arm thread for the GIL (measured: the
    # simulator at 85-100 % CPU, joint states at 13-54 Hz instead of 200, gaps over 1 s;
    # single-threaded 15 % CPU, 200 Hz, gaps under 16 ms).
    return run_node(SensorSim, args)


if __name__ == '__main__':
    raise SystemExit(main())
