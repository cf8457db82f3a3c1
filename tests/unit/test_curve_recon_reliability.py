"""Bad input to curve_recon_node's cores: implausible depth intrinsics and depth values
are refused with a reason (never an OverflowError or a normal made from them), and any
spacing in the parameter's range gives waypoints with proper rotations."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from curve_recon_node.waypoints import (
    bridge_gaps,
    check_depth_intrinsics,
    normals_from_depth,
    resample,
    stranded_runs,
    usable_depth,
    waypoint_frames,
    without_reversals,
)
from vgm_common.conversions import matrices_to_path
from vgm_common.errors import InvalidInput

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
W, H = 640, 480


def tilted_plane_depth(K, normal_cam, distance):
    """Depth (H, W) [m] of the plane n . x = distance seen by the pinhole K."""
    v, u = np.mgrid[0:H, 0:W]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], 2)
    return distance / (rays @ normal_cam)


def points_on_plane(normal_cam, distance, n=20):
    """Points of the plane in view (camera frame = base here)."""
    t = np.linspace(-0.05, 0.05, n)
    a = np.cross(normal_cam, [0, 1, 0])
    a /= np.linalg.norm(a)
    b = np.cross(normal_cam, a)
    return distance * normal_cam + t[:, None] * a + 0.5 * t[:, None] * b


def test_huge_intrinsics_are_refused_with_a_reason():
    depth = np.full((H, W), 0.5)
    huge = np.full((3, 3), 1e308)
    with pytest.raises(InvalidInput, match='finite|focal'):
        normals_from_depth(np.array([[0.0, 0.0, 0.5]]), depth, huge, np.eye(4))
    for bad in (
        np.diag([1e308, 1e308, 1.0]),
        np.diag([0.0, 500.0, 1.0]),
        np.array([[500.0, 0, 1e9], [0, 500, 240], [0, 0, 1]]),
        np.array([[500.0, 0, 320], [3, 500, 240], [0, 0, 1]]),
    ):
        with pytest.raises(InvalidInput):
            check_depth_intrinsics(bad, W, H)
    check_depth_intrinsics(K, W, H)


def test_negative_zero_and_huge_depths_give_no_normals():
    normal = np.array([0.3, -0.2, -1.0])
    normal /= np.linalg.norm(normal)
    distance = -0.5  # the plane faces the camera: n . x = -0.5 for x in front
    depth = tilted_plane_depth(K, normal, distance)
    points = points_on_plane(normal, distance)
    good = normals_from_depth(points, depth, K, np.eye(4), 9)
    # the true normal faces the camera (toward -z here), within a fraction of a degree
    assert np.all(np.isfinite(good))
    assert np.degrees(np.arccos(np.clip(good @ normal, -1, 1))).max() < 0.5
    for bad_value in (-0.5, 0.0, 1e30, np.inf):
        bad = np.full((H, W), bad_value)
        cleaned, removed = usable_depth(bad)
        assert np.isnan(cleaned).all() and sum(removed.values()) == H * W
        assert np.isnan(normals_from_depth(points, bad, K, np.eye(4), 9)).all()
    # a depth of some other surface (2 m, the waypoints at ~0.5 m) gives no normal either
    assert np.isnan(normals_from_depth(points, np.full((H, W), 2.0), K, np.eye(4))).all()
    # half the image unusable: the rest still gives the normals where it is valid
    mixed = depth.copy()
    mixed[:, : W // 2] = -1.0
    normals = normals_from_depth(points, mixed, K, np.eye(4), 9)
    u = K[0, 0] * points[:, 0] / points[:, 2] + K[0, 2]
    right = u > W // 2 + 8
    assert np.all(np.isfinite(normals[right])) and np.all(np.isnan(normals[u < W // 2 - 8]))


@pytest.mark.parametrize('spacing', [1e-4, 0.005, 0.2, 0.5, 1.0])
@pytest.mark.parametrize('closed', [True, False])
def test_any_spacing_gives_proper_rotations(spacing, closed):
    t = np.linspace(0, 2 * np.pi if closed else np.pi, 400, endpoint=not closed)
    loop = np.column_stack([0.6 + 0.08 * np.cos(t), 0.05 * np.sin(t), 0.3 + 0.01 * np.sin(2 * t)])
    waypoints = resample(loop, closed, spacing)
    assert len(waypoints) >= (3 if closed else 2)
    frames = waypoint_frames(waypoints, closed)
    R = frames[:, :3, :3]
    np.testing.assert_allclose(
        R @ np.swapaxes(R, 1, 2), np.tile(np.eye(3), (len(R), 1, 1)), atol=1e-9
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    assert len(matrices_to_path(frames, 1, 'base_link').poses) == len(waypoints)


def test_a_lone_point_between_two_gaps_is_stranded_and_the_loop_stays_closed():
    """A wrong root left alone (its neighbours removed as outliers) sits between two
    jumps; kept, it opened the quick scene's loop on some noise draws."""
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    loop = np.column_stack([0.1 * np.cos(t), 0.1 * np.sin(t), np.zeros_like(t)])
    points = np.delete(loop, np.r_[20:25, 26:31], axis=0)  # a lone point at t[25]...
    points[20] += [0.0, 0.0, 0.06]  # ...60 mm off the curve
    stranded = stranded_runs(points, True, max_gap_m=0.04)
    assert np.flatnonzero(stranded).tolist() == [20]
    # one run, a gap within the limit, or every run short: nothing is stranded
    assert not stranded_runs(loop, True, 0.04).any()
    assert not stranded_runs(np.delete(points, 20, axis=0), True, 0.04).any()
    assert not stranded_runs(points[18:23], False, 0.04).any()


