"""bench_pa10_ik.py --over-topics: pa10_ik_node beside the damped-least-squares peer
(pa10_dls_peer_node.py, ``DlsPeer``) over the topics, each against its own sensor_sim
process on the same scenario, one after the other.

The grid: example-robot-data 7-DOF arms (``ARMS``; ``--all-arms``: every one of
task_generator.ROBOT_DATA_ARMS) x path shapes (task_generator.PATH_SHAPES) x planes tilted
``TILTS_DEG`` x the arm ``CONDITIONS`` (ideal, its commands 20 ms late, half speed); a
seeded sample of it by default (``--cases N``), ``--whole-grid`` for all of it;
``--only 2,5``: those cases of it alone (0-based, each with the seed it has in the whole
run: before/after comparisons on a few cases); ``--ours a:=1,b:=2``: pa10_ik_node with
those parameters. Every
run: its own ROS_DOMAIN_ID, localhost discovery, its processes started and stopped as
process groups (tests/harness.py), bounded waits on conditions.

Figures (vgm_evaluation.task_generator.goal_figures) on what the bench's own probe
received: tool poses and pressure readings stamped between the controller's first
'tracking' and first 'done' status (touchdown at the desired force to the path's end),
joint states and commands from the start call to the end (limit margin, commanded joint
speed / limit); task time = the start call to the first 'done' status (the path's end).
"""

import itertools
import os
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'tests'))
from pa10_dls_peer import PEER_SPEED  # noqa: E402
from pa10_goals import GOALS, meets_goals  # noqa: E402
from vgm_evaluation.bench_report import markdown_table, save_figure, write_results  # noqa: E402

from harness import NodeProcess, executable, next_ros_env, small_scenario  # noqa: E402
from vgm_evaluation import task_generator  # noqa: E402

OUT = REPO / 'bench' / 'results' / 'pa10_ik_topics'
PEER_NODE = Path(__file__).resolve().parent / 'pa10_dls_peer_node.py'
ARMS = ('panda', 'tiago', 'xarm7', 'talos_left')  # the issue's; --all-arms: every one
TILTS_DEG = (0.0, 15.0, 30.0, 45.0)
CONDITIONS = {  # name: (arm_speed_scale, arm_command_delay [s])
    'ideal': (1.0, 0.0),
    'delay 20 ms': (1.0, 0.02),
    'half speed': (0.5, 0.0),
}
DESIRED_FORCE = 5.0  # [N]
TASK_TIMEOUT = 240.0  # [s] start call to lifted: far beyond any run measured
# Domains 201-232 (tests/harness.py takes 1-200): each run the next one.
_domains = itertools.count(os.getpid() % 32)


def run_env():
    """A node environment (tests/harness.py) on the next private domain."""
    env = next_ros_env()
    env['ROS_DOMAIN_ID'] = str(201 + next(_domains) % 32)
    return env


