#!/usr/bin/env python3
"""Benchmark of pa10_ik_node's cores (no ROS): the seed's Table 7.1 and force tracking.

Part A (Table 7.1, figs 7.14-7.21): the thesis PA-10 model (`pa10_thesis`), trajectories
Gamma1 (a closed curve on S3 through the tool's start) and Gamma2 from the seed's initial
joint vectors, T = 6 s, quintic timing so rdot_d(0) = rdot_d(T) = 0; RMS position and
orientation errors of q integrated (Euler, dt = 1 ms) for primal_dual (the seed's network,
W = diag(1,-1,-1,1,-1,1,1), K = 100, integrated exactly, no pose feedback, as published),
ours (closed-form KKT with the same W, |W| where it fails, pose feedback) and dls
(damping 0.05, pose feedback); time per control step (Jacobian + solve); the literal
fixed-step rules at mu = eta = 0.02.

Part B: TrackingController with sensor_sim's arm and spring contact in-process on the
closed curves of the S1, S2 and default (S3) scenarios: force error and lateral error
along the whole curve.

Part C (`--cases`): generated cases (vgm_evaluation.task_generator): PA-10-like
random arms and the Franka Panda x planes, paraboloid domes and S1-S3 tilted 0-45 deg x
lines, arcs, figure eights, spirals and tight loops near the reach, the arm simulated
following positions or velocities, at full or half the commanded speed; ours against
the damped-least-squares IK (method dls, same phase machine and force law) and the
thesis's primal-dual network, on the same inputs, with a stop mid-motion.

Part D (`--robot-data`): every 7-DOF arm of example-robot-data as it ships
(task_generator.ROBOT_DATA_ARMS: chain base -> tip frame, the rest locked) x path shapes x
tilted planes, ours beside the damped-least-squares peer (method dls, same phase machine),
each path first through the joint-limit reachability check from the start joints.

Part E (`--pace`): the pace beside a conventional peer: the PA-10 (its 0.1 m tool) on a
plane tilted by 20 deg, a 0.8 m lemniscate, the arm following positions at full speed or
half speed; ours (node defaults) beside ``DlsPeer``, a conventional damped-least-squares controller
with its own phase logic and force loop (no governor: its reference runs on the clock at
``PEER_SPEED``); task time, pace ratio ours / peer and the goal figures, from a start in
free space and from a start already in contact at the first waypoint.

Part F (`--over-topics`, pa10_ik_topics.py): ours (pa10_ik_node) beside the DLS peer
(pa10_dls_peer_node.py: ``DlsPeer`` as a node) over the topics against sensor_sim, on
example-robot-data arms x path shapes x tilted planes x {ideal arm, commands 20 ms late,
half-speed arm}: a seeded sample (``--cases N``, default 12) or ``--whole-grid``.

Run: source ros2_ws/install/setup.bash && .venv/bin/python bench/bench_pa10_ik.py
     [--cases-only [--arms N]]   (Part C alone: N random arms and the Panda)
     [--robot-data [--shapes arc,figure_eight] [--tilts 20,45]]   (Part D alone)
     [--pace]   (Part E alone)
     [--over-topics [--cases N | --whole-grid] [--all-arms] [--seed S] [--only i,j]
      [--ours name:=value,...]]
     (Part F alone: bench/results/pa10_ik_topics/)
Writes bench/results/pa10_ik/ (results.md, results.json, PNG plots) and, for Part C,
bench/results/pa10_ik_cases/ (results.md, results.json).
"""

import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
for package in ('pa10_ik_node', 'sensor_sim', 'vgm_common'):
    sys.path.insert(0, str(REPO / 'src' / package))

from pa10_dls_peer import PEER_SPEED, DlsPeer  # noqa: E402
from pa10_goals import GOALS, meets_goals  # noqa: E402
from pa10_ik_topics import main_over_topics  # noqa: E402
from vgm_evaluation.bench_report import markdown_table, save_figure, write_results  # noqa: E402

from pa10_ik_node.ik import RateSolver, pose_error  # noqa: E402
from pa10_ik_node.thesis import fixed_step_matrix, primal_dual_velocity_fixed_step  # noqa: E402
from pa10_ik_node.tracking import (  # noqa: E402
    TrackingConfig,
    TrackingController,
    force_tilt_angle,
    next_target_on_tangent_plane,
)
from sensor_sim.arm_sim import SimulatedArm  # noqa: E402
from sensor_sim.curves import curve_polylines  # noqa: E402
from sensor_sim.scenario import load_scenario  # noqa: E402
from sensor_sim.surfaces import normal_base, surface_points_base  # noqa: E402
from vgm_common.robot_model import load_robot  # noqa: E402
from vgm_evaluation import task_generator  # noqa: E402

