"""sensor_sim: the synthetic rig. Three cameras (left, right, aux), the calibration
stage, the pressure sensor at the tool tip and a simulated PA-10, from a scenario file.

Timeline: with ``calibration_phase`` true the chart is shown at every stage pose of the
scenario (``captures_per_pose`` captures each, ``/calibration/target_pose`` stamped like
the images), then the scene with the curve is captured until shutdown. The arm runs
throughout at ``joint_state_rate``.
"""

import threading
import time
from pathlib import Path

import numpy as np
import yaml
from geometry_msgs.msg import PoseStamped, WrenchStamped
from sensor_msgs.msg import Image, JointState
from trajectory_msgs.msg import JointTrajectory

from sensor_sim.arm_sim import ARM_MODES, SimulatedArm
from sensor_sim.contact import contact_force
from sensor_sim.curves import curve_polylines
from sensor_sim.render import SceneRenderer, add_noise
from sensor_sim.scenario import (
    CAMERA_NAMES,
    CHART_MOTIONS,
    load_scenario,
    resolve_scenario_path,
    with_chart_motion,
)
from vgm_common.calibration_io import write_calibration
from vgm_common.conversions import make_header, matrix_to_pose_stamped, numpy_to_image, stamp_to_ns
from vgm_common.errors import InvalidInput
from vgm_common.graph_node import GraphNode
from vgm_common.node_main import run_node
from vgm_common.parameters import Param
from vgm_common.qos import DEFAULT_QOS
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

