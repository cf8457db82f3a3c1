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

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra, minimum_spanning_tree
from scipy.spatial import cKDTree

from curve_recon_node.algebraic_curves import IntArray
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

LINK_RADIUS_PX = 2.0  # [px] ridge points this near are neighbours on a chain (the default)
END_STRENGTH_SHARE = 0.75  # an open chain's end cap: ridge strength below this x its median
END_MARGIN_WIDTHS = 0.5  # [line widths] trimmed beyond the end cap
END_TRIM_MAX_WIDTHS = 3.0  # [line widths] the most trimmed at an end


@dataclass(frozen=True)
class Chain:
    """An ordered curve chain in one image: ``pixels`` (N, 2) float [px] along the curve,
    ``closed`` true if the last point joins back to the first (not repeated); ``bridged``
    (N,) bool marks points interpolated across a crossing's gap (None: none are)."""

    pixels: np.ndarray
    closed: bool
    bridged: np.ndarray | None = None

    @property
    def measured(self) -> np.ndarray:
        """(N,) bool: the points found in the image (not bridged)."""
        if self.bridged is None:
            return np.ones(len(self.pixels), dtype=bool)
        return ~self.bridged

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
    return _link_pairs(
        points, _neighbour_pairs(points, link_radius_px), link_radius_px, min_points
    )


def _neighbour_pairs(points: FloatArray, link_radius_px: float) -> np.ndarray:
    """(L, 2) index pairs of the (N, 2) points within ``link_radius_px`` of each other."""
    if len(points) < 2:
        return np.empty((0, 2), dtype=int)
    return cKDTree(points).query_pairs(link_radius_px, output_type='ndarray')


def _link_pairs(
    points: FloatArray, pairs: np.ndarray, link_radius_px: float, min_points: int
) -> list[Chain]:
    """``link_chains`` on the points' neighbour ``pairs``."""
    if len(points) < max(min_points, 2) or len(pairs) == 0:
        return []
    weights = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    return _longest_paths(points, pairs, weights, link_radius_px, min_points)


def _group_sizes(n: int, pairs: np.ndarray) -> IntArray:
    """(n,) size of each point's connected group under the neighbour ``pairs``."""
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return np.bincount(labels)[labels]


def _longest_paths(
    points: FloatArray,
    pairs: np.ndarray,
    weights: FloatArray,
    link_radius_px: float,
    min_points: int,
) -> list[Chain]:
    """The longest path of the minimum spanning tree of each connected group of
    ``points`` linked by ``pairs`` (weights: their lengths) as a ``Chain``, longest
    first; groups and paths of fewer than ``min_points`` points are dropped."""
    if len(pairs) == 0:
        return []
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


def trim_chain(chain: Chain, trim_px: float, trim_end_px: float | None = None) -> Chain | None:
    """An open chain without ``trim_px`` [px] of arc length at its start and
    ``trim_end_px`` (default ``trim_px``) at its end (closed chains are returned as they
    are); None if nothing is left."""
    trim_end_px = trim_px if trim_end_px is None else trim_end_px
    if chain.closed or (trim_px <= 0 and trim_end_px <= 0):
        return chain
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(chain.pixels, axis=0), axis=1))])
    keep = (arc >= trim_px) & (arc <= arc[-1] - trim_end_px)
    if keep.sum() < 2:
        return None
    return Chain(chain.pixels[keep], False, None if chain.bridged is None else chain.bridged[keep])


