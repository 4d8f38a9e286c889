"""The feedback LMI: K and M with (A_k + B K)^T M + M (A_k + B K) <= -lambda M at every vertex, the smallest gain.

``feedback: linear_gain`` synthesises K so that k(z, x, u) = u + K (z - x) renders the pair incrementally stable
(Definition 1); the interface then adds K (x - p(xi)) (eq. (15)).  In X = M^-1 and Y = K X the condition is an LMI.
"""

from __future__ import annotations

from ashc_cli.design.solvers import cp
import numpy as np

from ashc_cli.errors import NumericalError
from ashc_cli.design.contraction.vertex import BISECTION_RTOL, CERTIFIED_BACKOFF, value_of_M, solve_with_clarabel, unknown_M, largest_decay_rate_for, lmi_margins


#: With a synthesised feedback the decay rate is searched up to this cap (1/s) by ``maximise``.
FEEDBACK_MAX_RATE = 100.0


#: The feedback LMI is imposed at the rate lambda (1 + FEEDBACK_RATE_MARGIN) so that the numpy re-check at
#: lambda sees a strictly negative margin (the problem minimises the gain, not the margin).
FEEDBACK_RATE_MARGIN = 1e-3


#: Condition numbers tried for X = M^-1 (I <= X <= kappa I), smallest first: the smallest gain over a set of
#: well-conditioned M.  Without a cap the least gain is approached only as M degenerates (the uniform gain G,
#: through dbar = sup ||sqrt(M) dp/dxi delta||, then grows without bound).
FEEDBACK_CONDITION = (1e2, 1e4, 1e6)


def solve_lmi_feedback(A_list: list[np.ndarray], B: np.ndarray, lam: float, structure: str = "full",
                       weights: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray | None, float, str]:
    """M and the smallest gain K with (A + B K)^T M + M (A + B K) <= -lambda M at every vertex, for a fixed lambda:
    the decrease of the plant and its copy (eq. (3)) under k(z, x, u) = u + K (z - x).

    In X = M^-1 and Y = K X the condition is the LMI A X + X A^T + B Y + Y^T B^T + lambda X <= 0 (imposed at
    lambda (1 + FEEDBACK_RATE_MARGIN), so the re-check at lambda is strict).  Among the solutions with
    I <= X <= kappa I the one with the smallest weighted gain is taken: minimise mu subject to
    Z >= Y X^-1 Y^T = K X K^T (a Schur complement) and Z_ii <= mu w_i^2, w_i half the width of input i's range.
    K X K^T is what the certified region of a saturating interface pays for (|K_i e| <= sqrt(c K_i X K_i^T) on
    {W <= c}, :func:`bound.certified_region`), so the smallest gain certifies the largest region.  kappa runs
    through :data:`FEEDBACK_CONDITION` until the LMI is feasible.  (A maximum-margin problem is unbounded when B
    has full row rank, and with a rank-deficient B returns gains of order 10^3 that shrink the region to nothing.)

    Parameters
    ----------
    A_list : list of ndarray
        The vertex matrices.
    B : ndarray (n, m)
        The constant input matrix.
    lam : float
        The decay rate.
    structure : {"full", "diagonal"}
        The form of X (and M).
    weights : ndarray (m,), optional
        Half-widths of the input ranges (default 1).

    Returns
    -------
    M, K : ndarray or None
        None if no gain makes the LMI feasible.
    mu : float
        The optimal weighted gain max_i K_i X K_i^T / w_i^2 (inf without a solution).
    status : str
        cvxpy's status string, with the condition cap used.
    """
    # The loosest cap first: its feasible set holds every tighter one's, so when the solver declares it infeasible no
    # cap is feasible (a refinement round or a bisection step that fails costs one solve, not three).  Otherwise the
    # tightest feasible cap is used, as if tried in order.
    loosest = FEEDBACK_CONDITION[-1]
    last = _min_gain(A_list, B, lam, structure, weights, loosest)
    if last[0] is None and "infeasible" in last[3]:
        return None, None, np.inf, last[3]
    status = "not solved"
    for kappa in FEEDBACK_CONDITION:
        M, K, mu, status = _min_gain(A_list, B, lam, structure, weights, kappa) if kappa != loosest else last
        if M is not None:
            return M, K, mu, f"{status} (I <= M^-1 <= {kappa:g} I)"
    return None, None, np.inf, status


