"""Stage 1: asymptotic stabilisability by a quadratic incremental Lyapunov function (eq. egLMI).

With f(x, u) = A(u) x + b(u) and A affine in u (eq. ConvertSystemLinear), V(x, z) = (x - z)^T M (x - z)
(eq. egV) satisfies Theorem StabiliseLyap with k(z, x, u) = u when

    A(u)^T M + M A(u) <= -lambda M,   M > 0                                          (eq. egLMI)

for all u in U; since the left side is affine in u it suffices to impose it at the vertices of the box U.
The LMI is solved with cvxpy + Clarabel, maximising the margin t in A^T M + M A + lambda M <= t I under
the normalisation trace(M) = n, M >= 1e-3 I, and re-checked in numpy at the vertices and on a sweep of U.
That normalisation bounds trace(M) / lambda_min(M) by 4000, so a rate whose every M is more ill-conditioned
is refused by it; such a rate is then tried scale-free (:func:`solve_lmi_scale_free`: minimise the condition
number, I <= M <= kappa I), and accepted only if the numpy re-check of its margin, relative to ||M||, is
negative (:func:`certify_rate`, used by the fixed rate and by every step of the ``maximise`` bisection).
``maximise`` tries the eigenvalue bound on lambda first (often attained: then one solve decides), and narrows
its bracket from below by the rate each M found certifies and from above by the infeasibility the solver's
duals prove (:func:`largest_decay_rate`); the rate it reports is always one its M certifies.
M is searched in full, or diagonal (``stabilisability.structure``; ``auto`` tries a diagonal M first above
:data:`FULL_MAX_STATES` states, where the dense SDP grows like n^6: 13 s at n = 64, 300 s and 7.7 GiB at 128).

When f is not affine in x, the same LMI is imposed on a polytope that contains the Jacobian df/dx over
``concrete.state_box`` x U (:func:`jacobian_polytope`); the certificate then holds for solutions in that box.

``feedback: linear_gain`` (a plant that is not incrementally stable, with g(x) = B constant) synthesises K so
that k(z, x, u) = u + K (z - x) renders the pair incrementally stable: with X = M^-1 and Y = K X the
condition (A(u) + B K)^T M + M (A(u) + B K) <= -lambda M becomes the LMI
A X + X A^T + B Y + Y^T B^T + lambda X <= t I (t < 0); the interface then adds K (x - p(xi)) (eq. Interface).
"""

from __future__ import annotations

import itertools

import cvxpy as cp
import numpy as np
import scipy.linalg as sla
import sympy as sp
from flint import arb

from .. import proofs
from ..artefacts import Artefact, Check
from ..errors import DesignError, NumericalError, SpecError
from ..grids import domain_grid, maximise_on_box
from ..model import Model, jumps, sparse_jacobian, tidy

NAME = "stabilise"
UPSTREAM: tuple[str, ...] = ()

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
#: With a synthesised feedback the decay rate is searched up to this cap (1/s) by ``maximise``.
FEEDBACK_MAX_RATE = 100.0
#: The scale-free problem asks A^T M + M A + lambda M <= -SCALE_FREE_MARGIN kappa I with I <= M <= kappa I, so
#: its margin relative to ||M|| is at least this (ten times MARGIN_TOL, room for the solver's tolerance).
SCALE_FREE_MARGIN = 1e-7


def affine_form(model: Model, J: sp.Matrix | None = None) -> tuple[sp.Matrix, sp.Matrix]:
    """Write f(x, u) = A(u) x + b(u) symbolically (eq. ConvertSystemLinear).

    ``J``, if given, is df/dx already computed (A is that Jacobian when f is affine in x).

    Returns
    -------
    A, b : sympy Matrix
        A(u) (n x n, affine in u) and b(u) (n x 1).

    Raises
    ------
    DesignError
        If f is not affine in x, or A is not affine in u.
    """
    A = sparse_jacobian(model.f, model.x) if J is None else J
    xs, us = set(model.x), list(model.u)
    for (i, j), e in np.ndenumerate(np.array(A, dtype=object)):
        if e.free_symbols & xs:
            raise DesignError("concrete", f"f(x, u) is not affine in x: df{i + 1}/d{model.x[j]} = {e} depends on x",
                              "f(x, u) = A(u) x + b(u) for stabilisability.method polytopic_lmi or given")
        if not e.free_symbols.intersection(us):
            continue
        for a, b in itertools.product(us, us):
            second = sp.diff(e, a, b)
            if second != 0 and sp.simplify(second) != 0:   # simplify only what is not plainly zero
                raise DesignError("concrete", f"A(u) is not affine in u: entry ({i + 1}, {j + 1}) = {e}",
                                  "A(u) affine in u so that the LMI at the vertices of U covers all of U")
    b = tidy(sp.expand(model.f - A * model.x))
    for i, e in enumerate(b):
        if e.free_symbols & xs:
            raise DesignError("concrete", f"f(x, u) is not affine in x: f{i + 1} - (A x){i + 1} = {e} depends on x (a jump such as sign(x) has a zero "
                              "derivative almost everywhere but is not affine)",
                              "f(x, u) = A(u) x + b(u), or a concrete.state_box on which f is Lipschitz and C^1 almost everywhere")
    return tidy(A), b


#: At most this many Jacobian entries may vary over the state box (the polytope has 2^k vertices).
MAX_VARYING_ENTRIES = 12
RANGE_SAMPLES = 40000
#: Seconds the branch and bound may spend enclosing one end of one Jacobian entry's range (then the range is
#: only sampled, and the LMI row says so).
ENCLOSURE_TIME_BUDGET = 20.0
#: Relative width at which that branch and bound stops (the enclosure is rigorous at any width; a tighter one
#: only makes the LMI less conservative).
ENCLOSURE_RTOL = 1e-6


