"""The fuzz suite: every node, each its own process on a private domain, fed what a
wrong driver, a mistyped command or a bad bag sends, then something good.

Per node: bad messages on every topic it subscribes (encodings, sizes, NaN, inf, 1e308,
wrong lengths, frames, stamps going backwards), every parameter changed to values of
the wrong kind, non-finite, out of range and across its range, services called out of
order and all at once, a flood; after each case the process is alive and answers
get_parameters, input it must refuse is reported (a `rejected` diagnostic or a warning),
memory stays bounded, and at the end a good input is still processed. Bad start-up
arguments end every executable in one error line with a non-zero status."""

import shutil

import bad_messages
import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from fuzz_tools import Fuzzer, fuzz_parameters, wait_gone
from geometry_msgs.msg import PoseStamped, WrenchStamped
from mcap.reader import SeekingReader
from nav_msgs.msg import Path
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState
from std_msgs.msg import String
from std_srvs.srv import Trigger
from stereo_coding_node.scenes import generated_scene
from stereo_msgs.msg import DisparityImage
from trajectory_msgs.msg import JointTrajectory

from bag_tools.bag_writer import BagWriter
from harness import executable, publish_rig, small_scenario
from sensor_sim.render import SceneRenderer, add_noise
from sensor_sim.scenario import load_scenario
from stereo_coding_node import blind
from vgm_common.calibration_io import write_calibration
from vgm_common.conversions import (
    grey_to_compressed_jpeg,
    make_header,
    matrix_to_pose_stamped,
    numpy_to_image,
    stamp_to_ns,
)
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.robot_model import JOINT_NAMES
from vgm_common.topics import (
    CAMERA_INFO_TOPICS,
    CODED_COMPRESSED_TOPIC,
    CODED_IMAGE_TOPIC,
    DECODED_DISPARITY_TOPIC,
    DEPTH_INFO_TOPIC,
    DIAGNOSTICS_TOPIC,
    DISPARITY_TOPIC,
    FUSED_DEPTH_TOPIC,
    IMAGE_TOPICS,
    JOINT_STATES_TOPIC,
    JOINT_TRAJECTORY_TOPIC,
    LEFT_RECT_TOPIC,
    OPTICAL_FRAMES,
    POSE_TOPICS,
    PRESSURE_TOPIC,
    TARGET_POSE_TOPIC,
    TOOL_POSE_TOPIC,
    WAYPOINTS_TOPIC,
)

MIN_CASES = 20  # kinds of bad input per node, at least
FLOOD_IMAGES = 100
SIMULTANEOUS_CALLERS = 20  # of a service
FLOOD_MEMORY_BOUND = 400e6  # [bytes] RSS growth allowed by a flood
TARGET_POSE_TOPIC = TARGET_POSE_TOPIC


@pytest.fixture(scope='module')
def small_scene(tmp_path_factory):
    """The default scenario at 320x240 (intrinsics halved), its true calibration file,
    and a renderer of it."""
    directory = tmp_path_factory.mktemp('scene')
    path = small_scenario(directory)
    scenario = load_scenario(path)
    write_calibration(directory / 'calibration', scenario.cameras, OPTICAL_FRAMES)
    return (
        scenario,
        path,
        directory / 'calibration' / 'calibration.yaml',
        SceneRenderer(scenario, supersample=2),
    )


def grey(array, scenario, index):
    noisy = add_noise(array, scenario.noise.image_sigma, np.random.default_rng([7, index]))
    return noisy


class Capture:
    """Publishes images of one stamp on the node's image topics (and a chart pose for
    calib_node), as a synchronized capture."""

    def __init__(self, fuzzer, cameras, with_target_pose=False):
        self.fuzzer = fuzzer
        self.cameras = cameras
        self.with_target_pose = with_target_pose
        self.stamp_ns = 1_000_000_000

    def next_stamp(self):
        self.stamp_ns += 100_000_000
        return self.stamp_ns

    def publish(self, images_by_camera, stamp_ns, T_base_chart=None):
        for camera in self.cameras:
            msg = images_by_camera[camera]
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 10**9)
            self.fuzzer.publisher(IMAGE_TOPICS[camera], Image).publish(msg)
        if self.with_target_pose:
            T = np.eye(4) if T_base_chart is None else T_base_chart
            T[2, 3] = T[2, 3] or 0.4
            self.fuzzer.publisher(TARGET_POSE_TOPIC, PoseStamped).publish(
                matrix_to_pose_stamped(T, stamp_ns, 'base_link')
            )


