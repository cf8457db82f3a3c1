"""vgm_launch as a user runs it: nodes from one params file as separate processes, log
lines prefixed, all stopped on Ctrl-C or when one fails, non-zero exit on failure."""

import signal

import psutil
import pytest
import yaml

from harness import SCENARIO_DIR, executable, wait_for


def params_file(tmp_path, scenario):
    path = tmp_path / 'graph.yaml'
    path.write_text(
        yaml.safe_dump(
            {
                'recorder': {
                    'ros__parameters': {'output_dir': str(tmp_path), 'bag_name': 'launched'}
                },
                'sensor_sim': {
                    'ros__parameters': {
                        'scenario': str(scenario),
                        'calibration_phase': False,
                        'rate': 5.0,
                    }
                },
            }
        )
    )
    return path


@pytest.mark.parametrize('sigint_ignored', [False, True])
def test_ctrl_c_stops_every_node_cleanly(spawn, tmp_path, sigint_ignored):
    """Also when started as a background job (a script's `&`, nohup): SIGINT comes in
    ignored, and the launcher once ignored it too."""
    argv = [
        str(executable('vgm_common', 'vgm_launch')),
        str(params_file(tmp_path, SCENARIO_DIR / 'default.yaml')),
    ]
    if sigint_ignored:
        argv = ['bash', '-c', 'trap "" INT; exec "$@"', 'vgm_launch', *argv]
    launch = spawn(argv, name='vgm_launch')
    wait_for(
        lambda: '[sensor_sim] ' in launch.output() and 'publishing 3 cameras' in launch.output(),
        60,
        'sensor_sim to start publishing',
    )
    wait_for(
        lambda: 'recording /stereo/left/image_raw' in launch.output(),
        30,
        'the recorder to record the images',
    )
    status = launch.stop(signal.SIGINT, timeout=30)
    output = launch.output()
    assert status == 0, output
    assert '[recorder  ] ' in output  # every line carries its node's name
    assert 'published:' in output and 'closed' in output  # both shut down cleanly
    assert (tmp_path / 'launched' / 'metadata.yaml').exists()


def test_a_failing_node_stops_the_others_and_the_exit_status_says_so(spawn, tmp_path):
    bad = yaml.safe_load((SCENARIO_DIR / 'default.yaml').read_text())
    del bad['contact']
    bad_path = tmp_path / 'bad.yaml'
    bad_path.write_text(yaml.safe_dump(bad))
    launch = spawn([executable('vgm_common', 'vgm_launch'), params_file(tmp_path, bad_path)])
    launch.proc.wait(60)
    output = launch.output()
    assert launch.proc.returncode == 1, output
    assert 'sensor_sim failed with exit status 2' in output
    assert 'contact' in output and 'Traceback' not in output


def test_unknown_node_in_the_command_line_is_refused(spawn, tmp_path):
    launch = spawn(
        [
            executable('vgm_common', 'vgm_launch'),
            params_file(tmp_path, SCENARIO_DIR / 'default.yaml'),
            '--nodes',
            'nope',
        ]
    )
    launch.proc.wait(30)
    assert launch.proc.returncode == 2 and 'no section for nope' in launch.output()


def test_no_node_outlives_a_killed_launcher(spawn, tmp_path):
    launch = spawn(
        [
            executable('vgm_common', 'vgm_launch'),
            params_file(tmp_path, SCENARIO_DIR / 'default.yaml'),
        ]
    )
    nodes = wait_for(
        lambda: len(psutil.Process(launch.proc.pid).children()) == 2
        and psutil.Process(launch.proc.pid).children(),
        30,
        'two node processes',
    )
    launch.stop(signal.SIGKILL)
    wait_for(
        lambda: not any(
            node.is_running() and node.status() != psutil.STATUS_ZOMBIE for node in nodes
        ),
        30,
        'the nodes to exit with the launcher',
    )