OUT = REPO / 'bench' / 'results' / 'pa10_ik'
W_THESIS = np.array([1.0, -1.0, -1.0, 1.0, -1.0, 1.0, 1.0])
Q0 = {
    'Gamma1': np.array([0.1288, 0.0, 0.3125, 0.0, 0.0, 0.3241, 0.038]),
    'Gamma2': np.array([0.20, 0.0, 0.0, -0.28, 0.0, -0.10, -0.03]),
    # Gamma1's q(0) has q4 = 0: the arm is fully stretched (|p| = d3 + d5 + d7), on the
    # workspace boundary; a velocity-level IK cannot bend the elbow from there (J has
    # no radial component). The same curve from an elbow bent by 0.3 rad:
    'Gamma1_bent': np.array([0.1288, 0.0, 0.3125, 0.3, 0.0, 0.3241, 0.038]),
}
CURVE = {'Gamma1': 'Gamma1', 'Gamma2': 'Gamma2', 'Gamma1_bent': 'Gamma1'}
THESIS_TABLE = {
    'Gamma1': (1.8e-5, 4.17e-5),
    'Gamma2': (3.6e-4, 2.16e-5),
    'Gamma1_bent': (1.8e-5, 4.17e-5),
}
DURATION = 6.0  # [s]
DT = 1e-3  # [s] control step of Part A
FEEDBACK_GAIN = 300.0  # [1/s] pose feedback of ours and dls


def quintic(t):
    """s(t) in [0, 1] with zero velocity and acceleration at 0 and DURATION."""
    x = np.clip(t / DURATION, 0.0, 1.0)
    return 10 * x**3 - 15 * x**4 + 6 * x**5


def s3_normal(u, v):
    n = np.array([-(v + 0.5), -u, 1.0])  # S3: z = uv + 0.5u - 0.6, gradient (v + 0.5, u)
    return n / np.linalg.norm(n)


def gamma_pose(name, T0, t):
    """Desired tool pose (4, 4) at time t: Gamma1 a closed loop on S3 (surface units =
    the thesis model's units) through the start, the tool axis turning with the normal;
    Gamma2 an open space curve in the range of fig. 7.13 (A7.13: no formula given)."""
    s = quintic(t)
    T = np.eye(4)
    if CURVE[name] == 'Gamma1':
        theta, rho = 2 * np.pi * s, 0.3
        u, v = rho * (np.cos(theta) - 1.0), rho * np.sin(theta)
        offset = np.array([u, v, u * v + 0.5 * u])
        tilt, _ = Rotation.align_vectors([s3_normal(u, v)], [s3_normal(0.0, 0.0)])
        T[:3, :3] = tilt.as_matrix() @ T0[:3, :3]
    else:
        offset = np.array([-0.7 * s, 0.5 * np.sin(2 * np.pi * s), -0.5 * s])
        T[:3, :3] = Rotation.from_rotvec([0.0, 0.2 * s, 0.3 * s]).as_matrix() @ T0[:3, :3]
    T[:3, 3] = T0[:3, 3] + offset
    return T


def desired_twist(name, T0, t, h=1e-5):
    """rdot_d (6,) [units/s, rad/s] by central differences of the pose."""
    return pose_error(gamma_pose(name, T0, t - h), gamma_pose(name, T0, t + h)) / (2 * h)


def run_table(name, method, robot):
    q = Q0[name].copy()
    T0 = robot.forward_kinematics(q)
    # ours_identity: the node's default weights W = I.
    solver = RateSolver(
        method.replace('_identity', ''),
        np.ones(7) if method.endswith('_identity') else W_THESIS,
        K=100.0,
        damping=0.05,
    )
    feedback = 0.0 if method == 'primal_dual' else FEEDBACK_GAIN
    steps = int(round(DURATION / DT))
    log = {k: [] for k in ('t', 'p_err', 'o_err', 'q', 'qdot', 'r_d', 'rdot_d')}
    step_times, failures, diverged = [], 0, 0
    for k in range(steps + 1):
        t = k * DT
        T_d = gamma_pose(name, T0, t)
        twist = desired_twist(name, T0, t)
        started = time.perf_counter()
        T = robot.forward_kinematics(q)
        J = robot.jacobian(q)
        error = pose_error(T, T_d)
        qdot, info = solver.solve(J, twist + feedback * error)
        step_times.append(time.perf_counter() - started)
        failures += info.get('null_space_positive') is False
        diverged += bool(info.get('diverged'))
        log['t'].append(t)
        log['p_err'].append(np.linalg.norm(error[:3]))
        log['o_err'].append(np.linalg.norm(error[3:]))
        log['q'].append(q.copy())
        log['qdot'].append(qdot)
        log['r_d'].append(
            np.concatenate([T_d[:3, 3], Rotation.from_matrix(T_d[:3, :3]).as_rotvec()])
        )
        log['rdot_d'].append(twist)
        if k < steps:
            q = q + qdot * DT
    log = {key: np.array(value) for key, value in log.items()}
    return {
        'rms_position': float(np.sqrt(np.mean(log['p_err'] ** 2))),
        'rms_orientation': float(np.sqrt(np.mean(log['o_err'] ** 2))),
        'max_position': float(log['p_err'].max()),
        'step_ms_median': float(np.median(step_times) * 1e3),
        'null_space_failures': int(failures),
        'network_diverged': int(diverged),
        'steps': steps + 1,
    }, log