def fuzz_images(fuzzer, capture, survive_labels=('empty frame_id', '1x1 image', '16-bit image')):
    """Each bad image as a whole capture (every camera the same bad image, one stamp)."""
    stamp = capture.next_stamp()
    for label, _ in bad_messages.images(stamp, OPTICAL_FRAMES['left']):
        stamp = capture.next_stamp()
        by_camera = {
            camera: dict(bad_messages.images(stamp, OPTICAL_FRAMES[camera]))[label]
            for camera in capture.cameras
        }
        act = fuzzer.survive if label in survive_labels else fuzzer.reject
        act(f'capture: {label}', lambda b=by_camera, s=stamp: capture.publish(b, s))


def fuzz_camera_infos(fuzzer, cameras):
    for camera in cameras:
        publisher = fuzzer.publisher(CAMERA_INFO_TOPICS[camera], CameraInfo, LATCHED_QOS)
        for label, msg in bad_messages.camera_infos():
            fuzzer.reject(
                f'{CAMERA_INFO_TOPICS[camera]}: {label}', lambda m=msg, p=publisher: p.publish(m)
            )


def flood_images(fuzzer, capture, size=(480, 640)):
    before = fuzzer.rss_bytes()
    rng = np.random.default_rng(0)
    frame = rng.integers(0, 256, size, dtype=np.uint8)
    for _ in range(FLOOD_IMAGES):
        stamp = capture.next_stamp()
        capture.publish(
            {c: numpy_to_image(frame, 'mono8', stamp, OPTICAL_FRAMES[c]) for c in capture.cameras},
            stamp,
        )
    fuzzer.survive(f'a flood of {FLOOD_IMAGES} captures', lambda: None)
    grown = fuzzer.rss_bytes() - before
    assert grown < FLOOD_MEMORY_BOUND, f'{fuzzer.node_name} grew by {grown / 1e6:.0f} MB'


def collect(probe, msg_type, topic, qos=DEFAULT_QOS):
    received = []
    probe.create_subscription(msg_type, topic, received.append, qos)
    return received


def finish(fuzzer):
    assert len(set(fuzzer.cases)) >= MIN_CASES, fuzzer.cases
    assert 'Traceback' not in fuzzer.process.output(), fuzzer.process.output()[-3000:]
    print(fuzzer.summary())  # pytest -s: the README's reliability table


def start(spawn, rclpy_node, name, *args, package=None):
    if name == 'sfs_stereo_node':
        args = ('-p', 'log_every:=0.0', *args)
    process = spawn([executable(package or name, name), '--ros-args', *args])
    fuzzer = Fuzzer(rclpy_node, process, name)
    fuzzer.wait_until_serving()
    return fuzzer


# -- the nodes ---------------------------------------------------------------------------


