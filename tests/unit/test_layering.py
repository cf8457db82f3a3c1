"""The layering docs/architecture.md states, checked on the sources: the algorithm cores
import no rclpy (only node files and vgm_common's node edges do), no node package
imports vgm_evaluation (the generators are for benches, tests and the demo), and the node
packages stand side by side on vgm_common, none importing another."""

import ast

import pytest

from harness import REPO_ROOT

SRC = REPO_ROOT / 'src'
NODE_PACKAGES = sorted(p.name for p in SRC.iterdir() if (p / 'package.xml').exists())
# Besides the node files (node.py, *_node.py), the modules that may use rclpy: vgm_common's
# node edges, QoS profiles and camera subscriptions, and bag_tools' topic discovery.
ROS_EDGES = {
    'graph_node.py',
    'parameters.py',
    'diagnostics.py',
    'subscriber_gate.py',
    'node_main.py',
    'qos.py',
    'topic_discovery.py',
    'camera_topics.py',
    'graph_probe.py',
    'deferred_service.py',
}
# The one import across node packages: live_view finds topics as the recorder does.
ALLOWED_NEIGHBOURS = {'live_view': {'bag_tools'}}


def imported_packages(path):
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split('.')[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module.split('.')[0])
    return names


@pytest.mark.parametrize('package', NODE_PACKAGES)
def test_cores_import_no_rclpy_and_nodes_no_evaluation_code(package):
    for path in sorted((SRC / package / package).glob('*.py')):
        imported = imported_packages(path)
        if package != 'vgm_evaluation':
            assert 'vgm_evaluation' not in imported, f'{path} imports vgm_evaluation'
        if not (
            path.name == 'node.py' or path.name.endswith('_node.py') or path.name in ROS_EDGES
        ):
            assert not imported & {'rclpy'}, f'{path} is a core and imports rclpy'


@pytest.mark.parametrize('package', [p for p in NODE_PACKAGES if p != 'vgm_evaluation'])
def test_node_packages_import_only_vgm_common_of_ours(package):
    others = set(NODE_PACKAGES) - {package, 'vgm_common'} - ALLOWED_NEIGHBOURS.get(package, set())
    for path in sorted((SRC / package / package).glob('*.py')):
        crossing = imported_packages(path) & others
        assert not crossing, (
            f'{path} imports {sorted(crossing)}: a node package stands on vgm_common only'
        )
