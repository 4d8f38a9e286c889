"""The vertex LMI of eq. (28) for a fixed set of matrices A_k: find M > 0 with A_k^T M + M A_k + lambda M <= 0.

With f(x, u) = A(u) x + b(u) and A affine in u (eq. (27)) the A_k are A(u) at the vertices of U; with a Jacobian
decomposed into terms (:mod:`ashc_cli.design.contraction.terms`) they are the corners of the box of term values.  The
LMI is solved with cvxpy + Clarabel, maximising the margin t in A^T M + M A + lambda M <= t I under the
normalisation trace(M) = n, M >= 1e-3 I, and re-checked in numpy.  That normalisation bounds trace(M) / lambda_min(M)
by 4000, so a rate whose every M is more ill-conditioned is then tried scale-free (:func:`solve_lmi_scale_free`:
minimise the condition number, I <= M <= kappa I), and accepted only if the numpy re-check of its margin, relative to
||M||, is negative (:func:`certify_rate`, used by the fixed rate and by every step of the ``maximise`` bisection).
``maximise`` tries the eigenvalue bound on lambda first, and narrows its bracket from below by the rate each M found
certifies and from above by the infeasibility the solver's duals prove (:func:`largest_decay_rate`); the rate it
reports is always one its M certifies.  M is searched in full, or diagonal (``stabilisability.structure``).
The callers pass A_k divided by the plant's rate scale (:func:`lmi_scale`), so these tolerances are relative.
"""

from __future__ import annotations

import itertools

from ashc_cli.design.solvers import cp
import numpy as np
import scipy.linalg as sla

from ashc_cli.errors import NumericalError

NAME = "stabilise"


#: Smallest eigenvalue imposed on M (with trace(M) = n) so that M > 0 strictly.
M_MIN_EIG = 1e-3


#: A margin t must be below -MARGIN_TOL for lambda to count as feasible.
MARGIN_TOL = 1e-8


#: Relative width at which the bisection on lambda stops.
BISECTION_RTOL = 1e-4


SWEEP_POINTS = 201


#: The bisection raises its lower end to the rate an M found certifies, less this relative amount (so that
#: the numpy re-check sees a strictly negative margin, not a rounding-level zero).
CERTIFIED_BACKOFF = 1e-6


#: ``structure: auto`` searches a full M up to this many states (one Clarabel solve takes 0.65 s at n = 32
#: and 13 s at n = 64 on the 2-core machine), and a diagonal M first above it.
FULL_MAX_STATES = 32


#: The scale-free problem asks A^T M + M A + lambda M <= -SCALE_FREE_MARGIN kappa I with I <= M <= kappa I, so
#: its margin relative to ||M|| is at least this (ten times MARGIN_TOL, room for the solver's tolerance).
SCALE_FREE_MARGIN = 1e-7


def vertices(U: np.ndarray) -> np.ndarray:
    """The 2^m vertices of the box U, one per row.

    Parameters
    ----------
    U : ndarray (m, 2)
        The input box (``concrete.input_bounds``).

    Returns
    -------
    ndarray (2^m, m)
        In the order of ``itertools.product`` (the last input varying fastest).
    """
    return np.array(list(itertools.product(*[(lo, hi) for lo, hi in U])), dtype=float)


def sweep(U: np.ndarray, points: int = SWEEP_POINTS) -> np.ndarray:
    """Points of U to re-check the LMI on: a grid of about ``points`` points (rows).

    Parameters
    ----------
    U : ndarray (m, 2)
        The input box.
    points : int
        The number of points aimed at: k = max(2, round(points^(1/m))) per axis.

    Returns
    -------
    ndarray (k^m, m)
    """
    per_axis = max(2, int(round(points ** (1.0 / len(U)))))
    axes = [np.linspace(lo, hi, per_axis) for lo, hi in U]
    return np.array(list(itertools.product(*axes)), dtype=float)


def lmi_scale(A_list: list[np.ndarray]) -> float:
    """The plant's rate scale: the largest spectral radius of the A_k (its fastest time constant, whatever the
    units of the states), or the largest ||A_k||_2 where every eigenvalue is 0; 1 for an all-zero A.

    Parameters
    ----------
    A_list : list of ndarray (n, n)
        The vertex matrices, in the plant's units.

    Returns
    -------
    float
        A positive rate (1/time) the callers divide the A_k and the rates by.
    """
    s = max(float(np.abs(np.linalg.eigvals(A)).max()) for A in A_list)
    if not (np.isfinite(s) and s > 0):
        s = max(float(np.linalg.norm(A, 2)) for A in A_list)
    return s if np.isfinite(s) and s > 0 else 1.0