def test_sfs_stereo_node(spawn, rclpy_node, small_scene):
    scenario, _, calibration, renderer = small_scene
    fuzzer = start(spawn, rclpy_node, 'sfs_stereo_node', '-p', 'max_rate:=0.0')
    publishers, _ = publish_rig(rclpy_node, calibration)  # noqa: F841 (kept alive)
    capture = Capture(fuzzer, ('left', 'right'))
    fuzz_images(fuzzer, capture)
    fuzz_camera_infos(fuzzer, ('left',))
    publishers, _ = publish_rig(rclpy_node, calibration)  # the good rig again
    fuzz_parameters(fuzzer)
    flood_images(fuzzer, capture)
    fused = collect(rclpy_node, Image, FUSED_DEPTH_TOPIC)
    good = {
        c: grey(renderer.scene_image(c), scenario, i).round().clip(0, 255).astype(np.uint8)
        for i, c in enumerate(('left', 'right'))
    }

    def good_pair_fused(what):
        stamp = capture.next_stamp()
        capture.publish(
            {c: numpy_to_image(good[c], 'mono8', stamp, OPTICAL_FRAMES[c]) for c in good}, stamp
        )
        rclpy_node.spin_until(
            lambda: any(stamp_to_ns(m.header.stamp) == stamp for m in fused), 120, what
        )

    good_pair_fused('fused depth of a good pair after the fuzzing')
    # With the rectification cached: one pair of another size than the calibration's
    # (it once cleared the cache and ended depth for good), the left image on both topics.
    for label, pair in (
        ('a 160x120 pair under a 320x240 calibration', {c: good[c][::2, ::2] for c in good}),
        ('the left image on both topics', {c: good['left'] for c in good}),
    ):
        stamp = capture.next_stamp()
        msgs = {c: numpy_to_image(pair[c], 'mono8', stamp, OPTICAL_FRAMES[c]) for c in pair}
        fuzzer.reject(label, lambda m=msgs, s=stamp: capture.publish(m, s))
    good_pair_fused('fused depth of a good pair after the odd-sized and the doubled pairs')
    finish(fuzzer)


def test_curve_recon_node(spawn, rclpy_node, small_scene):
    scenario, _, calibration, renderer = small_scene
    fuzzer = start(spawn, rclpy_node, 'curve_recon_node', '-p', 'service_timeout:=5.0')
    publishers, _ = publish_rig(rclpy_node, calibration)  # noqa: F841 (kept alive)
    capture = Capture(fuzzer, ('left', 'right', 'aux'))
    # All at once: twenty reconstruct callers, no capture coming: every one is answered
    # (no capture within service_timeout) while the probe spins.
    clients = [
        rclpy_node.create_client(Trigger, '/curve_recon_node/reconstruct')
        for _ in range(SIMULTANEOUS_CALLERS)
    ]
    rclpy_node.spin_until(
        lambda: all(c.service_is_ready() for c in clients), 30, 'the reconstruct service'
    )
    fuzzer.cases.append(f'{SIMULTANEOUS_CALLERS} reconstruct callers, no capture coming')
    futures = [c.call_async(Trigger.Request()) for c in clients]
    try:
        rclpy_node.spin_until(lambda: all(f.done() for f in futures), 60, 'every answer')
    except TimeoutError:
        raise AssertionError(
            f'{sum(f.done() for f in futures)} of {SIMULTANEOUS_CALLERS} simultaneous '
            'reconstruct callers answered'
        ) from None
    assert all('no synchronized capture' in f.result().message for f in futures)
    fuzzer.check_serving(f'{SIMULTANEOUS_CALLERS} reconstruct callers')
    # Out of order: four calls waiting while bad input comes and parameters are read
    # (fewer than a caller's default history of replies: the probe does not always spin).
    waiting = [c.call_async(Trigger.Request()) for c in clients[:4]]
    fuzzer.cases.append('four reconstruct calls waiting, no capture')
    fuzzer.check_serving('four reconstruct calls waiting')
    fuzz_images(fuzzer, capture)
    fuzz_camera_infos(fuzzer, ('left', 'aux'))
    depth_info = fuzzer.publisher(DEPTH_INFO_TOPIC, CameraInfo)
    for label, msg in bad_messages.camera_infos():
        fuzzer.reject(f'/depth/camera_info: {label}', lambda m=msg: depth_info.publish(m))
    depth = fuzzer.publisher(FUSED_DEPTH_TOPIC, Image)
    depth_info.publish(_good_depth_info())  # the depth values themselves are at fault
    for label, value in (('negative depth', -1.0), ('zero depth', 0.0), ('depth 1e30', 1e30)):
        msg = numpy_to_image(
            np.full((240, 320), value, np.float32),
            '32FC1',
            capture.next_stamp(),
            OPTICAL_FRAMES['left'],
        )
        fuzzer.reject(f'/depth/fused: {label}', lambda m=msg: depth.publish(m))
    publishers, _ = publish_rig(rclpy_node, calibration)
    fuzz_parameters(fuzzer)
    flood_images(fuzzer, capture)
    rclpy_node.spin_until(
        lambda: all(f.done() for f in waiting), 60, 'an answer to the four waiting calls'
    )
    # Good captures, one a second as a camera streams (automatic reconstruction tries at
    # most once a second): waypoints.
    waypoints = collect(rclpy_node, Path, WAYPOINTS_TOPIC, LATCHED_QOS)
    scene = {
        c: grey(renderer.scene_image(c), scenario, i).round().clip(0, 255).astype(np.uint8)
        for i, c in enumerate(('left', 'right', 'aux'))
    }
    good_stamps = set()

    def show_scene():
        stamp = capture.next_stamp()
        good_stamps.add(stamp)
        capture.publish(
            {c: numpy_to_image(scene[c], 'mono8', stamp, OPTICAL_FRAMES[c]) for c in scene}, stamp
        )

    timer = rclpy_node.create_timer(1.0, show_scene)
    rclpy_node.spin_until(
        lambda: any(stamp_to_ns(m.header.stamp) in good_stamps for m in waypoints),
        120,
        'waypoints of a good capture after the fuzzing',
    )
    rclpy_node.destroy_timer(timer)
    finish(fuzzer)


