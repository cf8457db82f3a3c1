"""curve_recon_node's ReconstructionSession without ROS: a capture of the quick scenario
(true cameras) is reconstructed within a millimetre of the true curve and published with
the base's -z approach; a fused depth (the true surface, in a rectified frame) that
comes later, first without then with its intrinsics, makes it republish with approach
axes along the true surface normals; a chart capture, an image of the wrong size, an
undecodable image and a capture without a curve are answered with their reasons, and
the ~/reconstruct calls time out on the injected clock."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from curve_recon_node.pipeline import ReconstructionSettings
from curve_recon_node.session import CHART_POSE_GRACE, ReconstructionSession
from harness import ManualClock
from vgm_common.errors import InvalidInput

NAMES = ('left', 'right', 'aux')


@pytest.fixture(scope='module')
def quick():
    """The quick scenario's renderer, cameras, noisy grey images and dense true curve."""
    from sensor_sim.render import SceneRenderer, add_noise
    from sensor_sim.scenario import load_scenario, resolve_scenario_path

    scenario = load_scenario(resolve_scenario_path('quick'))
    renderer = SceneRenderer(scenario)
    images = {
        name: add_noise(
            renderer.scene_image(name), scenario.noise.image_sigma, np.random.default_rng(i)
        ).astype(float)
        for i, name in enumerate(NAMES)
    }
    truth = np.vstack(renderer.curve_polylines_base())
    return SimpleNamespace(scenario=scenario, renderer=renderer, images=images, truth=truth)


def parameters():
    return SimpleNamespace(
        use_depth_normals=True, normal_window_px=15, method='ray_roots', degree=2
    )


def new_session(clock=None):
    """A session whose chart-pose grace is recorded, not waited."""
    waits = []
    session = ReconstructionSession(
        parameters(), clock or ManualClock(10.0), lambda s: waits.append(s) or False
    )
    return session, waits


def take(session, stamp_ns):
    """The job of capture ``stamp_ns``, wanted as after a calibration change."""
    session.scheduler.calibration_changed()
    job, names = session.take_capture(stamp_ns, NAMES, NAMES, views=3, aux_wait=2.0)
    assert names == NAMES
    return job


def rectified_left_depth(quick):
    """The true surface's depth [m] as seen by an undistorted camera with the left
    camera's K and pose (rectification R = I): (H, W), NaN where unseen."""
    left = quick.scenario.cameras['left']
    hit = quick.renderer.hit_points_base('left').reshape(-1, 3)
    hit = hit[np.all(np.isfinite(hit), axis=1)]
    x = left.to_camera(hit)
    u = np.round(left.K[0, 0] * x[:, 0] / x[:, 2] + left.K[0, 2]).astype(int)
    v = np.round(left.K[1, 1] * x[:, 1] / x[:, 2] + left.K[1, 2]).astype(int)
    inside = (u >= 0) & (u < left.width) & (v >= 0) & (v < left.height)
    depth = np.full((left.height, left.width), np.nan)
    depth[v[inside], u[inside]] = x[inside, 2]
    return depth