PARAMETERS = [
    Param(
        'scenario',
        'default',
        'Scenario file, or the name of a shipped one.',
        read_only=True,
    ),
    Param(
        'calibration_phase',
        True,
        'Show the chart at every stage pose first.',
        read_only=True,
    ),
    Param(
        'chart_motion',
        '',
        'How the chart is shown in the calibration phase: stage (at the stage poses, '
        "with /calibration/target_pose) or handheld (a hand's poses around them, spread "
        "over the images, no target pose); empty takes the scenario's calibration.motion.",
        choices=('', *CHART_MOTIONS),
        read_only=True,
    ),
    Param(
        'rate',
        0.0,
        'Camera frame rate [Hz]; 0 takes the scenario rate.',
        range=(0.0, 200.0),
        read_only=True,
    ),
    Param(
        'joint_state_rate',
        200.0,
        'Arm simulation, /joint_states and /tool/pressure rate [Hz].',
        range=(100.0, 1000.0),
        read_only=True,
    ),
    Param(
        'ground_truth_dir',
        '',
        'Where the true cameras, curve and depth maps are '
        'written for tests and benchmarks; empty: not written.',
        read_only=True,
    ),
    *subscriber_gate_params('Publish only once every camera topic has'),
    Param(
        'arm_mode',
        'position',
        'The simulated arm follows the commanded '
        "'position' (set points) or only the commanded 'velocity'.",
        choices=ARM_MODES,
        read_only=True,
    ),
    Param(
        'arm_speed_scale',
        1.0,
        'Fraction of the commanded motion the arm makes (< 1: an arm slower than commanded).',
        range=(0.01, 1.0),
        read_only=True,
    ),
    Param(
        'arm_command_delay',
        0.0,
        '[s] The arm follows each joint trajectory only this long after it arrives '
        '(a controller or network with that much command latency); 0: at once.',
        range=(0.0, 1.0),
        read_only=True,
    ),
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

    def __init__(self):
        super().__init__(PARAMETERS)
        self.scenario = load_scenario(resolve_scenario_path(self.params.scenario))
        if self.params.chart_motion and self.scenario.calibration is not None:
            self.scenario = with_chart_motion(self.scenario, self.params.chart_motion)
        self.get_logger().info(f'scenario {self.scenario.name} ({self.scenario.path})')
        # Publishers first: subscribers (a recorder) discover and match them while the
        # scene renders, so not even the first capture is lost.
        self._create_publishers()
        self._render_scene()
        self._build_arm()
        self._init_state()
        self._start()

    def _create_publishers(self):
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

    def _render_scene(self):
        started = time.monotonic()
        self.renderer = SceneRenderer(self.scenario)
        self.calibration_phase = (
            self.params.calibration_phase and self.scenario.calibration is not None
        )
        self._render_everything()
        self.get_logger().info(f'rendered the scene in {time.monotonic() - started:.2f} s')

    def _build_arm(self):
        robot = self.scenario.robot
        self.robot = load_robot(
            robot.model,
            robot.tool_length,
            robot.tip_frame,
            base_frame=robot.base_frame,
            base_placement=robot.base_placement,
        )
        self.arm = SimulatedArm.from_robot_model(
            self.robot,
            robot.initial_joints,
            self.params.arm_mode,
            self.params.arm_speed_scale,
            self.params.arm_command_delay,
        )
        if self.params.ground_truth_dir:
            self._write_ground_truth(Path(self.params.ground_truth_dir))

    def _init_state(self):
        calibration = self.scenario.calibration
        self.chart_frames = 0
        if self.calibration_phase and calibration is not None:
            self.chart_frames = len(calibration.T_base_chart) * calibration.captures_per_pose
        self.frame_index = 0
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
        self.published = {
            topic: 0
            for topic in (
                *IMAGE_TOPICS.values(),
                TARGET_POSE_TOPIC,
                JOINT_STATES_TOPIC,
                PRESSURE_TOPIC,
            )
        }
        self.rng_pressure = np.random.default_rng([self.scenario.seed, 1_000_003])

    def _start(self):
        """Takes joint trajectories, starts the arm thread and the capture timer."""
        self.create_subscription(
            JointTrajectory,
            JOINT_TRAJECTORY_TOPIC,
            self._on_joint_trajectory,
            DEFAULT_QOS,
        )
        self.arm_period = 1.0 / self.params.joint_state_rate
        self.last_arm_time = None
        # The arm runs in its own thread on an absolute schedule: an executor timer at
        # 200 Hz is starved by the captures (measured: 77-160 Hz instead of 200).
        self.arm_thread = threading.Thread(target=self._run_arm, name='arm', daemon=True)
        self.arm_thread.start()
        self.create_timer(1.0, self._publish_diagnostics)
        frame_rate = self.params.rate or self.scenario.rate
        self.create_timer(1.0 / frame_rate, self._capture)
        self.get_logger().info(
            f'publishing 3 cameras at {frame_rate:g} Hz ({self.chart_frames} calibration '
            f'captures first), joint states at {self.params.joint_state_rate:g} Hz, arm '
            f'{self.scenario.robot.model} following {self.params.arm_mode}s '
            f'x{self.params.arm_speed_scale:g}, commands '
            f'{self.params.arm_command_delay * 1e3:g} ms late'
        )

    # --- cameras ---------------------------------------------------------------------

    def _render_everything(self):
        """Render every clean image now, so captures keep their rate from the first."""
        calibration = self.scenario.calibration
        for name in CAMERA_NAMES:
            self.renderer.scene_image(name)
            if self.calibration_phase and calibration is not None:
                for pose_index in range(len(calibration.T_base_chart)):
                    self.renderer.chart_image(name, pose_index)

    def _capture(self):
        """One capture: the three images (and the chart pose) with one stamp."""
        if not self.gate.is_open():  # the arm starts publishing too
            return
        with self.capture_lock:
            if not self.closed:
                self._publish_capture()

    def _publish_capture(self):
        stamp_ns = self.get_clock().now().nanoseconds
        k = self.frame_index
        self.frame_index += 1
        pose_index = None
        calibration = self.scenario.calibration
        if k < self.chart_frames and calibration is not None:  # the calibration phase
            pose_index = k // calibration.captures_per_pose
            if calibration.motion == 'stage':  # a hand's poses are not measured
                self.target_pose_publisher.publish(
                    matrix_to_pose_stamped(
                        calibration.T_base_chart[pose_index], stamp_ns, BASE_FRAME
                    )
                )
                self.published[TARGET_POSE_TOPIC] += 1
            if k + 1 == self.chart_frames:
                self.get_logger().info('calibration phase done: showing the scene')
        for camera_index, name in enumerate(CAMERA_NAMES):
            clean = (
                self.renderer.scene_image(name)
                if pose_index is None
                else self.renderer.chart_image(name, pose_index)
            )
            # Same scenario, seed and frame: the same noise, bit for bit.
            rng = np.random.default_rng([self.scenario.seed, k, camera_index])
            pixels = add_noise(clean, self.scenario.noise.image_sigma, rng)
            self.image_publishers[name].publish(
                numpy_to_image(pixels, 'mono8', stamp_ns, OPTICAL_FRAMES[name])
            )
            self.published[IMAGE_TOPICS[name]] += 1

    # --- arm and pressure sensor ---------------------------------------------------

    def _on_joint_trajectory(self, msg):
        try:
            times = np.array(
                [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9 for p in msg.points]
            )
            positions = [list(p.positions) for p in msg.points]
            velocities = [list(p.velocities) for p in msg.points]
            if any(len(v) != len(p) for v, p in zip(velocities, positions) if v):
                raise InvalidInput('velocities and positions differ in length')
            has_velocities = bool(msg.points) and all(velocities)
            start = stamp_to_ns(msg.header.stamp) * 1e-9 or self._now()
            with self.arm_lock:
                self.arm.set_trajectory(
                    list(msg.joint_names),
                    times,
                    np.array(positions, dtype=float),
                    np.array(velocities, dtype=float) if has_velocities else None,
                    start,
                )
        except (InvalidInput, ValueError) as error:
            with self.arm_lock:
                self.arm.hold()
            self.diagnostics.reject(JOINT_TRAJECTORY_TOPIC, error)

    def _now(self):
        return self.get_clock().now().nanoseconds * 1e-9

    def _run_arm(self):
        self.gate.opened.wait()
        next_tick = time.monotonic()
        while True:
            with self.arm_lock:
                if self.closed:
                    return
                self._step_arm_and_publish()
            next_tick += self.arm_period
            delay = next_tick - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                next_tick = time.monotonic()  # running late: no burst to catch up

    def _step_arm_and_publish(self):
        now = self._now()
        dt = self.arm_period if self.last_arm_time is None else now - self.last_arm_time
        self.last_arm_time = now
        q, qdot = self.arm.step(now, max(dt, 0.0))
        stamp_ns = int(now * 1e9)
        self.joint_state_publisher.publish(
            JointState(
                header=make_header(stamp_ns, BASE_FRAME),
                name=list(self.robot.joint_names),
                position=q.tolist(),
                velocity=qdot.tolist(),
            )
        )
        self.published[JOINT_STATES_TOPIC] += 1

        T_base_tool = self.robot.forward_kinematics(q)
        contact = contact_force(
            T_base_tool[:3, 3], self.scenario.surface, self.scenario.contact_stiffness
        )
        force = contact.force
        if force > 0:
            force = max(
                0.0, force + self.rng_pressure.normal(0.0, self.scenario.noise.pressure_sigma)
            )
        wrench = WrenchStamped(header=make_header(stamp_ns, self.scenario.robot.tip_frame))
        wrench.wrench.force.z = float(force)
        self.pressure_publisher.publish(wrench)
        self.published[PRESSURE_TOPIC] += 1

    def _publish_diagnostics(self):
        phase = 'calibration' if self.frame_index < self.chart_frames else 'scene'
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

    def close(self):
        """Final counts, so a recording can be checked for lost messages
        (``parse_published_counts`` reads them back)."""
        # rclpy's executor shutdown does not wait for running callbacks: these locks do,
        # so the counts are final.
        with self.capture_lock, self.arm_lock:
            self.closed = True
        self.gate.opened.set()  # releases an arm thread still waiting for subscribers
        counts = ' '.join(f'{topic}={n}' for topic, n in self.published.items())
        self.get_logger().info(f'published: {counts}')

    # --- ground truth (files only: no pipeline node reads them) ------------------

    def _write_ground_truth(self, directory):
        directory.mkdir(parents=True, exist_ok=True)
        cameras = {
            name: {
                'width': cam.width,
                'height': cam.height,
                'K': cam.K.tolist(),
                'distortion_model': cam.distortion_model,
                'D': cam.D.tolist(),
                'T_base_camera': cam.T_base_camera.tolist(),
            }
            for name, cam in self.scenario.cameras.items()
        }
        (directory / 'cameras.yaml').write_text(yaml.safe_dump(cameras))
        if all(c.distortion_model == 'plumb_bob' for c in self.scenario.cameras.values()):
            # The true rig as a calibration file: calib_node's `calibration_file` loads it.
            write_calibration(
                directory / 'true_calibration', self.scenario.cameras, OPTICAL_FRAMES
            )
        pieces = curve_polylines(self.scenario.curve, self.scenario.surface)
        np.savez(directory / 'curve_base.npz', *pieces)
        for name in CAMERA_NAMES:
            np.save(directory / f'depth_{name}.npy', self.renderer.depth(name))
        calibration = self.scenario.calibration
        if calibration is not None:
            np.save(directory / 'T_base_chart.npy', np.stack(calibration.T_base_chart))
        self.get_logger().info(f'ground truth written to {directory}')


def main(args=None):
    """Run sensor_sim until SIGINT/SIGTERM; exit status 2 on an unusable parameter or
    scenario at start-up (one line)."""
    # One executor thread beside the arm's: rclpy's MultiThreadedExecutor spun on the
    # 100 Hz command subscription and starved the arm thread for the GIL (measured: the
    # simulator at 85-100 % CPU, joint states at 13-54 Hz instead of 200, gaps over 1 s;
    # single-threaded 15 % CPU, 200 Hz, gaps under 16 ms).
    return run_node(SensorSim, args)


if __name__ == '__main__':
    raise SystemExit(main())