class TopicProbe:
    """The bench's rclpy node on the run's domain: publishes the path, calls the start
    service, records what the controller and the simulator publish."""

    def __init__(self, domain_id, status_name):
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped, WrenchStamped
        from nav_msgs.msg import Path as PathMsg
        from rclpy.executors import SingleThreadedExecutor
        from sensor_msgs.msg import JointState
        from trajectory_msgs.msg import JointTrajectory

        from vgm_common.qos import DEFAULT_QOS, LATCHED_QOS

        self.rclpy, self.status_name = rclpy, status_name
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node('bench_probe', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.poses, self.pressures, self.joints, self.commands = [], [], [], []
        self.statuses = []  # (stamp [s], {key: value})
        sub = self.node.create_subscription
        sub(PoseStamped, '/tool_pose', self._stamped(self.poses, _tip), DEFAULT_QOS)
        sub(WrenchStamped, '/tool/pressure', self._stamped(self.pressures, _force), DEFAULT_QOS)
        sub(JointState, '/joint_states', self._stamped(self.joints, _positions), DEFAULT_QOS)
        sub(
            JointTrajectory,
            '/pa10_controller/joint_trajectory',
            lambda msg: self.commands.append(
                (time.time(), np.array(msg.points[0].velocities) if msg.points else None)
            ),
            DEFAULT_QOS,
        )
        sub(DiagnosticArray, '/diagnostics', self._on_diagnostics, DEFAULT_QOS)
        self.path_publisher = self.node.create_publisher(PathMsg, '/curve/waypoints', LATCHED_QOS)

    @staticmethod
    def _stamped(log, value):
        return lambda msg: log.append((_seconds(msg.header.stamp), value(msg)))

    def _on_diagnostics(self, msg):
        for status in msg.status:
            if status.name == self.status_name:
                self.statuses.append(
                    (_seconds(msg.header.stamp), {kv.key: kv.value for kv in status.values})
                )

    def spin_until(self, condition, timeout, what, processes=()):
        """Spin until ``condition()``; TimeoutError after ``timeout`` [s] or as soon as
        one of ``processes`` (NodeProcess) has exited, naming its last output line."""
        deadline = time.monotonic() + timeout
        while not condition():
            for process in processes:
                if not process.alive():
                    lines = process.output().strip().splitlines() or ['no output']
                    raise TimeoutError(
                        f'{Path(process.argv[1 if "python" in process.argv[0] else 0]).name} '
                        f'exited waiting for {what}: {lines[-1][-300:]}'
                    )
            if time.monotonic() > deadline:
                raise TimeoutError(f'timed out after {timeout:.0f} s waiting for {what}')
            self.executor.spin_once(timeout_sec=0.05)

    def last(self, key):
        return self.statuses[-1][1].get(key) if self.statuses else None

    def first_stamp(self, phase):
        return next((t for t, values in self.statuses if values['phase'] == phase), None)

    def call(self, service, timeout=30.0):
        from std_srvs.srv import Trigger

        client = self.node.create_client(Trigger, service)
        self.spin_until(client.service_is_ready, timeout, f'service {service}')
        future = client.call_async(Trigger.Request())
        self.spin_until(future.done, timeout, f'{service} response')
        return future.result()

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)


def _seconds(stamp):
    return stamp.sec + stamp.nanosec * 1e-9


def _tip(msg):
    p = msg.pose.position
    return np.array([p.x, p.y, p.z])


def _force(msg):
    return msg.wrench.force.z


def _positions(msg):
    return np.array(msg.position)


def controller_argv(controller, built, scenario, ours_params=()):
    """The command line of ``controller`` ('ours': pa10_ik_node at its defaults but for
    ``ours_params``, 'name:=value' each; 'peer': the DLS peer node) on the case's arm."""
    arm = built.spec.arm
    common = [
        '-p',
        f'robot:={scenario["robot"]["model"]}',
        '-p',
        f'tip_frame:={arm.tip_frame}',
        '-p',
        f"base_frame:='{arm.base_frame}'",
        '-p',
        f'desired_force:={DESIRED_FORCE}',
        '-p',
        f'contact_stiffness:={float(scenario["contact"]["stiffness"])}',
    ]
    # The topic tests' watchdog: on the loaded 2-core machine the simulator was once
    # starved for 1.0-1.1 s, and a stop on stale pressure is no tracking figure.
    watchdog = ['-p', 'pressure_timeout:=3.0']
    if controller == 'ours':
        extra = [arg for param in ours_params for arg in ('-p', param)]
        return [executable('pa10_ik_node'), '--ros-args', *common, *watchdog, *extra]
    return [sys.executable, PEER_NODE, '--ros-args', *common]


class Refused(Exception):
    """The controller's start service refused the task (its message)."""


