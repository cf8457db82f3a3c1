"""Each package's ``params/<node>.yaml`` lists exactly the parameters its node declares,
with the node's defaults: the file users copy must not drift from the code.

Each node is constructed in this process (its parameters are declared in ``__init__``) on
the test's private domain, read, closed and destroyed."""
import importlib
import math
from pathlib import Path

import pytest
import rclpy
import yaml

from harness import REPO_ROOT

NODES = {  # params file -> {node name in the file: 'module:Class'}
    'calib_node/params/calib_node.yaml': {'calib_node': 'calib_node.node:CalibNode'},
    'curve_recon_node/params/curve_recon_node.yaml': {
        'curve_recon_node': 'curve_recon_node.node:CurveReconNode'},
    'sfs_stereo_node/params/sfs_stereo_node.yaml': {
        'sfs_stereo_node': 'sfs_stereo_node.node:SfsStereoNode'},
    'pa10_ik_node/params/pa10_ik_node.yaml': {'pa10_ik_node': 'pa10_ik_node.node:Pa10IkNode'},
    'stereo_coding_node/params/stereo_coding.yaml': {
        'stereo_coding_node': 'stereo_coding_node.encoder_node:StereoCodingNode',
        'stereo_decoding_node': 'stereo_coding_node.decoder_node:StereoDecodingNode'},
}
NOT_LISTED = {'use_sim_time', 'start_type_description_service'}  # every rclpy node's


def flatten(section, prefix=''):
    """{'a': {'b': 1}} -> {'a.b': 1}: how ROS names nested parameters."""
    flat = {}
    for key, value in section.items():
        if isinstance(value, dict):
            flat.update(flatten(value, f'{prefix}{key}.'))
        else:
            flat[prefix + key] = value
    return flat


def same(a, b):
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, (int, float)) and isinstance(b, (int, float)) and \
            math.isclose(a, b, rel_tol=1e-12, abs_tol=0.0)
    return a == b


@pytest.fixture
def default_context(ros_env, monkeypatch):
    for key in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE'):
        monkeypatch.setenv(key, ros_env[key])
    rclpy.init()
    yield
    rclpy.shutdown()


def declared_defaults(class_path):
    module, name = class_path.split(':')
    node = getattr(importlib.import_module(module), name)()
    try:
        return {name: parameter.value for name, parameter in node._parameters.items()
                if name not in NOT_LISTED}
    finally:
        if hasattr(node, 'close'):
            node.close()
        node.destroy_node()


@pytest.mark.parametrize('params_file', sorted(NODES))
def test_params_file_lists_what_the_node_declares(params_file, default_context):
    sections = yaml.safe_load((REPO_ROOT / 'src' / params_file).read_text())
    assert set(sections) == set(NODES[params_file]), 'nodes in the file'
    for node_name, class_path in NODES[params_file].items():
        listed = flatten(sections[node_name]['ros__parameters'])
        declared = declared_defaults(class_path)
        assert sorted(set(declared) - set(listed)) == [], f'{node_name}: not in {params_file}'
        assert sorted(set(listed) - set(declared)) == [], f'{node_name}: not declared'
        differ = {name: (listed[name], declared[name]) for name in listed
                  if not same(listed[name], declared[name])}
        assert differ == {}, f'{node_name}: (file, node default) differ'


def test_every_params_file_is_checked():
    found = {str(path.relative_to(REPO_ROOT / 'src'))
             for path in Path(REPO_ROOT / 'src').glob('*/params/*.yaml')
             if path.parent.parent.name != 'vgm_common'}  # graph.yaml: the demo's values
    assert found == set(NODES)