def _good_depth_info():
    K = [300.0, 0, 160, 0, 300.0, 120, 0, 0, 1]
    return CameraInfo(
        header=make_header(1, OPTICAL_FRAMES['left']),
        width=320,
        height=240,
        distortion_model='plumb_bob',
        d=[0.0] * 5,
        k=K,
        r=[1.0, 0, 0, 0, 1, 0, 0, 0, 1],
        p=K[:3] + [0.0] + K[3:6] + [0.0] + K[6:] + [0.0],
    )


def test_calib_node(spawn, rclpy_node, small_scene):
    scenario, _, _, renderer = small_scene
    fuzzer = start(
        spawn,
        rclpy_node,
        'calib_node',
        '-p',
        'chart.rows:=6',
        '-p',
        'chart.cols:=9',
        '-p',
        f'chart.spacing:={scenario.calibration.spacing}',
    )
    for service in ('calibrate', 'reset', 'reset', 'calibrate'):
        fuzzer.cases.append(f'{service} out of order')
        answer = fuzzer.trigger(service)
        assert answer is not None and answer.message
        fuzzer.check_serving(f'{service} out of order')
    capture = Capture(fuzzer, ('left', 'right', 'aux'), with_target_pose=True)
    fuzz_images(fuzzer, capture)
    target = fuzzer.publisher(TARGET_POSE_TOPIC, PoseStamped)
    for label, msg in bad_messages.poses(capture.next_stamp()):
        fuzzer.reject(f'{TARGET_POSE_TOPIC}: {label}', lambda m=msg: target.publish(m))
    fuzz_parameters(fuzzer)
    flood_images(fuzzer, capture, size=(240, 320))  # a camera keeps its size
    # A good chart view is taken.
    views = []
    rclpy_node.create_subscription(
        DiagnosticArray,
        DIAGNOSTICS_TOPIC,
        lambda m: views.extend(
            int(v.value)
            for s in m.status
            if s.name == 'calib_node: views'
            for v in s.values
            if v.key == 'views'
        ),
        DEFAULT_QOS,
    )
    fuzzer.trigger('reset')
    chart = {
        c: grey(renderer.chart_image(c, 0), scenario, i).round().clip(0, 255).astype(np.uint8)
        for i, c in enumerate(('left', 'right', 'aux'))
    }

    def show_chart():  # as the stage does: the chart in view capture after capture
        stamp = capture.next_stamp()
        capture.publish(
            {c: numpy_to_image(chart[c], 'mono8', stamp, OPTICAL_FRAMES[c]) for c in chart},
            stamp,
            scenario.calibration.T_base_chart[0].copy(),
        )

    timer = rclpy_node.create_timer(1.0, show_chart)
    rclpy_node.spin_until(
        lambda: views and views[-1] >= 1,
        120,
        'calib_node to take a good chart view after the fuzzing',
    )
    rclpy_node.destroy_timer(timer)
    finish(fuzzer)


