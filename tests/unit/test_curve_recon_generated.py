"""curve_recon_node on generated curve families (vgm_evaluation.curve_families, the bench's
part C draws): the causes of local excursions traced there, each on its draw against
the true curve, and each cause's mechanism on its own."""

import numpy as np
import pytest
from vgm_evaluation.metrics import curve_agreement

from curve_recon_node.piecewise import PiecewiseCurve, View, select_candidates
from curve_recon_node.pipeline import ReconstructionSettings, _end_on_holes, reconstruct_capture
from curve_recon_node.waypoints import robust_arc_parameter
from vgm_common.camera_model import PinholeCamera

F_PX = 600.0


def reconstruct_draw(family, seed, noise_grey):
    """The reconstruction of the bench's draw and the case (its true curve)."""
    from vgm_evaluation.curve_families import generate_case

    from sensor_sim.render import SceneRenderer, add_noise

    case = generate_case(family, seed)
    renderer = SceneRenderer(case.scenario)
    images = {
        name: add_noise(
            renderer.scene_image(name),
            noise_grey,
            np.random.default_rng([seed, int(10 * noise_grey), i]),
        ).astype(float)
        for i, name in enumerate(('left', 'right', 'aux'))
    }
    settings = ReconstructionSettings(degree=case.degree, line_width_px=case.line_width_px)
    result = reconstruct_capture(images, case.scenario.cameras, settings)
    return result, case


@pytest.mark.parametrize(
    'family, seed, noise_grey, max_mm, rms_mm',
    [
        # a ghost (three cones meeting 55 mm off the curve, 0.02 px from view 3's curve,
        # beating the true root's 0.04 px) at one sample, and one 6.8 mm off at another:
        # before the order test 0.41 / 2.14 mm (their neighbours lost as outliers, the
        # hole bridged), now 0.06 / 0.26 mm
        ('saddle_loop', 2, 4.0, 0.5, 0.15),
        # the last 30 mm seen nearly end-on by view 1 (one chain step: 8.8 mm): smoothed
        # against view 1's chain index, 17 good points there were dropped as outliers
        # and the 26 mm hole bridged: 0.59 / 2.07 mm before, now 0.06 / 0.28 mm
        ('inflection', 3, 0.0, 0.5, 0.15),
        # one cubic per view within the RMS tolerance (0.07 px) but 0.1-0.18 px off a
        # stretch of view 1's chain that runs near the epipolar planes: 0.8 mm there;
        # 0.076 / 0.33 mm before the bias split (the reference: 0.016 / 0.07), now
        # 0.014 / 0.04 mm
        ('near_straight', 3, 0.0, 0.1, 0.03),
        # a 35 mm stretch seen end-on by view 1 (4 samples): coverage 0.69 (the run cut
        # there) before views 2 and 3 filled it, now 0.997 at 0.13 / 0.40 mm
        ('helix', 3, 4.0, 0.6, 0.2),
        # a lone wrong root 37 mm off makes two long steps in a row: filled from views
        # 2 and 3 as if they were end-on holes, they put 132 true points out of order
        # and split the curve (coverage 0.67); two long steps in a row are no hole
        ('inflection', 0, 4.0, 0.3, 0.1),
        # the last point of the open curve 1.7 mm off, its own local fit following it
        # (no points beyond): 0.18 / 1.61 mm, now judged by its neighbours' fit, 0.04 /
        # 0.14 mm
        ('parabola', 2, 4.0, 0.3, 0.1),
        # a (2, 3) torus knot: its images cross themselves, traced through the
        # crossings (before: "only 18 of 327 samples"); true points projecting into
        # another view's crossing gap were refused and ghosts up to 0.4 m off took their
        # samples until the gaps were bridged (0.33 / 1.99 mm, coverage 0.89, then
        # 0.05 / 0.28 mm, coverage 0.915); now 0.07 / 0.28 mm, coverage 1.000
        ('torus_knot', 3, 0.0, 0.4, 0.1),
        # the open helix's ends: a fixed trim of 3 line widths cut 1-1.8 widths of good
        # chain beyond each end cap in every view, 13 mm of curve (coverage 0.943); the
        # trim now ends where the ridge strength comes back (0.997, 0.12 / 0.29 mm)
        ('helix', 0, 4.0, 0.5, 0.2),
        # view 1 sees a 35 mm stretch end-on and its samples there land at either end of
        # it, out of order: three long steps in a row, so no hole was filled and the run
        # was cut (coverage 0.64 with the chains the end trim above leaves); a run of
        # long steps whose outer points are far apart is filled (1.000, 0.24 / 0.73 mm)
        ('twisted_cubic', 3, 4.0, 1.0, 0.3),
    ],
)
def test_traced_draws_within_a_millimetre(family, seed, noise_grey, max_mm, rms_mm):
    result, case = reconstruct_draw(family, seed, noise_grey)
    # the bench's measures: the share of the true curve within 3 mm of the waypoints
    agreement = curve_agreement(result.waypoints_base, case.truth_base, result.closed, case.closed)
    distance, coverage = agreement.distance_m, agreement.coverage
    print(
        f'{family} seed {seed} noise {noise_grey}: RMS {1e3 * np.sqrt(np.mean(distance**2)):.3f}'
        f' mm, max {1e3 * distance.max():.3f} mm, coverage {coverage:.3f}, {result.stats}'
    )
    assert distance.max() < max_mm * 1e-3
    assert np.sqrt(np.mean(distance**2)) < rms_mm * 1e-3
    assert coverage > 0.98