def lmi_margins(A_list: list[np.ndarray], M: np.ndarray, lam: float) -> np.ndarray:
    """Largest eigenvalue of A^T M + M A + lambda M for each A (<= 0 where eq. (28) holds).

    Parameters
    ----------
    A_list : list of ndarray (n, n)
        The vertex matrices.
    M : ndarray (n, n)
        Symmetric.
    lam : float
        The decay rate, in the units of A_list.

    Returns
    -------
    ndarray (len(A_list),)
    """
    return np.array([np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() for A in A_list])


def solve_with_clarabel(problem: cp.Problem, what: str) -> cp.Problem:
    """Solve with Clarabel; a solver failure becomes a NumericalError naming the problem.

    Parameters
    ----------
    problem : cvxpy Problem
    what : str
        The problem's name in the error message ("the LMI at lambda = 2 (full M)").

    Returns
    -------
    cvxpy Problem
        ``problem`` itself, solved (its status may still be infeasible or inaccurate).
    """
    try:
        problem.solve(solver=cp.CLARABEL)
    except cp.SolverError as exc:
        raise NumericalError(NAME, f"Clarabel failed on {what} ({exc})", "a solvable LMI") from None
    return problem


def unknown_M(n: int, structure: str) -> tuple[cp.Variable, cp.Expression, list]:
    """The matrix unknown of eq. (28) in the given structure, and the constraint M >= eps I for it.

    ``full``: a symmetric n x n variable (n (n + 1) / 2 unknowns, a dense LMI).  ``diagonal``: M = diag(d), n
    unknowns; the LMI then has the sparsity of A + A^T, which Clarabel's chordal decomposition splits into
    small cones, and M >= eps I is the linear constraint d >= eps (a network of stages is often diagonally
    stable with the stored energy as certificate).

    Parameters
    ----------
    n : int
        The number of states.
    structure : {"full", "diagonal"}
        The form of M (anything but ``diagonal`` is full).

    Returns
    -------
    var : cvxpy Variable
        The unknown: d (n,) for ``diagonal``, the symmetric (n, n) M for ``full``.
    M : cvxpy Expression (n, n)
        M in terms of ``var``.
    positive : list of cvxpy Constraint
        M >= M_MIN_EIG I.
    """
    if structure == "diagonal":
        d = cp.Variable(n)
        return d, cp.diag(d), [d >= M_MIN_EIG]
    M = cp.Variable((n, n), symmetric=True)
    return M, M, [M >> M_MIN_EIG * np.eye(n)]


def value_of_M(var: cp.Variable, structure: str) -> np.ndarray:
    """The numeric M (symmetrised) of a solved unknown.

    Parameters
    ----------
    var : cvxpy Variable
        The ``var`` of :func:`unknown_M`, after a solve.
    structure : {"full", "diagonal"}
        The structure it was made with.

    Returns
    -------
    ndarray (n, n)
    """
    if structure == "diagonal":
        return np.diag(np.asarray(var.value, dtype=float))
    return 0.5 * (var.value + var.value.T)


def solve_lmi(A_list: list[np.ndarray], lam: float, structure: str = "full") -> tuple[np.ndarray | None, float, str]:
    """Find M maximising the margin of eq. (28) at the given vertices for a fixed lambda (with the quadratic V of
    eq. (30), eq. (28) is Theorem 1's decrease condition, eq. (5b)).

    Parameters
    ----------
    A_list : list of ndarray
        A(u) at the vertices of U.
    lam : float
        The decay rate lambda.
    structure : {"full", "diagonal"}
        The form of M searched (see :func:`unknown_M`).

    Returns
    -------
    M : ndarray or None
        The solution (None if the solver found none).
    t : float
        The optimal margin: A^T M + M A + lambda M <= t I at every vertex (t < 0 when feasible).
    status : str
        cvxpy's status string.
    """
    M, t, status, _, _ = _max_margin(A_list, lam, structure)
    return M, t, status


#: Problems kept compiled (cvxpy's canonicalisation of a few thousand small LMIs costs seconds; a bisection re-solves
#: the same problem at a dozen rates, so the rate is a cvxpy Parameter and the compiled problem is reused).
_COMPILED: dict = {}
_COMPILED_MAX = 6