def run_one(built, controller, condition, directory, ours_params=()):
    """One run of ``controller`` on the built case under the arm ``condition``; the row."""
    scale, delay = CONDITIONS[condition]
    urdf = Path(directory) / f'{built.spec.arm.name}.urdf'
    template = yaml.safe_load(small_scenario(Path(directory)).read_text())
    scenario = task_generator.plane_scenario(built, template, urdf)
    scenario_path = Path(directory) / 'scenario.yaml'
    scenario_path.write_text(yaml.safe_dump(scenario))
    env = run_env()
    tag = f'{controller}-{int(time.time() * 1e3)}'
    processes = []
    status_name = 'pa10_ik_node: tracking' if controller == 'ours' else 'dls_peer: tracking'
    probe = TopicProbe(int(env['ROS_DOMAIN_ID']), status_name)
    row = {'controller': controller}
    try:
        sim_argv = [executable('sensor_sim'), '--ros-args', '-p', f'scenario:={scenario_path}']
        sim_argv += ['-p', 'calibration_phase:=false', '-p', 'rate:=1']
        sim_argv += ['-p', f'arm_speed_scale:={scale}', '-p', f'arm_command_delay:={delay}']
        processes.append(NodeProcess(sim_argv, env, Path(directory) / f'sim-{tag}.log'))
        node = NodeProcess(
            controller_argv(controller, built, scenario, ours_params),
            env,
            Path(directory) / f'{tag}.log',
        )
        processes.append(node)
        probe.path_publisher.publish(_path_message(built.waypoints))
        probe.spin_until(
            lambda: len(probe.poses) > 10
            and len(probe.pressures) > 10
            and 'waypoints:' in node.output(),
            120,
            'tool poses, pressure, the path taken',
            processes,
        )
        service = (
            '/pa10_ik_node/start_tracking' if controller == 'ours' else '/dls_peer/start_tracking'
        )
        response = probe.call(service)
        started = time.time()
        if not response.success:
            raise Refused(response.message)
        probe.spin_until(
            lambda: probe.last('phase') in ('failed', 'stopped')
            or (probe.last('phase') == 'done' and probe.last('stage') == 'lifted'),
            TASK_TIMEOUT,
            f'{controller} done and lifted',
            processes,
        )
        row.update(_figures(probe, built, started))
        row.update(phase=probe.last('phase'), stage=probe.last('stage'))
        # pa10_ik_node's median control step (IK included) over its last 500 steps; the
        # peer reports none.
        row['step_ms'] = float(probe.last('step_time_ms') or 'nan')
        # and of its IK alone (Jacobian, task, solve), the arm's lag it measured, the
        # response it estimated (nan from a node before it reported them)
        row['ik_ms'] = float(probe.last('ik_time_ms') or 'nan')
        row['lag_ms'] = float(probe.last('arm_lag_ms') or 'nan')
        row['response'] = float(probe.last('arm_response') or 'nan')
        row['reason'] = probe.last('reason') or ''
        crashed = [p.argv[0] for p in processes if 'Traceback' in p.output()]
        if crashed:
            row.update(phase='crashed', reason=f'a traceback in {crashed}')
    except Refused as error:
        row.update(phase='refused', reason=str(error))
    except TimeoutError as error:
        row.update(phase='timeout', reason=str(error), stage=probe.last('stage'))
    finally:
        for process in reversed(processes):
            process.stop()
        probe.close()
    row['missed'] = meets_goals(row) if 'rms_mm' in row else [f'ended {row["phase"]}']
    return row


def _path_message(waypoints):
    from vgm_common.conversions import matrices_to_path

    return matrices_to_path(waypoints, time.time_ns(), 'base_link')


def _figures(probe, built, started):
    touchdown, end = probe.first_stamp('tracking'), probe.first_stamp('done')
    figures = {'task_s': end - started if end else float('nan')}
    if touchdown is None or end is None:
        return figures
    tips = [tip for t, tip in probe.poses if touchdown <= t <= end]
    forces = [f for t, f in probe.pressures if touchdown <= t <= end]
    figures.update(
        task_generator.goal_figures(tips, forces, built.surface, built.path_base, DESIRED_FORCE)
    )
    robot = built.robot
    q = np.array([q for t, q in probe.joints if t >= started])
    qdot = np.array([v for t, v in probe.commands if t >= started and v is not None and len(v)])
    figures.update(
        tracking_s=end - touchdown,
        limit_margin_rad=float(np.min(np.minimum(q - robot.lower_limits, robot.upper_limits - q))),
        velocity_ratio=float(np.max(np.abs(qdot) / robot.velocity_limits)) if len(qdot) else 0.0,
    )
    return figures


def grid(arms):
    return [
        (arm, shape, tilt, condition)
        for arm in arms
        for shape in task_generator.PATH_SHAPES
        for tilt in TILTS_DEG
        for condition in CONDITIONS
    ]


def sample(arms, count, seed):
    """``count`` cases of the grid, drawn with ``seed``: arm i mod the arms and condition
    i mod 3 (4 arms x 3 conditions: every pair in 12 cases), the path shapes in a drawn
    order, one after the other, each with a drawn tilt."""
    rng = np.random.default_rng(seed)
    shapes = rng.permutation(task_generator.PATH_SHAPES)
    return [
        (
            arms[i % len(arms)],
            str(shapes[i % len(shapes)]),
            float(rng.choice(TILTS_DEG)),
            list(CONDITIONS)[i % len(CONDITIONS)],
        )
        for i in range(count)
    ]


