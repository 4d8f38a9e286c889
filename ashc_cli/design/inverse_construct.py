"""Constructions of the left inverse m for the inverse stage (Section IV-C): the closed-form branches of
kappa(m) = y that sympy finds, and, for one abstract state without one, kappa^-1 as a Chebyshev interpolant;
and the tolerances of the checks of a hand-written m against a fitted p.
:mod:`ashc_cli.design.stages.inverse` chooses among them and checks what it chose."""

from __future__ import annotations

import numpy as np
import sympy as sp

from ashc_cli.numerics import chebyshev
from ashc_cli.design.artefacts import Artefact
from ashc_cli.design.upstream import dp_function
from ashc_cli.problem.model import Model, sparse_jacobian, within_budget

__all__ = ["LEFT_INVERSE_TOL", "CONDITION_II_RTOL", "COMPOSE_SAFETY", "SOLVE_MAX_OPS", "closed_form_branches", "branch_residuals", "numeric_inverse",
           "composed_tolerances"]

#: m(p(xi)) - xi must be below this on V (absolute, in units of xi).
LEFT_INVERSE_TOL = 1e-9
#: h(x) - kappa(m(x)) must be below this, relative to the size of Y, on samples of X_y.
CONDITION_II_RTOL = 1e-9
#: kappa is handed to sympy.solve only when it is this small (a fitted polynomial of high degree is not).
SOLVE_MAX_OPS = 300


def closed_form_branches(model: Model, kappa: sp.Matrix, ys: list[sp.Symbol]) -> list[list[sp.Expr]]:
    """The solutions mu(y) of kappa(mu) = y that sympy finds (each a list, one entry per abstract state).

    Parameters
    ----------
    model : Model
    kappa : sympy Matrix (p, 1)
        kappa(xi) (kappa stage).
    ys : list of Symbol
        The output symbols y, one per row of kappa.

    Returns
    -------
    list of list of sympy expressions in ys
        Empty when kappa is too large for sympy.solve, or sympy finds nothing within its budget.
    """
    def solvable(e: sp.Expr) -> bool:
        if sp.count_ops(e) > SOLVE_MAX_OPS:
            return False
        if not e.atoms(sp.Float):
            return True
        # A fitted (float) kappa: only a polynomial of low degree; sympy.solve stalls on the rest.
        return e.is_polynomial(*model.xi) and sp.Poly(e, *model.xi).total_degree() <= 4

    if not all(solvable(e) for e in kappa):
        return []
    mus = [sp.Dummy(f"mu{k}", real=True) for k in range(model.n_hat)]
    equations = [sp.Eq(e.xreplace(dict(zip(model.xi, mus))), yk) for e, yk in zip(kappa, ys)]
    rational = all(sp.sympify(e).is_rational_function(*model.xi) for e in kappa)
    try:
        # check=False: every branch is verified numerically below (m(p(xi)) = xi on V), and sympy's own
        # check (checksol) took 0.7 of the 0.8 s of this stage on the Cuk converter.  A transcendental kappa
        # (tanh, exp of xi) gets a time budget: sympy may search for minutes without an answer.
        if rational:
            solutions = sp.solve(equations, mus, dict=True, check=False)
        else:
            solutions = within_budget(_solve_all, equations, mus)
    except (NotImplementedError, ValueError, TypeError, TimeoutError):
        return []
    return [[sol[mu] for mu in mus] for sol in solutions if set(sol) == set(mus)]


def _solve_all(equations: list, unknowns: list) -> list[dict]:
    """sympy.solve of the equations for the unknowns, every solution as a dict (:func:`within_budget` runs it)."""
    return sp.solve(equations, unknowns, dict=True, check=False)


def branch_residuals(model: Model, branches: list[list[sp.Expr]], ys: list[sp.Symbol], y_grid: np.ndarray, grid: np.ndarray) -> list[float]:
    """max |m(kappa(xi)) - xi| over the grid of V for each candidate m(y) (inf where it is not finite there).

    Parameters
    ----------
    model : Model
    branches : list of list of sympy expressions
        Candidates m(y), as :func:`closed_form_branches` returns them.
    ys : list of Symbol
        The output symbols.
    y_grid, grid : ndarray (p, N), (n_hat, N)
        kappa at the grid points, and the grid points of V.

    Returns
    -------
    list of float
    """
    residuals = []
    for branch in branches:
        values = np.broadcast_to(model.numeric(branch, ys)(*y_grid)[:, 0, :], grid.shape)
        residuals.append(float(np.abs(values - grid).max()) if np.all(np.isfinite(values)) else np.inf)
    return residuals