def _key(A_list: list[np.ndarray], *extra) -> tuple:
    import hashlib

    digest = hashlib.sha1(np.ascontiguousarray(np.stack(A_list)).tobytes()).hexdigest()
    return (digest, len(A_list), A_list[0].shape) + extra


def _remember(key: tuple, value):
    if len(_COMPILED) >= _COMPILED_MAX:
        _COMPILED.pop(next(iter(_COMPILED)))
    _COMPILED[key] = value
    return value


def _margin_problem(A_list: list[np.ndarray], structure: str, with_cone: bool):
    """The maximum-margin problem of :func:`_max_margin` with the rate as a Parameter (built once per vertex set)."""
    key = _key(A_list, structure, with_cone, "margin")
    if key in _COMPILED:
        return _COMPILED[key]
    n = A_list[0].shape[0]
    eye = np.eye(n)
    var, M, positive = unknown_M(n, structure)
    t = cp.Variable()
    rate = cp.Parameter(nonneg=True)
    lmis = [A.T @ M + M @ A + rate * M << t * eye for A in A_list]
    constraints = [cp.trace(M) == n] + (positive if with_cone else []) + lmis
    return _remember(key, (cp.Problem(cp.Minimize(t), constraints), var, t, lmis, rate))


def _max_margin(A_list: list[np.ndarray], lam: float, structure: str, cone: bool = True,
                hopeless_cone: bool = False) -> tuple[np.ndarray | None, float, str, float, list[np.ndarray] | None]:
    """:func:`solve_lmi`, the optimal margin without the cone M >= eps I (inf when that problem had none), and
    that problem's dual matrices (one per vertex; None without them).

    The second number decides whether the scale-free problem can help: any M > 0 with a negative margin,
    scaled to trace n, has a negative margin in the problem without the cone, so a non-negative optimum there
    means that lambda is infeasible for every M.  ``cone=False`` skips the problem with the cone (the caller
    knows it fails at this lambda); ``hopeless_cone`` skips it when the margin without the cone is already
    >= -MARGIN_TOL (the cone only raises the margin, so it cannot certify), returning that margin as t.
    """
    free_t, duals = np.inf, None
    # First without the cone M >= eps I (a third of the work at n = 64): when some A + lambda/2 I is Hurwitz,
    # the LMI with t < 0 already forces M > 0 (Lyapunov), and M is checked; otherwise solve with the cone.
    for with_cone in (False, True):
        if with_cone and not cone:
            return None, free_t, "not solved (the cone problem fails at a lower rate)", free_t, duals
        if with_cone and hopeless_cone and free_t >= -MARGIN_TOL:
            return None, free_t, "not solved (the margin without the cone is >= -MARGIN_TOL)", free_t, duals
        problem, var, t, lmis, rate = _margin_problem(A_list, structure, with_cone)
        rate.value = float(lam)
        problem = solve_with_clarabel(problem, f"the LMI at lambda = {lam:g} ({structure} M)")
        if var.value is None or t.value is None:
            if with_cone:
                return None, np.inf, str(problem.status), free_t, duals
            continue
        Mv = value_of_M(var, structure)
        if not with_cone:
            free_t = float(t.value)
            if all(c.dual_value is not None for c in lmis):
                duals = [np.asarray(c.dual_value, dtype=float) for c in lmis]
        if with_cone or (float(t.value) < -MARGIN_TOL and np.linalg.eigvalsh(Mv).min() >= M_MIN_EIG):
            return Mv, float(t.value), str(problem.status), free_t, duals
    return None, np.inf, "infeasible", free_t, duals