def end_trims_px(
    chain: Chain, points: FloatArray, strength: FloatArray, line_width_px: float
) -> tuple[float, float]:
    """Arc length [px] to trim at the start and at the end of an open chain.

    The smoothed bar's round cap pulls the ridge off the curve near a line's end (up to
    ~3.5 px past it). Measured on 36 ends of six open part-C draws (widths 2.2-4.6 px,
    noise 0 and 4 grey): the stretch more than 0.5 px off the true curve is 1.2-2.65
    line widths long, and it is where the ridge strength stays below 0.75 of the
    chain's median (equal on 24 ends, at most 0.54 widths shorter on the others). So
    each end is trimmed up to its first point of at least END_STRENGTH_SHARE of the
    median strength plus END_MARGIN_WIDTHS, at most END_TRIM_MAX_WIDTHS (the former
    fixed trim): a fixed 3 widths cut up to 1.8 widths of good chain at each end, 13
    mm of a helix's 350 mm in 3D.

    Args:
        chain: an open chain (its points are ridge points or lie between them).
        points, strength: the image's ridge points (N, 2) [px] and their strengths (N,).
        line_width_px: the line width [px].
    """
    most = END_TRIM_MAX_WIDTHS * line_width_px
    if not len(points):
        return most, most
    chain_strength = strength[cKDTree(points).query(chain.pixels)[1]]
    strong = chain_strength >= END_STRENGTH_SHARE * np.median(chain_strength)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(chain.pixels, axis=0), axis=1))])
    margin = END_MARGIN_WIDTHS * line_width_px
    first, last = np.argmax(strong), len(strong) - 1 - np.argmax(strong[::-1])
    # an end at full strength shows no cap: no end of the line but a break in it (where
    # another strand comes near), whose ridge that strand pulls: the most is trimmed
    start = min(arc[first] + margin, most) if first > 0 else most
    end = min(arc[-1] - arc[last] + margin, most) if last < len(strong) - 1 else most
    return start, end


def extract_chains(
    image: npt.ArrayLike,
    line_width_px: float = 3.0,
    min_contrast_grey: float = 8.0,
    min_chain_px: float = 40.0,
    link_radius_px: float = LINK_RADIUS_PX,
) -> list[Chain]:
    """The dark curve chains of one image: ridge points linked into chains at least
    ``min_chain_px`` long [px], longest first.

    The ends of an open chain are trimmed where the smoothed bar's round cap pulls the
    ridge off the curve (``end_trims_px``: 1.5-3 line widths)."""
    points, strength, normals = ridge_points(image, line_width_px, min_contrast_grey)
    min_points = max(5, int(min_chain_px / 2))
    pairs = _neighbour_pairs(points, link_radius_px)
    chains = _link_pairs(points, pairs, link_radius_px, min_points)
    strand_points = max(5, int(STRAND_MIN_WIDTHS * line_width_px))
    # a strand is linked within a group of neighbours: points of smaller groups (the
    # surface's texture: 290-440 points in groups of at most 5 on each default image,
    # 40-190 px from the curve) can be no strand, and they made every capture traced
    if chains and (
        len(chains) > 1
        or crossing_points(
            points[_group_sizes(len(points), pairs) >= strand_points],
            chains[0],
            line_width_px,
            min_points,
        )
    ):
        # the curve crosses itself (or is broken): follow its strands through the gaps
        strands = strand_chains(points, normals, link_radius_px, line_width_px, strand_points)
        traced = join_at_crossings(strands, line_width_px, link_radius_px)
        if traced and traced[0].length_px > TRACED_GAIN * chains[0].length_px:
            chains = traced
    trimmed = [trim_chain(c, *end_trims_px(c, points, strength, line_width_px)) for c in chains]
    return [c for c in trimmed if c is not None and c.length_px >= min_chain_px]


# Tracing a curve through its own crossings (a knot's image, a figure-eight seen edge-on).
# Linked by proximity alone, two strands that cross join at the crossing into one tree,
# and its longest path turns there: a (2, 3) torus knot's chain was 15-57 % of its image.
STRAND_ANGLE_DEG = 35.0  # a link, and the two points' tangents, within this of each other
END_DIRECTION_PX = 6.0  # [px] an end's outward direction: from this far back along the chain
JOIN_ANGLE_DEG = 35.0  # a crossing's two ends continue each other within this
JOIN_GAP_WIDTHS = 10.0  # [line widths] longest gap bridged at a crossing
CROSSING_MIN_POINTS = 3  # a point is at a crossing with this many differently turned near it
STRAND_MIN_WIDTHS = 3.0  # [line widths] shortest strand between two crossings kept
TRACED_GAIN = 1.05  # the traced curve replaces the longest chain if this much longer
CUSP_GAP_RADII = 3.0  # [crossing radii] ends this near are joined at any angle
MATCHING_GROUP = 12  # crossings' ends paired exhaustively up to this many in a group
OFF_PATH_WIDTHS = 2.0  # [line widths] a point this far from its tree's longest path is no spur


