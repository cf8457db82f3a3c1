"""curve_recon_node cores beyond single conics: curve extraction from images (subpixel,
chains), piecewise fits, piecewise ray-roots / cone least-squares reconstruction of a
loop no single conic fits, two-view ambiguity, ordering, resampling, orientation and
normals from depth; all against synthetic ground truth."""

import cv2
import numpy as np
import pytest

from curve_recon_node.curve_extraction import extract_chains, link_chains
from curve_recon_node.piecewise import (
    PiecewiseCurve,
    View,
    _real_positive_roots,
    pinv_solve,
    reconstruct_ray_roots,
    refine_points,
    select_candidates,
)
from curve_recon_node.thesis import reconstruct_cone_lsq
from curve_recon_node.waypoints import (
    normals_from_depth,
    open_at_largest_gap,
    resample,
    smooth_along_curve,
    split_at_gaps,
    waypoint_frames,
)
from vgm_common.camera_model import PinholeCamera
from vgm_common.geometry import look_at_rotation, make_transform

F_PX = 600.0
K = np.array([[F_PX, 0.0, 320.0], [0.0, F_PX, 240.0], [0.0, 0.0, 1.0]])
TARGET = np.array([0.6, 0.0, 0.3])
CENTRES = [(0.95, -0.07, 0.92), (0.95, 0.07, 0.92), (0.40, 0.45, 0.95)]  # default rig


def cameras():
    return [
        PinholeCamera(
            640,
            480,
            K,
            np.zeros(5),
            make_transform(look_at_rotation(c, TARGET, up=(0.0, 0.0, 1.0)), c),
        )
        for c in CENTRES
    ]


def loop_points(t):
    """A non-planar closed loop (a 'saddle' ellipse, 0.24 x 0.16 m) no conic fits."""
    return TARGET + np.column_stack(
        [0.12 * np.cos(t) + 0.02 * np.cos(2 * t), 0.08 * np.sin(t), 0.03 * np.cos(2 * t)]
    )