def test_a_steady_bias_within_the_rms_tolerance_splits_the_piece():
    """A circle arc with a 0.15 px bump (sigma 20 chain points) in the middle of its 400:
    one conic fits it within the RMS tolerance (0.03 px < 0.1 px) but misses the bump by
    0.08 px for dozens of points; only the bias test splits it, and the pieces then
    come within 0.05 px of every chain point."""
    t = np.linspace(0.0, 1.2 * np.pi, 400)
    radius = 0.2 + 0.15 / F_PX * np.exp(-0.5 * ((np.arange(400) - 200) / 20.0) ** 2)
    xy = radius[:, None] * np.column_stack([np.cos(t), np.sin(t)])
    one_piece = PiecewiseCurve(xy, False, 2, F_PX, fit_tolerance_px=np.inf)
    assert one_piece.pieces[0].rms_px < 0.05
    assert np.abs(one_piece.distance(xy)[0]).max() * F_PX > 0.07
    curve = PiecewiseCurve(xy, False, 2, F_PX)
    assert len(curve.pieces) > 1
    assert np.abs(curve.distance(xy)[0]).max() * F_PX < 0.05


def test_a_ghost_out_of_chain_order_loses_to_the_true_root():
    """Per sample: the true root (on the curve in all views) and, at sample 20, a ghost
    nearer view 3's curve whose projections land on another stretch of views 2 and 3's
    chains. Without the order views the ghost wins; with them the true root does, and
    the ghost is counted."""
    t = np.linspace(0.0, 1.5 * np.pi, 300)
    xy = 0.2 * np.column_stack([np.cos(t), np.sin(t)])  # [normalised]
    curve = PiecewiseCurve(xy, False, 2, F_PX)
    # one camera at the origin looking along +z sees the 3D points (x, y, 1) at xy: as
    # every view here, so a point's chain index is the same in all three
    view = View(curve, PinholeCamera.at_pose(np.eye(3), np.zeros(3)))
    samples = np.arange(10, 40)
    true_points = np.column_stack([xy[samples], np.ones(len(samples))])
    ghost = np.append(xy[200], 1.0)  # on every view's curve, far along the chains
    rays = np.append(np.arange(len(samples)), 10)
    candidates = np.vstack([true_points, ghost])
    candidates[10] += [1e-4, 0.0, 0.0]  # the true root 0.06 px off: the ghost is nearer
    without, _ = select_candidates(rays, candidates, len(samples), samples, view, 2.0, 2e-3)
    np.testing.assert_allclose(without[10], ghost)
    points, info = select_candidates(
        rays, candidates, len(samples), samples, view, 2.0, 2e-3, order_views=(view, view)
    )
    np.testing.assert_allclose(points[10], candidates[10])
    assert info['n_out_of_order'] == 1 and len(points) == len(samples)


def test_robust_arc_parameter_keeps_a_true_jump_and_ignores_a_lone_outlier():
    """Points 1 mm apart with one true 9 mm jump (view 1 seeing a stretch end-on) and a
    lone point 20 mm off the curve: the parameter follows the length along the curve,
    the jump included, and the outlier adds nothing."""
    x = np.concatenate([np.arange(0, 30) * 1e-3, 0.038 + np.arange(0, 30) * 1e-3])
    points = np.column_stack([x, np.zeros_like(x), np.zeros_like(x)])
    points[45, 1] = 0.02
    t, total = robust_arc_parameter(points, closed=False)
    np.testing.assert_allclose(t[-1], x[-1], atol=1e-9)
    np.testing.assert_allclose(total, x[-1], atol=1e-9)
    np.testing.assert_allclose(np.diff(t), np.diff(x), atol=1e-9)


def test_end_on_holes_include_runs_out_of_order_but_not_a_lone_wrong_root():
    """Points 1 mm apart along x (spacing 5 mm: a step over 10 mm is long). One long
    step is a hole; a run of long steps whose outer points are far apart (view 1's
    samples at either end of an end-on stretch) is one hole; a run out to a wrong root
    and back is none."""
    line = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)]) * 1e-3
    after = line + [0.040, 0.0, 0.0]
    one = np.vstack([line, after])
    assert _end_on_holes(one, False, 0.005) == [(9, 10)]
    zigzag = np.vstack([line, [[0.040, 0, 0], [0.0095, 0, 0]], after[1:]])
    assert _end_on_holes(zigzag, False, 0.005) == [(9, 12)]
    lone = np.vstack([line[:5], [[0.0045, 0.037, 0.0]], line[5:]])
    assert _end_on_holes(lone, False, 0.005) == []
    # on a loop the closing step counts: a hole from the last point to the first
    assert _end_on_holes(np.arange(21.0)[:, None] * [1e-3, 0.0, 0.0], True, 0.005) == [(20, 21)]