def fixed_step_report(robot):
    J = robot.jacobian(Q0['Gamma1'])
    radius = float(np.max(np.abs(np.linalg.eigvals(fixed_step_matrix(J, np.diag(W_THESIS))))))
    _, _, norms = primal_dual_velocity_fixed_step(
        J, np.diag(W_THESIS), np.ones(6) * 0.1, iterations=50
    )
    diverged_at = int(np.argmax(norms > 1e10)) if np.any(norms > 1e10) else None
    return radius, diverged_at


def plot_table(logs, path):
    try:
        import matplotlib

        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    for name, by_method in logs.items():
        log = by_method['ours_identity']
        fig, axes = plt.subplots(2, 3, figsize=(15, 8))
        panels = [
            ('r_d', 'r_d (position, rotation vector)'),
            ('rdot_d', 'rdot_d'),
            ('qdot', 'qdot [rad/s] (ours)'),
            ('q', 'q [rad] (ours)'),
        ]
        for ax, (key, title) in zip(axes.flat, panels):
            ax.plot(log['t'], log[key])
            ax.set_title(f'{name}: {title}')
            ax.set_xlabel('t [s]')
        for ax, key, title in (
            (axes[1, 1], 'p_err', 'position error'),
            (axes[1, 2], 'o_err', 'orientation error [rad]'),
        ):
            for method, method_log in by_method.items():
                ax.semilogy(method_log['t'], np.maximum(method_log[key], 1e-16), label=method)
            ax.set_title(f'{name}: {title}')
            ax.set_xlabel('t [s]')
            ax.legend()
        fig.tight_layout()
        save_figure(fig, path / f'table71_{name}.png')
    return True


# --- Part B: force tracking in the simulated contact --------------------------------


def curve_waypoints(scenario, spacing=0.002):
    """Waypoints every ~``spacing`` [m] on the scenario's true curve, true normals."""
    curve = curve_polylines(scenario.curve, scenario.surface)[0]
    steps = np.linalg.norm(np.diff(curve, axis=0), axis=1)
    every = max(1, int(round(spacing / np.median(steps))))
    points = curve[:-1:every]
    normals = normal_base(scenario.surface, points)
    ahead = np.roll(points, -1, axis=0)
    return np.array(
        [next_target_on_tangent_plane(p, n, q)[1] for p, n, q in zip(points, normals, ahead)]
    )


def run_force(
    scenario_name, force_law='integral', speed=0.02, dt=0.01, depth_error=0.0, force_gain=5.0
):
    """One whole closed curve under force control. ``depth_error`` [m]: the waypoints are
    displaced by depth_error * sin(2 * 2 pi * s / length) along their approach axis (a
    reconstructed curve off the surface), which the force law has to absorb."""
    scenario = load_scenario(REPO / 'src' / 'sensor_sim' / 'scenarios' / f'{scenario_name}.yaml')
    robot = load_robot(scenario.robot.model, scenario.robot.tool_length)
    waypoints = curve_waypoints(scenario)
    if depth_error:
        fraction = np.linspace(0.0, 1.0, len(waypoints), endpoint=False)
        waypoints[:, :3, 3] += (depth_error * np.sin(4 * np.pi * fraction))[:, None] * waypoints[
            :, :3, 2
        ]
    desired = 5.0
    controller = TrackingController(
        robot,
        RateSolver('ours', np.ones(7)),
        TrackingConfig(
            desired_force=desired,
            stiffness=scenario.contact_stiffness,
            speed=speed,
            force_law=force_law,
            force_gain=force_gain,
        ),
        max_joint_velocity=1.0,
    )
    controller.start(waypoints)
    log = task_generator.run_closed_loop(
        controller,
        robot,
        SimulatedArm.from_robot_model(robot, scenario.robot.initial_joints),
        scenario.surface,
        scenario.contact_stiffness,
        dt=dt,
        max_time=200.0,
        pressure_sigma=scenario.noise.pressure_sigma,
        rng=np.random.default_rng(scenario.seed),
        hold_time=0.0,
        finished=lambda c: c.phase in ('done', 'failed', 'stopped'),
    )
    tracking = [i for i, phase in enumerate(log.phases) if phase == 'tracking']
    forces = np.array(log.forces)[tracking]
    phis = [force_tilt_angle(log.readings[i], desired) for i in tracking]
    rms, _ = controller.stats.summary()
    return {
        'scenario': scenario_name,
        'surface': scenario.surface.kind,
        'force_law': force_law,
        'force_gain': force_gain,
        'depth_error_mm': depth_error * 1e3,
        'phase': controller.phase,
        'reason': controller.reason,
        'path_length_m': controller.path.length,
        'closed': controller.path.closed,
        'sim_time_s': log.times[-1],
        'rms_lateral_mm': rms * 1e3,
        'max_lateral_mm': float(np.max(controller.stats.position_errors)) * 1e3,
        'true_force_min_N': float(forces.min()),
        'true_force_max_N': float(forces.max()),
        'max_force_error_pct': float(np.max(np.abs(forces - desired)) / desired * 100),
        'rms_force_error_N': float(np.sqrt(np.mean((forces - desired) ** 2))),
        'phi_range_rad': [float(np.min(phis)), float(np.max(phis))],
        'step_ms_median': float(np.median(log.step_times) * 1e3),
    }


# --- Part C: generated arms x surfaces x paths -------------------------------------