def refuse_jumps(model: Model) -> None:
    """Refuse an f with a jump (sign, square, step of a state) inside state_box x U: the Jacobian LMI's mean-value
    argument needs f Lipschitz there.  (abs, min and max are Lipschitz and handled by their generalised derivatives.)

    Raises
    ------
    DesignError
        Naming the field, the function and where its argument crosses the jump.
    """
    fields = [(f"concrete.f_bar[{i}]", e) for i, e in enumerate(model.f_bar)]
    fields += [(f"concrete.g[{i}][{j}]", model.g[i, j]) for i in range(model.n) for j in range(model.m)]
    proofs.refuse_jumps(model, fields, list(model.x) + list(model.u), np.r_[model.state_box, model.U],
                        "f is not Lipschitz on state_box x U, so no Jacobian LMI (eq. egLMI) can certify it",
                        "a smooth approximation of the jump", check="lmi_margin")


def jacobian_polytope(model: Model, J: sp.Matrix | None = None) -> tuple[sp.Matrix, list[np.ndarray], np.ndarray, dict]:
    """A polytope containing the Jacobian df/dx(x, u) for x in ``concrete.state_box`` and u in U.

    For f not affine in x, V(x, z) = (x - z)^T M (x - z) decays at rate lambda along any pair of solutions
    that stay in the (convex) state box if J^T M + M J <= -lambda M for every J = df/dx(s, u) with s in the
    box (the mean-value form f(x, u) - f(z, u) = int_0^1 J(z + s (x - z), u) ds (x - z)).  Each entry of J
    that varies is enclosed over box x U by ball arithmetic with branch and bound (:func:`proofs.range_on_box`:
    rigorous at any width, so a steep term such as tanh(50000 x) whose derivative peaks in a band 1e-4 wide is
    inside the range), and the LMI is imposed at the 2^k vertices of the box of entry ranges, which contains J.
    Where ball arithmetic cannot enclose an entry (or the enclosure is not finite), its range comes from a
    grid refined by bounded local searches, widened by 1e-9 relative: the LMI is then only *sampled*
    (``meta["ranges_proved"]`` is False) and ``ashc check`` says so.

    Returns
    -------
    J : sympy Matrix
        df/dx(x, u).
    A_list : list of ndarray
        The vertex matrices.
    ranges : ndarray, shape (k, 2)
        The range of each varying entry.
    meta : dict
        Which entries vary, how their ranges were found (``ranges_proved``), and the sampled ranges beside them.

    Raises
    ------
    SpecError
        Without ``concrete.state_box``.
    DesignError
        If more than ``MAX_VARYING_ENTRIES`` entries vary, or an entry is unbounded on the box.
    """
    if model.state_box is None:
        raise SpecError("concrete.state_box", "missing: f(x, u) is not affine in x, so the incremental LMI is imposed on the Jacobian over a box of states",
                        "one pair [lo, hi] per state (the region the design is certified on)")
    J = sparse_jacobian(model.f, model.x) if J is None else J
    args = list(model.x) + list(model.u)
    box = np.r_[model.state_box, model.U]
    varying = [(i, j) for (i, j), e in np.ndenumerate(np.array(J, dtype=object)) if e.free_symbols & set(args)]
    if len(varying) > MAX_VARYING_ENTRIES:
        raise DesignError("concrete", f"{len(varying)} Jacobian entries vary over the state box (at most {MAX_VARYING_ENTRIES}: the polytope has 2^k vertices)",
                          "fewer state-dependent terms, or f affine in x")
    pts = domain_grid(box, RANGE_SAMPLES)
    ranges, sampled, how = [], [], []
    for i, j in varying:
        name = f"df{i + 1}/d{model.x[j]}"
        fun = model.numeric([J[i, j]], args)
        vals = np.broadcast_to(fun(*pts)[0, 0], pts.shape[1])
        if not np.all(np.isfinite(vals)):
            bad = pts[:, int(np.argmax(~np.isfinite(vals)))]
            raise DesignError("concrete.state_box", f"{name} is not finite on the box (at {np.round(bad, 6).tolist()})", "a box on which f is C^1")
        hi, _ = maximise_on_box(pts, vals, lambda z, fun=fun: float(fun(*z)[0, 0]), box)
        neg_lo, _ = maximise_on_box(pts, -vals, lambda z, fun=fun: -float(fun(*z)[0, 0]), box)
        lo = -neg_lo
        sampled.append((lo, hi))
        enclosed = _enclose_entry(model, J[i, j], args, box)
        if enclosed is not None:
            ranges.append(enclosed)
            how.append("enclosed")
        else:
            pad = 1e-9 * max(1.0, abs(lo), abs(hi))
            ranges.append((lo - pad, hi + pad))
            how.append("sampled")
    J0 = np.array(model.substitute(J.xreplace({a: 0 for a in args})), dtype=float)
    A_list = []
    for corner in itertools.product(*ranges):
        A = J0.copy()
        for (i, j), value in zip(varying, corner):
            A[i, j] = value
        A_list.append(A)
    proved = all(h == "enclosed" for h in how)
    meta = {"jacobian_entries": [f"df{i + 1}/d{model.x[j]}" for i, j in varying],
            "state_box": model.state_box.tolist(), "ranges_proved": proved,
            "range_method": ("ball-arithmetic enclosure over box x U by branch and bound (rigorous)" if proved else
                             "enclosure where ball arithmetic reaches, else a grid of box x U refined by L-BFGS-B and widened 1e-9 (sampled): "
                             + ", ".join(f"{n} {h}" for n, h in zip((f'df{i + 1}/d{model.x[j]}' for i, j in varying), how))),
            "ranges_sampled": [list(r) for r in sampled]}
    return J, A_list, np.array(ranges, dtype=float).reshape(-1, 2), meta