def crossing_points(
    points: FloatArray, chain: Chain, line_width_px: float, min_points: int
) -> bool:
    """True when at least ``min_points`` of the ridge ``points`` lie farther than
    ``OFF_PATH_WIDTHS`` line widths from ``chain`` yet within reach of some chain: another
    strand of the curve that the chain left at a crossing (spurs and doubled responses
    lie within a pixel or two of it)."""
    distance, _ = cKDTree(chain.pixels).query(points)
    return int(np.sum(distance > OFF_PATH_WIDTHS * line_width_px)) >= min_points


def strand_chains(
    points: FloatArray,
    normals: FloatArray,
    link_radius_px: float,
    line_width_px: float,
    min_points: int,
) -> list[Chain]:
    """Chains of ridge points linked only along the line (both points' tangents, normal
    to ``normals``, within ``STRAND_ANGLE_DEG`` of the link and of each other), without
    the points near a crossing: those with a point within a line width plus
    ``link_radius_px`` whose tangent differs by more than ``STRAND_ANGLE_DEG`` (the other
    strand). Linked through a crossing's centre, whose points turn gradually from one
    strand's direction to the other's, a strand's longest path turned onto the other
    strand and the crossing's remaining arms were dropped as spurs. (At least
    ``CROSSING_MIN_POINTS`` such points: one may be noise.)"""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(points) < max(min_points, 2):
        return []
    tangent = np.column_stack([-normals[:, 1], normals[:, 0]])
    along = np.cos(np.radians(STRAND_ANGLE_DEG))
    tree = cKDTree(points)
    near = tree.query_pairs(line_width_px + link_radius_px, output_type='ndarray')
    across = near[np.abs(np.sum(tangent[near[:, 0]] * tangent[near[:, 1]], axis=1)) < along]
    # several such points, not one: a lone noise response beside a line (4 px off,
    # turned 90 deg) cut a figure-eight's strand where it came near
    at_crossing = np.bincount(across.ravel(), minlength=len(points)) >= CROSSING_MIN_POINTS
    pairs = tree.query_pairs(link_radius_px, output_type='ndarray')
    pairs = pairs[~at_crossing[pairs[:, 0]] & ~at_crossing[pairs[:, 1]]]
    if len(pairs) == 0:
        return []
    link = points[pairs[:, 1]] - points[pairs[:, 0]]
    length = np.maximum(np.linalg.norm(link, axis=1), 1e-9)
    i, j = pairs[:, 0], pairs[:, 1]
    aligned = (
        (np.abs(np.sum(tangent[i] * link, axis=1)) >= along * length)
        & (np.abs(np.sum(tangent[j] * link, axis=1)) >= along * length)
        & (np.abs(np.sum(tangent[i] * tangent[j], axis=1)) >= along)
    )
    return _longest_paths(points, pairs[aligned], length[aligned], link_radius_px, min_points)