def test_pa10_ik_node(spawn, rclpy_node):
    fuzzer = start(spawn, rclpy_node, 'pa10_ik_node')
    joints = fuzzer.publisher(JOINT_STATES_TOPIC, JointState)
    pressure = fuzzer.publisher(PRESSURE_TOPIC, WrenchStamped)
    waypoints = fuzzer.publisher(WAYPOINTS_TOPIC, Path, LATCHED_QOS)
    tool_poses = collect(rclpy_node, PoseStamped, TOOL_POSE_TOPIC)
    q_home = [0.0, 0.5, 0.0, 1.2, 0.0, 0.8, 0.0]
    good_state = JointState(name=list(JOINT_NAMES), position=q_home)
    feed = rclpy_node.create_timer(
        0.02, lambda: (joints.publish(good_state), pressure.publish(_wrench(0.0)))
    )
    rclpy_node.spin_until(lambda: tool_poses, 30, 'the tool pose of a good joint state')
    for service in ('stop', 'start_tracking', 'stop', 'stop'):
        fuzzer.cases.append(f'{service} out of order')
        assert fuzzer.trigger(service) is not None
        fuzzer.check_serving(f'{service} out of order')
    for label, msg in bad_messages.joint_states(JOINT_NAMES):
        fuzzer.reject(f'/joint_states: {label}', lambda m=msg: joints.publish(m))
    for label, msg in bad_messages.wrenches():
        fuzzer.reject(f'/tool/pressure: {label}', lambda m=msg: pressure.publish(m))
    for label, msg in bad_messages.paths():
        fuzzer.reject(f'/curve/waypoints: {label}', lambda m=msg: waypoints.publish(m))
    # Failure, stop, start, failure, stop: an unreachable path, then an untrackable one.
    for label, msg in bad_messages.paths():
        if label not in ('100 m away', 'approach axis along the path'):
            continue
        waypoints.publish(msg)
        for service in ('start_tracking', 'stop', 'start_tracking', 'stop'):
            fuzzer.cases.append(f'{label}: {service}')
            assert fuzzer.trigger(service) is not None
            fuzzer.check_serving(f'{label}: {service}')
    fuzz_parameters(fuzzer)
    # Still serving a good joint state: its tool pose.
    count = len(tool_poses)
    rclpy_node.spin_until(
        lambda: len(tool_poses) > count + 5,
        30,
        'tool poses of good joint states after the fuzzing',
    )
    rclpy_node.destroy_timer(feed)
    finish(fuzzer)


def _wrench(force):
    msg = WrenchStamped()
    msg.header.frame_id = 'tool0'
    msg.wrench.force.z = force
    return msg


def test_sensor_sim(spawn, rclpy_node, small_scene):
    _, scenario_path, _, _ = small_scene
    fuzzer = start(
        spawn,
        rclpy_node,
        'sensor_sim',
        '-p',
        f'scenario:={scenario_path}',
        '-p',
        'calibration_phase:=false',
        '-p',
        'rate:=1.0',
    )
    commands = fuzzer.publisher(JOINT_TRAJECTORY_TOPIC, JointTrajectory)
    for label, msg in bad_messages.joint_trajectories(JOINT_NAMES):
        fuzzer.reject(f'joint_trajectory: {label}', lambda m=msg: commands.publish(m))
    for label, msg in bad_messages.unusual_joint_trajectories(JOINT_NAMES):
        fuzzer.survive(f'joint_trajectory: {label}', lambda m=msg: commands.publish(m))
    fuzz_parameters(fuzzer)
    # A good command moves the arm.
    states = collect(rclpy_node, JointState, JOINT_STATES_TOPIC)
    rclpy_node.spin_until(lambda: states, 30, 'joint states')
    q0 = np.array(states[-1].position)
    good = bad_messages.joint_trajectories(JOINT_NAMES)[2][1]  # NaN positions, fixed:
    good.points[0].positions = [float(q + 0.05) for q in q0]
    commands.publish(good)
    rclpy_node.spin_until(
        lambda: np.abs(np.array(states[-1].position) - q0).max() > 0.04,
        30,
        'the arm to follow a good command after the fuzzing',
    )
    finish(fuzzer)