def test_a_point_on_a_fit_but_off_the_chain_is_as_far_as_the_chain():
    # the chain goes three quarters round an ellipse and closes across the rest with a
    # chord (as a chain cuts across a loop of the image it cannot resolve); the fitted
    # ellipse runs on round the missing quarter, where the view saw nothing: a point
    # there is 0 px from the fit (by its Sampson distance) but 17 px from the chain
    angle = np.linspace(0.0, 1.5 * np.pi, 300)
    chain = np.column_stack([0.1 * np.cos(angle), 0.05 * np.sin(angle)])
    curve = PiecewiseCurve(chain, True, 2, F_PX, fit_tolerance_px=np.inf)
    assert len(curve.pieces) == 1
    off = np.array([[0.1 * np.cos(1.75 * np.pi), 0.05 * np.sin(1.75 * np.pi)]])
    index, _ = curve.nearest(off)
    sampson, _ = curve.owner_distance(off, index)
    chord = np.array([chain[-1], chain[0]])
    u = (chord[1] - chord[0]) / np.linalg.norm(chord[1] - chord[0])
    to_chord = abs(u[0] * (off[0, 1] - chord[0, 1]) - u[1] * (off[0, 0] - chord[0, 0]))
    seen = curve.seen_distance(off, index)
    assert abs(sampson[0]) * F_PX < 1e-6
    np.testing.assert_allclose(seen * F_PX, to_chord * F_PX - 0.5, atol=1e-9)
    assert seen[0] * F_PX > 10.0
    # on and beside the chain the Sampson distance stands: points 0.3 px off it
    normal = np.column_stack([np.cos(angle) / 0.1, np.sin(angle) / 0.05])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    beside = chain[10:-10] + 0.3 / F_PX * normal[10:-10]
    index, _ = curve.nearest(beside)
    sampson, _ = curve.owner_distance(beside, index)
    np.testing.assert_array_equal(curve.seen_distance(beside, index), np.abs(sampson))
    np.testing.assert_allclose(np.abs(sampson) * F_PX, 0.3, atol=0.01)


def test_roots_on_a_fits_continuation_off_view_3s_chain_are_refused():
    # twisted_cubic seed 2 at noise 4: 29-31 short cubic pieces per view; roots where
    # a piece's fitted curve runs on past its stretch of chain passed the third view at
    # a Sampson distance near 0 though pixels from the chain: 0.56 / 3.16 mm before,
    # 0.31 / 0.86 mm now they are judged by their distance to the chain (the
    # triangulation reference: 1.17 mm RMS)
    result, case = reconstruct_draw('twisted_cubic', 2, 4.0)
    agreement = curve_agreement(result.waypoints_base, case.truth_base, result.closed, case.closed)
    rms_mm, max_mm = 1e3 * agreement.rms_m, 1e3 * agreement.max_m
    print(f'{rms_mm:.3f} / {max_mm:.3f} mm, coverage {agreement.coverage:.3f}')
    assert agreement.max_m < 1e-3
    assert agreement.rms_m < 0.4e-3
    assert agreement.coverage > 0.95


def test_a_root_off_the_intersecting_views_chain_ranks_after_the_true_root():
    # sphere_loop seed 1 at noise 2 (the topic test's draw): in the views 1 + 3 pass a
    # root on a view-3 piece's continuation, 2.2-2.6 px off view 3's chain, met view
    # 2's curve 0.01 px closer than the true root of the same ray and won (a 4.5 mm
    # excursion). Here the intersecting view saw three quarters of an ellipse (its chain
    # closed across the rest by a chord, the fit running on round it) and the checking
    # view all of it; one camera, so a point's image is the same in both.
    angle = np.linspace(0.0, 2 * np.pi, 400, endpoint=False)
    ellipse = np.column_stack([0.1 * np.cos(angle), 0.05 * np.sin(angle)])
    camera = PinholeCamera.at_pose(np.eye(3), np.zeros(3))
    checker = View(PiecewiseCurve(ellipse, True, 2, F_PX, fit_tolerance_px=np.inf), camera)
    partial = ellipse[:300]
    intersecting = View(PiecewiseCurve(partial, True, 2, F_PX, fit_tolerance_px=np.inf), camera)
    true_root = np.append(partial[100] + [1e-4, 0.0], 1.0)  # 0.06 px off both curves
    continuation = np.append(ellipse[350], 1.0)  # on both fits, 17 px off the chain
    candidates = np.vstack([true_root, continuation])
    rays, samples = np.array([0, 0]), np.array([100])
    args = (rays, candidates, 1, samples, checker, 2.0, 2e-3)
    order_views = (intersecting, intersecting)
    nearest_fit, _ = select_candidates(*args, order_views=order_views)
    np.testing.assert_allclose(nearest_fit[0], continuation)
    points, info = select_candidates(*args, order_views=order_views, off_chain_last=True)
    np.testing.assert_allclose(points[0], true_root)
    assert info['n_rejected_view3'] == 0