CASES_OUT = REPO / 'bench' / 'results' / 'pa10_ik_cases'
# method -> (RateSolver method, W, TrackingConfig changes). dls_plain: the conventional
# peer, DLS IK with the plain pose feedback (no integral across the approach axis, no
# compensation of a slow arm's measured response).
CASE_METHODS = {
    'ours': ('ours', np.ones(7), {'adapt_response': False}),
    'ours_adaptive': ('ours', np.ones(7), {'adapt_response': True}),
    'dls': ('dls', np.ones(7), {'adapt_response': False}),
    'dls_plain': ('dls', np.ones(7), {'pose_integral_gain': 0.0, 'adapt_response': False}),
    'primal_dual': ('primal_dual', W_THESIS, {}),
}


def run_case(built, method, stop_at_progress=None):
    """One generated case under ``method``; its goal figures (README)."""
    desired, stiffness = 5.0, 2000.0
    solver_method, weights, changes = CASE_METHODS[method]
    controller = TrackingController(
        built.robot,
        RateSolver(solver_method, weights),
        TrackingConfig(desired_force=desired, stiffness=stiffness, speed=0.015, **changes),
        max_joint_velocity=1.0,
    )
    controller.start(built.waypoints)
    log = task_generator.run_closed_loop(
        controller,
        built.robot,
        built.simulated_arm(),
        built.surface,
        stiffness,
        stop_at_progress=stop_at_progress,
    )
    row = task_generator.tracking_metrics(
        log, built.surface, built.path_base, desired, built.robot
    )
    row.update(phase=controller.phase, stage=controller.stage, reason=controller.reason)
    return row


def main_cases(seed=13, random_arms=2):
    """Part C; the tables are rewritten after every case (a long run can be cut short)."""
    import tempfile

    rows = []
    with tempfile.TemporaryDirectory() as directory:
        for index, spec in enumerate(task_generator.generate_cases(seed, random_arms)):
            built = task_generator.build_case(spec, directory)
            for method in CASE_METHODS:
                # The thesis's network costs ~20 ms a step: on the first arm's cases only.
                if method == 'primal_dual' and index >= len(task_generator.SURFACE_KINDS):
                    continue
                row = run_case(built, method)
                row.update(
                    case=spec.label,
                    method=method,
                    missed=meets_goals(row),
                    stop_mid_latency_ms=float('nan'),
                )
                if method == 'ours':  # stop mid-motion: same case, half-way along
                    stop = run_case(built, method, stop_at_progress=0.5)
                    row.update(
                        stop_mid_latency_ms=stop['stop_latency_ms'], stop_mid_phase=stop['phase']
                    )
                rows.append(row)
                print(
                    f'{spec.label} | {method}: {row["phase"]} rms {row["rms_mm"]:.4f} mm, '
                    f'passed {row["passed_fraction"]:.3f}, force p95 '
                    f'{row["force_p95_pct"]:.2f} %, step {row["step_ms_median"]:.3f} ms, '
                    f'stop {row["stop_mid_latency_ms"]:.0f} ms {row["missed"]}',
                    flush=True,
                )
            write_case_tables(rows, seed)


def write_case_tables(rows, seed):
    lines = [
        '# pa10_ik_node: generated cases',
        '',
        'Command: `source ros2_ws/install/setup.bash && .venv/bin/python '
        'bench/bench_pa10_ik.py --cases-only`',
        '',
        f'Seed {seed}: vgm_evaluation.task_generator.generate_cases. Every case: 5 N '
        'desired, contact stiffness 2000 N/m (estimate exact), 0.015 m/s, control '
        "100 Hz, the arm simulated at 200 Hz. RMS = distance of the tip's foot point on "
        'the surface to the true path while tracking; passed = fraction of the path '
        'with a foot point within 2 mm; force p95 = 95th percentile of |force error| / '
        'desired; stop = time from a stop half-way along the path to zero joint '
        'velocity; qdot/limit = largest commanded joint speed over its limit; margin = '
        'closest approach to a position limit. Step times measured on a loaded 2-core '
        'machine (ours, dls and primal_dual back to back on the same inputs).',
        '',
        f'Goals: RMS < {GOALS["rms_mm"]} mm, passed > {GOALS["passed_fraction"] * 100:g} '
        f'%, force p95 < {GOALS["force_p95_pct"]:g} %, no limit exceeded, stop within '
        f'{GOALS["stop_latency_ms"]:g} ms, step < {GOALS["step_ms_median"]:g} ms median.',
    ]
    table = ['', '## Every case', ''] + markdown_table(
        (
            'case',
            'method',
            'end',
            'RMS [mm]',
            'max [mm]',
            'passed [%]',
            'force p95 [%]',
            'qdot/limit',
            'margin [rad]',
            'step [ms]',
            'stop [ms]',
            'goals missed',
        ),
        (
            (
                row['case'],
                row['method'],
                row['phase'],
                f'{row["rms_mm"]:.4f}',
                f'{row["max_mm"]:.4f}',
                f'{row["passed_fraction"] * 100:.1f}',
                f'{row["force_p95_pct"]:.2f}',
                f'{row["velocity_ratio"]:.2f}',
                f'{row["limit_margin_rad"]:.3f}',
                f'{row["step_ms_median"]:.3f}',
                f'{row["stop_mid_latency_ms"]:.0f}',
                '; '.join(row['missed']) or 'none',
            )
            for row in rows
        ),
    )
    ours_step = np.median([r['step_ms_median'] for r in rows if r['method'] == 'ours'])
    by_method = {method: [r for r in rows if r['method'] == method] for method in CASE_METHODS}
    steps = {
        method: np.median([r['step_ms_median'] for r in mine])
        for method, mine in by_method.items()
    }
    summary = ['', '## Summary', ''] + markdown_table(
        (
            'method',
            'cases',
            'all goals met',
            'done',
            'median RMS [mm]',
            'median step [ms]',
            'step ratio to ours',
        ),
        (
            (
                method,
                len(mine),
                sum(not r['missed'] for r in mine),
                sum(r['phase'] == 'done' for r in mine),
                f'{np.nanmedian([r["rms_mm"] for r in mine]):.4f}',
                f'{steps[method]:.3f}',
                f'{steps[method] / ours_step:.2f}',
            )
            for method, mine in by_method.items()
        ),
    )
    failures = [
        f'- {r["case"]}: {"; ".join(r["missed"])}'
        for r in rows
        if r['method'] == 'primal_dual' and r['missed']
    ]
    summary += [
        '',
        "Where the thesis's primal-dual method (W = diag(1,-1,-1,1,-1,1,1)) misses the goals:",
        '',
    ] + (failures or ['- nowhere'])
    write_results(CASES_OUT, 'results', lines + summary + table, rows, echo=False)


