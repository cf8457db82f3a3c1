"""Each package's ``params/<node>.yaml`` and README parameter tables list exactly the
parameters its node declares, with the node's defaults: what users copy and read must not
drift from the code.

Each node is constructed in this process (its parameters are declared in ``__init__``) on
the test's private domain, read, closed and destroyed."""

import importlib
import math
import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import rclpy
import yaml
from rclpy.serialization import serialize_message
from std_msgs.msg import String

from bag_tools.bag_writer import BagWriter
from harness import REPO_ROOT

NODES = {  # params file -> {node name in the file: 'module:Class'}
    'calib_node/params/calib_node.yaml': {'calib_node': 'calib_node.node:CalibNode'},
    'curve_recon_node/params/curve_recon_node.yaml': {
        'curve_recon_node': 'curve_recon_node.node:CurveReconNode'
    },
    'sfs_stereo_node/params/sfs_stereo_node.yaml': {
        'sfs_stereo_node': 'sfs_stereo_node.node:SfsStereoNode'
    },
    'pa10_ik_node/params/pa10_ik_node.yaml': {'pa10_ik_node': 'pa10_ik_node.node:Pa10IkNode'},
    'sensor_sim/params/sensor_sim.yaml': {'sensor_sim': 'sensor_sim.sensor_sim_node:SensorSim'},
    'bag_tools/params/recorder.yaml': {'recorder': 'bag_tools.recorder_node:RecorderNode'},
    'bag_tools/params/player.yaml': {'player': 'bag_tools.player_node:PlayerNode'},
    'bag_tools/params/image_publisher.yaml': {
        'image_publisher': 'bag_tools.image_publisher_node:ImagePublisher'
    },
    'live_view/params/live_view.yaml': {'live_view': 'live_view.node:LiveViewNode'},
    'stereo_coding_node/params/stereo_coding.yaml': {
        'stereo_coding_node': 'stereo_coding_node.encoder_node:StereoCodingNode',
        'stereo_decoding_node': 'stereo_coding_node.decoder_node:StereoDecodingNode',
    },
}
NOT_LISTED = {'use_sim_time', 'start_type_description_service'}  # every rclpy node's
# live_view binds its port as it is constructed: any free one here; the recorder creates
# its bag: in the test's own directory; the player and image_publisher need a bag and a
# folder of images: made there. Only the names of these parameters are compared.
OVERRIDDEN = {
    'live_view': {'port': '0'},
    'recorder': {'output_dir': '{tmp_path}'},
    'player': {'bag': '{tmp_path}/played'},
    'image_publisher': {'folder': '{tmp_path}/images'},
}


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
        return (
            isinstance(a, (int, float))
            and isinstance(b, (int, float))
            and math.isclose(a, b, rel_tol=1e-12, abs_tol=0.0)
        )
    return a == b


@pytest.fixture
def default_context(ros_env, monkeypatch, tmp_path):
    with BagWriter(tmp_path / 'played') as bag:
        bag.add_topic('/a', 'std_msgs/msg/String')
        bag.write('/a', bytes(serialize_message(String(data='a'))), 1)
    for name in ('left', 'right'):  # one image set for image_publisher
        (tmp_path / 'images').mkdir(exist_ok=True)
        cv2.imwrite(str(tmp_path / 'images' / f'{name}.png'), np.zeros((4, 4), np.uint8))
    for key in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE'):
        monkeypatch.setenv(key, ros_env[key])
    rclpy.init(
        args=[
            '--ros-args',
            *(
                arg
                for node, values in OVERRIDDEN.items()
                for name, value in values.items()
                for arg in ('-p', f'{node}:{name}:={value.format(tmp_path=tmp_path)}')
            ),
        ]
    )
    yield
    rclpy.shutdown()