def numeric_inverse(kappa_fn, xs: np.ndarray, y_grid: np.ndarray, y: sp.Symbol, xi_breaks=()) -> tuple[sp.Expr, float, str] | None:
    """kappa^-1 as a (piecewise) Chebyshev interpolant on kappa(V), for one abstract state with kappa strictly monotone.

    kappa(xi) = t is solved for xi by bisection (all points at once) at the Chebyshev nodes of each piece of
    kappa(V) (:func:`ashc_cli.numerics.chebyshev.fit_adaptive`: pieces of degree <= ``chebyshev.PIECE_MAX_DEGREE``,
    V split where one is not enough); on each piece the lowest degree with max |m(t) - kappa^-1(t)| below
    ``LEFT_INVERSE_TOL`` / 100 on an independent grid of it is kept.  Its formula is a Piecewise of Horner
    forms, each in its piece's own scaled variable: a single interpolant of degree 80 had power coefficients
    near 1e13 and missed kappa^-1 by 2.9e3.

    Parameters
    ----------
    kappa_fn : callable
        kappa for numpy (one array of xi, values (1, 1, ...)): the kappa stage's series, or its formula compiled.
    xs, y_grid : ndarray (N,)
        A grid of V (increasing) and kappa on it.
    y : Symbol
        The output symbol m is written in.
    xi_breaks : sequence of float
        Where the pieces of a piecewise kappa meet: m's pieces meet at their images, so that each piece of m
        inverts one smooth piece of kappa.

    Returns
    -------
    (m_of_y, residual, how) or None
        m(y), max |m(kappa(xi)) - xi| on the grid of V, and the interpolant's make-up (``degree 12`` or
        ``5 pieces of degree <= 32``); None if kappa is not strictly monotone on V.

    Raises
    ------
    ashc_cli.errors.FitError
        If no piecewise interpolant reaches the tolerance (kappa too steep somewhere).
    """
    dk = np.diff(y_grid)
    if not (np.all(dk > 0) or np.all(dk < 0)):
        return None
    lo, hi = float(xs[0]), float(xs[-1])
    increasing = bool(dk[0] > 0)

    def roots(t: np.ndarray) -> np.ndarray:
        """xi with kappa(xi) = t, by bisection on [lo, hi] for every t at once (kappa monotone), to round-off."""
        a, b = np.full(t.shape, lo), np.full(t.shape, hi)
        for _ in range(BISECTION_STEPS):
            mid = 0.5 * (a + b)
            above = (np.asarray(kappa_fn(mid), dtype=float).reshape(-1) > t) == increasing
            a, b = np.where(above, a, mid), np.where(above, mid, b)
        return 0.5 * (a + b)

    def sample(z: np.ndarray) -> np.ndarray:
        return roots(z[0])[None, :]

    checked: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}   # each piece's check grid and roots, once

    def accept(piece: chebyshev.Series) -> tuple[bool, float]:
        key = tuple(piece.box[0])
        if key not in checked:
            t = np.linspace(*key, 201)
            checked[key] = t, roots(t)
        t, exact = checked[key]
        measure = float(np.abs(piece.at(t[None, :])[0] - exact).max())
        return measure <= LEFT_INVERSE_TOL / 100, measure   # well inside: condition (ii) inherits the error

    y_breaks = np.asarray(kappa_fn(np.asarray(xi_breaks, dtype=float)), dtype=float).reshape(-1) if len(xi_breaks) else ()
    m = chebyshev.fit_adaptive(sample, (float(y_grid.min()), float(y_grid.max())), accept, breaks=y_breaks)
    residual = float(np.abs(m.at(y_grid[None, :])[0, 0] - xs).max())
    how = f"{len(m.pieces)} pieces of degree <= {m.degree}" if isinstance(m, chebyshev.PiecewiseSeries) else f"degree {m.degree}"
    formula = m.to_sympy([y])[0] if m.horner else chebyshev.to_sympy(m.coeffs, m.box, [y])[0]
    return formula, residual, how


#: Bisection steps for kappa(xi) = t: 2^-80 of the width of V is below round-off.
BISECTION_STEPS = 80


#: A check that composes a hand-written m with a fitted p allows this many times the error p carries into it.
COMPOSE_SAFETY = 10.0


def composed_tolerances(model: Model, man: Artefact, m: sp.Matrix, p_grid: np.ndarray) -> dict:
    """The tolerances of the checks of a hand-written m against a fitted p: each default plus ``COMPOSE_SAFETY``
    times what the fit's error of p (``values/p_error`` of the manifold, e per state) becomes through the check.

    m(p(xi)) - xi moves by |dm/dx| e; p(m(p(xi))) - p(xi) by |dp/dxi| |dm/dx| e; h(p(m(x))) - h(x) by |dh/dx| e
    (each on the grid of V).  A p with no estimated error (a closed form, or a collocation: NaN) adds nothing.

    Parameters
    ----------
    model : Model
        The spec's systems.
    man : Artefact
        The manifold stage's artefact (``p_error``, ``dp_dxi``).
    m : sympy Matrix (n_hat, 1)
        The spec's m, in x.
    p_grid : ndarray (n, N)
        p on the grid of V.

    Returns
    -------
    dict
        left, i, ii (the three tolerances) and p_error (the largest entry of e).
    """
    # Not estimated (NaN) or not found (inf: Newton failed from p): no allowance, the defaults stand.
    e = np.nan_to_num(np.asarray(man.values.get("p_error", np.zeros(model.n)), dtype=float).reshape(-1), nan=0.0, posinf=0.0)
    out = {"left": LEFT_INVERSE_TOL, "i": LEFT_INVERSE_TOL, "ii": CONDITION_II_RTOL, "p_error": float(e.max(initial=0.0))}
    if not np.any(e > 0):
        return out
    N = p_grid.shape[1]
    dm = np.broadcast_to(model.numeric(sparse_jacobian(m, model.x), list(model.x))(*p_grid), (model.n_hat, model.n, N))
    moved = np.einsum("ijN,j->iN", np.abs(dm), e)                                            # |dm/dx| e, (n_hat, N)
    dp = np.broadcast_to(dp_function(man, model)(*np.asarray(man.value("xi_grid"))), (model.n, model.n_hat, N))
    dh = np.broadcast_to(model.numeric(sparse_jacobian(model.h, model.x), list(model.x))(*p_grid), (model.p, model.n, N))
    out["left"] += COMPOSE_SAFETY * float(moved.max())
    out["i"] += COMPOSE_SAFETY * float(np.einsum("ikN,kN->iN", np.abs(dp), moved).max() / max(1.0, np.abs(p_grid).max()))
    out["ii"] += COMPOSE_SAFETY * float(np.einsum("ijN,j->iN", np.abs(dh), e).max() / max(1.0, np.ptp(model.Y, axis=1).max()))
    return out
