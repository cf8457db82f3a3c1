"""Shared test harness: private ROS domains, node processes that are always torn down,
and bounded waits on conditions (never fixed sleeps)."""
import itertools
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
INSTALL_DIR = REPO_ROOT / 'ros2_ws' / 'install'
SCENARIO_DIR = REPO_ROOT / 'src' / 'sensor_sim' / 'scenarios'

# Each test process (pytest-xdist worker or not) gets its own block of domain ids.
_domain_ids = itertools.count(10 + (os.getpid() % 40) * 5)


def executable(package, name=None):
    """Path of an installed executable, the file `ros2 run <package> <name>` resolves."""
    path = INSTALL_DIR / package / 'lib' / package / (name or package)
    if not path.exists():
        raise FileNotFoundError(f'{path} is not installed: run `make build`')
    return path


def wait_for(condition, timeout, interval=0.05, what='condition'):
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
            self.argv, env=env, stdout=self._log, stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL, start_new_session=True)

    def output(self):
        self._log.flush()
        return self.log_path.read_text(errors='replace')

    def alive(self):
        return self.proc.poll() is None

    def stop(self, sig=signal.SIGINT, timeout=10.0):
        """Signal the whole process group; escalate to SIGKILL after ``timeout`` [s]."""
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, sig)
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
            except ProcessLookupError:
                pass
        self._log.close()
        return self.proc.returncode


@pytest.fixture
def ros_env():
    """Environment for node processes: a private domain, localhost-only discovery."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(next(_domain_ids) % 200 + 1)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['PYTHONUNBUFFERED'] = '1'
    return env


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
        executor, cond, timeout, what)
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