def _min_gain(A_list: list[np.ndarray], B: np.ndarray, lam: float, structure: str, weights: np.ndarray | None,
              kappa: float) -> tuple[np.ndarray | None, np.ndarray | None, float, str]:
    """:func:`solve_lmi_feedback` for one condition cap kappa (a solver failure counts as no solution)."""
    n, m = B.shape
    var, X, _ = unknown_M(n, structure)
    Y = cp.Variable((m, n))
    Z = cp.Variable((m, m), symmetric=True)
    mu = cp.Variable()
    w = np.ones(m) if weights is None else np.asarray(weights, dtype=float)
    eye = np.eye(n)
    probe = lam * (1.0 + FEEDBACK_RATE_MARGIN)
    constraints = [X >> eye, X << kappa * eye, cp.bmat([[Z, Y], [Y.T, X]]) >> 0, cp.diag(Z) <= mu * w**2]
    constraints += [A @ X + X @ A.T + B @ Y + Y.T @ B.T + probe * X << 0 for A in A_list]
    try:
        problem = solve_with_clarabel(cp.Problem(cp.Minimize(mu), constraints), f"the feedback LMI at lambda = {lam:g} ({structure} M)")
    except NumericalError as exc:
        return None, None, np.inf, exc.what
    if var.value is None or mu.value is None or problem.status not in ("optimal", "optimal_inaccurate"):
        return None, None, np.inf, str(problem.status)
    Xv = value_of_M(var, structure)
    if not np.all(np.isfinite(Xv)) or np.linalg.eigvalsh(Xv).min() <= 0:
        return None, None, np.inf, str(problem.status)
    M = np.linalg.inv(Xv)
    M = 0.5 * (M + M.T)
    K = np.asarray(Y.value, dtype=float) @ M
    if lmi_margins([A + B @ K for A in A_list], M, lam).max() >= 0:   # an inaccurate solve is not a certificate
        return None, None, np.inf, f"{problem.status} (the re-check of its M, K fails)"
    return M, K, float(mu.value), str(problem.status)


def largest_feedback_rate(A_list: list[np.ndarray], B: np.ndarray, structure: str, weights: np.ndarray | None = None) -> tuple[float, tuple | None]:
    """:func:`largest_decay_rate` with a synthesised gain K: bisection on lambda up to FEEDBACK_MAX_RATE (any rate
    may be reachable with feedback), each M, K found raising the lower end to the rate it certifies; the K
    returned is the smallest gain (:func:`solve_lmi_feedback`) at the rate found.

    Parameters
    ----------
    A_list : list of ndarray (n, n)
        The vertex matrices (the stage divides them by the rate scale, :func:`lmi_scale`).
    B : ndarray (n, m)
        The constant input matrix (divided by the same scale).
    structure : {"full", "diagonal"}
        The form of X = M^-1.
    weights : ndarray (m,), optional
        Half-widths of the input ranges (default 1).

    Returns
    -------
    lam : float
        The rate found, in the units of A_list (0 when no gain certifies any rate).
    found : tuple of ndarray or None
        (M, K), M (n, n) and K (m, n), certifying lam; None when no rate was certified.
    """
    upper = FEEDBACK_MAX_RATE
    lo, hi, best = 0.0, upper, None
    while hi - lo > BISECTION_RTOL * upper:
        mid = 0.5 * (lo + hi)
        try:
            M, K, _, _ = solve_lmi_feedback(A_list, B, mid, structure, weights)
        except NumericalError:
            M = K = None        # an inaccurate or failed solve: not certified at this rate
        if M is not None:
            closed_loop = [A + B @ K for A in A_list]
            lo, best = max(mid, min(hi, (1.0 - CERTIFIED_BACKOFF) * largest_decay_rate_for(closed_loop, M))), (M, K)
        else:
            hi = mid
    if best is not None:
        # The gain minimised at the rate reported (the bisection's M, K may hold a larger gain).
        M, K, _, _ = solve_lmi_feedback(A_list, B, lo, structure, weights)
        if M is not None:
            best = (M, K)
    return lo, best

