"""curve_recon_node's extraction of image curves that cross themselves (a knot's image, a
figure-eight seen edge-on): one closed chain through the crossings, in order along the
curve, against the drawn curve."""

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from curve_recon_node.curve_extraction import extract_chains, link_chains, ridge_points

SPECK_GREY = 60.0  # alone each gives at most 5 ridge points, as sensor_sim's texture does


def curve_image(truth, width_px=3.0, noise=1.0, seed=0, size=(480, 640), specks=0):
    """A dark antialiased closed polyline ``truth`` (M, 2) [px] on a shaded background,
    with ``specks`` pixels ``SPECK_GREY`` darker (a textured surface) over 10 px from it."""
    v, u = np.mgrid[0 : size[0], 0 : size[1]]
    image = 120.0 + 0.1 * u + 0.05 * v
    mask = np.zeros(size, np.uint8)
    rng = np.random.default_rng(seed + 1)
    centres = rng.uniform([20, 20], [size[1] - 20, size[0] - 20], size=(4 * specks, 2))
    u0, v0 = np.round(centres[cKDTree(truth).query(centres)[0] > 10][:specks]).astype(int).T
    image[v0, u0] -= SPECK_GREY
    cv2.polylines(
        mask,
        [np.round(truth * 256).astype(np.int32)],
        True,
        255,
        int(round(width_px)),
        cv2.LINE_AA,
        shift=8,
    )
    image *= 1.0 - 0.6 * mask / 255.0
    image += np.random.default_rng(seed).normal(scale=noise, size=size)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def trefoil(t, scale=110.0, centre=(320.3, 240.6)):
    """The trefoil's standard diagram: three crossings at 120 deg to each other."""
    x = np.sin(t) + 2 * np.sin(2 * t)
    y = np.cos(t) - 2 * np.cos(2 * t)
    return np.column_stack([centre[0] + scale / 3 * x, centre[1] + scale / 3 * y])


def figure_eight(t, centre=(320.3, 240.6)):
    """A lemniscate (one crossing, at 2 x 34 deg) such as a figure-eight seen edge-on."""
    return np.column_stack([centre[0] + 200 * np.sin(t), centre[1] + 70 * np.sin(2 * t)])


@pytest.mark.parametrize(
    'shape, crossings, specks', [(trefoil, 3, 0), (figure_eight, 1, 0), (figure_eight, 1, 150)]
)
def test_a_self_crossing_curve_is_one_closed_chain_in_curve_order(shape, crossings, specks):
    """(With specks of texture around it, which alone do not make the extraction trace
    strands, the crossing still does.)"""
    t = np.linspace(0, 2 * np.pi, 6000, endpoint=False)
    truth = shape(t)
    image = curve_image(truth, specks=specks)
    length = np.sum(np.linalg.norm(np.diff(np.vstack([truth, truth[:1]]), axis=0), axis=1))
    # linked by proximity alone the crossings join the strands into one tree whose
    # longest path turns at a crossing: part of the curve
    points, _, _ = ridge_points(image, 3.0, 8.0)
    assert link_chains(points)[0].length_px < 0.8 * length
    chains = extract_chains(image, line_width_px=3.0)
    chain = chains[0]
    assert chain.closed
    assert chain.length_px == pytest.approx(length, rel=0.02)
    distance, index = cKDTree(truth).query(chain.pixels)
    measured = chain.measured
    # the points found in the image are as accurate as on a simple curve; the Hermite
    # arcs bridged across each crossing (both strands, about 2 x (w + 2 px) each) less so
    assert np.sqrt(np.mean(distance[measured] ** 2)) < 0.15 and distance[measured].max() < 0.5
    assert distance[~measured].max() < 1.0
    # each crossing bridged once on each strand (around the loop: the closing gap too)
    bridges = np.count_nonzero(np.diff(np.append(measured, measured[0]).astype(int)) == 1)
    assert bridges == 2 * crossings
    # in order along the curve: the truth index of the measured points (a bridged point
    # at a crossing's centre is as near the other strand) advances by small steps once
    # round, one way (a strand's last point may hook back by under a pixel)
    per_px = len(t) / length
    step = np.diff(np.append(index[measured], index[measured][0]))
    step = (step + len(t) // 2) % len(t) - len(t) // 2
    assert abs(np.sum(step)) == len(t)
    assert np.all(step * np.sign(np.sum(step)) > -per_px)
    assert np.abs(step).max() < 4 * (3.0 + 2.0) * per_px  # a bridge: 2 x (w + 2 px)