def declared_defaults(class_path):
    module, name = class_path.split(':')
    node = getattr(importlib.import_module(module), name)()
    try:
        return {
            name: parameter.value
            for name, parameter in node._parameters.items()
            if name not in NOT_LISTED
        }
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
        overridden = set(OVERRIDDEN.get(node_name, {}))
        assert sorted(set(declared) - set(listed)) == [], f'{node_name}: not in {params_file}'
        assert sorted(set(listed) - set(declared)) == [], f'{node_name}: not declared'
        differ = {
            name: (listed[name], declared[name])
            for name in listed
            if name not in overridden and not same(listed[name], declared[name])
        }
        assert differ == {}, f'{node_name}: (file, node default) differ'


def readme_tables(text):
    """{name: default cell} of the `| name | default | meaning |` tables in ``text``; a row
    naming several (`a`, `b` or `a` / `b`) gives each name the row's whole default cell,
    and each value in turn when there are as many."""
    rows, in_table = {}, False
    for line in text.splitlines():
        cells = (
            [c.strip() for c in line.strip().strip('|').split('|')] if line.startswith('|') else []
        )
        if cells[:2] in (['name', 'default'], ['parameter', 'default']):
            in_table = True
        elif not cells:
            in_table = False
        elif in_table and not set(cells[0]) <= set('-: '):
            names = re.findall(r'`([^`]+)`', cells[0]) or re.split(r'\s*(?:,|/)\s*', cells[0])
            defaults = re.split(r'\s*(?:,|/)\s*', cells[1]) if len(names) > 1 else [cells[1]]
            for i, name in enumerate(names):
                rows[name] = defaults[i] if len(defaults) == len(names) else None
    return rows


def same_as_written(cell, value):
    """The README's default cell (`text`, 0.8, [1, 2], true) against the declared value,
    numbers to the README's rounding."""
    quoted = re.fullmatch(r'`([^`]*)`.*', cell)  # `0.5` s: the value, then its unit
    text = quoted.group(1) if quoted else cell
    try:
        written = (
            float(text) if re.fullmatch(r'[-+]?[\d.]+e[-+]?\d+', text) else yaml.safe_load(text)
        )  # (YAML 1.1 reads 1e-4 as a string)
    except yaml.YAMLError:
        return False
    if (
        isinstance(value, (int, float))
        and not isinstance(value, bool)
        and isinstance(written, (int, float))
    ):
        return math.isclose(written, value, rel_tol=0.01, abs_tol=1e-12)
    if isinstance(value, list) and isinstance(written, list) and len(value) == len(written):
        return all(same_as_written(str(w), v) for w, v in zip(written, value))
    return written == value or (written is None and value == '') or text == str(value)


READMES = {  # README -> the nodes whose parameters its tables list
    'calib_node/README.md': ['calib_node.node:CalibNode'],
    'curve_recon_node/README.md': ['curve_recon_node.node:CurveReconNode'],
    'sfs_stereo_node/README.md': ['sfs_stereo_node.node:SfsStereoNode'],
    'pa10_ik_node/README.md': ['pa10_ik_node.node:Pa10IkNode'],
    'stereo_coding_node/README.md': [
        'stereo_coding_node.encoder_node:StereoCodingNode',
        'stereo_coding_node.decoder_node:StereoDecodingNode',
    ],
    'live_view/README.md': ['live_view.node:LiveViewNode'],
    # the simulator's, the recorder's and the player's tables
    '../README.md': [
        'sensor_sim.sensor_sim_node:SensorSim',
        'bag_tools.recorder_node:RecorderNode',
        'bag_tools.player_node:PlayerNode',
        'bag_tools.image_publisher_node:ImagePublisher',
    ],
}


def tables_of_nodes(text, class_paths):
    """{the README text listing their parameters: the nodes' class paths}: a node's
    generated table (``<!-- parameters of MODULE: ...``), else the whole README, whose
    tables may list several nodes' parameters (which then must agree on a name's default)."""
    texts = {}
    for class_path in class_paths:
        module = re.escape(class_path.split(':')[0])
        generated = re.search(
            rf'<!-- parameters of {module}: .*?-->\n(.*?)<!-- end of parameters -->', text, re.S
        )
        texts.setdefault(generated.group(1) if generated else text, []).append(class_path)
    return texts