def join_at_crossings(
    branches: Sequence[Chain], line_width_px: float, link_radius_px: float
) -> list[Chain]:
    """``branches`` (open chains ending at crossings) joined end to end where one
    continues the other across a gap: each end's partner is the end that lies ahead of it
    within ``JOIN_GAP_WIDTHS`` line widths and whose own direction points back at it,
    both within ``JOIN_ANGLE_DEG`` (the straightest continuation, pairs taken best
    first). The joined curves (closed when the walk comes back to its start), longest
    first; nothing is inserted in a gap. The branches of a knot's image form one closed
    curve this way: going straight through every crossing of a knot diagram visits all
    of it."""
    # (position, outward direction) of each branch's start (2b) and stop (2b + 1)
    ends = [
        (pixels[0], _outward_direction(pixels))
        for branch in branches
        for pixels in (branch.pixels, branch.pixels[::-1])
    ]
    n_ends = 2 * len(branches)
    partner = np.full(n_ends, -1)
    if n_ends > 2:
        position = np.array([e[0] for e in ends])
        direction = np.array([e[1] for e in ends])
        tree = cKDTree(position)
        pairs = tree.query_pairs(JOIN_GAP_WIDTHS * line_width_px, output_type='ndarray')
        pairs = pairs[pairs[:, 0] // 2 != pairs[:, 1] // 2]  # (a branch's own two ends: a loop)
        gap = position[pairs[:, 1]] - position[pairs[:, 0]]
        gap /= np.maximum(np.linalg.norm(gap, axis=1, keepdims=True), 1e-9)
        ahead = np.sum(direction[pairs[:, 0]] * gap, axis=1)
        back = -np.sum(direction[pairs[:, 1]] * gap, axis=1)
        facing = -np.sum(direction[pairs[:, 0]] * direction[pairs[:, 1]], axis=1)
        worst = np.minimum(np.minimum(ahead, back), facing)
        continuing = worst >= np.cos(np.radians(JOIN_ANGLE_DEG))
        for a, b in _matching(pairs[continuing], 1.0 - worst[continuing], n_ends):
            partner[a], partner[b] = b, a
        # then ends left over that nearly touch, whatever their directions: at a cusp or a
        # tight loop of the image curve (a knot seen along a tangent) the points within a
        # crossing radius of a differently turned tangent are gone too, and the two arms
        # end side by side
        near = np.linalg.norm(position[pairs[:, 1]] - position[pairs[:, 0]], axis=1)
        for k in np.argsort(near):
            if near[k] > CUSP_GAP_RADII * (line_width_px + link_radius_px):
                break
            a, b = pairs[k]
            if partner[a] < 0 and partner[b] < 0:
                partner[a], partner[b] = b, a
    joined = []
    visited = np.zeros(len(branches), dtype=bool)
    for first in np.argsort([-b.length_px for b in branches]):
        if visited[first]:
            continue
        forward, closed = _walk(branches, partner, visited, 2 * first + 1)
        backward, _ = ([], False) if closed else _walk(branches, partner, visited, 2 * first)
        pieces = [p[::-1] for p in backward[::-1]] + [branches[first].pixels] + forward
        pixels, bridged = _bridged(pieces, closed)
        joined.append(Chain(pixels, closed, bridged))
    joined.sort(key=lambda c: -c.length_px)
    return joined


def _outward_direction(pixels: FloatArray) -> FloatArray:
    """Unit direction (2,) in which the chain ``pixels`` leaves its first point: from the
    point ``END_DIRECTION_PX`` back along it."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pixels, axis=0), axis=1))])
    back = pixels[min(int(np.searchsorted(arc, END_DIRECTION_PX)), len(pixels) - 1)]
    direction = pixels[0] - back
    return direction / max(float(np.linalg.norm(direction)), 1e-9)


def _bridged(pieces: Sequence[FloatArray], closed: bool) -> tuple[FloatArray, np.ndarray]:
    """The ``pieces`` (chains in walking order) as one chain, each gap between them (and
    the closing one if ``closed``) filled by points about a pixel apart on the cubic
    Hermite arc along both ends' directions, and the (N,) mask of those points. Views 2
    and 3 need the chain there: a true point projecting into another view's crossing gap
    was more than the support distance from its chain and refused, and a ghost took its
    sample (torus_knot seed 3: 30 of 1250 samples up to 0.4 m off). The arc is a guess
    (up to 4 px off across a cusp): the fits and view 1's samples leave it out."""
    joined: list[FloatArray] = []
    bridged: list[np.ndarray] = []
    following = list(pieces[1:]) + ([pieces[0]] if closed else [])
    for piece, after in zip(pieces, [*following, None]):
        joined.append(piece)
        bridged.append(np.zeros(len(piece), dtype=bool))
        if after is None:
            continue
        start, stop = piece[-1], after[0]
        length = float(np.linalg.norm(stop - start))
        count = int(np.ceil(length)) - 1
        if count < 1:
            continue
        t = (np.arange(1, count + 1) / (count + 1))[:, None]
        leaving = _outward_direction(piece[::-1]) * length
        entering = -_outward_direction(after) * length
        joined.append(
            (2 * t**3 - 3 * t**2 + 1) * start
            + (t**3 - 2 * t**2 + t) * leaving
            + (-2 * t**3 + 3 * t**2) * stop
            + (t**3 - t**2) * entering
        )
        bridged.append(np.ones(count, dtype=bool))
    return np.vstack(joined), np.concatenate(bridged)


def _matching(pairs: np.ndarray, cost: FloatArray, n_nodes: int) -> list[tuple[int, int]]:
    """Pairs (a, b) of nodes, each node in at most one: in each connected group of the
    candidate ``pairs`` the most pairs, and of those the least summed ``cost``. At a
    shallow crossing the straightest-looking pair can be wrong (two ends of different
    strands nearly in line): taken first, it left the other two ends unpaired, while
    both right pairs pass. Groups of up to MATCHING_GROUP nodes are searched
    exhaustively, larger ones greedily (cheapest pair first)."""
    _, label = (
        connected_components(
            coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n_nodes,) * 2),
            directed=False,
        )
        if len(pairs)
        else (0, np.arange(n_nodes))
    )
    chosen: list[tuple[int, int]] = []
    for group in np.unique(label[pairs[:, 0]]) if len(pairs) else []:
        inside = label[pairs[:, 0]] == group
        group_pairs, group_cost = pairs[inside].tolist(), cost[inside].tolist()
        if len(np.unique(pairs[inside])) <= MATCHING_GROUP:
            chosen += _best_matching(group_pairs, group_cost)[2]
            continue
        used: set[int] = set()
        for k in np.argsort(group_cost):
            a, b = group_pairs[k]
            if a not in used and b not in used:
                used |= {a, b}
                chosen.append((a, b))
    return chosen


