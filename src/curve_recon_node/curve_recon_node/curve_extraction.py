"""Curve pixels from an image: a thin dark line on a shaded surface (step 1).

The seed finds the curve with an edge detector (Canny). A drawn line has two edges, so
here the line's *centre* is found instead, with Steger's ridge detector (1998): the
Gaussian-smoothed image's Hessian has a large positive eigenvalue across a dark line,
and the second-order Taylor expansion along that eigenvector gives the centre to a
fraction of a pixel. The subpixel points are then linked into ordered chains: a minimum
spanning tree of the points within ``link_radius_px`` of each other, whose longest path
is the chain (spurs and double responses fall off it); a chain whose two ends are within
``link_radius_px`` of each other and which is long enough is a closed loop.

Pixels are (u, v) = (column, row), pixel centres at integers (OpenCV convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra, minimum_spanning_tree
from scipy.spatial import cKDTree

from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray


@dataclass(frozen=True)
class Chain:
    """An ordered curve chain in one image: ``pixels`` (N, 2) float [px] along the curve,
    ``closed`` true if the last point joins back to the first (not repeated)."""

    pixels: np.ndarray
    closed: bool

    @property
    def length_px(self) -> float:
        """Length of the polyline through ``pixels`` [px], the closing step included when
        ``closed``."""
        steps = np.linalg.norm(np.diff(self.pixels, axis=0), axis=1).sum()
        if self.closed:
            steps += np.linalg.norm(self.pixels[0] - self.pixels[-1])
        return float(steps)


def line_sigma(line_width_px: float) -> float:
    """Steger's scale for a bar profile of width w: sigma >= w / (2 sqrt 3) keeps the
    centre a single maximum; a little more smooths noise [px]."""
    return max(0.8, 1.0 * float(line_width_px) / (2.0 * np.sqrt(3.0)) + 0.4)


def line_response(contrast_grey: float, line_width_px: float, sigma: float) -> float:
    """Second derivative [grey / px^2] that a dark bar of depth ``contrast_grey`` and width
    ``line_width_px`` gives at its centre after Gaussian smoothing with ``sigma`` [px]:
    the difference of G' at the two bar edges."""
    half = 0.5 * float(line_width_px)
    g_prime = half / (np.sqrt(2 * np.pi) * sigma**3) * np.exp(-(half**2) / (2 * sigma**2))
    return contrast_grey * 2.0 * g_prime


