"""Topic level, real processes: a node started and stopped cleanly prints no warning,
no error and no Python 'exception was never retrieved' (the multi-threaded nodes did,
at every Ctrl-C, from callbacks that outlived rclpy's executor shutdown)."""

import re

import pytest
from diagnostic_msgs.msg import DiagnosticArray

from harness import executable
from vgm_common.qos import DEFAULT_QOS
from vgm_common.topics import DIAGNOSTICS_TOPIC

PROBLEM = re.compile(r'\[(WARN|ERROR)\]|never retrieved|never awaited|Traceback')


@pytest.mark.parametrize('package', ['sensor_sim', 'calib_node', 'curve_recon_node'])
def test_a_clean_start_and_stop_prints_no_warning_or_error(spawn, rclpy_node, package):
    statuses = []
    rclpy_node.create_subscription(
        DiagnosticArray,
        DIAGNOSTICS_TOPIC,
        lambda msg: statuses.extend(s.name for s in msg.status),
        DEFAULT_QOS,
    )
    node = spawn([executable(package)])
    # Its callbacks run on the executor's threads: then stop it.
    rclpy_node.spin_until(
        lambda: any(name.startswith(f'{package}: ') for name in statuses),
        60.0,
        f'diagnostics from {package}',
    )
    assert node.stop() == 0
    output = node.output()
    assert not PROBLEM.search(output), output
