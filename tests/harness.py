"""Test harness: installed executables, node processes that are always torn down, and
bounded waits on conditions (never fixed sleeps). Fixtures are in conftest.py."""

import itertools
import os
import signal
import subprocess
import time
from pathlib import Path

import yaml

from vgm_common.launcher import stop_process_group

REPO_ROOT = Path(__file__).resolve().parents[1]
INSTALL_DIR = REPO_ROOT / 'ros2_ws' / 'install'
SCENARIO_DIR = REPO_ROOT / 'src' / 'sensor_sim' / 'scenarios'

# Each pytest process gets its own block of domain ids.
_domain_ids = itertools.count(10 + (os.getpid() % 40) * 5)


class ManualClock:
    """The monotonic clock [s] injected into a node's ROS-free object by a unit test: it
    moves only when the test sets ``now``, so a timeout is a step of the test, not a wait."""

    def __init__(self, now=0.0):
        self.now = now

    def __call__(self):
        return self.now


def next_ros_env():
    """Environment for node processes: a private domain, localhost-only discovery."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(next(_domain_ids) % 200 + 1)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['PYTHONUNBUFFERED'] = '1'
    for variable in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS'):  # as vgm_launch does
        env.setdefault(variable, '1')
    return env


def executable(package, name=None):
    """Path of an installed executable, the file `ros2 run <package> <name>` resolves."""
    path = INSTALL_DIR / package / 'lib' / package / (name or package)
    if not path.exists():
        raise FileNotFoundError(f'{path} is not installed: run `make build`')
    return path


def wait_for(condition, timeout, what='condition', interval=0.05):
    """Poll ``condition()`` until it returns a truthy value or ``timeout`` [s] passes."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f'timed out after {timeout:.0f} s waiting for {what}')
        time.sleep(interval)


class NodeProcess:
    """A node started as its own process group, its output captured to a log file."""

    def __init__(self, argv, env, log_path):
        self.argv = [str(a) for a in argv]
        self.log_path = Path(log_path)
        self._log = open(self.log_path, 'wb')
        self.proc = subprocess.Popen(
            self.argv,
            env=env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )

    def output(self):
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors='replace')

    def alive(self):
        return self.proc.poll() is None

    def stop(self, sig=signal.SIGINT, timeout=10.0):
        """Signal the whole process group; escalate to SIGKILL after ``timeout`` [s]."""
        stop_process_group(self.proc, sig, timeout)
        self._log.close()
        return self.proc.returncode


def publish_rig(node, calibration_path, stamp_ns=1):
    """Publish a calibration file's cameras on the latched camera_info and pose topics,
    as calib_node does with `calibration_file` (the left/right pair rectified); returns
    the publishers (keep them alive) and the rig {name: (PinholeCamera, R, P)}."""
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import CameraInfo

    from vgm_common.calibration_io import read_calibration, stereo_rectification
    from vgm_common.conversions import camera_to_camera_info, matrix_to_pose_stamped
    from vgm_common.qos import LATCHED_QOS
    from vgm_common.topics import BASE_FRAME, CAMERA_INFO_TOPICS, OPTICAL_FRAMES, POSE_TOPICS

    rig = read_calibration(calibration_path)
    rectified = stereo_rectification(rig['left'][0], rig['right'][0])
    rig = {name: (camera, *rectified.get(name, (R, P))) for name, (camera, R, P) in rig.items()}
    publishers = []
    for name, (camera, R, P) in rig.items():
        info = node.create_publisher(CameraInfo, CAMERA_INFO_TOPICS[name], LATCHED_QOS)
        pose = node.create_publisher(PoseStamped, POSE_TOPICS[name], LATCHED_QOS)
        info.publish(camera_to_camera_info(camera, stamp_ns, OPTICAL_FRAMES[name], R, P))
        pose.publish(matrix_to_pose_stamped(camera.T_base_camera, stamp_ns, BASE_FRAME))
        publishers += [info, pose]
    return publishers, rig


def small_scenario(tmp_path):
    """The default scenario with 320x240 cameras (intrinsics halved) as a file in
    ``tmp_path``: quicker to render and match than 640x480."""
    data = yaml.safe_load((SCENARIO_DIR / 'default.yaml').read_text())
    for camera in data['cameras'].values():
        camera['width'], camera['height'] = 320, 240
        for key in ('fx', 'fy'):
            camera[key] /= 2
        # pixel centres: u_small = (u + 0.5) / 2 - 0.5
        for key in ('cx', 'cy'):
            camera[key] = (camera[key] + 0.5) / 2 - 0.5
    path = tmp_path / 'small.yaml'
    path.write_text(yaml.safe_dump(data))
    return path