ROBOT_DATA_OUT = REPO / 'bench' / 'results' / 'pa10_ik_robot_data'


def _option(name, default):
    return sys.argv[sys.argv.index(name) + 1] if name in sys.argv else default


def main_robot_data(shapes, tilts_deg, seed=7):
    """Part D: the example-robot-data arms x ``shapes`` x planes tilted by ``tilts_deg``,
    ours and dls on the same inputs; returns the rows and writes the table."""
    import tempfile

    rows = []
    with tempfile.TemporaryDirectory() as directory:
        for name in task_generator.ROBOT_DATA_ARMS:
            arm = task_generator.robot_data_arm(name)
            for shape in shapes:
                for tilt in tilts_deg:
                    spec = task_generator.CaseSpec(
                        arm, 'plane', np.radians(tilt), shape, 'position', 1.0, seed
                    )
                    built = task_generator.build_case(spec, directory)
                    for method in ('ours', 'dls'):
                        rows.append(_robot_data_row(built, spec, method))
                        print(_robot_data_line(rows[-1]), flush=True)
    write_results(
        ROBOT_DATA_OUT, 'results', _robot_data_table(rows, shapes, tilts_deg, seed), rows
    )
    return rows


def _robot_data_row(built, spec, method):
    """One arm x path x plane under ``method``: the reachability check, then the task."""
    from pa10_ik_node.tracking import Unreachable

    desired, stiffness, dt = 5.0, 2000.0, 0.01
    solver_method, weights, changes = CASE_METHODS[method]
    controller = TrackingController(
        built.robot,
        RateSolver(solver_method, weights),
        TrackingConfig(desired_force=desired, stiffness=stiffness, speed=0.015, **changes),
        max_joint_velocity=1.0,
    )
    row = {
        'arm': spec.arm.name,
        'shape': spec.path_shape,
        'tilt_deg': float(np.degrees(spec.tilt_rad)),
        'method': method,
    }
    started = time.perf_counter()
    try:
        controller.start(built.waypoints, spec.arm.start_joints)
    except Unreachable as error:
        row.update(phase='refused', reason=str(error), missed=[f'refused: {error}'])
        return row
    row['check_s'] = time.perf_counter() - started
    log = task_generator.run_closed_loop(
        controller, built.robot, built.simulated_arm(), built.surface, stiffness, dt=dt
    )
    row.update(
        task_generator.tracking_metrics(log, built.surface, built.path_base, desired, built.robot)
    )
    tracking = [i for i, phase in enumerate(log.phases) if phase == 'tracking']
    row.update(
        phase=controller.phase,
        stage=controller.stage,
        reason=controller.reason,
        task_s=len(log.phases) * dt,
        tracking_s=(tracking[-1] - tracking[0] + 1) * dt if tracking else float('nan'),
    )
    row['missed'] = meets_goals(row)
    return row


def _robot_data_line(row):
    case = f'{row["arm"]} / {row["shape"]} / {row["tilt_deg"]:.0f} deg | {row["method"]}'
    if row['phase'] == 'refused':
        return f'{case}: {row["reason"]}'
    return (
        f'{case}: {row["phase"]} rms {row["rms_mm"]:.4f} mm, passed {row["passed_fraction"]:.3f}, '
        f'force p95 {row["force_p95_pct"]:.2f} %, task {row["task_s"]:.1f} s, step '
        f'{row["step_ms_median"]:.3f} ms {row["missed"]}'
    )