def test_recorder_and_player(spawn, rclpy_node, tmp_path):
    recorder = start(
        spawn,
        rclpy_node,
        'recorder',
        '-p',
        f'output_dir:={tmp_path}',
        '-p',
        'bag_name:=fuzz',
        package='bag_tools',
    )
    # One topic with two types (from two participants: DDS refuses it within one) is
    # refused with a warning; a flood is recorded or counted.
    other = rclpy.Context()
    rclpy.init(context=other)
    other_node = rclpy.create_node('other_type', context=other)
    try:
        other_node.create_publisher(String, '/fuzz/two_types', DEFAULT_QOS)
        recorder.reject(
            'a topic with two types',
            lambda: rclpy_node.create_publisher(JointState, '/fuzz/two_types', DEFAULT_QOS),
        )
    finally:
        other_node.destroy_node()
        rclpy.shutdown(context=other)
    flood = recorder.publisher('/fuzz/flood', JointState)
    before = recorder.rss_bytes()
    recorder.survive(
        'a flood of 5000 joint states',
        lambda: [flood.publish(JointState(name=['a'], position=[float(i)])) for i in range(5000)],
    )
    assert recorder.rss_bytes() - before < FLOOD_MEMORY_BOUND
    fuzz_parameters(recorder)
    # Nothing changes while recording.
    recorder.refuse_parameter('topics changed while recording', 'topics', ['/fuzz/flood'])
    finish_recorder = recorder.process.stop()
    assert finish_recorder == 0

    with BagWriter(tmp_path / 'tiny') as writer:
        writer.add_topic('/fuzz/js', 'sensor_msgs/msg/JointState')
        for i in range(5):
            writer.write('/fuzz/js', serialize_message(JointState()), 10**9 * (i + 1))
    player = start(
        spawn,
        rclpy_node,
        'player',
        '-p',
        f'bag:={tmp_path / "tiny"}',
        '-p',
        'loop:=true',
        '-p',
        'wait_for_subscribers:=0.0',
        package='bag_tools',
    )
    fuzz_parameters(player)
    assert len(set(recorder.cases + player.cases)) >= MIN_CASES
    assert 'Traceback' not in player.process.output()
    print(recorder.summary())
    # The recorder's bag, damaged: each copy ends the player in one error line, status 1.
    for label, damage in _BAG_DAMAGES.items():
        copy = tmp_path / label.replace(' ', '_')
        shutil.copytree(tmp_path / 'fuzz', copy)
        (data_file,) = copy.glob('*.mcap')
        damage(data_file)
        player.cases.append(f'damaged bag: {label}')
        damaged = spawn(
            [
                executable('bag_tools', 'player'),
                '--ros-args',
                '-p',
                f'bag:={copy}',
                '-p',
                'wait_for_subscribers:=0.0',
            ],
            name=f'player-{copy.name}',
        )
        assert wait_gone(damaged, 60), f'the player of a bag with {label} did not exit'
        output = damaged.output()
        errors = [line for line in output.splitlines() if '[ERROR]' in line]
        assert damaged.proc.returncode == 1 and 'Traceback' not in output, (label, output)
        assert len(errors) == 1 and 'is damaged' in errors[0], (label, output)
        player.outcomes[f'damaged bag: {label}'] = 'refused'
    print(player.summary())


