"""Shared fixtures: private ROS domains, node processes torn down pass or fail, and an
rclpy node in the test process on the same domain."""

import sys
import time
from pathlib import Path

import pytest

from harness import NodeProcess, executable, next_ros_env, wait_for  # noqa: F401 (re-exported)
from vgm_common.node_main import use_fastdds_profile

# The test's own publishers use the graph's Fast DDS profile, as the nodes do. With the
# stock one (a 512 KB shared-memory segment, 3 s heartbeats) a target pose sent between
# image bursts came up to 3 s late under load.
use_fastdds_profile()

MARKER_OF_DIRECTORY = {
    'unit': 'unit',
    'topic': 'topic',
    'bag_tools': 'topic',
    'fuzz': 'topic',
    'integration': 'integration',
    'browser': 'integration',
    'multihost': 'integration',
}


def pytest_collection_modifyitems(items):
    """Each test marked by its directory (pytest.ini lists the markers)."""
    for item in items:
        directory = Path(item.fspath).parent.name
        item.add_marker(MARKER_OF_DIRECTORY[directory])


@pytest.fixture
def ros_env():
    return next_ros_env()


@pytest.fixture
def spawn(ros_env, tmp_path):
    """Start processes with ``spawn(argv)``; all are stopped at teardown, pass or fail."""
    started = []

    def _spawn(argv, name=None, env=None):
        name = name or Path(str(argv[0])).name
        log_path = tmp_path / f'{name}-{len(started)}.log'
        node = NodeProcess(argv, env or ros_env, log_path)
        started.append(node)
        return node

    yield _spawn
    for node in reversed(started):
        node.stop()
    for node in started:
        sys.stdout.write(f'--- {node.log_path.name} ---\n{node.output()[-3000:]}\n')


@pytest.fixture
def rclpy_node(ros_env, monkeypatch):
    """An rclpy node in this test process, on the same private domain as ``spawn``."""
    for key in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE'):
        monkeypatch.setenv(key, ros_env[key])
    import rclpy

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node('test_probe', context=context)
    from rclpy.executors import SingleThreadedExecutor

    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    node.spin_until = lambda cond, timeout, what='condition': _spin_until(
        executor, cond, timeout, what
    )
    try:
        yield node
    finally:
        executor.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=context)


def _spin_until(executor, condition, timeout, what):
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f'timed out after {timeout:.0f} s waiting for {what}')
        executor.spin_once(timeout_sec=0.05)
    return True