def _robot_data_table(rows, shapes, tilts_deg, seed):
    command = (
        'nice -n 10 .venv/bin/python bench/bench_pa10_ik.py --robot-data --shapes '
        f'{",".join(shapes)} --tilts {",".join(f"{t:g}" for t in tilts_deg)}'
    )
    cells = []
    for r in rows:
        case = (r['arm'], r['shape'], f'{r["tilt_deg"]:.0f}', r['method'])
        if r['phase'] == 'refused':
            cells.append((*case, 'refused', *[''] * 8, r['reason']))
            continue
        cells.append(
            (
                *case,
                r['phase'],
                f'{r["rms_mm"]:.4f}',
                f'{r["passed_fraction"] * 100:.1f}',
                f'{r["force_p95_pct"]:.2f}',
                f'{r["limit_margin_rad"]:.3f}',
                f'{r["task_s"]:.1f}',
                f'{r["tracking_s"]:.1f}',
                f'{r["step_ms_median"]:.3f}',
                f'{r["check_s"]:.2f}',
                '; '.join(r['missed']) or 'none',
            )
        )
    return [
        f'Command (from the repository root, after `source ros2_ws/install/setup.bash`): '
        f'`{command}`; seed {seed}; in process (no topics): 5 N, 2000 N/m, 0.015 m/s, '
        'control 100 Hz, the arm following positions at 200 Hz.',
        '',
        *markdown_table(ROBOT_DATA_COLUMNS, cells),
    ]


ROBOT_DATA_COLUMNS = (
    'arm',
    'path',
    'tilt [deg]',
    'method',
    'end',
    'RMS [mm]',
    'passed [%]',
    'force p95 [%]',
    'margin [rad]',
    'task [s]',
    'tracking [s]',
    'step [ms]',
    'check [s]',
    'goals missed',
)


PACE_OUT = REPO / 'bench' / 'results' / 'pa10_ik_pace'
PACE_PATH_LENGTH = 0.8  # [m]


def pace_case(tilt_deg=20.0, seed=25):
    """The PA-10 on a plane tilted by ``tilt_deg`` 0.1 m ahead of its tool, a lemniscate
    of Gerono PACE_PATH_LENGTH long: (robot, start joints, surface, waypoints, dense
    path)."""
    robot = load_robot('pa10', 0.1)
    q0 = task_generator.PA10_START_JOINTS.copy()
    rng = np.random.default_rng(seed)
    surface = task_generator.posed_surface('plane', robot, q0, np.radians(tilt_deg), rng)
    a = 2 * np.pi * np.linspace(0.0, 1.0, 4001)[:-1]
    unit = np.column_stack([np.sin(a), np.sin(a) * np.cos(a)])
    unit_length = np.sum(np.linalg.norm(np.diff(np.vstack([unit, unit[:1]]), axis=0), axis=1))
    xy = unit * PACE_PATH_LENGTH / unit_length
    waypoints = task_generator.surface_waypoints(surface, xy, True)
    path_base = surface_points_base(surface, xy / surface.scale)
    return robot, q0, surface, waypoints, np.vstack([path_base, path_base[:1]])


def pace_row(
    controller_name,
    start,
    speed_scale,
    delay_s=0.0,
    desired=5.0,
    stiffness=2000.0,
    dt=0.01,
):
    """One pace run: ``controller_name`` 'ours' (node defaults), 'ours_latency' (with
    command_latency = ``delay_s``) or 'peer', ``start`` 'free' (the start pose) or
    'contact' (at the first waypoint with the desired force), the arm at ``speed_scale``
    with its commands ``delay_s`` [s] late."""
    from sensor_sim.arm_sim import SimulatedArm

    robot, q0, surface, waypoints, path_base = pace_case()
    if start == 'contact':
        from pa10_ik_node.reach import joints_at

        pressing = waypoints[0].copy()
        pressing[:3, 3] += desired / stiffness * pressing[:3, 2]
        q0 = joints_at(robot, q0, pressing)
    if controller_name.startswith('ours'):
        latency = delay_s if controller_name == 'ours_latency' else 0.0
        controller = TrackingController(
            robot,
            RateSolver('ours', np.ones(7)),
            TrackingConfig(desired_force=desired, stiffness=stiffness, command_latency=latency),
            max_joint_velocity=1.0,
        )
        controller.start(waypoints, q0)
    else:
        controller = DlsPeer(robot, waypoints, desired, stiffness)
    arm = SimulatedArm.from_robot_model(robot, q0, 'position', speed_scale)
    hold = 0.5
    log = task_generator.run_closed_loop(
        controller,
        robot,
        arm,
        surface,
        stiffness,
        dt=dt,
        max_time=200.0,
        hold_time=hold,
        command_delay_steps=int(round(delay_s / dt)),
        node_commands=controller_name.startswith('ours'),  # the peer node's: from q
    )
    row = task_generator.tracking_metrics(log, surface, path_base, desired, robot)
    phases = np.array(log.phases)
    first_done = np.flatnonzero(phases == 'done')
    # Whether the tip left the surface between the start and tracking (a lift-off).
    before_tracking = np.flatnonzero(phases == 'tracking')
    early = np.array(log.forces)[: before_tracking[0] if len(before_tracking) else 0]
    row.update(
        controller=controller_name,
        start=start,
        speed_scale=speed_scale,
        delay_ms=delay_s * 1e3,
        phase=controller.phase,
        stage=controller.stage,
        reason=controller.reason,
        task_s=len(phases) * dt - hold,
        tracking_s=float((first_done[0] if len(first_done) else len(phases)) - before_tracking[0])
        * dt
        if len(before_tracking)
        else float('nan'),
        lost_contact=bool(start == 'contact' and len(early) and np.min(early) <= 0.0),
    )
    row['missed'] = meets_goals(row)
    return row