def infeasible_from(A_list: list[np.ndarray], Z_list: list[np.ndarray], lam: float, structure: str = "full") -> float:
    """A rate above which eq. (28) is infeasible, from dual matrices Z_k (one per vertex): inf if they prove nothing.

    For any Z_k >= 0 let W = sum Z_k and S(mu) = sum (A_k Z_k + Z_k A_k^T) + mu W.  An M > 0 feasible at mu
    gives 0 >= sum tr(Z_k (A_k^T M + M A_k + mu M)) = tr(M S(mu)), which is impossible when S(mu) >= 0 and
    S(mu) != 0; S(mu) grows with mu, so every rate from the smallest such mu on is infeasible.  For a diagonal
    M only diag(S(mu)) counts (>= 0 with a positive entry).  The Z_k are the solver's duals of the problem
    without the cone (projected onto Z >= 0), which put that mu at or below the probed lambda when the probed
    margin is >= 0.  The test is a numpy one, with a margin for rounding (S(mu) positive definite, or for a
    diagonal M diag(S(mu)) positive where W is non-zero); the bound only ends the search, it is never a
    certificate (the rate reported is always one its M certifies).

    Parameters
    ----------
    A_list : list of ndarray
        The vertex matrices.
    Z_list : list of ndarray
        One symmetric n x n matrix per vertex.
    lam : float
        The probed rate: mu is sought in [0, lam].
    structure : {"full", "diagonal"}

    Returns
    -------
    float
        The smallest mu in [0, lam] (to 1e-12 relative) at which the test passes, or inf if it fails at lam.
    """
    Zs = []
    for Z in Z_list:
        w, V = np.linalg.eigh(0.5 * (Z + Z.T))
        Zs.append((V * np.clip(w, 0.0, None)) @ V.T)
    S0 = sum(A @ Z + Z @ A.T for A, Z in zip(A_list, Zs))
    W = sum(Zs)
    scale = np.abs(S0).max() + lam * np.abs(W).max()
    if not np.isfinite(scale) or scale == 0:
        return np.inf
    floor = 1e-9 * scale           # S(mu) must be positive by more than the rounding of its sums
    if structure == "diagonal":
        # A row where Z vanishes (W_jj = 0, so S_jj = 0 exactly) adds nothing; every other S_jj must be > 0.
        active = np.diag(W) > 0

        def proves(mu: float) -> bool:
            d = np.diag(S0) + mu * np.diag(W)
            return bool(active.any() and d[active].min() > floor and np.all(d[~active] >= 0))
    else:
        def proves(mu: float) -> bool:
            return bool(np.linalg.eigvalsh(S0 + mu * W).min() > floor)
    if not proves(lam):
        return np.inf
    a, b = 0.0, lam
    if proves(a):
        return a
    while b - a > 1e-12 * lam:
        mid = 0.5 * (a + b)
        a, b = (a, mid) if proves(mid) else (mid, b)
    return b


def solve_lmi_scale_free(A_list: list[np.ndarray], lam: float, structure: str = "full") -> tuple[np.ndarray | None, float, str]:
    """Find M for eq. (28) at a fixed lambda whatever its scaling: the best-conditioned one.

    Minimise kappa subject to I <= M <= kappa I and A^T M + M A + lambda M <= -SCALE_FREE_MARGIN kappa I at
    every vertex.  Without the lower bound every constraint is homogeneous in (M, kappa), so feasibility does
    not depend on how M is scaled (unlike trace(M) = n with M >= 1e-3 I, which caps trace(M) / lambda_min(M)
    at 4000), and the margin relative to ||M|| <= kappa is at least SCALE_FREE_MARGIN.

    Parameters
    ----------
    A_list : list of ndarray (n, n)
        The vertex matrices (divided by the rate scale, as lam).
    lam : float
        The decay rate.
    structure : {"full", "diagonal"}
        The form of M.

    Returns
    -------
    M : ndarray or None
        The solution scaled to trace(M) = n (None if the solver found none).
    kappa : float
        The condition number bound of the solution (inf without one).
    status : str
        cvxpy's status string.
    """
    n = A_list[0].shape[0]
    key = _key(A_list, structure, "scale_free")
    if key in _COMPILED:
        problem, var, kappa, rate = _COMPILED[key]
    else:
        eye = np.eye(n)
        kappa = cp.Variable()
        rate = cp.Parameter(nonneg=True)
        if structure == "diagonal":
            var = cp.Variable(n)
            M = cp.diag(var)
            constraints = [var >= 1.0, var <= kappa]
        else:
            var = M = cp.Variable((n, n), symmetric=True)
            constraints = [M >> eye, M << kappa * eye]
        constraints += [A.T @ M + M @ A + rate * M << -SCALE_FREE_MARGIN * kappa * eye for A in A_list]
        problem, var, kappa, rate = _remember(key, (cp.Problem(cp.Minimize(kappa), constraints), var, kappa, rate))
    rate.value = float(lam)
    problem = solve_with_clarabel(problem, f"the scale-free LMI at lambda = {lam:g} ({structure} M)")
    if var.value is None or kappa.value is None:
        return None, np.inf, str(problem.status)
    Mv = value_of_M(var, structure)
    return n * Mv / np.trace(Mv), float(kappa.value), str(problem.status)