def _enclose_entry(model: Model, entry: sp.Expr, args: list, box: np.ndarray) -> tuple[float, float] | None:
    """Proved bounds lo <= entry <= hi over the box (ball arithmetic, branch and bound), or None where ball
    arithmetic cannot enclose the entry or the enclosure is not finite."""
    try:
        fun = proofs.compile_claims(model, [entry], args)
    except proofs.interval.UnsupportedExpression:
        return None
    lo, ok_lo = proofs.inf_on_box(fun, box, rtol=ENCLOSURE_RTOL, time_budget=ENCLOSURE_TIME_BUDGET)
    hi, ok_hi, _ = proofs.sup_on_box(fun, box, rtol=ENCLOSURE_RTOL, time_budget=ENCLOSURE_TIME_BUDGET)
    return (lo, hi) if ok_lo and ok_hi else None


def jacobian_samples(model: Model, J: sp.Matrix, count: int = 2000, seed: int = 2) -> tuple[list[np.ndarray], np.ndarray]:
    """df/dx at random points of state_box x U (the numpy re-check of the Jacobian LMI), and the points (rows of (x, u))."""
    rng = np.random.default_rng(seed)
    box = np.r_[model.state_box, model.U]
    pts = rng.uniform(box[:, 0:1], box[:, 1:2], size=(len(box), count))
    values = np.broadcast_to(model.numeric(J, list(model.x) + list(model.u))(*pts), J.shape + (count,))
    return list(np.moveaxis(values, -1, 0)), pts.T


def vertices(U: np.ndarray) -> np.ndarray:
    """The 2^m vertices of the box U, one per row."""
    return np.array(list(itertools.product(*[(lo, hi) for lo, hi in U])), dtype=float)


def sweep(U: np.ndarray, points: int = SWEEP_POINTS) -> np.ndarray:
    """Points of U to re-check the LMI on: a grid of about ``points`` points (rows)."""
    per_axis = max(2, int(round(points ** (1.0 / len(U)))))
    axes = [np.linspace(lo, hi, per_axis) for lo, hi in U]
    return np.array(list(itertools.product(*axes)), dtype=float)


def lmi_scale(A_list: list[np.ndarray]) -> float:
    """The plant's rate scale: the largest spectral radius of the A_k (its fastest time constant, whatever the
    units of the states), or the largest ||A_k||_2 where every eigenvalue is 0; 1 for an all-zero A."""
    s = max(float(np.abs(np.linalg.eigvals(A)).max()) for A in A_list)
    if not (np.isfinite(s) and s > 0):
        s = max(float(np.linalg.norm(A, 2)) for A in A_list)
    return s if np.isfinite(s) and s > 0 else 1.0


def lmi_margins(A_list: list[np.ndarray], M: np.ndarray, lam: float) -> np.ndarray:
    """Largest eigenvalue of A^T M + M A + lambda M for each A (<= 0 where eq. egLMI holds)."""
    return np.array([np.linalg.eigvalsh(A.T @ M + M @ A + lam * M).max() for A in A_list])


def _solve(problem: cp.Problem, what: str) -> cp.Problem:
    """Solve with Clarabel; a solver failure becomes a NumericalError naming the problem."""
    try:
        problem.solve(solver=cp.CLARABEL)
    except cp.SolverError as exc:
        raise NumericalError(NAME, f"Clarabel failed on {what} ({exc})", "a solvable LMI") from None
    return problem


def _unknown(n: int, structure: str) -> tuple[cp.Variable, cp.Expression, list]:
    """The matrix unknown of eq. egLMI in the given structure, and the constraint M >= eps I for it.

    ``full``: a symmetric n x n variable (n (n + 1) / 2 unknowns, a dense LMI).  ``diagonal``: M = diag(d), n
    unknowns; the LMI then has the sparsity of A + A^T, which Clarabel's chordal decomposition splits into
    small cones, and M >= eps I is the linear constraint d >= eps (a network of stages is often diagonally
    stable with the stored energy as certificate).
    """
    if structure == "diagonal":
        d = cp.Variable(n)
        return d, cp.diag(d), [d >= M_MIN_EIG]
    M = cp.Variable((n, n), symmetric=True)
    return M, M, [M >> M_MIN_EIG * np.eye(n)]


def _matrix(var: cp.Variable, structure: str) -> np.ndarray:
    """The numeric M (symmetrised) of a solved unknown."""
    if structure == "diagonal":
        return np.diag(np.asarray(var.value, dtype=float))
    return 0.5 * (var.value + var.value.T)