def main_pace():
    """Part E: ours beside the DLS peer on the 0.8 m lemniscate; writes the table."""
    rows = []
    runs = [('free', 1.0, 0.0), ('contact', 1.0, 0.0), ('free', 0.5, 0.0)]
    runs += [('free', scale, delay) for scale in (1.0, 0.5) for delay in (0.02, 0.05)]
    for start, scale, delay in runs:
        names = ('peer', 'ours', 'ours_latency') if delay else ('peer', 'ours')
        pair = {name: pace_row(name, start, scale, delay) for name in names}
        for name in names:
            rows.append(pair[name])
            pair[name]['pace_ratio'] = pair[name]['task_s'] / pair['peer']['task_s']
        for r in pair.values():
            print(
                f'{r["controller"]} start {start} x{scale:g} delay {delay * 1e3:g} ms: '
                f'{r["phase"]}/{r["stage"]} task '
                f'{r["task_s"]:.1f} s tracking {r["tracking_s"]:.1f} s rms {r["rms_mm"]:.4f} '
                f'mm passed {r["passed_fraction"]:.3f} force p95 {r["force_p95_pct"]:.2f} % '
                f'lost contact {r["lost_contact"]} ratio {r.get("pace_ratio", 1.0):.2f} '
                f'{r["missed"]}',
                flush=True,
            )
    lines = [
        'Command (from the repository root, after `source ros2_ws/install/setup.bash`): '
        '`nice -n 10 .venv/bin/python bench/bench_pa10_ik.py --pace`; in process: the '
        f'PA-10 (0.1 m tool), a {PACE_PATH_LENGTH} m lemniscate on a plane tilted 20 deg, '
        '5 N, 2000 N/m, control 100 Hz, the arm following positions at 200 Hz (x0.5: '
        f'half speed), its commands delay [ms] late; peer = DlsPeer at {PEER_SPEED} m/s; '
        'ours = node defaults, ours_latency = + command_latency = the delay.',
        '',
    ]
    lines += markdown_table(
        (
            'start',
            'arm',
            'delay [ms]',
            'controller',
            'end',
            'task [s]',
            '/ peer',
            'tracking [s]',
            'RMS [mm]',
            'max [mm]',
            'passed [%]',
            'force p95 [%]',
            'lost contact',
            'step [ms]',
            'goals missed',
        ),
        (
            (
                r['start'],
                f'x{r["speed_scale"]:g}',
                f'{r["delay_ms"]:g}',
                r['controller'],
                r['phase'],
                f'{r["task_s"]:.1f}',
                f'{r["pace_ratio"]:.2f}',
                f'{r["tracking_s"]:.1f}',
                f'{r["rms_mm"]:.4f}',
                f'{r["max_mm"]:.3f}',
                f'{r["passed_fraction"] * 100:.1f}',
                f'{r["force_p95_pct"]:.2f}',
                'yes' if r['lost_contact'] else 'no',
                f'{r["step_ms_median"]:.3f}',
                '; '.join(r['missed']) or 'none',
            )
            for r in rows
        ),
    )
    write_results(PACE_OUT, 'results', lines, rows)
    return rows


def main_part_alone():
    """Run the part the command line names alone (C-F); False if it names none."""
    if '--over-topics' in sys.argv:
        main_over_topics(sys.argv[1:])
    elif '--pace' in sys.argv:
        main_pace()
    elif '--robot-data' in sys.argv:
        shapes = _option('--shapes', 'arc,figure_eight').split(',')
        tilts = [float(t) for t in _option('--tilts', '20,45').split(',')]
        main_robot_data(shapes, tilts)
    elif '--cases-only' in sys.argv:
        arms = int(sys.argv[sys.argv.index('--arms') + 1]) if '--arms' in sys.argv else 2
        main_cases(random_arms=arms)
    else:
        return False
    return True