def relative_margin(A_list: list[np.ndarray], M: np.ndarray, lam: float) -> float:
    """Largest eigenvalue of A^T M + M A + lambda M over the vertices, over ||M||_2 (numpy; < 0: certified).

    Parameters
    ----------
    A_list, M, lam
        As for :func:`lmi_margins` (M positive definite).

    Returns
    -------
    float
    """
    return float(lmi_margins(A_list, M, lam).max() / np.linalg.eigvalsh(M).max())


def certify_rate(A_list: list[np.ndarray], lam: float, structure: str = "full", cone: bool = True,
                 scale_free: bool = True) -> tuple[np.ndarray | None, float, str, dict]:
    """An M certifying eq. (28) at lambda, or None: the feasibility test of a fixed rate and of the bisection.

    First the maximum-margin problem (:func:`solve_lmi`; accepted when its margin is below -MARGIN_TOL, as
    before, and the numpy margin of its M is negative), then, unless that problem shows lambda infeasible for
    every M, the scale-free one (:func:`solve_lmi_scale_free`), accepted only when the numpy margin of its M
    relative to ||M|| is below -MARGIN_TOL (the solver's word is not taken near the edge of feasibility).
    The maximum-margin problem with the cone is not solved when the one without it already has a margin
    >= -MARGIN_TOL (it could not certify), nor with ``cone=False`` (the bisection knows it fails here); the
    scale-free problem not with ``scale_free=False``.

    Parameters
    ----------
    A_list : list of ndarray (n, n)
        The vertex matrices (divided by the rate scale, as lam).
    lam : float
        The decay rate to certify.
    structure : {"full", "diagonal"}
        The form of M.
    cone : bool
        False: skip the maximum-margin problem with the cone M >= eps I.
    scale_free : bool
        False: skip the scale-free problem.

    Returns
    -------
    M : ndarray or None
    t : float
        The maximum-margin problem's optimal margin (for messages; without the cone when that one was skipped).
    status : str
    info : dict
        ``formulation`` ("max_margin" or "scale_free"), and for the scale-free one its condition number bound
        and re-checked relative margin, when M is found.  Always: ``cone_failed`` (the cone problem cannot
        certify this rate, hence no higher one) and ``infeasible_from`` (a rate above which no M exists, by
        :func:`infeasible_from`; inf when not shown).
    """
    M, t, status, free_t, duals = _max_margin(A_list, lam, structure, cone=cone, hopeless_cone=True)
    failed = {"cone_failed": not cone or t >= -MARGIN_TOL, "infeasible_from": np.inf}
    if M is not None and t < -MARGIN_TOL and lmi_margins(A_list, M, lam).max() < 0:
        return M, t, status, {"formulation": "max_margin", "cone_failed": False, "infeasible_from": np.inf}
    # Necessary: every vertex has Re eig(A) < -lambda / 2; and the problem without the cone must have t < 0.
    if free_t >= 0 or any(np.linalg.eigvals(A).real.max() >= -0.5 * lam for A in A_list):
        if free_t >= 0 and duals is not None:
            failed["infeasible_from"] = infeasible_from(A_list, duals, lam, structure)
        return None, t, status, failed
    if not scale_free:
        return None, t, status, failed
    Ms, kappa, status_s = solve_lmi_scale_free(A_list, lam, structure)
    if Ms is None or not np.all(np.isfinite(Ms)):
        return None, t, status, failed
    rel = relative_margin(A_list, Ms, lam)
    if rel < -MARGIN_TOL and np.linalg.eigvalsh(Ms).min() > 0:
        return Ms, t, status_s, {**failed, "formulation": "scale_free", "condition_bound": kappa, "relative_margin": rel}
    return None, t, status, failed


