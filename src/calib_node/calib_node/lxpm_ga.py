"""The thesis's real-coded LX-PM genetic algorithm (ALGORITHMS.md §3.4, A4.4-A4.6) and the
stereo calibration objective (4.3.2) it minimises.

The whole population is evaluated in one call of the objective, (P, D) -> (P,); only the
generations are a Python loop. Every random draw comes from the caller's
``numpy.random.Generator``, so a seed fixes the result.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from calib_node.seed_camera import PopulationCost
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray

LX_VARIANTS = ('printed', 'symmetric')
LX_DRAWS = ('gene', 'pair')  # one phi per gene (A4.5's resolution) or one per parent pair

Objective = Callable[[FloatArray], npt.ArrayLike]  # (P, D) population -> (P,) costs


class GAResult(NamedTuple):
    """What :func:`lxpm_ga` found: the best individual, its cost and the best cost per
    generation."""

    best: np.ndarray  # (D,) best individual found
    best_cost: float
    history: np.ndarray  # (generations,) best cost after each generation, non-increasing


def laplace_phi(
    u: npt.ArrayLike, a: float = 0.0, b: float = 0.15, variant: str = 'printed'
) -> FloatArray:
    """Laplace crossover spread phi for uniform draws u in (0, 1) (4.4.1, A4.5).

    ``'printed'``: a - b ln u for u <= 1/2, else a + b ln u (half the draws >= a + b ln 2,
    the rest in (a - b ln 2, a]). ``'symmetric'``: the Laplace quantile a + b ln 2u for
    u <= 1/2, else a - b ln(2 - 2u).
    """
    draws = np.maximum(np.asarray(u, dtype=float), np.finfo(float).tiny)  # never ln 0
    low = draws <= 0.5
    if variant == 'printed':
        return np.where(low, a - b * np.log(draws), a + b * np.log(draws))
    if variant == 'symmetric':
        with np.errstate(divide='ignore'):
            return np.where(low, a + b * np.log(2 * draws), a - b * np.log(2 - 2 * draws))
    raise InvalidInput(
        f'lx_variant: expected one of {LX_VARIANTS}, got {variant!r}', key='lx_variant'
    )


def laplace_crossover(
    x1: FloatArray,
    x2: FloatArray,
    rng: np.random.Generator,
    probability: float = 0.9,
    a: float = 0.0,
    b: float = 0.15,
    variant: str = 'printed',
    draw: str = 'gene',
) -> tuple[FloatArray, FloatArray]:
    """Children of the (M, D) parent pairs: y_i = x_i + phi |x1 - x2|, one phi per gene
    (``draw='gene'``, A4.5) or one per pair (``'pair'``).

    Each pair crosses with ``probability``, otherwise its children are copies.
    Returns (y1, y2), each (M, D), not clipped.
    """
    cross = rng.random(int(x1.shape[0])) < probability  # int(): else the stub's float overload
    if draw not in LX_DRAWS:
        raise InvalidInput(f'lx_draw: expected one of {LX_DRAWS}, got {draw!r}', key='lx_draw')
    shape = x1.shape if draw == 'gene' else (x1.shape[0], 1)
    phi = laplace_phi(rng.random(shape), a, b, variant)
    spread = np.where(cross[:, None], phi * np.abs(x1 - x2), 0.0)
    return x1 + spread, x2 + spread


def power_mutation(
    x: FloatArray,
    lower: FloatArray,
    upper: FloatArray,
    rng: np.random.Generator,
    probability: float = 0.005,
    index: float = 0.25,
) -> FloatArray:
    """Power mutation of each gene of (M, D) ``x`` with ``probability`` (A4.4).

    s = s1^(1/index), t = (x - xl) / (xu - xl), r ~ U[0, 1]: y = x - s (x - xl) if t < r,
    else y = x + s (xu - x). For x in [xl, xu] the result stays in [xl, xu].
    """
    mutate = rng.random(x.shape) < probability
    s = rng.random(x.shape) ** (1.0 / index)
    r = rng.random(x.shape)
    width = upper - lower
    t = (x - lower) / np.where(width > 0, width, 1.0)
    y = np.where(t < r, x - s * (x - lower), x + s * (upper - x))
    return np.where(mutate, y, x)


def tournament_select(
    cost: FloatArray, count: int, rng: np.random.Generator, size: int = 3
) -> npt.NDArray[np.int64]:
    """Indices (count,) of the winners of ``count`` tournaments of ``size`` (lowest cost)."""
    entrants = rng.integers(0, cost.shape[0], size=(count, size))
    return entrants[np.arange(count), np.argmin(cost[entrants], axis=1)]


def _evaluate(objective: Objective, population: FloatArray) -> FloatArray:
    cost = np.asarray(objective(population), dtype=float)
    if cost.shape != (population.shape[0],):
        raise InvalidInput(
            f'objective: expected shape ({population.shape[0]},), got {cost.shape}',
            key='objective',
        )
    return np.where(np.isnan(cost), np.inf, cost)


def lxpm_ga(
    objective: Objective,
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    rng: np.random.Generator,
    population: int = 240,
    generations: int = 200,
    crossover_probability: float = 0.9,
    mutation_probability: float = 0.005,
    laplace_a: float = 0.0,
    laplace_b: float = 0.15,
    pm_index: float = 0.25,
    lx_variant: str = 'printed',
    tournament: int = 3,
    elitism: int = 1,
    progress: Callable[[int, float], object] | None = None,
    lx_draw: str = 'gene',
) -> GAResult:
    """Minimise ``objective`` over the box [lower, upper] with the LX-PM GA (§3.4).

    Uniform initialisation in the box; each generation: ``tournament`` selection, Laplace
    crossover of consecutive winners, clipping to the box, power mutation, then the
    ``elitism`` best of the previous generation replace the worst children.

    Args:
        objective: (P, D) -> (P,) costs; NaN counts as +inf.
        lower, upper: (D,) bounds, lower <= upper.
        rng: ``numpy.random.Generator``, the only source of randomness.
        progress: optional ``progress(generation, best_cost)``, called with generation 0
            after the initial evaluation and after each generation 1..generations.

    Returns:
        GAResult(best (D,), best_cost, history (generations,)).

    Raises:
        ValueError: on bad bounds, sizes or ``lx_variant``.
    """
    lower = np.array(lower, dtype=float)
    upper = np.array(upper, dtype=float)
    if lower.ndim != 1 or lower.shape != upper.shape or np.any(lower > upper):
        raise InvalidInput(
            f'lower, upper: expected equal (D,) shapes with lower <= upper, '
            f'got {lower.shape} and {upper.shape}'
        )
    if lx_variant not in LX_VARIANTS:
        raise InvalidInput(
            f'lx_variant: expected one of {LX_VARIANTS}, got {lx_variant!r}', key='lx_variant'
        )
    if population < 2 or not 0 <= elitism < population or tournament < 1:
        raise InvalidInput(
            f'need population >= 2, 0 <= elitism < population and '
            f'tournament >= 1, got {population}, {elitism}, {tournament}'
        )
    pairs = (population + 1) // 2

    x = lower + rng.random((population, lower.size)) * (upper - lower)
    cost = _evaluate(objective, x)
    if progress is not None:
        progress(0, float(cost.min()))
    history = np.empty(generations)
    for generation in range(generations):
        elite = np.argsort(cost, kind='stable')[:elitism]
        parents = x[tournament_select(cost, 2 * pairs, rng, tournament)]
        y1, y2 = laplace_crossover(
            parents[0::2],
            parents[1::2],
            rng,
            crossover_probability,
            laplace_a,
            laplace_b,
            lx_variant,
            lx_draw,
        )
        children = np.clip(np.concatenate([y1, y2])[:population], lower, upper)
        children = power_mutation(children, lower, upper, rng, mutation_probability, pm_index)
        child_cost = _evaluate(objective, children)
        worst = np.argsort(child_cost, kind='stable')[population - elitism :]
        children[worst], child_cost[worst] = x[elite], cost[elite]
        x, cost = children, child_cost
        history[generation] = cost.min()
        if progress is not None:
            progress(generation + 1, float(history[generation]))
    best = int(np.argmin(cost))
    return GAResult(best=x[best].copy(), best_cost=float(cost[best]), history=history)


def stereo_objective(
    points_world: npt.ArrayLike,
    pixels_left: npt.ArrayLike,
    pixels_right: npt.ArrayLike,
    distortion: str = 'implicit',
) -> Callable[[npt.ArrayLike], FloatArray]:
    """The calibration cost (4.3.2) with the full §3.2 model (A4.3): (P, 24) -> (P,).

    Columns 0..11 are the left camera, 12..23 the right, each in ``PARAM_NAMES`` order.
    The cost is the sum over the N points of the squared pixel residuals in both images
    [px^2]; an individual that puts any point at Z <= 0 in either camera costs +inf.

    Args:
        points_world: (N, 3) control points [unit].
        pixels_left, pixels_right: (N, 2) observed pixels (u, v).
    """
    points_world = np.array(points_world, dtype=float)
    observed = [np.array(pixels_left, dtype=float), np.array(pixels_right, dtype=float)]
    if points_world.ndim != 2 or points_world.shape[1] != 3:
        raise InvalidInput(
            f'points_world: expected shape (N, 3), got {points_world.shape}', key='points_world'
        )
    for name, pixels in zip(('pixels_left', 'pixels_right'), observed):
        if pixels.shape != (points_world.shape[0], 2):
            raise InvalidInput(
                f'{name}: expected shape ({points_world.shape[0]}, 2), got {pixels.shape}'
            )

    costs = [PopulationCost(points_world, pixels, distortion) for pixels in observed]

    def cost(q: npt.ArrayLike) -> FloatArray:
        q = np.asarray(q, dtype=float)
        if q.ndim != 2 or q.shape[1] != 24:
            raise InvalidInput(f'q: expected shape (P, 24), got {q.shape}', key='q')
        return costs[0](q[:, :12]) + costs[1](q[:, 12:])

    return cost


def rig_objective(
    observations: Iterable[tuple[npt.ArrayLike, npt.ArrayLike]], distortion: str = 'implicit'
) -> Callable[[npt.ArrayLike], FloatArray]:
    """The cost (4.3.2) of M cameras with their own point sets: (P, 12 M) -> (P,).

    ``observations``: list of (points_world (N_c, 3), pixels (N_c, 2)) per camera; genes
    12 c .. 12 c + 11 are camera c in ``PARAM_NAMES`` order. The sum of the squared pixel
    residuals over every camera [px^2]; +inf where a point is at Z <= 0. With the same
    points in two cameras it is :func:`stereo_objective`.
    """
    cameras: list[tuple[FloatArray, FloatArray]] = []
    for points_world, pixels in observations:
        points_world = np.array(points_world, dtype=float)
        pixels = np.array(pixels, dtype=float)
        if (
            points_world.ndim != 2
            or points_world.shape[1] != 3
            or pixels.shape != (points_world.shape[0], 2)
        ):
            raise InvalidInput(
                f'observations: expected (N, 3) points and (N, 2) pixels, got '
                f'{points_world.shape} and {pixels.shape}'
            )
        cameras.append((points_world, pixels))

    costs = [PopulationCost(points_world, pixels, distortion) for points_world, pixels in cameras]

    def cost(q: npt.ArrayLike) -> FloatArray:
        q = np.asarray(q, dtype=float)
        if q.ndim != 2 or q.shape[1] != 12 * len(cameras):
            raise InvalidInput(
                f'q: expected shape (P, {12 * len(cameras)}), got {q.shape}', key='q'
            )
        total = np.zeros(q.shape[0])
        for c, camera_cost in enumerate(costs):
            total += camera_cost(q[:, 12 * c : 12 * c + 12])
        return total

    return cost