def solve_lmi(A_list: list[np.ndarray], lam: float, structure: str = "full") -> tuple[np.ndarray | None, float, str]:
    """Find M maximising the margin of eq. egLMI at the given vertices for a fixed lambda.

    Parameters
    ----------
    A_list : list of ndarray
        A(u) at the vertices of U.
    lam : float
        The decay rate lambda.
    structure : {"full", "diagonal"}
        The form of M searched (see :func:`_unknown`).

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
    n = A_list[0].shape[0]
    eye = np.eye(n)
    free_t, duals = np.inf, None
    # First without the cone M >= eps I (a third of the work at n = 64): when some A + lambda/2 I is Hurwitz,
    # the LMI with t < 0 already forces M > 0 (Lyapunov), and M is checked; otherwise solve with the cone.
    for with_cone in (False, True):
        if with_cone and not cone:
            return None, free_t, "not solved (the cone problem fails at a lower rate)", free_t, duals
        if with_cone and hopeless_cone and free_t >= -MARGIN_TOL:
            return None, free_t, "not solved (the margin without the cone is >= -MARGIN_TOL)", free_t, duals
        var, M, positive = _unknown(n, structure)
        t = cp.Variable()
        lmis = [A.T @ M + M @ A + lam * M << t * eye for A in A_list]
        constraints = [cp.trace(M) == n] + (positive if with_cone else []) + lmis
        problem = _solve(cp.Problem(cp.Minimize(t), constraints), f"the LMI at lambda = {lam:g} ({structure} M)")
        if var.value is None or t.value is None:
            if with_cone:
                return None, np.inf, str(problem.status), free_t, duals
            continue
        Mv = _matrix(var, structure)
        if not with_cone:
            free_t = float(t.value)
            if all(c.dual_value is not None for c in lmis):
                duals = [np.asarray(c.dual_value, dtype=float) for c in lmis]
        if with_cone or (float(t.value) < -MARGIN_TOL and np.linalg.eigvalsh(Mv).min() >= M_MIN_EIG):
            return Mv, float(t.value), str(problem.status), free_t, duals
    return None, np.inf, "infeasible", free_t, duals


def infeasible_from(A_list: list[np.ndarray], Z_list: list[np.ndarray], lam: float, structure: str = "full") -> float:
    """A rate above which eq. egLMI is infeasible, from dual matrices Z_k (one per vertex): inf if they prove nothing.

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
    """Find M for eq. egLMI at a fixed lambda whatever its scaling: the best-conditioned one.

    Minimise kappa subject to I <= M <= kappa I and A^T M + M A + lambda M <= -SCALE_FREE_MARGIN kappa I at
    every vertex.  Without the lower bound every constraint is homogeneous in (M, kappa), so feasibility does
    not depend on how M is scaled (unlike trace(M) = n with M >= 1e-3 I, which caps trace(M) / lambda_min(M)
    at 4000), and the margin relative to ||M|| <= kappa is at least SCALE_FREE_MARGIN.

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
    eye = np.eye(n)
    kappa = cp.Variable()
    if structure == "diagonal":
        var = cp.Variable(n)
        M = cp.diag(var)
        constraints = [var >= 1.0, var <= kappa]
    else:
        var = M = cp.Variable((n, n), symmetric=True)
        constraints = [M >> eye, M << kappa * eye]
    constraints += [A.T @ M + M @ A + lam * M << -SCALE_FREE_MARGIN * kappa * eye for A in A_list]
    problem = _solve(cp.Problem(cp.Minimize(kappa), constraints), f"the scale-free LMI at lambda = {lam:g} ({structure} M)")
    if var.value is None or kappa.value is None:
        return None, np.inf, str(problem.status)
    Mv = _matrix(var, structure)
    return n * Mv / np.trace(Mv), float(kappa.value), str(problem.status)


def relative_margin(A_list: list[np.ndarray], M: np.ndarray, lam: float) -> float:
    """Largest eigenvalue of A^T M + M A + lambda M over the vertices, over ||M||_2 (numpy; < 0: certified)."""
    return float(lmi_margins(A_list, M, lam).max() / np.linalg.eigvalsh(M).max())


def certify_rate(A_list: list[np.ndarray], lam: float, structure: str = "full", cone: bool = True,
                 scale_free: bool = True) -> tuple[np.ndarray | None, float, str, dict]:
    """An M certifying eq. egLMI at lambda, or None: the feasibility test of a fixed rate and of the bisection.

    First the maximum-margin problem (:func:`solve_lmi`; accepted when its margin is below -MARGIN_TOL, as
    before, and the numpy margin of its M is negative), then, unless that problem shows lambda infeasible for
    every M, the scale-free one (:func:`solve_lmi_scale_free`), accepted only when the numpy margin of its M
    relative to ||M|| is below -MARGIN_TOL (the solver's word is not taken near the edge of feasibility).
    The maximum-margin problem with the cone is not solved when the one without it already has a margin
    >= -MARGIN_TOL (it could not certify), nor with ``cone=False`` (the bisection knows it fails here); the
    scale-free problem not with ``scale_free=False``.

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


#: The feedback LMI is imposed at the rate lambda (1 + FEEDBACK_RATE_MARGIN) so that the numpy re-check at
#: lambda sees a strictly negative margin (the problem minimises the gain, not the margin).
FEEDBACK_RATE_MARGIN = 1e-3
#: Condition numbers tried for X = M^-1 (I <= X <= kappa I), smallest first: the smallest gain over a set of
#: well-conditioned M.  Without a cap the least gain is approached only as M degenerates (the uniform gain G,
#: through dbar = sup ||sqrt(M) dp/dxi delta||, then grows without bound).
FEEDBACK_CONDITION = (1e2, 1e4, 1e6)


def solve_lmi_feedback(A_list: list[np.ndarray], B: np.ndarray, lam: float, structure: str = "full",
                       weights: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray | None, float, str]:
    """M and the smallest gain K with (A + B K)^T M + M (A + B K) <= -lambda M at every vertex, for a fixed lambda.

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
    status = "not solved"
    for kappa in FEEDBACK_CONDITION:
        M, K, mu, status = _min_gain(A_list, B, lam, structure, weights, kappa)
        if M is not None:
            return M, K, mu, f"{status} (I <= M^-1 <= {kappa:g} I)"
    return None, None, np.inf, status


def _min_gain(A_list: list[np.ndarray], B: np.ndarray, lam: float, structure: str, weights: np.ndarray | None,
              kappa: float) -> tuple[np.ndarray | None, np.ndarray | None, float, str]:
    """:func:`solve_lmi_feedback` for one condition cap kappa (a solver failure counts as no solution)."""
    n, m = B.shape
    var, X, _ = _unknown(n, structure)
    Y = cp.Variable((m, n))
    Z = cp.Variable((m, m), symmetric=True)
    mu = cp.Variable()
    w = np.ones(m) if weights is None else np.asarray(weights, dtype=float)
    eye = np.eye(n)
    probe = lam * (1.0 + FEEDBACK_RATE_MARGIN)
    constraints = [X >> eye, X << kappa * eye, cp.bmat([[Z, Y], [Y.T, X]]) >> 0, cp.diag(Z) <= mu * w**2]
    constraints += [A @ X + X @ A.T + B @ Y + Y.T @ B.T + probe * X << 0 for A in A_list]
    try:
        problem = _solve(cp.Problem(cp.Minimize(mu), constraints), f"the feedback LMI at lambda = {lam:g} ({structure} M)")
    except NumericalError as exc:
        return None, None, np.inf, exc.what
    if var.value is None or mu.value is None or problem.status not in ("optimal", "optimal_inaccurate"):
        return None, None, np.inf, str(problem.status)
    Xv = _matrix(var, structure)
    if not np.all(np.isfinite(Xv)) or np.linalg.eigvalsh(Xv).min() <= 0:
        return None, None, np.inf, str(problem.status)
    M = np.linalg.inv(Xv)
    M = 0.5 * (M + M.T)
    K = np.asarray(Y.value, dtype=float) @ M
    if lmi_margins([A + B @ K for A in A_list], M, lam).max() >= 0:   # an inaccurate solve is not a certificate
        return None, None, np.inf, f"{problem.status} (the re-check of its M, K fails)"
    return M, K, float(mu.value), str(problem.status)


def largest_decay_rate(A_list: list[np.ndarray], B: np.ndarray | None = None, structure: str = "full",
                       info: dict | None = None) -> tuple[float, np.ndarray | None]:
    """The largest lambda for which eq. egLMI is feasible, by bisection on lambda, and its M.

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
    """
    if B is not None:
        return _largest_feedback_rate(A_list, B, structure)   # the gain-minimising path: _synthesise_feedback
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


def _largest_feedback_rate(A_list: list[np.ndarray], B: np.ndarray, structure: str, weights: np.ndarray | None = None) -> tuple[float, tuple | None]:
    """:func:`largest_decay_rate` with a synthesised gain K: bisection on lambda up to FEEDBACK_MAX_RATE (any rate
    may be reachable with feedback), each M, K found raising the lower end to the rate it certifies; the K
    returned is the smallest gain (:func:`solve_lmi_feedback`) at the rate found."""
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


def largest_decay_rate_for(A_list: list[np.ndarray], M: np.ndarray) -> float:
    """The largest lambda a given M certifies: min over vertices of the generalised eigenvalues of
    -(A^T M + M A) relative to M."""
    return float(min(sla.eigh(-(A.T @ M + M @ A), M, eigvals_only=True).min() for A in A_list))


def _ball_lmi(A: list[list], M: np.ndarray, lam: float) -> list[list]:
    """-(A^T M + M A + lambda M) with A a ball matrix (eq. egLMI as a matrix that must be >= 0)."""
    n = len(A)
    Mb = proofs.matrix_balls(M)
    MA = [[sum((Mb[i][k] * A[k][j] for k in range(n)), arb(0)) for j in range(n)] for i in range(n)]
    return [[-(MA[j][i] + MA[i][j] + arb(lam) * Mb[i][j]) for j in range(n)] for i in range(n)]


def prove_lmi(model: Model, A_sym: sp.Matrix, verts: np.ndarray, affine: bool, K: np.ndarray, M: np.ndarray, lam: float,
              ranges_proved: bool = False) -> tuple[float, str]:
    """A proved upper bound of the largest eigenvalue of A_cl^T M + M A_cl + lambda M over U (or state_box x U).

    The vertex argument: the LMI is affine in A_cl, so it holds on the convex hull of the vertex matrices
    once it holds at each of them.  For f affine in x with A(u) affine in u the vertices are A(u_k) at the
    vertices of U; for the Jacobian polytope they are the corners of the box of entry ranges, enclosed by ball
    arithmetic over state_box x U in :func:`jacobian_polytope` (``ranges_proved``; sampled ranges prove
    nothing).  Each vertex matrix is formed in ball arithmetic from the formulas (parameters exact as doubles)
    and its LMI proved by an arb Cholesky.

    Returns
    -------
    margin : float
        The proved bound (inf when no proof was found).
    how : str
        What was proved, or why not.
    """
    if model.n > proofs.MAX_PROOF_STATES:
        return np.inf, f"not attempted above {proofs.MAX_PROOF_STATES} states"
    args = list(model.u) if affine else list(model.x) + list(model.u)
    if affine and not proofs.affine_in(A_sym, model.u):
        return np.inf, "A(u) is not affine in u, so its vertices do not bound it"
    if not affine and not ranges_proved:
        return np.inf, "the ranges of the Jacobian entries over state_box x U were only sampled (ball arithmetic could not enclose them)"
    try:
        fA = proofs.BoxFunction(model, {"A": A_sym}, args)
        BK = None
        if np.any(K != 0):
            fB = proofs.BoxFunction(model, {"g": model.g}, list(model.x))
            B = fB([arb(0)] * model.n)["g"]
            Kb = proofs.matrix_balls(K)
            BK = [[sum((B[i][k] * Kb[k][j] for k in range(model.m)), arb(0)) for j in range(model.n)] for i in range(model.n)]
        if affine:
            corners = [fA([arb(float(c)) for c in vtx])["A"] for vtx in verts]
        else:
            box = np.r_[model.state_box, model.U]
            A_any = fA(proofs.ball_box(box))["A"]            # constant entries are thin balls
            varying = [(i, j) for (i, j), e in np.ndenumerate(np.array(A_sym, dtype=object)) if e.free_symbols & set(args)]
            corners = []
            for corner in itertools.product(*[tuple(r) for r in verts]):
                A = [row[:] for row in A_any]
                for (i, j), value in zip(varying, corner):
                    A[i][j] = arb(float(value))
                corners.append(A)
        worst = -np.inf
        for A in corners:
            Acl = A if BK is None else [[A[i][j] + BK[i][j] for j in range(model.n)] for i in range(model.n)]
            worst = max(worst, -proofs.psd_lower_bound_balls(_ball_lmi(Acl, M, lam)))
    except proofs.interval.UnsupportedExpression as exc:
        return np.inf, f"ball arithmetic cannot enclose A ({exc})"
    where = "the vertices of U (A(u) affine in u)" if affine else "the corners of the enclosed Jacobian ranges over state_box x U"
    return float(worst), f"arb Cholesky of -(A^T M + M A + lambda M) at {where}"


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Certify stabilisability: M and lambda of eq. egLMI, with margins re-checked in numpy.

    Parameters
    ----------
    model : Model
        The spec's systems.
    upstream : dict
        Unused (the first stage).

    Returns
    -------
    Artefact
        Values M, lambda, vertex and sweep margins, lmi_margin; expressions A(u), b(u).

    Raises
    ------
    DesignError
        If f is not of the class the method needs, M is not positive definite, or the LMI is
        infeasible at the requested decay rate (the message gives the largest feasible one).
    NumericalError
        If the solver claims success but the numpy re-check fails.
    """
    st = model.spec.stabilisability
    meta: dict = {"method": st.method, "feedback": st.feedback}
    # Without a state box a plant not affine in x is refused by affine_form, with its reason.
    J = sparse_jacobian(model.f, model.x)
    # (a sign of a state has a Jacobian free of x almost everywhere, but f is not affine: its jump needs the box)
    affine = model.state_box is None or not (any(e.free_symbols & set(model.x) for e in J) or jumps(model.f, model.x))
    if affine:
        A_sym, b_sym = affine_form(model, J)
        A_num = model.numeric(A_sym, list(model.u))
        verts = vertices(model.U)
        A_vertices = [A_num(*vtx) for vtx in verts]
    else:
        if st.feedback == "linear_gain":
            raise SpecError("stabilisability.feedback", "'linear_gain' with f not affine in x", "feedback: identity (the Jacobian LMI certifies the plant itself)")
        refuse_jumps(model)
        A_sym, A_vertices, ranges, jmeta = jacobian_polytope(model, J)
        b_sym = sp.zeros(model.n, 1)
        verts = ranges
        meta.update(jmeta, condition="J(x, u)^T M + M J(x, u) <= -lambda M on state_box x U (Jacobian polytope)")
    K = np.zeros((model.m, model.n))
    # The LMI is solved on A / s, s the largest spectral radius (rates divided by s too; M and K are unchanged), so that
    # its tolerances are relative to the plant's own time scale: a plant in nanoseconds or in days is solved
    # as one in seconds.
    scale = lmi_scale(A_vertices)
    scaled = [A / scale for A in A_vertices]
    meta["lmi_scale"] = scale
    if not affine:
        meta["_ranges"] = ranges

    if st.feedback == "linear_gain":
        M, K, lam, meta = _synthesise_feedback(model, st, scaled, meta, scale)
    elif st.method == "given":
        M = np.array(st.M, dtype=float)
        if not np.allclose(M, M.T, rtol=0, atol=1e-12 * max(1.0, np.abs(M).max())):
            raise SpecError("stabilisability.M", "is not symmetric", "a symmetric positive definite matrix")
        if np.linalg.eigvalsh(M).min() <= 0:
            raise DesignError("stabilisability.M", f"is not positive definite (smallest eigenvalue {np.linalg.eigvalsh(M).min():.4g})", "M > 0", check="M_positive")
        lam_max = largest_decay_rate_for(A_vertices, M)
        lam = lam_max if st.decay_rate == "maximise" else float(st.decay_rate)
        meta.update(solver="none (M given; verified in numpy)")
    else:
        meta.update(solver="CLARABEL via cvxpy", normalisation=f"trace(M) = n (and M >= {M_MIN_EIG} I in the maximum-margin problem)",
                    objective="minimise t subject to A(u_k)^T M + M A(u_k) + lambda M <= t I at every vertex u_k",
                    margin_tol=MARGIN_TOL,
                    fallback=f"when that does not certify lambda: minimise kappa subject to I <= M <= kappa I and A(u_k)^T M + M A(u_k) + lambda M "
                             f"<= -{SCALE_FREE_MARGIN:g} kappa I, accepted when the numpy margin over ||M|| is below -{MARGIN_TOL:g}; M scaled to trace(M) = n")
        M, lam, meta = _search(scaled, st, structures(st.structure, model.n), meta, model, scale)

    meta.pop("_ranges", None)
    B_K = np.array(model.substitute(model.g), dtype=float) @ K if st.feedback == "linear_gain" else 0.0
    vertex_margins = lmi_margins([A + B_K for A in A_vertices], M, lam)
    if affine:
        sweep_u = sweep(model.U)
        A_sweep = np.broadcast_to(A_num(*sweep_u.T), (model.n, model.n, len(sweep_u)))   # one vectorised call
        sweep_margins = lmi_margins([A_sweep[:, :, k] + B_K for k in range(len(sweep_u))], M, lam)
    else:
        sweep_u = np.zeros((0, model.m))
        samples, where = jacobian_samples(model, A_sym)
        sweep_margins = lmi_margins(samples, M, lam)
        if sweep_margins.max() > 0:
            # A point of the box whose Jacobian breaks the LMI: the (sampled) ranges missed it, and no M found on
            # them certifies the plant. A counter-example, not a solver failure.
            k = int(np.argmax(sweep_margins))
            x_at, u_at = where[k, :model.n], where[k, model.n:]
            raise DesignError("stabilisability", f"eq. egLMI fails at x = {np.round(x_at, 6).tolist()}, u = {np.round(u_at, 6).tolist()} "
                              f"(margin {sweep_margins[k]:.3g} > 0 at lambda = {lam:.6g}): its Jacobian lies outside the sampled ranges "
                              f"({meta.get('range_method', '')})", "Jacobian ranges that ball arithmetic can enclose, or a smaller state_box",
                              check="lmi_margin")
    margin = float(max(vertex_margins.max(), sweep_margins.max()))
    eig_M = np.linalg.eigvalsh(M)
    meta.update(M_condition_number=float(eig_M.max() / eig_M.min()) if eig_M.min() > 0 else None)
    if (st.method == "polytopic_lmi" or st.feedback == "linear_gain") and margin > 0:
        raise NumericalError(NAME, f"Clarabel reported a solution but the numpy re-check finds margin {margin:.3g} > 0", "a certified M (margin <= 0)")
    if st.method == "given" and margin > 0:
        raise DesignError("stabilisability.M", f"does not satisfy eq. egLMI at lambda = {lam:g} (margin {margin:.4g} > 0)",
                          f"a decay_rate <= {largest_decay_rate_for(A_vertices, M):.6g}, the largest this M certifies", check="lmi_margin")

    proved_margin, proof = prove_lmi(model, A_sym, verts, affine, K, M, lam, ranges_proved=bool(meta.get("ranges_proved", False)))
    margin_evidence = proofs.PROVED if proved_margin <= 0 else proofs.SAMPLED
    M_lower = proofs.lambda_min_lower(M) if model.n <= proofs.MAX_PROOF_STATES else -np.inf
    meta.update(lmi_proof=proof if proved_margin <= 0 else f"not proved: {proof} (bound {proved_margin:.3g})")

    art = Artefact(stage=NAME, meta=meta)
    art.values.update({
        "lmi_margin_proved": proved_margin, "M_min_eigenvalue_proved": M_lower,
        "M": M, "K": K, "lambda": lam, "vertices": verts, "vertex_margins": vertex_margins, "sweep_u": sweep_u,
        "sweep_margins": sweep_margins, "lmi_margin": margin, "M_eigenvalues": eig_M,
        "A_vertices": np.stack(A_vertices), "relative_margin": margin / eig_M.max(),
    })
    art.exprs.update({"A": A_sym, "b": b_sym})
    if margin_evidence == proofs.PROVED:
        art.checks["lmi_margin"] = Check(proved_margin, True, "proved upper bound of the largest eigenvalue of A_cl^T M + M A_cl + lambda M, A_cl = A + B K "
                                         f"(K = 0 for identity feedback; <= 0: eq. egLMI holds): {proof}", proofs.PROVED)
    else:
        art.checks["lmi_margin"] = Check(margin, margin <= 0, "largest eigenvalue of A_cl(u)^T M + M A_cl(u) + lambda M over the vertices and a sweep of U, A_cl = A + B K "
                                         f"(K = 0 for identity feedback; <= 0: eq. egLMI holds); proof: {meta['lmi_proof']}")
    if M_lower > 0:
        art.checks["M_positive"] = Check(M_lower, True, "proved lower bound of the smallest eigenvalue of M (> 0; arb Cholesky)", proofs.PROVED)
    else:
        art.checks["M_positive"] = Check(float(eig_M.min()), bool(eig_M.min() > 0), "smallest eigenvalue of M (> 0; numpy)")
    return art


def structures(choice: str, n: int) -> list[str]:
    """The forms of M to try, in order, for ``stabilisability.structure`` (see :data:`FULL_MAX_STATES`)."""
    if choice != "auto":
        return [choice]
    return ["full"] if n <= FULL_MAX_STATES else ["diagonal", "full"]


def _search(A_vertices: list[np.ndarray], st, tries: list[str], meta: dict, model: Model, scale: float = 1.0) -> tuple[np.ndarray, float, dict]:
    """M and lambda of eq. egLMI (identity feedback), trying each structure of M in turn.

    ``A_vertices`` are divided by ``scale`` (so are the rates inside; the lambda returned is in the plant's units).
    A later structure is tried only when the earlier one finds no M (at the requested rate, or with any
    positive rate for ``maximise``); ``meta["structure"]`` records the one used and ``meta["tried"]`` all.
    """
    tried = []
    for structure in tries:
        tried.append(structure)
        if st.decay_rate == "maximise":
            how: dict = {}
            lam, M = largest_decay_rate(A_vertices, structure=structure, info=how)
            if M is not None:
                meta.update(structure=structure, tried=tried, bisection_rtol=BISECTION_RTOL,
                            bisection_bracket=[lam * scale, float(how["upper_bound"]) * scale], **_formulation_meta(how))
                return M, lam * scale, meta
            continue
        lam = float(st.decay_rate)
        M, t, status, info = certify_rate(A_vertices, lam / scale, structure)
        if M is not None:
            meta.update(structure=structure, tried=tried, status=status, optimal_margin=t * scale, **_formulation_meta(info))
            return M, lam, meta
    worst = _worst_vertex_text(model, A_vertices, meta, scale)
    other = ("feedback: linear_gain (g constant, f affine in x) to synthesise a stabilising K" if "jacobian_entries" not in meta
             else "a smaller concrete.state_box (the Jacobian ranges are taken over all of it, each entry independently)")
    # The eigenvalues bound every rate from above (Re eig(A_k) <= -lambda / 2); below that bound the solver's
    # failure to find an M is not a proof that none exists (an M may have to be very ill-conditioned).
    eig_bound = min(-2.0 * float(np.linalg.eigvals(A).real.max()) for A in A_vertices) * scale
    unproved = (f"; the eigenvalues allow rates up to {eig_bound:.6g}, so an M may exist that the solver could not reach "
                f"(very ill-conditioned): a given M (method: given) is verified exactly") if eig_bound > 0 else ""
    if st.decay_rate == "maximise":
        what = "no M certifies any decay rate lambda > 0" if eig_bound <= 0 else "the solver found no M certifying a decay rate lambda > 0"
        raise DesignError("stabilisability", f"{what} (eq. egLMI){worst}{unproved}",
                          f"a plant that is incrementally stable on the set, or {other}", check="lmi_margin")
    best, _ = largest_decay_rate(A_vertices, structure=tries[-1])
    hint = (f"decay_rate below {best * scale:.6g} (the largest the solver certifies), or 'maximise'" if best > 0
            else f"a plant that is incrementally stable on the set, or {other}")
    margin = f"best margin {t * scale:.3g}" if np.isfinite(t) else "no solution"
    raise DesignError("stabilisability.decay_rate", f"the LMI of eq. egLMI is infeasible at lambda = {lam:g} ({margin}"
                      f"{'' if tried == ['full'] else ', M ' + ' or '.join(tried)}){worst if best <= 0 else ''}"
                      f"{unproved if best <= 0 and lam * 1.0 < eig_bound else ''}",
                      hint, check="lmi_margin")


def _formulation_meta(info: dict) -> dict:
    """Which problem gave M, for the artefact's meta."""
    out = {}
    if info:
        out["formulation"] = info["formulation"]
        if info["formulation"] == "scale_free":
            out.update(scale_free_objective=f"minimise kappa subject to I <= M <= kappa I and A(u_k)^T M + M A(u_k) + lambda M <= -{SCALE_FREE_MARGIN:g} kappa I; M then scaled to trace(M) = n",
                       scale_free_relative_margin=info["relative_margin"])
    return out


def _synthesise_feedback(model: Model, st, A_vertices: list[np.ndarray], meta: dict, scale: float = 1.0):
    """M, K and lambda for ``feedback: linear_gain`` (g constant), by the LMI in X = M^-1, Y = K X with the smallest
    gain (:func:`solve_lmi_feedback`).  ``A_vertices`` are divided by ``scale`` (rates too; K is unchanged)."""
    if st.method != "polytopic_lmi":
        raise SpecError("stabilisability.method", f"'{st.method}' with feedback linear_gain", "method polytopic_lmi (K is synthesised)")
    if any(e.free_symbols & set(model.x) for e in model.g):
        raise DesignError("concrete.g", "feedback linear_gain needs a constant input matrix g", "g independent of x, or feedback identity")
    B = np.array(model.substitute(model.g), dtype=float) / scale
    weights = np.maximum(0.5 * (model.U[:, 1] - model.U[:, 0]), 1e-300)
    structure = "diagonal" if st.structure == "diagonal" else "full"   # auto: the feedback LMI is searched in full
    meta.update(solver="CLARABEL via cvxpy",
                normalisation="I <= M^-1 <= kappa I, kappa the first of %s that is feasible" % list(FEEDBACK_CONDITION),
                objective="minimise mu subject to A X + X A^T + B Y + Y^T B^T + lambda (1 + %g) X <= 0 at every vertex and "
                          "K_i X K_i^T <= mu w_i^2 (w_i: half the width of U_i); K = Y X^-1, M = X^-1: the smallest gain, "
                          "the largest region where no input clips" % FEEDBACK_RATE_MARGIN,
                structure=structure)
    if st.decay_rate == "maximise":
        lam, found = _largest_feedback_rate(A_vertices, B, structure, weights)
        if found is None:
            raise DesignError("stabilisability", "no feedback gain K makes A(u) + B K incrementally stable with a positive decay rate "
                              f"at every vertex{_worst_vertex_text(model, A_vertices, meta, scale)}",
                              "a stabilisable pair (A(u), B) at every vertex of U", check="lmi_margin")
        M, K = found
        lam *= scale
        meta.update(bisection_rtol=BISECTION_RTOL, rate_cap=FEEDBACK_MAX_RATE * scale)
    else:
        lam = float(st.decay_rate)
        M, K, mu, status = solve_lmi_feedback(A_vertices, B, lam / scale, structure, weights)
        meta.update(status=status, weighted_gain=mu)
        if M is None:
            best, _ = _largest_feedback_rate(A_vertices, B, structure, weights)
            hint = (f"decay_rate below {best * scale:.6g} (the largest the solver certifies with feedback), or 'maximise'" if best > 0 else
                    f"a stabilisable pair (A(u), B) at every vertex of U{_worst_vertex_text(model, A_vertices, meta, scale)}")
            raise DesignError("stabilisability.decay_rate", f"no feedback gain makes eq. egLMI feasible at lambda = {lam:g}", hint, check="lmi_margin")
    return M, np.asarray(K, dtype=float), lam, meta


def _worst_vertex_text(model: Model, A_vertices: list[np.ndarray], meta: dict, scale: float = 1.0) -> str:
    """'; at u = [..] A has an eigenvalue with real part 0.5' (or at the corner of the Jacobian ranges df2/dx1 = ..):
    the vertex whose A is least stable, which bounds every rate from above (lambda <= -2 Re eig(A))."""
    k = int(np.argmax([np.linalg.eigvals(A).real.max() for A in A_vertices]))
    re = float(np.linalg.eigvals(A_vertices[k]).real.max()) * scale
    if "jacobian_entries" in meta:
        ranges = meta.get("_ranges")
        names = meta["jacobian_entries"]
        corner = list(itertools.product(*[tuple(r) for r in ranges]))[k] if ranges is not None else ()
        where = ", ".join(f"{n} = {v:.6g}" for n, v in zip(names, corner))
        ranges_text = "; ".join(f"{n} in [{lo:.6g}, {hi:.6g}]" for n, (lo, hi) in zip(names, ranges)) if ranges is not None else ""
        return (f"; at the corner {where} of the Jacobian ranges over state_box x U ({ranges_text}) df/dx has an eigenvalue "
                f"with real part {re:.4g}")
    verts = vertices(model.U)
    return f"; at the vertex u = {np.round(verts[k], 6).tolist()} of U, A(u) has an eigenvalue with real part {re:.4g}"


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``."""
    v = art.values
    return {
        "lambda": float(v["lambda"]),
        "M": np.asarray(v["M"]).tolist(),
        "K": np.asarray(v["K"]).tolist() if "K" in v else None,
        "lmi_margin": float(v["lmi_margin"]),
        "vertex_margins": np.asarray(v["vertex_margins"]).tolist(),
        "M_min_eigenvalue": float(np.min(v["M_eigenvalues"])),
        "method": art.meta.get("method"),
        "A": [str(e) for e in art.exprs["A"]],
    }


def headline(art: Artefact) -> str:
    """One progress line."""
    return f"lambda = {art.values['lambda']:.6g}, lmi_margin = {art.values['lmi_margin']:.3g}"