def ridge_points(
    image: npt.ArrayLike, line_width_px: float = 3.0, min_contrast_grey: float = 8.0
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Subpixel centre points of thin dark lines (Steger).

    Args:
        image: (H, W) grey image (any real dtype).
        line_width_px: expected full line width [px].
        min_contrast_grey: weakest line kept: how much darker than its surroundings a line
            of that width must be [grey levels].

    Returns:
        points (N, 2) float [px] (u, v), strength (N,) [grey levels of equivalent line
        contrast], normals (N, 2) unit vectors across the line.
    """
    image = np.asarray(image)
    if image.ndim != 2 or min(image.shape) < 8:
        raise InvalidInput(
            f'image: expected a 2D grey image, got shape {image.shape}',
            key='image',
            value=image.shape,
        )
    sigma = line_sigma(line_width_px)
    smooth = cv2.GaussianBlur(image.astype(np.float32), (0, 0), sigma)
    # central differences of the smoothed image: derivatives of the Gaussian-filtered image
    hxx = cv2.Sobel(smooth, cv2.CV_32F, 2, 0, ksize=1)
    hyy = cv2.Sobel(smooth, cv2.CV_32F, 0, 2, ksize=1)
    hxy = cv2.Sobel(smooth, cv2.CV_32F, 1, 1, ksize=3, scale=0.25)
    # largest eigenvalue lam = half_trace + root of [[hxx, hxy], [hxy, hyy]] <= max(hxx,
    # hyy) + |hxy|: that cheap bound (OpenCV, whole image) leaves a few thousand pixels
    # near lines for the exact test lam > threshold (it is compared with a slightly lower
    # value so that rounding cannot drop a pixel the exact test keeps)
    threshold = line_response(min_contrast_grey, line_width_px, sigma)
    # (the ignores: OpenCV takes a scalar second operand, its stubs list only arrays)
    bound = cv2.add(cv2.max(hxx, hyy), cv2.absdiff(hxy, 0.0))  # type: ignore[call-overload]
    near_line = cv2.compare(bound, 0.999 * threshold, cv2.CMP_GT)  # type: ignore[call-overload]
    near_line[:2, :] = near_line[-2:, :] = near_line[:, :2] = near_line[:, -2:] = 0
    found = cv2.findNonZero(near_line)  # row by row, as np.nonzero
    if found is None:
        return np.empty((0, 2)), np.empty(0), np.empty((0, 2))
    u, v = found.reshape(-1, 2).T
    a, b, c = hxx[v, u], hxy[v, u], hyy[v, u]
    lam_c = 0.5 * (a + c) + np.sqrt((0.5 * (a - c)) ** 2 + b**2)
    candidate = lam_c > threshold
    u, v, a, b, c, lam_c = (x[candidate] for x in (u, v, a, b, c, lam_c))
    # eigenvector of lam: (b, lam - a) or (lam - c, b), whichever is better conditioned
    use2 = np.hypot(lam_c - c, b) > np.hypot(b, lam_c - a)
    nx, ny = np.where(use2, lam_c - c, b), np.where(use2, b, lam_c - a)
    norm = np.hypot(nx, ny)
    with np.errstate(divide='ignore', invalid='ignore'):  # float64 from here on
        nx = np.where(norm > 0, nx / norm, 1.0).astype(float)
        ny = np.where(norm > 0, ny / norm, 0.0).astype(float)
    # gradient of the smoothed image along the normal, by central differences (only at
    # these pixels)
    gx = 0.5 * (smooth[v, u + 1] - smooth[v, u - 1])
    gy = 0.5 * (smooth[v + 1, u] - smooth[v - 1, u])
    t = -(gx * nx + gy * ny) / lam_c  # Newton step to the extremum across the line [px]
    offset_u, offset_v = t * nx, t * ny
    inside = (np.abs(offset_u) <= 0.5) & (np.abs(offset_v) <= 0.5)
    points = np.column_stack([u[inside] + offset_u[inside], v[inside] + offset_v[inside]])
    normal = np.column_stack([nx, ny])
    strength = lam_c[inside] / line_response(1.0, line_width_px, sigma)
    return points.astype(float), strength.astype(float), normal[inside]


def link_chains(
    points: npt.ArrayLike, link_radius_px: float = 2.0, min_points: int = 20
) -> list[Chain]:
    """Order (N, 2) subpixel points into chains (list of ``Chain``, longest first).

    Each connected group of points (neighbours within ``link_radius_px``) becomes the
    longest path of its minimum spanning tree; points off that path (spurs, doubled
    responses) are dropped. Groups of fewer than ``min_points`` points are dropped.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(points) < max(min_points, 2):
        return []
    tree = cKDTree(points)
    pairs = tree.query_pairs(link_radius_px, output_type='ndarray')
    if len(pairs) == 0:
        return []
    weights = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    weights = np.maximum(weights, 1e-9)  # a zero weight would read as 'no edge'
    n = len(points)
    graph = coo_matrix((weights, (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()
    n_groups, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels, minlength=n_groups)
    mst = minimum_spanning_tree(graph)
    # both directions stored once, so the path searches need not transpose it each time
    mst = (mst + mst.T).tocsr()
    chains = []
    for group in np.nonzero(sizes >= min_points)[0]:
        start = int(np.nonzero(labels == group)[0][0])
        far = _farthest(mst, start)[0]
        end, predecessors = _farthest(mst, far)
        predecessor = predecessors.tolist()  # plain ints: the walk is a Python loop
        path = [end]
        while path[-1] != far:
            path.append(predecessor[path[-1]])
        if len(path) < min_points:
            continue
        pixels = points[np.array(path)]
        gap = np.linalg.norm(pixels[0] - pixels[-1])
        closed = bool(gap <= link_radius_px and len(path) > 4 * link_radius_px + 4)
        chains.append(Chain(pixels, closed))
    chains.sort(key=lambda c: -c.length_px)
    return chains


def _farthest(tree_graph: csr_matrix, source: int) -> tuple[int, np.ndarray]:
    """Vertex of a tree (symmetric sparse matrix) farthest (by path length) from
    ``source``, and predecessors."""
    distance, predecessors = dijkstra(
        tree_graph, directed=True, indices=source, return_predecessors=True
    )
    distance[~np.isfinite(distance)] = -1.0
    return int(np.argmax(distance)), predecessors


def resample_chain(chain: Chain, step_px: float = 1.0) -> Chain:
    """Chain resampled at (about) equal arc-length steps [px] along its polyline."""
    pixels = chain.pixels
    if chain.closed:
        pixels = np.vstack([pixels, pixels[:1]])
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pixels, axis=0), axis=1))])
    if arc[-1] <= step_px:
        return chain
    count = int(np.floor(arc[-1] / step_px))
    s = np.linspace(0.0, arc[-1], count + (0 if chain.closed else 1), endpoint=not chain.closed)
    resampled = np.column_stack([np.interp(s, arc, pixels[:, 0]), np.interp(s, arc, pixels[:, 1])])
    return Chain(resampled, chain.closed)


def trim_chain(chain: Chain, trim_px: float) -> Chain | None:
    """An open chain without ``trim_px`` [px] of arc length at each end (closed chains are
    returned as they are); None if nothing is left."""
    if chain.closed or trim_px <= 0:
        return chain
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(chain.pixels, axis=0), axis=1))])
    keep = (arc >= trim_px) & (arc <= arc[-1] - trim_px)
    return Chain(chain.pixels[keep], False) if keep.sum() >= 2 else None


def extract_chains(
    image: npt.ArrayLike,
    line_width_px: float = 3.0,
    min_contrast_grey: float = 8.0,
    min_chain_px: float = 40.0,
    link_radius_px: float = 2.0,
) -> list[Chain]:
    """The dark curve chains of one image: ridge points linked into chains at least
    ``min_chain_px`` long [px], longest first.

    The ends of an open chain are trimmed by 3 line widths: there the smoothed bar's
    round cap pulls the ridge up to ~3.4 px past the true end (measured on sensor_sim's
    3 px lines)."""
    points, _, _ = ridge_points(image, line_width_px, min_contrast_grey)
    chains = link_chains(points, link_radius_px, min_points=max(5, int(min_chain_px / 2)))
    trimmed = [trim_chain(c, 3.0 * line_width_px) for c in chains]
    return [c for c in trimmed if c is not None and c.length_px >= min_chain_px]