def ellipse_image(centre, axes, angle_deg, size=(480, 640), noise=1.0, seed=0, closed=True):
    """A dark antialiased ellipse (or arc; cv2 thickness 3: 5 px wide at half depth) on a
    shaded background, and its dense true points (M, 2) [px]."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0 : size[0], 0 : size[1]]
    image = 120.0 + 0.1 * u + 0.05 * v
    t = np.linspace(0, 2 * np.pi if closed else np.pi, 4000)
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    local = np.column_stack([axes[0] * np.cos(t), axes[1] * np.sin(t)])
    truth = centre + local @ np.array([[c, s], [-s, c]])
    mask = np.zeros(size, np.uint8)
    cv2.polylines(
        mask, [np.round(truth * 256).astype(np.int32)], closed, 255, 3, cv2.LINE_AA, shift=8
    )
    image *= 1.0 - 0.6 * mask / 255.0
    image += rng.normal(scale=noise, size=size)
    return np.clip(np.round(image), 0, 255).astype(np.uint8), truth


def test_extraction_finds_subpixel_ordered_closed_chain():
    image, truth = ellipse_image(np.array([300.3, 250.7]), (120.0, 70.0), 25.0)
    chains = extract_chains(image, line_width_px=3.0)
    assert len(chains) == 1 and chains[0].closed
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(truth).query(chains[0].pixels)
    # cv2's antialiased line is not exactly symmetric: 0.1 px RMS is its own accuracy
    assert np.sqrt(np.mean(distance**2)) < 0.15 and distance.max() < 0.5
    # ordered: consecutive points ~1 px apart, the truth index advances monotonically
    steps = np.linalg.norm(np.diff(chains[0].pixels, axis=0), axis=1)
    assert steps.max() < 2.0
    perimeter = np.sum(np.linalg.norm(np.diff(truth, axis=0), axis=1))
    assert chains[0].length_px == pytest.approx(perimeter, rel=0.05)


def test_extraction_open_arc_is_trimmed_and_blank_or_chart_images_give_nothing():
    image, truth = ellipse_image(np.array([320.0, 240.0]), (150.0, 90.0), 0.0, closed=False)
    # cv2's thickness-3 antialiased line is 5 px wide at half depth (measured across it):
    # the end trim follows the ridge strength at the given width (told 3 px, the
    # wider line's round cap keeps its strength and leaves a hook 3.6 px off)
    chains = extract_chains(image, line_width_px=5.0)
    assert len(chains) == 1 and not chains[0].closed
    from scipy.spatial import cKDTree

    distance = cKDTree(truth).query(chains[0].pixels)[0]
    # trimmed end caps: nothing left off the curve (measured 0.24 px)
    assert distance.max() < 0.5
    blank, _ = ellipse_image(np.array([320.0, 240.0]), (150.0, 90.0), 0.0, noise=2.0)
    blank = np.clip(
        blank.astype(float) * 0
        + 140
        + np.random.default_rng(1).normal(scale=2.0, size=blank.shape),
        0,
        255,
    )
    assert extract_chains(blank) == []
    # a chessboard (what sensor_sim shows during calibration) has edges, not thin lines
    board = np.kron((np.indices((8, 10)).sum(axis=0) % 2) * 200.0 + 30.0, np.ones((40, 40)))
    board = cv2.GaussianBlur(board, (0, 0), 0.8)[:480, :640]
    assert all(c.length_px < 60 for c in extract_chains(board))


def test_link_chains_orders_shuffled_points_of_a_circle():
    t = np.linspace(0, 2 * np.pi, 300, endpoint=False)
    circle = np.column_stack([100 + 50 * np.cos(t), 100 + 50 * np.sin(t)])
    order = np.random.default_rng(3).permutation(len(t))
    chains = link_chains(circle[order], link_radius_px=2.0)
    assert len(chains) == 1 and chains[0].closed and len(chains[0].pixels) == 300
    # the chain walks the circle: the angle changes by one step between neighbours
    angles = np.unwrap(np.arctan2(chains[0].pixels[:, 1] - 100, chains[0].pixels[:, 0] - 100))
    np.testing.assert_allclose(np.abs(np.diff(angles)), 2 * np.pi / 300, rtol=1e-6)


def test_real_positive_roots_match_numpy():
    rng = np.random.default_rng(4)
    poly = rng.normal(size=(50, 4))
    poly[:5, 3] = 0.0  # some of lower degree
    rows, roots = _real_positive_roots(poly)
    for i in range(50):
        expected = np.roots(np.trim_zeros(poly[i, ::-1], 'f'))
        expected = np.sort(expected.real[(np.abs(expected.imag) < 1e-9) & (expected.real > 0)])
        np.testing.assert_allclose(np.sort(roots[rows == i]), expected, rtol=1e-8)


def test_real_positive_roots_of_quadratics_and_lines_match_numpy():
    """The closed form for degrees 1 and 2, incl. (nearly) double roots."""
    rng = np.random.default_rng(6)
    poly = rng.normal(size=(400, 3))
    poly[:50, 2] = 0.0  # lines
    c0, c2 = np.abs(poly[50:150, 0]), np.abs(poly[50:150, 2])
    poly[50:150, 1] = -2.0 * np.sqrt(c0 * c2)  # double root sqrt(c0 / c2) > 0
    poly[50:150, 0], poly[50:150, 2] = c0, c2
    rows, roots = _real_positive_roots(poly)
    for i in range(len(poly)):
        expected = np.roots(np.trim_zeros(poly[i, ::-1], 'f'))
        if 50 <= i < 150:  # rounding may make the double root a close complex pair
            np.testing.assert_allclose(
                roots[rows == i], [np.sqrt(c0[i - 50] / c2[i - 50])] * 2, rtol=1e-6
            )
            continue
        expected = np.sort(expected.real[(np.abs(expected.imag) < 1e-9) & (expected.real > 0)])
        np.testing.assert_allclose(np.sort(roots[rows == i]), expected, rtol=1e-8)


def test_real_positive_roots_of_cubics_against_their_true_roots():
    """The closed form for cubics: built from known roots (three real over four decades,
    one real and a complex pair, a double root), then scaled and tested."""
    rng = np.random.default_rng(8)
    n = 2000
    real = np.sort(np.exp(rng.uniform(np.log(1e-2), np.log(1e2), size=(n, 3))), axis=1)
    real *= rng.choice([-1.0, 1.0], size=(n, 3))
    pair = rng.uniform(0.5, 3.0, size=n) * real[:, 0] + 1j * rng.uniform(0.05, 2.0, size=n)
    kinds = np.arange(n) % 3  # 0: three real, 1: one real and a pair, 2: a double root
    roots = np.where(
        kinds[:, None] == 0,
        real,
        np.where(
            kinds[:, None] == 1,
            np.column_stack([real[:, 0], pair, np.conj(pair)]),
            np.column_stack([real[:, 0], real[:, 1], real[:, 1]]),
        ),
    )
    poly = np.array([np.poly(r)[::-1].real for r in roots]) * rng.uniform(0.1, 10, size=(n, 1))
    rows, found = _real_positive_roots(poly)
    for i in range(n):
        true = np.sort(roots[i].real[(roots[i].imag == 0) & (roots[i].real > 0)])
        got = np.sort(found[rows == i])
        if kinds[i] == 2 and real[i, 1] > 0:  # a double root: maybe a close complex pair
            assert len(got) == len(true)
            np.testing.assert_allclose(got, true, rtol=1e-6)
        else:
            np.testing.assert_allclose(got, true, rtol=1e-9)


@pytest.mark.parametrize('views', [3, 2])
def test_pinv_solve_matches_numpy_pinv(views):
    """Batched closed-form minimum-norm solutions against np.linalg.pinv, for Jacobians of
    rank 3, 2 (the refinement's usual case: the tangent is a near-null direction), 1, 0."""
    rng = np.random.default_rng(7)
    for rank in (3, 2, 1, 0):
        basis = rng.normal(size=(300, rank, 3))
        J = np.einsum('qvr,qri->qvi', rng.normal(size=(300, views, rank)), basis)
        J += 1e-9 * rng.normal(size=J.shape)  # below rcond: dropped, as by pinv
        J *= np.exp(rng.uniform(-5, 5, size=(300, 1, 1)))
        r = rng.normal(size=(300, views))
        expected = np.einsum('qiv,qv->qi', np.linalg.pinv(J, rcond=1e-2), r)
        got = pinv_solve(J, r, rcond=1e-2)
        scale = np.maximum(np.linalg.norm(expected, axis=1, keepdims=True), 1e-300)
        # rows whose singular value ratio sits at rcond may legitimately differ
        s = np.linalg.svd(J, compute_uv=False)
        clear = np.all(np.abs(s / s[:, :1] - 1e-2) > 1e-4, axis=1) | (s[:, 0] == 0)
        assert clear.mean() > 0.95
        np.testing.assert_allclose(
            got[clear] / scale[clear], expected[clear] / scale[clear], atol=1e-7
        )


def make_views(sigma_px=0.0, n=800, seed=0, fit_tolerance_px=0.05):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    truth = loop_points(t)
    rng = np.random.default_rng(seed)
    views = []
    for camera in cameras():
        pixels, depth = camera.project(truth)
        assert np.all(depth > 0)
        pixels = pixels + rng.normal(scale=sigma_px, size=pixels.shape) if sigma_px else pixels
        curve = PiecewiseCurve(camera.undistort_pixels(pixels), True, 2, F_PX, fit_tolerance_px)
        views.append(View(curve, camera))
    return views, truth


def test_piecewise_fit_splits_a_loop_no_conic_fits():
    views, _ = make_views()
    for view in views:
        curve = view.curve
        single = PiecewiseCurve(curve.xy, True, 2, F_PX, fit_tolerance_px=np.inf)
        assert len(single.pieces) == 1 and single.rms_px > 0.3  # one conic is poor
        assert len(curve.pieces) > 2
        # split until 0.05 px, unless a piece got too short to split further (where the
        # aux view sees the loop nearly edge-on and its image turns sharply)
        piece_rms = np.array([p.rms_px for p in curve.pieces])
        assert np.mean(piece_rms <= 0.05) >= 0.85 and np.median(piece_rms) < 0.05
        # every chain point is in some piece; pieces overlap
        assert np.all(curve.member.any(axis=0)) and curve.member.sum() > len(curve.xy)
        # distances: 0 on the chain, about the offset off it (first order)
        # (over every chain point: the short unsplittable pieces of the aux view's sharp
        # turns reach 0.13 px with either fit, Taubin's or the algebraic one; 0.165 px
        # since pieces with a steady bias are split too, which leaves shorter ones there)
        on_chain = np.abs(curve.distance(curve.xy)[0]) * F_PX
        assert np.sqrt(np.mean(on_chain**2)) < 0.05 and on_chain.max() < 0.18
        distance, direction = curve.distance(curve.xy[::40])
        moved = curve.xy[::40] + 0.5 / F_PX * direction
        np.testing.assert_allclose(np.median(curve.distance(moved)[0] * F_PX), 0.5, atol=0.02)
        # (90th percentile 0.12 px before pieces with a steady bias were split too, 0.17
        # after: two samples at the aux view's sharp turns, whose shorter pieces' curves
        # bend away off the chain; views 1 and 2: 0.04 -> 0.01 px)
        assert np.percentile(np.abs(curve.distance(moved)[0] * F_PX - 0.5), 90) < 0.2


@pytest.mark.parametrize('method', ['ray_roots', 'cone_lsq'])
def test_piecewise_reconstruction_noise_free(method):
    views, truth = make_views()
    size = np.ptp(truth, axis=0).max()
    if method == 'ray_roots':
        points, info = reconstruct_ray_roots(*views, tol3_px=0.5)
        # each kept point lies on its own view-1 ray: compare with that sample's truth
        errors = np.linalg.norm(points - truth[info['sample_index']], axis=1)
        assert len(points) >= 0.9 * len(truth)
    else:
        points, info = reconstruct_cone_lsq(
            *views, tol3_px=0.5, seed_depths=np.geomspace(0.3, 3.0, 8)
        )
        assert len(points) >= 0.6 * len(truth)  # flat minima near tangencies rejected
        errors = None
    from scipy.spatial import cKDTree

    dense = loop_points(np.linspace(0, 2 * np.pi, 200000))
    distance = cKDTree(dense).query(points)[0]
    # issue goal: noise-free points within 1e-6 of the curve's size (met by single conics,
    # test_curve_recon.py); here the piecewise conics approximate the image curves to
    # 0.05 px, which bounds the error instead. Three cones also meet at isolated points
    # off the curve, which the third view cannot remove (the smoothing's outlier test
    # does): allow 1 % of such points.
    assert np.percentile(distance, 99) < 1e-2 * size
    assert np.median(distance) < 1e-3 * size
    if errors is not None:
        assert np.median(errors) < 1e-3 * size
    # refinement over all three views brings every point closer to all image curves
    refined, residuals, before = refine_points(points, views)
    assert np.sqrt(np.mean(residuals**2)) < 0.05
    assert np.sqrt(np.mean(residuals**2)) < np.sqrt(np.mean(before**2))
    assert np.all(np.isfinite(refined))


def test_piecewise_reconstruction_with_pixel_noise_and_two_views():
    views, truth = make_views(sigma_px=0.1, seed=5, fit_tolerance_px=0.15)
    points, info = reconstruct_ray_roots(*views, tol3_px=2.0)
    refined, _, _ = refine_points(points, views)
    from scipy.spatial import cKDTree

    dense = loop_points(np.linspace(0, 2 * np.pi, 200000))
    distance = cKDTree(dense).query(refined)[0]
    # [m] 0.1 px noise at 0.8 m; isolated triple-cone points (see above) excepted
    assert np.median(distance) < 5e-4 and np.percentile(distance, 95) < 2e-3
    assert len(points) + info['n_rejected_view3'] + info['n_without_candidates'] == len(truth)
    # two views: only unique intersections are kept; the rest is reported as ambiguous
    points2, info2 = reconstruct_ray_roots(views[0], views[1])
    assert info2['n_ambiguous'] > 0
    assert len(points2) + info2['n_ambiguous'] + info2['n_without_candidates'] == len(truth)
    assert np.sqrt(np.mean(cKDTree(dense).query(points2)[0] ** 2)) < 2e-3


def test_smoothing_ordering_and_resampling():
    t = np.linspace(0, 2 * np.pi, 500, endpoint=False)
    truth = loop_points(t)
    rng = np.random.default_rng(6)
    noisy = truth + rng.normal(scale=2e-4, size=truth.shape)
    noisy[100] += [0.01, 0.0, 0.0]  # an outlier
    smoothed, kept = smooth_along_curve(noisy, True, 0.02, np.arange(500.0), period=500)
    assert not kept[100] and kept.sum() >= 495
    from scipy.spatial import cKDTree

    dense = loop_points(np.linspace(0, 2 * np.pi, 200000))
    assert np.sqrt(np.mean(cKDTree(dense).query(smoothed)[0] ** 2)) < 1.5e-4  # noise 2e-4
    waypoints = resample(smoothed, True, 0.005)
    steps = np.linalg.norm(np.diff(np.vstack([waypoints, waypoints[:1]]), axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.005, rtol=0.05)
    assert np.linalg.norm(waypoints[0] - waypoints[-1]) > 0.004  # first not repeated
    # a gap wider than allowed opens the loop there, rolled to start after the gap
    cut = np.delete(truth, np.arange(200, 260), axis=0)
    opened, closed, parameter = open_at_largest_gap(cut, True, 0.02)
    assert not closed and np.allclose(opened[0], truth[260])
    assert np.all(np.diff(parameter) > 0)
    # two gaps: the open sequence splits into runs, never bridged
    runs = split_at_gaps(np.delete(opened, np.arange(100, 150), axis=0), 0.02)
    assert [len(r) for r in runs] == [100, len(opened) - 150]


def test_frames_and_normals_from_a_plane_depth():
    t = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    points = loop_points(t)
    frames = waypoint_frames(points, True)
    R = frames[:, :3, :3]
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    tangent = np.roll(points, -1, axis=0) - np.roll(points, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    np.testing.assert_allclose(R[:, :, 0], tangent, atol=1e-12)
    assert np.all(R[:, 2, 2] < -0.75)  # base -z made orthogonal to x (slopes < 0.85)
    # a tilted plane seen by a rectified camera: normals exact, facing the camera
    camera = cameras()[0]
    T_base_rect = camera.T_base_camera
    normal_base = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    n_rect = T_base_rect[:3, :3].T @ normal_base
    p0_rect = T_base_rect[:3, :3].T @ (TARGET - T_base_rect[:3, 3])
    v, u = np.mgrid[0:480, 0:640]
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones(u.shape)], 2)
    depth = (n_rect @ p0_rect) / (rays @ n_rect)  # z of the ray-plane intersection
    on_plane = points - ((points - TARGET) @ normal_base)[:, None] * normal_base
    normals = normals_from_depth(on_plane, depth, K, T_base_rect, window_px=7)
    np.testing.assert_allclose(normals, np.tile(normal_base, (100, 1)), atol=1e-6)
    frames = waypoint_frames(on_plane, True, -normals)
    np.testing.assert_allclose(
        frames[:, :3, 2] @ normal_base,
        -np.sqrt(1 - (frames[:, :3, 0] @ normal_base) ** 2),
        atol=1e-9,
    )


def test_third_view_rejects_a_root_on_a_pieces_continuation_off_its_chain():
    """A view-3 piece's implicit curve runs on beyond the stretch of chain it was fitted
    to: a spurious root projecting onto that continuation (Sampson distance 0) but far
    from anything view 3 saw must be rejected, while a root on the chain is kept."""
    angles = np.linspace(0.0, np.pi / 2, 200)
    arc_xy = 0.2 * np.column_stack([np.cos(angles), np.sin(angles)])  # [normalised]
    curve = PiecewiseCurve(arc_xy, False, 2, F_PX, fit_tolerance_px=np.inf)
    assert len(curve.pieces) == 1
    view3 = View(curve, PinholeCamera.at_pose(np.eye(3), np.zeros(3)))
    on_chain = np.array([0.2 * np.cos(0.7), 0.2 * np.sin(0.7), 1.0])
    spurious = np.array([-0.2, 0.0, 1.0])  # on the circle, 0.2 * F_PX px from the arc
    assert view3.distance_px(spurious[None])[0] < 0.05
    # limited to projections within 3 px of the chain: inf for it (120 px off), and the
    # same distance as without the limit for points 0-2.9 px off the chain (arc radius
    # 120 px), in front of and behind the camera
    assert view3.distance_px(spurious[None], within_px=3.0)[0] == np.inf
    offsets = np.linspace(0.0, 2.9, 7) / F_PX
    near = np.column_stack([(0.2 + offsets) * np.cos(0.7), (0.2 + offsets) * np.sin(0.7)])
    near = np.vstack([np.column_stack([near, np.ones(7)]), [[0.1, 0.1, -1.0]]])
    limited = view3.distance_px(near, within_px=3.0)
    np.testing.assert_array_equal(limited, view3.distance_px(near))
    # a circle's Sampson distance: (r'^2 - r^2) / (2 r') for a point at radius r'
    radius = 0.2 + offsets
    np.testing.assert_allclose(
        limited[:7], (radius**2 - 0.2**2) / (2 * radius) * F_PX, rtol=1e-6, atol=1e-9
    )
    assert limited[7] == np.inf
    points, info = select_candidates(
        np.array([0, 1]), np.stack([spurious, on_chain]), 2, np.array([10, 11]), view3, 2.0, 2e-3
    )
    np.testing.assert_allclose(points, on_chain[None], atol=1e-12)
    assert list(info['sample_index']) == [11] and info['n_rejected_view3'] == 1


def test_rank_two_steps_drop_the_direction_the_views_determine_least():
    """pinv_solve with ``max_rank`` 2 is the SVD solution without the smallest singular
    value. Refining true points of the noise-free loop pushed 2 mm off the curve (normal
    to it) without tangents: rank-2 steps move no point more than 1 mm along the true
    tangent, full-rank ones slide some by over 5 mm; both bring the median point back
    within 0.05 mm and the residuals from pixels to hundredths."""
    rng = np.random.default_rng(0)
    J, r = rng.normal(size=(5, 3, 3)), rng.normal(size=(5, 3))
    U, S, Vt = np.linalg.svd(J)
    truncated = np.einsum(
        'qki,qk->qi', Vt[:, :2], np.einsum('qvk,qv->qk', U[:, :, :2], r) / S[:, :2]
    )
    np.testing.assert_allclose(pinv_solve(J, r, 1e-6, max_rank=2), truncated, atol=1e-12)

    views, truth = make_views()
    t = np.linspace(0, 2 * np.pi, len(truth), endpoint=False)
    tangent = np.gradient(truth, t, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    # a unit normal per point, turning around the curve from point to point
    side = np.cross(tangent, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    other = np.cross(tangent, side)
    angle = np.linspace(0, 6 * np.pi, len(truth))[:, None]
    start = truth + 2e-3 * (np.cos(angle) * side + np.sin(angle) * other)  # [m]
    for rank, slide_limit in ((2, 1e-3), (3, np.inf)):
        refined, residuals, before = refine_points(start, views, max_rank=rank)
        slide = np.abs(np.sum((refined - start) * tangent, axis=1)).max()
        assert slide < slide_limit and (rank == 2 or slide > 5e-3)
        assert np.median(np.linalg.norm(refined - truth, axis=1)) < 5e-5
        assert np.sqrt(np.mean(residuals**2)) < 0.06 and np.sqrt(np.mean(before**2)) > 1.0