def main():
    if main_part_alone():
        return
    robot = load_robot('pa10_thesis', 0.0)
    table, logs = {}, {}
    for name in ('Gamma1', 'Gamma1_bent', 'Gamma2'):
        logs[name] = {}
        for method in ('primal_dual', 'ours', 'ours_identity', 'dls'):
            table[(name, method)], logs[name][method] = run_table(name, method, robot)
            print(name, method, table[(name, method)], flush=True)
    radius, diverged_at = fixed_step_report(robot)
    plotted = plot_table(logs, OUT)
    force_rows = []
    for scenario_name in ('S1', 'S2', 'default'):
        for force_law in ('integral', 'tilt'):
            row = run_force(scenario_name, force_law)
            force_rows.append(row)
            print(row, flush=True)
    # The tilt law is an integral law in disguise: d(depth)/dt = -v sin(phi) ~
    # v pi k / (2 lambda_d) * depth error, i.e. a gain of 12.6 /s at 0.02 m/s, 2000 N/m, 5 N.
    matched_gain = 0.02 * np.pi * 2000.0 / (2 * 5.0)
    for force_law, gain in (('integral', 5.0), ('tilt', 5.0), ('integral', matched_gain)):
        row = run_force('default', force_law, depth_error=0.001, force_gain=gain)
        force_rows.append(row)
        print(row, flush=True)

    lines = [
        '# pa10_ik_node benchmark',
        '',
        'Command: `source ros2_ws/install/setup.bash && .venv/bin/python bench/bench_pa10_ik.py`',
        '',
        '## Table 7.1 (thesis PA-10 model `pa10_thesis`, T = 6 s, dt = 1 ms)',
        '',
    ]
    lines += markdown_table(
        (
            'trajectory',
            'method',
            'RMS position',
            'RMS orientation [rad]',
            'max position',
            'thesis position',
            'thesis orientation',
            'median step [ms]',
            'W fails on null(J) [steps]',
            'network unstable [steps]',
        ),
        (
            (
                name,
                method,
                f'{row["rms_position"]:.3g}',
                f'{row["rms_orientation"]:.3g}',
                f'{row["max_position"]:.3g}',
                f'{THESIS_TABLE[name][0]:.3g}',
                f'{THESIS_TABLE[name][1]:.3g}',
                f'{row["step_ms_median"]:.3f}',
                f'{row["null_space_failures"]} / {row["steps"]}',
                row['network_diverged'],
            )
            for (name, method), row in table.items()
        ),
    )
    lines += [
        '',
        "Units: the thesis model's length unit (its link lengths 1.8, 3.6, 0.6) "
        "and rad. primal_dual = the seed's network as published (no pose feedback), "
        'integrated exactly per step (one matrix exponential = the "iterations" of a '
        'step), W = diag(1,-1,-1,1,-1,1,1), K = 100, |W| where W is not positive on '
        'null(J); ours = closed-form KKT with the same W (same fallback) + pose '
        f'feedback {FEEDBACK_GAIN:g}/s; ours_identity = the same with W = I (the '
        'node default); dls = damping 0.05 + the same feedback. One '
        'solve per control step for every method.',
        '',
        f"Literal fixed-step rules (mu = eta = 0.02, K = 100) at Gamma1's start: "
        f'spectral radius {radius:.1f} (> 1: divergent); the iterate norm passes 1e10 '
        f'after {diverged_at} iterations.',
        '',
        '## Force tracking in the simulated contact (whole closed curves, ours, '
        '5 N desired, 0.02 m/s, 100 Hz, pressure noise of the scenario)',
        '',
        'force_law: integral = ours (depth = lambda_d / k_est + integral of the force '
        "error); tilt = the thesis's 7.3.15 rule (the motion PQ' tilted by phi into / "
        'out of the surface at every control step, tracking.tilted_motion).',
        '',
        'The last three rows: the waypoints 1 mm * sin(2 turns) off the surface along '
        'their approach axis (+-2 N of depth disturbance); force_gain only acts in '
        "the integral law (the tilt law's equivalent gain is v pi k / (2 lambda_d) = "
        f'{0.02 * np.pi * 2000.0 / 10.0:.1f} /s).',
        '',
    ]
    lines += markdown_table(
        (
            'scenario',
            'surface',
            'force_law',
            'force_gain [1/s]',
            'waypoint depth error [mm]',
            'length [m]',
            'end phase',
            'RMS lateral [mm]',
            'max lateral [mm]',
            'true force range [N]',
            'max force error [%]',
            'RMS force error [N]',
            'phi range [rad]',
            'median step [ms]',
        ),
        (
            (
                row['scenario'],
                row['surface'],
                row['force_law'],
                f'{row["force_gain"]:.3g}',
                f'{row["depth_error_mm"]:g}',
                f'{row["path_length_m"]:.3f}',
                row['phase'],
                f'{row["rms_lateral_mm"]:.4f}',
                f'{row["max_lateral_mm"]:.4f}',
                f'{row["true_force_min_N"]:.3f}..{row["true_force_max_N"]:.3f}',
                f'{row["max_force_error_pct"]:.2f}',
                f'{row["rms_force_error_N"]:.4f}',
                f'{row["phi_range_rad"][0]:.4f}..{row["phi_range_rad"][1]:.4f}',
                f'{row["step_ms_median"]:.3f}',
            )
            for row in force_rows
        ),
    )
    if plotted:
        lines += [
            '',
            'Plots: table71_Gamma1.png, table71_Gamma2.png (r_d, rdot_d, qdot, q '
            'of ours as figs 7.14-7.21, and the errors of every method).',
        ]
    write_results(
        OUT,
        'results',
        lines,
        {
            'table71': {f'{n}/{m}': r for (n, m), r in table.items()},
            'fixed_step_spectral_radius': radius,
            'fixed_step_diverged_at': diverged_at,
            'force_tracking': force_rows,
        },
    )


if __name__ == '__main__':
    main()
