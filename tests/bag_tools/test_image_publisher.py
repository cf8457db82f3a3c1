"""Topic level, real processes: image_publisher publishes a folder of one's own
left/right/aux images, set by set with one stamp each and pixel for pixel, and the
calibration file's cameras on the latched camera_info and pose topics, as calib_node
would; a folder without matching sets is one start-up error line, exit status 2."""

import cv2
import numpy as np
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from harness import SCENARIO_DIR, executable, wait_for
from sensor_sim.scenario import load_scenario
from vgm_common.calibration_io import write_calibration
from vgm_common.conversions import image_to_numpy, stamp_to_ns
from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS
from vgm_common.topics import (
    CAMERA_INFO_TOPICS,
    CAMERA_NAMES,
    IMAGE_TOPICS,
    OPTICAL_FRAMES,
    POSE_TOPICS,
)

SETS = 3


def test_a_folder_of_images_and_a_calibration_reach_the_graph(spawn, rclpy_node, tmp_path):
    rng = np.random.default_rng(7)
    folder = tmp_path / 'images'
    (folder / 'aux').mkdir(parents=True)  # aux in a sub-folder, left/right by prefix
    written = {name: [] for name in CAMERA_NAMES}
    for i in range(SETS):
        for name in CAMERA_NAMES:
            image = rng.integers(0, 256, (48, 64), dtype=np.uint8)
            path = (
                folder / 'aux' / f'{i:02d}.png' if name == 'aux' else folder / f'{name}{i:02d}.png'
            )
            cv2.imwrite(str(path), image)
            written[name].append(image)
    scenario = load_scenario(SCENARIO_DIR / 'default.yaml')
    calibration = write_calibration(tmp_path / 'calibration', scenario.cameras, OPTICAL_FRAMES)

    received = {name: [] for name in CAMERA_NAMES}
    infos, poses = {}, {}
    for name in CAMERA_NAMES:
        rclpy_node.create_subscription(
            Image, IMAGE_TOPICS[name], received[name].append, DEFAULT_QOS
        )
        rclpy_node.create_subscription(
            CameraInfo,
            CAMERA_INFO_TOPICS[name],
            lambda m, n=name: infos.update({n: m}),
            LATCHED_QOS,
        )
        rclpy_node.create_subscription(
            PoseStamped, POSE_TOPICS[name], lambda m, n=name: poses.update({n: m}), LATCHED_QOS
        )
    node = spawn(
        [
            executable('bag_tools', 'image_publisher'),
            '--ros-args',
            '-p',
            f'folder:={folder}',
            '-p',
            'cameras:=[left, right, aux]',
            '-p',
            f'calibration_file:={calibration}',
            '-p',
            'rate:=5.0',
            '-p',
            'exit_when_done:=true',
        ]
    )
    rclpy_node.spin_until(
        lambda: all(len(received[n]) == SETS for n in CAMERA_NAMES)
        and len(infos) == 3 == len(poses),
        60.0,
        'every image set and the calibration',
    )
    for i in range(SETS):
        stamps = {stamp_to_ns(received[n][i].header.stamp) for n in CAMERA_NAMES}
        assert len(stamps) == 1, f'set {i}: one stamp for its images'
        for name in CAMERA_NAMES:
            msg = received[name][i]
            assert msg.encoding == 'mono8' and msg.header.frame_id == OPTICAL_FRAMES[name]
            np.testing.assert_array_equal(image_to_numpy(msg), written[name][i])
    for name, camera in scenario.cameras.items():
        np.testing.assert_allclose(np.reshape(infos[name].k, (3, 3)), camera.K)
        assert infos[name].header.frame_id == OPTICAL_FRAMES[name]
        assert poses[name].header.frame_id == 'base_link'
    wait_for(lambda: not node.alive(), 20.0, 'image_publisher to exit when done')
    assert node.proc.returncode == 0 and 'Traceback' not in node.output()


def test_a_folder_without_matching_sets_is_one_start_up_error(spawn, tmp_path):
    (tmp_path / 'left00.png').write_bytes(b'')
    node = spawn(
        [executable('bag_tools', 'image_publisher'), '--ros-args', '-p', f'folder:={tmp_path}']
    )
    wait_for(lambda: not node.alive(), 30.0, 'image_publisher to exit')
    errors = [line for line in node.output().splitlines() if '[ERROR]' in line]
    assert node.proc.returncode == 2 and len(errors) == 1, node.output()
    assert 'left 1, right 0' in errors[0] and 'Traceback' not in node.output()
