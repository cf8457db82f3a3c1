"""The demo's report and live line say one thing each: the tool path the summary
table measures is the one curve.png plots (beside the 3D distance, labelled), depth.png
shows the truth and each estimate's error by the table's measure, 3D axes are labelled,
and the live line names its measure and never prints NaN."""

import sys

import matplotlib.pyplot as plt
import numpy as np
import pytest

from harness import REPO_ROOT, SCENARIO_DIR
from sensor_sim.curves import curve_points_base
from sensor_sim.scenario import load_scenario
from sensor_sim.surfaces import normal_base

sys.path.insert(0, str(REPO_ROOT / 'scripts'))
import demo  # noqa: E402
import demo_evaluation as evaluation  # noqa: E402

PRESSING_M = 0.0025  # [m] 5 N into 2000 N/m


@pytest.fixture(scope='module')
def scenario():
    return load_scenario(SCENARIO_DIR / 'quick.yaml')


def test_the_live_line_names_its_measure_and_prints_no_nan():
    assert 'nan' not in demo.tracking_line({})
    approach = {'phase': 'approach', 'progress': '0.0', 'force_N': '0.0'}
    assert 'nan' not in demo.tracking_line({**approach, 'position_error_m': 'nan'})
    line = demo.tracking_line({**approach, 'phase': 'tracking', 'position_error_m': '0.00005'})
    assert f'{demo.LIVE_ERROR} 0.05 mm' in line
    assert any(demo.LIVE_ERROR in name for name, _ in demo.MEASURES)


def test_the_curve_figure_plots_the_table_s_tool_path_and_labels_both(scenario):
    curve = curve_points_base(scenario.curve, scenario.surface)
    pressed = curve - PRESSING_M * normal_base(scenario.surface, curve)  # tip into surface
    tracking = evaluation.tracking_errors(
        pressed, [curve], [5.0] * len(curve), 5.0, scenario.surface
    )
    on_surface, in_3d = evaluation.tool_path_distances(pressed, [curve], scenario.surface)
    assert tracking['path_rms_m'] == pytest.approx(np.sqrt(np.mean(on_surface**2)))
    assert tracking['path_rms_m'] < 1e-4 and in_3d.mean() == pytest.approx(PRESSING_M, rel=0.05)

    figures = {}
    data = {
        'curve': [curve],
        'waypoints': curve[::10],
        'tool_tracking': pressed,
        'tool_distances': (on_surface, in_3d),
    }
    demo.plot_curve(data, lambda fig, file, title, tight=True: figures.update({file: fig}))
    ax3d, ax = figures['curve.png'].axes
    assert (ax3d.get_xlabel(), ax3d.get_ylabel(), ax3d.get_zlabel()) == ('x [m]', 'y [m]', 'z [m]')
    labels = [line.get_label() for line in ax.get_lines()]
    rms_mm = tracking['path_rms_m'] * 1e3
    assert any(f'tip on the surface to true curve (RMS {rms_mm:.2f} mm)' in s for s in labels)
    assert any('pressing included' in label for label in labels)
    plt.close('all')


def test_the_depth_figure_shows_the_truth_and_each_estimate_s_error(scenario):
    shape = (60, 80)
    P = np.array([[100.0, 0, 40, 0], [0, 100.0, 30, 0], [0, 0, 1, 0]])
    T_base_left = scenario.cameras['left'].T_base_camera
    fused = np.full(shape, 0.7)
    heights = evaluation.depth_heights(fused, P, np.eye(3), T_base_left, scenario.surface)
    stats = evaluation.depth_errors(fused, P, np.eye(3), T_base_left, scenario.surface)
    assert stats['median_abs_m'] == pytest.approx(np.nanmedian(np.abs(heights)))
    figures = {}
    data = {
        'depth': {'/depth/fused': fused},
        'depth_heights': {'/depth/fused': heights},
        'depth_true': np.full(shape, 0.75),
    }
    demo.plot_depth(data, lambda fig, file, title, tight=True: figures.update({file: fig}))
    titles = [ax.get_title() for ax in figures['depth.png'].axes]
    assert 'true depth [m]' in titles
    assert any(f'median |h| {stats["median_abs_m"] * 1e3:.1f} mm' in title for title in titles), (
        titles
    )
    plt.close('all')
