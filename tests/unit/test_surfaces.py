"""Surfaces: closed forms, analytic gradients against finite differences, ray casting
against a brute-force march, normals and signed heights."""

from dataclasses import replace

import numpy as np
import pytest

from sensor_sim import surfaces
from sensor_sim.scenario import Surface, surface_centre_base
from vgm_common.geometry import make_transform, rpy_to_matrix

T_TILTED = make_transform(rpy_to_matrix(0.2, -0.3, 0.4), [0.6, -0.1, 0.25])
HEIGHTS = np.random.default_rng(5).normal(size=(7, 9))  # rows along y


def make_surface(kind, **changes):
    extent = {'vase': ((-0.5, 0.5), (0.0, 1.0)), 'heightmap': ((-1.0, 1.0), (-0.75, 0.75))}
    surface = Surface(
        kind=kind,
        T_base_surface=T_TILTED,
        scale=0.3,
        extent=extent.get(kind, ((-1.0, 1.0), (-1.0, 1.0))),
        albedo=0.8,
        roughness=0.0,
        radius=1.0,
        heights=HEIGHTS if kind == 'heightmap' else None,
        cell=0.25,
    )
    return replace(surface, **changes)


def interior_points(surface, n=200, seed=0):
    """Random (n, 2) points well inside the domain, off the vase's and sphere's rims and
    off the height map's cell edges (where the bilinear gradient jumps)."""
    rng = np.random.default_rng(seed)
    (x0, x1), (y0, y1) = surfaces.domain_box(surface)
    xy = np.column_stack([rng.uniform(x0, x1, 20 * n), rng.uniform(y0, y1, 20 * n)])
    if surface.kind == 'sphere':
        xy = xy[np.hypot(xy[:, 0], xy[:, 1]) < 0.9]
    if surface.kind == 'vase':
        xy = xy[np.abs(xy[:, 0]) < 0.8 * np.abs(surfaces._VASE_PROFILE(xy[:, 1]))]
    if surface.kind == 'heightmap':
        fraction = ((xy - [x0, y0]) / surface.cell) % 1.0
        xy = xy[np.all((fraction > 0.01) & (fraction < 0.99), axis=1)]
    return xy[:n]


ALL_KINDS = ('plane', 'S1', 'S2', 'S3', 'sphere', 'vase', 'heightmap')


@pytest.mark.parametrize('kind', ALL_KINDS)
def test_gradient_matches_finite_differences(kind):
    surface = make_surface(kind)
    xy = interior_points(surface)
    step = 1e-6
    numeric = np.column_stack(
        [
            (surfaces.height(surface, xy + [step, 0]) - surfaces.height(surface, xy - [step, 0])),
            (surfaces.height(surface, xy + [0, step]) - surfaces.height(surface, xy - [0, step])),
        ]
    ) / (2 * step)
    analytic = surfaces.gradient(surface, xy)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-6)


def test_heights_are_the_thesis_formulas():
    x, y = 0.3, -0.7
    xy = np.array([[x, y]])
    expected = {
        'S1': -(x + y**3),
        'S2': x * x * y * np.sin(x / 3) + np.cos(y * y),
        'S3': x * y + 0.5 * x - 0.6,
        'plane': 0.0,
        'sphere': np.sqrt(1 - x * x - y * y),
    }
    for kind, value in expected.items():
        assert surfaces.height(make_surface(kind), xy)[0] == pytest.approx(value, abs=1e-15)


def test_vase_profile_and_base_plane():
    vase = make_surface('vase')
    f = 0.15 - 0.1 * 0.4 * (6 * 0.4 + 1) ** 2 * (0.4 - 1) ** 2 * (3 * 0.4 - 2)
    assert surfaces.height(vase, [[0.0, 0.4]])[0] == pytest.approx(f, abs=1e-15)
    assert surfaces.height(vase, [[0.0, 0.0]])[0] == pytest.approx(0.15, abs=1e-15)
    assert surfaces.height(vase, [[0.45, 0.5]])[0] == 0.0  # outside the silhouette
    assert np.isnan(surfaces.height(vase, [[0.0, 1.2]])[0])


def test_heightmap_interpolates_its_grid():
    surface = make_surface('heightmap')
    rows, cols = np.mgrid[0 : HEIGHTS.shape[0], 0 : HEIGHTS.shape[1]]
    xy = np.column_stack([-1.0 + 0.25 * cols.ravel(), -0.75 + 0.25 * rows.ravel()])
    np.testing.assert_allclose(surfaces.height(surface, xy), HEIGHTS.ravel(), atol=1e-12)
    # Half way between two nodes along x: their mean.
    middle = surfaces.height(surface, [[-1.0 + 0.125, -0.75]])[0]
    assert middle == pytest.approx(HEIGHTS[0, :2].mean(), abs=1e-12)


def test_outside_the_domain_is_nan():
    assert np.isnan(surfaces.height(make_surface('S3'), [[1.5, 0.0]])[0])
    assert np.isnan(surfaces.height(make_surface('sphere'), [[0.9, 0.9]])[0])
    surface = make_surface('S2')
    outside_base = surfaces.surface_points_base(
        replace(surface, extent=((-3, 3), (-3, 3))), [[2.0, 0.0]]
    )
    assert np.isnan(surfaces.signed_height_base(surface, outside_base)[0])
    assert np.all(np.isnan(surfaces.normal_base(surface, outside_base)))