def main_over_topics(argv):
    import tempfile

    seed = int(_option(argv, '--seed', '11'))
    arms = tuple(task_generator.ROBOT_DATA_ARMS) if '--all-arms' in argv else ARMS
    if '--whole-grid' in argv:
        cases = grid(arms)
    else:
        cases = sample(arms, int(_option(argv, '--cases', '12')), seed)
    # --only i,j: those cases of the sample or grid alone, each as in the whole run
    only = {int(i) for i in _option(argv, '--only', '').split(',') if i}
    # --ours name:=value,name:=value: pa10_ik_node's parameters other than its defaults
    ours_params = [p for p in _option(argv, '--ours', '').split(',') if p]
    rows = []
    began = time.monotonic()
    for index, (arm_name, shape, tilt, condition) in enumerate(cases):
        if only and index not in only:
            continue
        spec = task_generator.CaseSpec(
            task_generator.robot_data_arm(arm_name),
            'plane',
            float(np.radians(tilt)),
            shape,
            'position',
            1.0,
            seed + index,
        )
        pair = {}
        with tempfile.TemporaryDirectory() as directory:
            built = task_generator.build_case(spec, directory)
            for controller in ('ours', 'peer'):
                pair[controller] = run_one(built, controller, condition, directory, ours_params)
        case = {'arm': arm_name, 'shape': shape, 'tilt_deg': tilt, 'condition': condition}
        ratio = pair['ours'].get('task_s', np.nan) / pair['peer'].get('task_s', np.nan)
        rows.append({**case, 'ours': pair['ours'], 'peer': pair['peer'], 'time_ratio': ratio})
        print(
            f'[{index + 1}/{len(cases)} {time.monotonic() - began:.0f} s] {arm_name} / {shape} / '
            f'{tilt:g} deg / {condition}: ours {_brief(pair["ours"])}; peer '
            f'{_brief(pair["peer"])}; time ratio {ratio:.2f}',
            flush=True,
        )
        write_tables(rows, argv, seed)
    return rows


def _option(argv, name, default):
    return argv[argv.index(name) + 1] if name in argv else default


def _brief(r):
    if 'rms_mm' not in r:
        return f'{r["phase"]} ({r.get("reason", "")})'
    return (
        f'{r["phase"]} RMS {r["rms_mm"]:.4f} mm max {r["max_mm"]:.3f} mm passed '
        f'{r["passed_fraction"] * 100:.1f} % force p95 {r["force_p95_pct"]:.2f} % task '
        f'{r["task_s"]:.1f} s step {r.get("step_ms", float("nan")):.3f} ms IK '
        f'{r.get("ik_ms", float("nan")):.3f} ms lag {r.get("lag_ms", float("nan")):.1f} ms '
        f'response {r.get("response", float("nan")):.2f}'
    )


def _cells(r):
    """The cells of one controller's run, from 'end' to 'goals missed'."""
    if 'rms_mm' not in r:
        return (r['phase'], *[''] * 10, r.get('reason', ''))
    return (
        r['phase'],
        f'{r["rms_mm"]:.4f}',
        f'{r["max_mm"]:.3f}',
        f'{r["passed_fraction"] * 100:.1f}',
        f'{r["force_p95_pct"]:.2f}',
        f'{r["limit_margin_rad"]:.3f}',
        f'{r["velocity_ratio"]:.2f}',
        f'{r["task_s"]:.1f}',
        f'{r.get("step_ms", float("nan")):.3f}',
        f'{r.get("ik_ms", float("nan")):.3f}',
        f'{r.get("lag_ms", float("nan")):.1f}',
        '; '.join(r['missed']) or 'none',
    )


COLUMNS = (
    'arm',
    'shape',
    'tilt [deg]',
    'condition',
    'controller',
    'end',
    'RMS [mm]',
    'max [mm]',
    'passed [%]',
    'force p95 [%]',
    'limit margin [rad]',
    'qdot / limit',
    'task [s]',
    'step [ms]',
    'IK [ms]',
    'lag [ms]',
    'goals missed',
    'time ours / peer',
)