def _best_matching(
    pairs: list[list[int]], cost: list[float]
) -> tuple[int, float, list[tuple[int, int]]]:
    """(number of pairs, summed cost, the pairs) of the matching of ``pairs`` with the
    most pairs and then the least cost (exhaustive: take the first pair or leave it)."""
    if not pairs:
        return 0, 0.0, []
    (a, b), rest, rest_cost = pairs[0], pairs[1:], cost[1:]
    without = _best_matching(rest, rest_cost)
    free = [k for k, (c, d) in enumerate(rest) if a not in (c, d) and b not in (c, d)]
    count, total, chosen = _best_matching([rest[k] for k in free], [rest_cost[k] for k in free])
    with_first = (count + 1, total + cost[0], [(a, b), *chosen])
    if (with_first[0], -with_first[1]) > (without[0], -without[1]):
        return with_first
    return without


def _walk(
    branches: Sequence[Chain], partner: np.ndarray, visited: np.ndarray, leave: int
) -> tuple[list[np.ndarray], bool]:
    """The branches' pixels met walking out of end ``leave`` through ``partner`` ends (each
    in walking order) until an unpaired end or a visited branch, and whether the walk came
    back to the branch it started from (a closed curve). Marks them ``visited``."""
    start = leave // 2
    visited[start] = True
    found: list[np.ndarray] = []
    end = partner[leave]
    while end >= 0:
        branch = end // 2
        if branch == start:
            return found, True
        if visited[branch]:
            break
        visited[branch] = True
        pixels = branches[branch].pixels
        found.append(pixels if end % 2 == 0 else pixels[::-1])
        end = partner[end ^ 1]
    return found, False