@pytest.mark.parametrize('readme', sorted(READMES))
def test_readme_tables_list_what_the_node_declares(readme, default_context):
    text = (REPO_ROOT / 'src' / readme).read_text()
    for section, class_paths in tables_of_nodes(text, READMES[readme]).items():
        check_readme_table(readme, readme_tables(section), class_paths)


def check_readme_table(readme, written, class_paths):
    declared = {}
    for class_path in class_paths:
        declared.update(declared_defaults(class_path))
    assert sorted(set(declared) - set(written)) == [], f'not in the tables of {readme}'
    assert sorted(set(written) - set(declared)) == [], f'in {readme} but not declared'
    overridden = {name for values in OVERRIDDEN.values() for name in values}
    differ = {
        name: (cell, declared[name])
        for name, cell in written.items()
        if cell is not None
        and name not in overridden
        and not same_as_written(cell, declared[name])
    }
    assert differ == {}, f'{readme}: (README, node default) differ'


def test_every_params_file_is_checked():
    found = {
        str(path.relative_to(REPO_ROOT / 'src'))
        for path in Path(REPO_ROOT / 'src').glob('*/params/*.yaml')
        if path.parent.parent.name != 'vgm_common'
    }  # graph.yaml: the demo's values
    assert found == set(NODES)


CORE_SETTINGS = {  # node -> its ConfigParams: the core settings its parameters fill
    'calib_node.node:CalibNode': ['GA', 'SESSION'],
    'curve_recon_node.node:CurveReconNode': ['SETTINGS'],
    'sfs_stereo_node.node:SfsStereoNode': ['DEPTH'],
    'pa10_ik_node.node:Pa10IkNode': ['ARM', 'SOLVER', 'TRACKING', 'LOOP'],
    'sensor_sim.sensor_sim_node:SensorSim': ['SIM', 'ARM'],
    'bag_tools.recorder_node:RecorderNode': ['BAG'],
    'bag_tools.player_node:PlayerNode': ['PLAYER'],
    'bag_tools.image_publisher_node:ImagePublisher': ['FOLDER'],
    'live_view.node:LiveViewNode': ['SERVER'],
    'stereo_coding_node.encoder_node:StereoCodingNode': ['CODING', 'ENCODER'],
    'stereo_coding_node.decoder_node:StereoDecodingNode': ['CODING', 'DECODER'],
}


@pytest.mark.parametrize('class_path', sorted(CORE_SETTINGS))
def test_parameters_default_to_the_core_settings(class_path, default_context):
    """A parameter that fills a field of a core's settings has the core's default (one
    source), and every renamed field names a declared parameter (else it does nothing)."""
    module = importlib.import_module(class_path.split(':')[0])
    declared = declared_defaults(class_path)
    for binding_name in CORE_SETTINGS[class_path]:
        binding = getattr(module, binding_name)
        names = binding.param_names(declared)
        assert names, f'{binding_name}: no parameter fills {binding.config_type.__name__}'
        core = {  # parameter -> the core's default (a tuple is a list parameter)
            param: list(value) if isinstance(value, tuple) else value
            for field, value in binding.field_defaults().items()
            if (param := names.get(field))
        }
        overridden = OVERRIDDEN.get(getattr(module, class_path.split(':')[1]).node_name, {})
        differ = {
            p: (declared[p], core[p])
            for p in core
            if p not in overridden and not same(declared[p], core[p])
        }
        assert differ == {}, f'{binding_name}: (declared, core default) differ'


def test_graph_yaml_has_a_section_for_every_node_the_demo_runs():
    """`vgm_launch graph.yaml --nodes <node>` works for each of them."""
    sys.path.insert(0, str(REPO_ROOT / 'scripts'))
    from demo import NODES as DEMO_NODES

    from vgm_common.launcher import node_names

    graph = REPO_ROOT / 'src' / 'vgm_common' / 'params' / 'graph.yaml'
    assert sorted(set(DEMO_NODES) - set(node_names(graph))) == []
