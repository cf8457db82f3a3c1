"""Shared fixtures: private ROS domains, node processes torn down pass or fail, and an
rclpy node in the test process on the same domain."""

import sys
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
def graph_probe(ros_env, monkeypatch):
    """A GraphProbe in this test process, on the same private domain as ``spawn``. It does
    not subscribe /diagnostics until ``watch_diagnostics()``: the nodes hold their first
    statuses until a subscriber matched, and some tests check that."""
    for key in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE'):
        monkeypatch.setenv(key, ros_env[key])
    from vgm_evaluation.graph_probe import GraphProbe

    probe = GraphProbe('test_probe', watch_diagnostics=False)
    try:
        yield probe
    finally:
        probe.close()


@pytest.fixture
def rclpy_node(graph_probe):
    """The graph probe's rclpy node, with ``spin_until(condition, timeout, what)`` and the
    probe itself as ``graph``."""
    node = graph_probe.node
    node.spin_until = graph_probe.wait
    node.graph = graph_probe
    return node