def test_normals_are_unit_upward_and_orthogonal_to_the_surface():
    surface = make_surface('S2')
    xy = interior_points(surface, 50)
    normals = surfaces.normal_base(surface, surfaces.surface_points_base(surface, xy))
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    step = 1e-6
    for offset in ([step, 0], [0, step]):
        tangent = surfaces.surface_points_base(
            surface, xy + offset
        ) - surfaces.surface_points_base(surface, xy - offset)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        np.testing.assert_allclose(np.sum(tangent * normals, axis=1), 0.0, atol=1e-8)
    # +z side of the surface frame.
    assert np.all(normals @ T_TILTED[:3, 2] > 0)


def test_signed_height_is_exact_for_a_plane_and_first_order_elsewhere():
    plane = make_surface('plane')
    point = surfaces.surface_points_base(plane, [[0.2, -0.3]])[0]
    normal = T_TILTED[:3, 2]
    for distance in (0.05, -0.02):
        assert surfaces.signed_height_base(plane, point + distance * normal)[0] == pytest.approx(
            distance, abs=1e-14
        )
    s3 = make_surface('S3')
    xy = interior_points(s3, 20)
    on_surface = surfaces.surface_points_base(s3, xy)
    normals = surfaces.normal_base(s3, on_surface)
    for distance in (1e-3, -1e-3):
        measured = surfaces.signed_height_base(s3, on_surface + distance * normals)
        np.testing.assert_allclose(measured, distance, atol=1e-5)  # error O(distance^2)


@pytest.mark.parametrize('kind', ALL_KINDS)
def test_ray_hits_lie_on_the_surface(kind):
    surface = make_surface(kind)
    xy = interior_points(surface, 300, seed=1)
    targets = surfaces.surface_points_base(surface, xy)
    origin = surface_centre_base(surface) + 0.8 * T_TILTED[:3, 2] + [0.1, 0.05, 0.0]
    t = surfaces.intersect_rays(surface, origin, targets - origin)
    assert np.isfinite(t).mean() > 0.9
    hits = origin + t[np.isfinite(t), None] * (targets - origin)[np.isfinite(t)]
    local = surfaces.to_surface_units(surface, hits)
    gap = local[:, 2] - surfaces.height(surface, local[:, :2])
    assert np.max(np.abs(gap)) < 1e-9
    # Rays aimed at visible surface points stop there (t = 1 with these directions) or at
    # an earlier hit (an occluding fold), never later.
    assert np.all(t[np.isfinite(t)] <= 1 + 1e-9)


@pytest.mark.parametrize('kind', ('S1', 'S2', 'vase', 'heightmap'))
def test_marching_finds_the_first_hit(kind):
    """Compare with a brute-force march at 2e-4 units per step, including grazing rays."""
    surface = make_surface(kind, scale=1.0, T_base_surface=np.eye(4))
    rng = np.random.default_rng(2)
    origin = np.array([0.1, 0.2, 2.5])
    directions = rng.normal(size=(80, 3))
    directions[:, 2] = -np.abs(directions[:, 2])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    t = surfaces.intersect_rays(surface, origin, directions)
    ts = np.arange(0.0, 8.0, 2e-4)
    for direction, t_hit in zip(directions, t):
        points = origin + ts[:, None] * direction
        gap = points[:, 2] - surfaces.height(surface, points[:, :2])
        sign = np.sign(gap)
        change = np.flatnonzero(
            np.isfinite(gap[:-1]) & np.isfinite(gap[1:]) & (sign[:-1] != sign[1:])
        )
        if len(change):
            assert t_hit == pytest.approx(ts[change[0]], abs=4e-4)
        else:
            assert np.isnan(t_hit)


def test_plane_and_sphere_closed_forms():
    plane = make_surface('plane', T_base_surface=np.eye(4), scale=2.0)
    t = surfaces.intersect_rays(
        plane, [0.0, 0.0, 3.0], [[0.0, 0.0, -2.0], [1.0, 0, -1.0], [0.0, 0.0, 1.0]]
    )
    assert t[0] == pytest.approx(1.5)  # hit = origin + t * direction
    assert np.isnan(t[1])  # hits the plane outside the extent (x = 3 m > 2 m)
    assert np.isnan(t[2])  # looks away
    sphere = make_surface('sphere', T_base_surface=np.eye(4), scale=0.5)
    t = surfaces.intersect_rays(sphere, [0.0, 0.0, 2.0], [[0.0, 0.0, -1.0], [0.1, 0, -1.0]])
    assert t[0] == pytest.approx(1.5)
    hit = np.array([0.0, 0.0, 2.0]) + t[1] * np.array([0.1, 0.0, -1.0])
    assert np.linalg.norm(hit) == pytest.approx(0.5, abs=1e-12)
    # From below the equator, the ray meets the inside of the cap.
    t = surfaces.intersect_rays(sphere, [0.0, 0.0, -1.0], [[0.0, 0.0, 1.0]])
    assert t[0] == pytest.approx(1.5)