def write_tables(rows, argv, seed):
    command = 'nice -n 10 .venv/bin/python bench/bench_pa10_ik.py ' + ' '.join(argv)
    met = {c: sum(not r[c]['missed'] for r in rows) for c in ('ours', 'peer')}
    ratios = np.array([r['time_ratio'] for r in rows], dtype=float)
    steps = np.array([r['ours'].get('step_ms', np.nan) for r in rows], dtype=float)
    all_met = sum(not r['ours']['missed'] and r['time_ratio'] <= 1.2 for r in rows)
    lines = [
        '# pa10_ik_node beside the DLS peer, over topics',
        '',
        f'Command (from the repository root, after `source ros2_ws/install/setup.bash`): '
        f'`{command.strip()}`; seed {seed}. Each case: sensor_sim (320x240 cameras, '
        'rate 1) with the arm and a plane, pa10_ik_node at its defaults (pressure_timeout '
        '3 s, as in the topic tests: ours) or '
        f'bench/pa10_dls_peer_node.py (peer: DlsPeer, {PEER_SPEED} m/s), one after the '
        f'other, each run its own domain; {DESIRED_FORCE:g} N, the scenario contact '
        'stiffness (2000 N/m), control 100 Hz, the arm at 200 Hz following positions; '
        'conditions: ideal, delay 20 ms (sensor_sim arm_command_delay 0.02), half speed '
        '(arm_speed_scale 0.5). Force from the simulated sensor (noise sigma 0.05 N: its '
        'p95 alone is 2 %). Figures from touchdown (first tracking status) to the '
        "path's end (first done status); task = start call to the path's end; limit "
        'margin = closest approach of a joint state to a position limit, qdot / limit = '
        'largest commanded joint speed over its limit (from the start call on); step, IK, '
        "lag: pa10_ik_node's diagnostics step_time_ms, ik_time_ms and arm_lag_ms at the end.",
        '',
        f'Goals: RMS < {GOALS["rms_mm"]} mm, passed > {GOALS["passed_fraction"] * 100:g} %, '
        f'force p95 < {GOALS["force_p95_pct"]:g} %, no joint limit exceeded, task time '
        '<= 1.2 x the peer.',
        '',
        f'Summary: {len(rows)} cases; all path/force/limit goals met: ours {met["ours"]}, '
        f'peer {met["peer"]}; time ratio ours / peer median {np.nanmedian(ratios):.2f}, '
        f'max {np.nanmax(ratios) if np.isfinite(ratios).any() else float("nan"):.2f}, '
        f'<= 1.2 in {int(np.sum(ratios <= 1.2))} of {len(rows)}; ours meets every goal '
        f'including the time in {all_met}; median control step of ours (pa10_ik_node '
        f'diagnostics step_time_ms, median of its last 500 steps, IK included; goal IK '
        f'step < 0.3 ms) {np.nanmedian(steps):.3f} ms (cases {np.nanmin(steps):.3f}-'
        f'{np.nanmax(steps):.3f}).',
        '',
    ]
    cells = []
    for r in rows:
        case = (r['arm'], r['shape'], f'{r["tilt_deg"]:g}', r['condition'])
        cells.append((*case, 'ours', *_cells(r['ours']), f'{r["time_ratio"]:.2f}'))
        cells.append((*case, 'peer', *_cells(r['peer']), ''))
    lines += markdown_table(COLUMNS, cells)
    write_results(OUT, 'results', lines, rows, echo=False)
    _plot(rows)


def _plot(rows):
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    labels = [f'{r["arm"]}\n{r["shape"]} {r["tilt_deg"]:g}\n{r["condition"]}' for r in rows]
    x = np.arange(len(rows))
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(max(8, 1.1 * len(rows)), 8), sharex=True)
    for offset, controller in ((-0.2, 'ours'), (0.2, 'peer')):
        rms = [r[controller].get('rms_mm', np.nan) for r in rows]
        top.bar(x + offset, rms, 0.4, label=controller)
    top.axhline(0.05, color='k', linestyle='--', label='goal 0.05 mm')
    top.set_yscale('log')
    top.set_ylabel('path RMS [mm]')
    top.legend()
    bottom.bar(x, [r['time_ratio'] for r in rows], 0.5)
    bottom.axhline(1.2, color='k', linestyle='--', label='goal 1.2')
    bottom.set_ylabel('task time ours / peer')
    bottom.set_xticks(x, labels, fontsize=7)
    bottom.legend()
    fig.tight_layout()
    save_figure(fig, OUT / 'rms_and_time_ratio.png')