def largest_decay_rate(A_list: list[np.ndarray], structure: str = "full", info: dict | None = None) -> tuple[float, np.ndarray | None]:
    """The largest lambda for which eq. (28) is feasible, by bisection on lambda, and its M.

    lambda cannot exceed -2 max Re eig(A) at any vertex (A^T M + M A <= -lambda M forces Re eig(A) <= -lambda / 2),
    which brackets the search; it stops when the bracket is narrower than BISECTION_RTOL times that bound.
    Without feedback each trial rate is decided by :func:`certify_rate` (maximum margin, then scale-free, both
    re-checked), so the answer does not depend on how M is normalised, and:

    * first the bound itself less half the tolerance, with the maximum-margin problem only (the scale-free one
      costs about four times as much at n = 64, and its M grows ill-conditioned towards a supremum that is not
      attained): the bound is often attained (one vertex, a ladder of cells), and then this one test ends the
      search.  Failing there leaves the bracket as it was unless the duals prove more (it would narrow it by
      half the tolerance only), so the bisection that follows is the one without this try (for the quarter car
      the scale-free M near the supremum depends on the exact rates tried);
    * each M found certifies its own rate (:func:`largest_decay_rate_for`), often well above the trial value,
      and that raises the lower end (the rate returned is always one an M certifies, less CERTIFIED_BACKOFF);
    * a rate the maximum-margin problem without the cone shows infeasible lowers the upper end to where its
      duals prove infeasibility (:func:`infeasible_from`), often well below the trial value;
    * above a rate where the maximum-margin problem with the cone M >= eps I failed it is not solved again (its
      margin only grows with lambda);
    * a solver failure at one rate counts as "not certified there" (re-raised if no rate is certified).

    ``info``, if given, receives certify_rate's description of the M returned and ``upper_bound``, the upper end
    of the final bracket (no rate above it was certified).

    Parameters
    ----------
    A_list : list of ndarray (n, n)
        The vertex matrices (the stage divides them by the rate scale, :func:`lmi_scale`).
    structure : {"full", "diagonal"}
        The form of M.
    info : dict, optional
        Filled as said above (cleared first), when an M is found.

    Returns
    -------
    lam : float
        The largest rate certified, in the units of A_list; 0 when none is.
    M : ndarray (n, n) or None
        Its certificate (trace(M) = n); None when no rate is certified.

    Raises
    ------
    NumericalError
        The last solver failure, when no rate was certified.
    """
    upper = min(-2.0 * np.linalg.eigvals(A).real.max() for A in A_list)
    if upper <= 0:
        return 0.0, None
    lo, hi, best = 0.0, upper, None
    cone_fails_from, failure = np.inf, None
    trial, first = (1.0 - 0.5 * BISECTION_RTOL) * upper, True
    while hi - lo > BISECTION_RTOL * upper:
        try:
            M, _, _, how = certify_rate(A_list, trial, structure, cone=trial < cone_fails_from, scale_free=not first)
        except NumericalError as exc:
            M, how, failure = None, {}, exc
        if M is not None:
            lo, best = max(trial, min(hi, (1.0 - CERTIFIED_BACKOFF) * largest_decay_rate_for(A_list, M))), M
            if info is not None:
                info.clear()
                info.update({k: v for k, v in how.items() if k not in ("cone_failed", "infeasible_from")})
        else:
            hi = max(lo, min(upper if first else trial, how.get("infeasible_from", np.inf)))
        if how.get("cone_failed"):
            cone_fails_from = min(cone_fails_from, trial)
        trial, first = 0.5 * (lo + hi), False
    if best is None and failure is not None:
        raise failure
    if info is not None and best is not None:
        info["upper_bound"] = hi
    return lo, best


def largest_decay_rate_for(A_list: list[np.ndarray], M: np.ndarray) -> float:
    """The largest lambda a given M certifies: min over vertices of the generalised eigenvalues of
    -(A^T M + M A) relative to M.

    Parameters
    ----------
    A_list : list of ndarray (n, n)
        The vertex matrices.
    M : ndarray (n, n)
        Symmetric positive definite.

    Returns
    -------
    float
        In the units of A_list; <= 0 when M certifies no positive rate.
    """
    return float(min(sla.eigh(-(A.T @ M + M @ A), M, eigvals_only=True).min() for A in A_list))


def structures(choice: str, n: int) -> list[str]:
    """The forms of M to try, in order, for ``stabilisability.structure`` (see :data:`FULL_MAX_STATES`).

    Parameters
    ----------
    choice : str
        ``stabilisability.structure``: ``auto``, ``full`` or ``diagonal``.
    n : int
        The number of states.

    Returns
    -------
    list of str
        ``[choice]``, or for ``auto`` ``["full"]`` up to FULL_MAX_STATES states and ``["diagonal", "full"]`` above.
    """
    if choice != "auto":
        return [choice]
    return ["full"] if n <= FULL_MAX_STATES else ["diagonal", "full"]

