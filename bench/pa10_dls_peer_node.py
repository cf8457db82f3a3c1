#!/usr/bin/env python3
"""The damped-least-squares peer over topics, for bench_pa10_ik.py --over-topics only
(never installed, no product node): ``DlsPeer`` of pa10_dls_peer.py closing the loop on
the topics pa10_ik_node uses, so both run against the same sensor_sim processes.

In: /curve/waypoints (latched), /joint_states, /tool/pressure (the tip frame's force.z).
Out: /pa10_controller/joint_trajectory (one point q + qdot h at h = 0.05 s with velocity
qdot, zero stamp: as pa10_ik_node sends it), /tool_pose (forward kinematics of the
measured joints). ``~/start_tracking`` (std_srvs/Trigger) starts the task on the newest
path; /diagnostics status 'dls_peer: tracking' carries phase and stage (idle, approach,
tracking, done; failed with the reason), published on every change and at 2 Hz.

Run: .venv/bin/python bench/pa10_dls_peer_node.py --ros-args -p robot:=<urdf>
     -p tip_frame:=<frame> [-p base_frame:=<frame>] [-p desired_force:=5.0]
     [-p contact_stiffness:=2000.0]
"""

import sys
import time
from pathlib import Path

import numpy as np
import rclpy
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import PoseStamped, WrenchStamped
from nav_msgs.msg import Path as PathMsg
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_srvs.srv import Trigger
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

sys.path.insert(0, str(Path(__file__).resolve().parent))
from pa10_dls_peer import PEER_SPEED, DlsPeer  # noqa: E402

from pa10_ik_node.path import validate_waypoints  # noqa: E402
from vgm_common.conversions import matrix_to_pose_stamped, path_to_matrices  # noqa: E402
from vgm_common.diagnostics import Diagnostics  # noqa: E402
from vgm_common.errors import InvalidInput  # noqa: E402
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS  # noqa: E402
from vgm_common.robot_model import load_robot  # noqa: E402
from vgm_common.topics import (  # noqa: E402
    BASE_FRAME,
    JOINT_STATES_TOPIC,
    JOINT_TRAJECTORY_TOPIC,
    PRESSURE_TOPIC,
    TOOL_POSE_TOPIC,
    WAYPOINTS_TOPIC,
)

RATE = 100.0  # [Hz] control, as pa10_ik_node's default
HORIZON = 0.05  # [s] time_from_start of the commanded point, as pa10_ik_node's default
ACTIVE = ('approach', 'tracking', 'done')  # DlsPeer steps on until lifted


class DlsPeerNode(Node):
    def __init__(self):
        super().__init__('dls_peer')
        declare = self.declare_parameter
        self.robot = load_robot(
            declare('robot', '').value,
            tip_frame=declare('tip_frame', 'tool0').value,
            base_frame=declare('base_frame', '').value,
        )
        self.desired = float(declare('desired_force', 5.0).value)
        self.stiffness = float(declare('contact_stiffness', 2000.0).value)
        self.tip_frame = self.get_parameter('tip_frame').value
        self.index = {name: i for i, name in enumerate(self.robot.joint_names)}
        self.q, self.force, self.waypoints, self.controller = None, 0.0, None, None
        self.last_step, self.last_phase = None, None
        self.diagnostics = Diagnostics(self)
        self.command_publisher = self.create_publisher(
            JointTrajectory, JOINT_TRAJECTORY_TOPIC, DEFAULT_QOS
        )
        self.pose_publisher = self.create_publisher(PoseStamped, TOOL_POSE_TOPIC, DEFAULT_QOS)
        self.create_subscription(JointState, JOINT_STATES_TOPIC, self._on_joints, DEFAULT_QOS)
        self.create_subscription(WrenchStamped, PRESSURE_TOPIC, self._on_pressure, DEFAULT_QOS)
        self.create_subscription(PathMsg, WAYPOINTS_TOPIC, self._on_waypoints, LATCHED_QOS)
        self.create_service(Trigger, '~/start_tracking', self._on_start)
        self.create_timer(1.0 / RATE, self._control_step)
        self.create_timer(0.5, self._publish_status)

    @property
    def phase(self):
        return self.controller.phase if self.controller else 'idle'

    def _on_joints(self, msg):
        if set(self.index) <= set(msg.name):
            q = np.empty(self.robot.n_joints)
            for name, value in zip(msg.name, msg.position):
                if name in self.index:
                    q[self.index[name]] = value
            self.q = q

    def _on_pressure(self, msg):
        if msg.header.frame_id == self.tip_frame and np.isfinite(msg.wrench.force.z):
            self.force = float(msg.wrench.force.z)

    def _on_waypoints(self, msg):
        try:
            self.waypoints = validate_waypoints(path_to_matrices(msg))
        except InvalidInput as error:
            self.get_logger().error(f'rejected {WAYPOINTS_TOPIC}: {error}')
            return
        self.get_logger().info(f'waypoints: {len(self.waypoints)}')

    def _on_start(self, request, response):
        if self.waypoints is None or self.q is None:
            response.success, response.message = False, 'no waypoints or joint states yet'
            return response
        self.controller = DlsPeer(self.robot, self.waypoints, self.desired, self.stiffness)
        self.last_step = None
        self._publish_status()
        response.success, response.message = True, f'started at {PEER_SPEED} m/s'
        return response

    def _control_step(self):
        if self.q is None:
            return
        q = self.q
        if self.phase in ACTIVE and self.controller.stage != 'lifted':
            # The step the timer really took, bounded (as pa10_ik_node does).
            now = time.monotonic()
            dt = 1.0 / RATE if self.last_step is None else min(now - self.last_step, 3 / RATE)
            self.last_step = now
            try:
                qdot, _ = self.controller.step(q, self.force, dt)
            except Exception as error:  # noqa: BLE001 - the bench sees the reason
                self.controller.phase, self.controller.reason = 'failed', repr(error)
                qdot = np.zeros(self.robot.n_joints)
            horizon = HORIZON if self.phase in ACTIVE else 0.0
            self._command(q, qdot if self.phase in ACTIVE else np.zeros_like(qdot), horizon)
        self.pose_publisher.publish(
            matrix_to_pose_stamped(
                self.robot.forward_kinematics(q), self.get_clock().now().nanoseconds, BASE_FRAME
            )
        )
        if self.phase != self.last_phase:
            self.last_phase = self.phase
            self.get_logger().info(f'phase {self.phase}')
            self._publish_status()

    def _command(self, q, qdot, horizon):
        seconds = int(horizon)
        point = JointTrajectoryPoint(
            positions=(q + qdot * horizon).tolist(),
            velocities=qdot.tolist(),
            time_from_start=Duration(sec=seconds, nanosec=int((horizon - seconds) * 1e9)),
        )
        self.command_publisher.publish(
            JointTrajectory(joint_names=list(self.robot.joint_names), points=[point])
        )

    def _publish_status(self):
        controller = self.controller
        values = {
            'phase': self.phase,
            'stage': controller.stage if controller else '',
            'progress': f'{controller.progress:.4f}' if controller else '0',
            'reason': controller.reason if controller else '',
        }
        level = 'error' if self.phase == 'failed' else 'ok'
        self.diagnostics.publish('tracking', level, self.phase, values)


def main():
    rclpy.init()
    node = DlsPeerNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