@pytest.mark.parametrize('frame', [2, 6, 9])
def test_noise_draws_that_opened_the_quick_loop_give_one_closed_curve(frame):
    """The quick scenario's captures 2, 6 and 9 (true cameras, the simulator's noise of
    that frame): one closed loop covering the whole curve (every true point within 5 mm
    of the waypoints' polyline, as the closed-loop demo asks)."""
    from curve_recon_node.pipeline import ReconstructionSettings, reconstruct_capture
    from sensor_sim.curves import curve_polylines
    from sensor_sim.render import SceneRenderer, add_noise
    from sensor_sim.scenario import load_scenario, resolve_scenario_path

    scenario = load_scenario(resolve_scenario_path('quick'))
    renderer = SceneRenderer(scenario)
    images = {
        name: add_noise(
            renderer.scene_image(name),
            scenario.noise.image_sigma,
            np.random.default_rng([scenario.seed, frame, i]),
        )
        for i, name in enumerate(('left', 'right', 'aux'))
    }
    result = reconstruct_capture(images, scenario.cameras, ReconstructionSettings())
    assert result.closed and result.stats['segments'] == 1
    truth = np.vstack(curve_polylines(scenario.curve, scenario.surface))
    loop = np.vstack([result.waypoints_base, result.waypoints_base[:1]])
    dense = np.vstack(
        [a + np.linspace(0, 1, 20)[:, None] * (b - a) for a, b in zip(loop[:-1], loop[1:])]
    )
    assert cKDTree(dense).query(truth)[0].max() < 5e-3


@pytest.mark.parametrize('closed', [False, True])
def test_a_hairpin_of_the_smoothed_path_is_removed(closed):
    """A local fit overshooting in a sparse stretch went out and back (cone_lsq on the
    default scene, some noise draws): resampled through, two waypoints came 0.6 mm apart
    at a 5 mm spacing."""
    t = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    loop = np.column_stack([0.1 * np.cos(t), 0.1 * np.sin(t), np.zeros_like(t)])
    hairpin = np.insert(loop, 31, loop[31] + 0.6 * (loop[31] - loop[30]), axis=0)
    hairpin[32] = loop[31] + 0.5 * (loop[31] - loop[30])  # ...and back a little
    kept = without_reversals(hairpin, closed)
    assert len(kept) == len(loop)
    steps = np.diff(kept, axis=0)
    assert np.all(np.sum(steps[1:] * steps[:-1], axis=1) > 0)
    np.testing.assert_array_equal(without_reversals(loop, closed), loop)


def test_a_hole_in_the_points_is_bridged_along_the_bend_not_across_it():
    """A 2 cm hole in a 3 cm circle: the chord would pass 1.65 mm inside it; the Hermite
    arc stays within 0.15 mm, keeps every given point, and leaves a curve without holes
    as it is. An open end next to a hole takes the chord's direction, never the other
    end's."""
    radius = 0.03
    angle = np.arange(0, 2 * np.pi, 1e-3 / radius)
    circle = np.column_stack([radius * np.cos(angle), radius * np.sin(angle), 0 * angle])
    hole = (angle > 1.0) & (angle < 1.0 + 0.02 / radius)
    given = circle[~hole]
    bridged = bridge_gaps(given, True, 0.01)
    off = np.abs(np.linalg.norm(bridged[:, :2], axis=1) - radius)
    assert off.max() < 1.5e-4 and len(bridged) > len(given)
    assert all(np.min(np.linalg.norm(bridged - p, axis=1)) == 0 for p in given)
    np.testing.assert_array_equal(bridge_gaps(circle, True, 0.01), circle)

    arc = circle[angle < 3.0]
    open_hole = np.vstack([arc[:1], arc[15:]])  # the first point 15 mm from the rest
    bridged = bridge_gaps(open_hole, False, 0.01)
    assert np.linalg.norm(bridged[1:] - bridged[:-1], axis=1).max() < 0.01
    assert np.all(np.linalg.norm(bridged[:, :2], axis=1) <= radius + 1e-12)
