"""The thesis's redundant IK (ALGORITHMS.md §6.5): the continuous primal-dual network
integrated exactly (``primal_dual_velocity``, ``method: primal_dual``) and its literal
fixed-step rules (``primal_dual_velocity_fixed_step``, which diverge at the thesis's values,
A7.4; the benchmark's). The problem they solve is in ``problem``; ours is in ``ik``. No ROS
here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.linalg

from pa10_ik_node.problem import (
    TWIST_DIM,
    absolute_weights,
    check_problem,
    initial_vector,
    null_space_positive,
)
from vgm_common.errors import InvalidInput
from vgm_common.geometry import FloatArray


@dataclass(frozen=True)
class PrimalDualInfo:
    """How a ``primal_dual_velocity`` solve went.

    Attributes:
        converged: both residuals are at most the requested tolerance.
        constraint_residual: ||J v - rdot_d|| at the end [m/s, rad/s mixed].
        stationarity_residual: ||W_used v + J^T u|| at the end.
        null_space_positive: ``W`` (the one given) is positive definite on null(J).
        min_null_eigenvalue: smallest eigenvalue of N^T W N (``inf`` if null(J) = {0}).
        fallback_used: ``weights_fallback`` replaced ``W`` because the check failed.
        gain: the K actually used (raised from the one given when H was not positive
            definite, see ``primal_dual_velocity``).
        min_h_eigenvalue: smallest eigenvalue of H = W_used + gain J^T J.
        t_final: integrated time of the network [s of network time].
    """

    converged: bool
    constraint_residual: float
    stationarity_residual: float
    null_space_positive: bool
    min_null_eigenvalue: float
    fallback_used: bool
    gain: float
    min_h_eigenvalue: float
    t_final: float


def primal_dual_velocity(
    J: npt.ArrayLike,
    W: npt.ArrayLike,
    rdot_d: npt.ArrayLike,
    K: float = 100.0,
    v0: npt.ArrayLike | None = None,
    u0: npt.ArrayLike | None = None,
    t_final: float = 1e5,
    tol: float = 1e-6,
    weights_fallback: npt.ArrayLike | None = None,
    null_space_tol: float = 1e-9,
    max_gain: float = 1e6,
) -> tuple[FloatArray, FloatArray, PrimalDualInfo]:
    """The thesis's continuous primal-dual network (7.4.9-7.4.12), integrated exactly.

    With ``H = W + K J^T J`` the network is

        vdot = -H v - J^T u + K J^T rdot_d,    udot = J v - rdot_d,

    linear with constant coefficients within a control step, so the state ``(v, u)`` at
    ``t_final`` is the exact solution: the matrix exponential of the affine system's
    augmented matrix applied to ``(v0, u0, 1)``. That is stiff-proof (A7.4) and as cheap
    for long horizons as for short ones. The slowest mode decays at about 1/K, so the
    default horizon is long in network time. Warm-start with the previous step's
    ``(v, u)``.

    Stability needs ``H`` positive definite (the Lyapunov argument of §6.5). If ``W`` is
    not positive definite on null(J) no K achieves that (A7.3); then ``weights_fallback``
    (default ``absolute_weights(W)``) replaces ``W`` and ``info.fallback_used`` says so.
    If ``W`` passes that test but ``H`` is still indefinite at the given K (K = 100 is not
    always enough, notably for the real PA-10's short links), K is doubled until it is, up
    to ``max_gain``; the KKT point does not depend on K. ``info.gain`` reports the K used.

    Args:
        J: (6, n) Jacobian; W: (n, n) symmetric weight; rdot_d: (6,) twist [m/s, rad/s].
        K: penalty gain (> 0).
        v0, u0: initial state (n,) [rad/s] and (6,); zeros when None.
        t_final: network time to integrate (> 0).
        tol: residual tolerance for ``info.converged``.
        weights_fallback: (n, n) weight used when the null-space check fails.
        null_space_tol: margin of the null-space check.
        max_gain: largest K tried when raising it.

    Returns:
        (qdot, lam, info): v (n,) [rad/s], u (6,) and a ``PrimalDualInfo``.

    Raises:
        InvalidInput: on wrong shapes, non-finite input or non-positive K / t_final.
    """
    J, W, rdot_d = check_problem(J, W, rdot_d)
    n = J.shape[1]
    if not K > 0 or not t_final > 0:
        raise InvalidInput(f'K and t_final must be > 0, got {K}, {t_final}', 'K', K)
    v0 = initial_vector(v0, n, 'v0')
    u0 = initial_vector(u0, TWIST_DIM, 'u0')
    positive, min_eig = null_space_positive(J, W, null_space_tol)
    W_used = W
    if not positive:
        W_used = (
            absolute_weights(W)
            if weights_fallback is None
            else check_problem(J, weights_fallback)[1]
        )
    gain = float(K)
    min_h_eig = np.linalg.eigvalsh(W_used + gain * J.T @ J)[0]
    while positive and min_h_eig <= 0 and 2 * gain <= max_gain:
        gain *= 2
        min_h_eig = np.linalg.eigvalsh(W_used + gain * J.T @ J)[0]
    # Augmented affine system: d/dt (v, u, 1) = M (v, u, 1).
    size = n + TWIST_DIM
    M = np.zeros((size + 1, size + 1))
    M[:n, :n] = -(W_used + gain * J.T @ J)
    M[:n, n:size] = -J.T
    M[n:size, :n] = J
    M[:n, size] = gain * J.T @ rdot_d
    M[n:size, size] = -rdot_d
    state = scipy.linalg.expm(M * t_final) @ np.concatenate([v0, u0, [1.0]])
    v, u = state[:n], state[n:size]
    constraint = float(np.linalg.norm(J @ v - rdot_d))
    stationarity = float(np.linalg.norm(W_used @ v + J.T @ u))
    info = PrimalDualInfo(
        converged=bool(constraint <= tol and stationarity <= tol),
        constraint_residual=constraint,
        stationarity_residual=stationarity,
        null_space_positive=positive,
        min_null_eigenvalue=min_eig,
        fallback_used=not positive,
        gain=gain,
        min_h_eigenvalue=float(min_h_eig),
        t_final=float(t_final),
    )
    return v, u, info


def fixed_step_matrix(
    J: npt.ArrayLike, W: npt.ArrayLike, K: float = 100.0, mu: float = 0.02, eta: float = 0.02
) -> FloatArray:
    """The (n+6, n+6) linear part of the literal learning rules of §6.5 on ``(qdot, lam)``.

    Its spectral radius decides whether ``primal_dual_velocity_fixed_step`` converges
    (< 1) or diverges (> 1); at the thesis's Gamma1 start it is about 108 (A7.4).
    """
    J, W = check_problem(J, W)
    n = J.shape[1]
    return np.block(
        [[np.eye(n) - mu * (W + K * J.T @ J), -mu * J.T], [eta * J, np.eye(TWIST_DIM)]]
    )


def primal_dual_velocity_fixed_step(
    J: npt.ArrayLike,
    W: npt.ArrayLike,
    rdot_d: npt.ArrayLike,
    K: float = 100.0,
    mu: float = 0.02,
    eta: float = 0.02,
    iterations: int = 100,
    v0: npt.ArrayLike | None = None,
    u0: npt.ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The thesis's discrete learning rules of §6.5, taken literally.

        qdot_{k+1} = qdot_k - mu [W qdot_k + J^T lam_k + K J^T (J qdot_k - rdot_d)]
        lam_{k+1}  = lam_k + eta (J qdot_k - rdot_d)

    Kept for the benchmark: at mu = eta = 0.02, K = 100 they diverge on the PA-10 (A7.4).

    Args:
        J: (6, n); W: (n, n); rdot_d: (6,) [m/s, rad/s]; K, mu, eta: gain and step sizes.
        iterations: number of updates.
        v0, u0: initial (n,) and (6,); zeros when None.

    Returns:
        (qdot, lam, norms): the final iterates and ``norms`` (iterations + 1,), the
        Euclidean norm of (qdot_k, lam_k) at every iterate, starting with the initial one.
    """
    J, W, rdot_d = check_problem(J, W, rdot_d)
    n = J.shape[1]
    qdot = initial_vector(v0, n, 'v0')
    lam = initial_vector(u0, TWIST_DIM, 'u0')
    norms = [np.hypot(np.linalg.norm(qdot), np.linalg.norm(lam))]
    for _ in range(int(iterations)):
        residual = J @ qdot - rdot_d
        qdot, lam = (qdot - mu * (W @ qdot + J.T @ lam + K * J.T @ residual), lam + eta * residual)
        norms.append(np.hypot(np.linalg.norm(qdot), np.linalg.norm(lam)))
    return qdot, lam, np.array(norms)