def _middle_chunk(path):
    with open(path, 'rb') as stream:
        chunks = SeekingReader(stream).get_summary().chunk_indexes
    return chunks[len(chunks) // 2]


def _overwrite(path, offset, data):
    with open(path, 'r+b') as stream:
        stream.seek(offset)
        stream.write(data)


def _cut(path, size):
    with open(path, 'r+b') as stream:
        stream.truncate(size)


_BAG_DAMAGES = {  # label -> damage(data file)
    'chunk records overwritten': lambda p: _overwrite(
        p,
        _middle_chunk(p).chunk_start_offset + _middle_chunk(p).chunk_length // 2,
        b'\xff' * 32,
    ),
    'chunk header overwritten': lambda p: _overwrite(
        p, _middle_chunk(p).chunk_start_offset + 1, b'\xff' * 40
    ),
    'file cut in a chunk': lambda p: _cut(
        p, _middle_chunk(p).chunk_start_offset + _middle_chunk(p).chunk_length // 2
    ),
    'file cut to its header': lambda p: _cut(p, 8),
}


def test_live_view(spawn, rclpy_node):
    fuzzer = start(spawn, rclpy_node, 'live_view', '-p', 'port:=0', '-p', 'discovery_period:=0.5')
    # A served topic that gains a publisher of another type in another process (DDS
    # refuses two types within one): its channel keeps the first type, and says so.
    rclpy_node.create_publisher(String, '/fuzz/two_types', DEFAULT_QOS)
    rclpy_node.spin_until(
        lambda: 'serving /fuzz/two_types' in fuzzer.process.output(),
        30,
        'live_view to serve /fuzz/two_types',
    )
    other = rclpy.Context()
    rclpy.init(context=other)
    other_node = rclpy.create_node('other_type', context=other)
    try:
        fuzzer.reject(
            'a served topic gains a second type',
            lambda: other_node.create_publisher(JointState, '/fuzz/two_types', DEFAULT_QOS),
        )
    finally:
        other_node.destroy_node()
        rclpy.shutdown(context=other)
    for topic in POSE_TOPICS.values():
        poses = fuzzer.publisher(topic, PoseStamped, LATCHED_QOS)
        for label, msg in bad_messages.poses():
            fuzzer.reject(f'{topic}: {label}', lambda m=msg, p=poses: p.publish(m))
    fuzz_parameters(fuzzer)
    # A good camera pose is still turned into a transform.
    sent = []
    rclpy_node.create_subscription(
        DiagnosticArray,
        DIAGNOSTICS_TOPIC,
        lambda m: sent.extend(
            int(v.value)
            for s in m.status
            if s.name == 'live_view: server'
            for v in s.values
            if v.key == 'transforms sent'
        ),
        DEFAULT_QOS,
    )
    rclpy_node.spin_until(lambda: sent, 30, 'the server status')
    before = sent[-1]
    T = np.eye(4)
    T[2, 3] = 1.0
    fuzzer.publisher(POSE_TOPICS['left'], PoseStamped, LATCHED_QOS).publish(
        matrix_to_pose_stamped(T, 1, 'base_link')
    )
    rclpy_node.spin_until(lambda: sent[-1] > before, 30, 'a transform of a good camera pose')
    finish(fuzzer)


def test_stereo_coding_node(spawn, rclpy_node):
    fuzzer = start(spawn, rclpy_node, 'stereo_coding_node')
    frame = OPTICAL_FRAMES['left']
    images = fuzzer.publisher(LEFT_RECT_TOPIC, Image)
    disparities = fuzzer.publisher(DISPARITY_TOPIC, DisparityImage)
    coded = collect(rclpy_node, Image, CODED_IMAGE_TOPIC)
    left, _, truth_px = generated_scene((240, 320), seed=5, max_disparity_px=24)
    stamp = [1_000_000_000]

    def send(image_msg, disparity_msg):
        stamp[0] += 1_000_000
        for msg in (image_msg, disparity_msg, disparity_msg.image):
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp[0], 10**9)
        images.publish(image_msg)
        disparities.publish(disparity_msg)

    def good_image():
        return numpy_to_image(left, 'mono8', 0, frame)

    refused = set()
    for label, msg in bad_messages.disparities(truth_px, 0, frame):
        fuzzer.reject(f'{DISPARITY_TOPIC}: {label}', lambda m=msg: send(good_image(), m))
        refused.add(stamp[0])
    for label, msg in bad_messages.images(0, frame):
        good = bad_messages.disparity_image(truth_px, 0, frame)
        act = fuzzer.survive if label == 'empty frame_id' else fuzzer.reject
        act(f'{LEFT_RECT_TOPIC}: {label}', lambda m=msg, d=good: send(m, d))
        if label != 'empty frame_id':
            refused.add(stamp[0])
    fuzz_parameters(fuzzer)
    # A good pair is coded; nothing of a refused one ever was.
    send(good_image(), bad_messages.disparity_image(truth_px, 0, frame))
    rclpy_node.spin_until(
        lambda: any(stamp_to_ns(m.header.stamp) == stamp[0] for m in coded),
        30,
        'the coded image of a good pair after the fuzzing',
    )
    assert not refused & {stamp_to_ns(m.header.stamp) for m in coded}
    finish(fuzzer)