def test_a_capture_is_published_then_republished_with_depth_normals(quick):
    from sensor_sim.surfaces import normal_base

    session, waits = new_session()
    cameras = {name: quick.scenario.cameras[name] for name in NAMES}
    left = SimpleNamespace(camera=cameras['left'], R=np.eye(3))
    job = take(session, 7)
    outcome = session.reconstruct(
        job, quick.images, np.asarray, cameras, ReconstructionSettings(), left
    )
    assert waits == [CHART_POSE_GRACE] and outcome.success and not outcome.rejections
    sent = outcome.publication
    assert sent.stamp_ns == 7 and sent.normals_source == 'base -z (no depth normals)'
    assert outcome.message.startswith(f'published {len(sent.frames_base)} waypoints (closed')
    assert outcome.log.endswith('approach from base -z (no depth normals)')
    level, _, values = outcome.report
    assert level == 'ok' and values['stamp_ns'] == 7 and values['method'] == 'ray_roots'
    # the waypoints within a millimetre of the true curve (RMS; measured 0.2-0.3 mm)
    distance = cKDTree(quick.truth).query(sent.frames_base[:, :3, 3])[0]
    assert np.sqrt(np.mean(distance**2)) < 1e-3
    assert np.all(sent.frames_base[:, 2, 2] < -0.5)  # z: the base's -z made orthogonal
    assert session.scheduler.take(8) is None  # succeeded: no more automatic attempts

    # the depth comes before its intrinsics: it waits; intrinsics of another stamp
    # leave it unused; the next depth image, its intrinsics known, is used: the
    # waypoints are to be republished
    depth = rectified_left_depth(quick)
    K, size = cameras['left'].K, (cameras['left'].width, cameras['left'].height)
    assert not session.add_depth(depth, 20).republish
    stale = session.depth_intrinsics(K, *size, stamp_ns=19)
    assert not stale.republish and 'of its stamp came: not used' in str(stale.rejections[0][1])
    assert session.add_depth(depth, 21).republish
    again = session.republish(left)
    assert again.success and again.publication.stamp_ns == 7
    assert again.log.startswith('fused depth arrived: republished')
    frames = again.publication.frames_base
    # z = -normal made orthogonal to x, against the true surface normal at the waypoint
    x, z = frames[:, :3, 0], frames[:, :3, 2]
    normal = normal_base(quick.scenario.surface, frames[:, :3, 3])
    expected = -normal + np.sum(normal * x, axis=1, keepdims=True) * x
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(np.sum(z * expected, axis=1), -1.0, 1.0)))
    assert np.median(angle) < 2.0 and np.percentile(angle, 95) < 5.0
    assert session.republish(left).publication is None  # published with normals already


def test_captures_that_cannot_be_reconstructed_say_why(quick):
    clock = ManualClock(10.0)
    session, _ = new_session(clock)
    cameras = {name: quick.scenario.cameras[name] for name in NAMES}
    settings = ReconstructionSettings()
    got = []
    assert session.scheduler.add_call(lambda *answer: got.append(answer), timeout=5.0) is None
    # the chart's pose came after the capture was taken: its call waits for the next
    job = take(session, 1)
    session.scheduler.chart_shown(1)
    chart = session.reconstruct(job, quick.images, np.asarray, cameras, settings, None)
    assert not chart.success and chart.message == 'chart capture' and job.calls == []
    assert session.scheduler.waiting == 1

    def undecodable(image):
        raise InvalidInput('expected a grey image', key='encoding')

    job = take(session, 2)
    bad = session.reconstruct(job, quick.images, undecodable, cameras, settings, None)
    assert bad.message == '/stereo/left/image_raw: expected a grey image'
    assert bad.rejections[0][0] == '/stereo/left/image_raw' and bad.publication is None
    small = {**quick.images, 'aux': quick.images['aux'][:-10]}
    wrong = session.reconstruct(take(session, 3), small, np.asarray, cameras, settings, None)
    assert wrong.rejections[0][0] == '/aux/image_raw' and 'camera_info says' in wrong.message
    blank = {name: np.full_like(image, 128.0) for name, image in quick.images.items()}
    none = session.reconstruct(take(session, 4), blank, np.asarray, cameras, settings, None)
    assert none.message.startswith('no curve: no curve in the left image')
    assert not none.success and session.last is None
    # a waiting call times out on the session's clock, naming what is not calibrated
    session.scheduler.add_call(lambda *answer: got.append(answer), timeout=5.0)
    clock.now += 5.0
    expired, message = session.expired_calls(['aux'], 5.0)
    assert (
        len(expired) == 1 and message == 'no synchronized capture within 5 s (not calibrated: aux)'
    )
    level, message, values = session.status(['aux'], 3, 0, {'matched': 4}, 0)
    assert level == 'warn' and 'aux' in message
    assert values['skipped_chart_captures'] == 1 and values['depth'] == 'no'