def test_stereo_decoding_node(spawn, rclpy_node):
    fuzzer = start(
        spawn,
        rclpy_node,
        'stereo_decoding_node',
        '-p',
        'transport:=compressed',
        package='stereo_coding_node',
    )
    frame = OPTICAL_FRAMES['left']
    coded = fuzzer.publisher(CODED_COMPRESSED_TOPIC, CompressedImage)
    decoded = collect(rclpy_node, DisparityImage, DECODED_DISPARITY_TOPIC)
    before = fuzzer.rss_bytes()
    for label, msg in bad_messages.compressed_images(1, frame):
        fuzzer.reject(f'{CODED_COMPRESSED_TOPIC}: {label}', lambda m=msg: coded.publish(m))
    grown = fuzzer.rss_bytes() - before
    assert grown < FLOOD_MEMORY_BOUND, f'stereo_decoding_node grew by {grown / 1e6:.0f} MB'
    fuzz_parameters(fuzzer)
    # A good coded image is decoded.
    left, _, truth_px = generated_scene((240, 320), seed=5, max_disparity_px=24)
    marked = blind.encode(left, truth_px, 'vgm-stereo')
    good = grey_to_compressed_jpeg(marked, 90, 2_000_000_000, frame)
    coded.publish(good)
    rclpy_node.spin_until(
        lambda: any(stamp_to_ns(m.header.stamp) == 2_000_000_000 for m in decoded),
        30,
        'the decoded disparity of a good coded image after the fuzzing',
    )
    finish(fuzzer)


# -- start-up --------------------------------------------------------------------------

STARTUP_PARAMETER = {
    'sfs_stereo_node': 'window',
    'curve_recon_node': 'degree',
    'calib_node': 'min_views',
    'pa10_ik_node': 'rate',
    'sensor_sim': 'rate',
    'recorder': 'flush_period',
    'player': 'rate',
    'live_view': 'port',
    'stereo_coding_node': 'jpeg_quality',
    'stereo_decoding_node': 'max_pixels',
}
PACKAGES = {
    'recorder': 'bag_tools',
    'player': 'bag_tools',
    'stereo_decoding_node': 'stereo_coding_node',
}


def test_bad_start_up_is_one_error_line(spawn, tmp_path):
    (tmp_path / 'bad.yaml').write_text('node: [\n')
    (tmp_path / 'list.yaml').write_text('- 1\n- 2\n')
    runs = {}
    for name, parameter in STARTUP_PARAMETER.items():
        package = PACKAGES.get(name, name)
        binary = executable(package, name)
        for label, args in (
            ('missing params file', ['--params-file', str(tmp_path / 'none.yaml')]),
            ('params file not YAML', ['--params-file', str(tmp_path / 'bad.yaml')]),
            ('params file a list', ['--params-file', str(tmp_path / 'list.yaml')]),
            ('wrong kind', ['-p', f'{parameter}:=[1, 2]']),
        ):
            runs[(name, label)] = spawn(
                [binary, '--ros-args', *args], name=f'{name}-{label.replace(" ", "_")}'
            )
    for (name, label), process in runs.items():
        assert wait_gone(process, 90), f'{name} with {label} did not exit'
        output = process.output()
        errors = [line for line in output.splitlines() if '[ERROR]' in line]
        assert process.proc.returncode not in (0, None), (name, label, output)
        assert len(errors) == 1 and 'Traceback' not in output, (name, label, output)
