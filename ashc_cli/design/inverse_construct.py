"""Constructions of the left inverse m for the inverse stage (Section IV-C): the closed-form branches of
kappa(m) = y that sympy finds, and, for one abstract state without one, kappa^-1 as a Chebyshev interpolant.
:mod:`ashc_cli.design.stages.inverse` chooses among them and checks what it chose."""

from __future__ import annotations

import numpy as np
import scipy.optimize as sopt
import sympy as sp

from ashc_cli.numerics import chebyshev
from ashc_cli.problem.model import Model, within_budget

__all__ = ["LEFT_INVERSE_TOL", "SOLVE_MAX_OPS", "MAX_INVERSE_DEGREE", "closed_form_branches", "branch_residuals", "numeric_inverse"]

#: m(p(xi)) - xi must be below this on V (absolute, in units of xi).
LEFT_INVERSE_TOL = 1e-9
#: kappa is handed to sympy.solve only when it is this small (a fitted polynomial of high degree is not).
SOLVE_MAX_OPS = 300
#: Highest degree of the Chebyshev interpolant of kappa^-1 (one abstract state, no closed form).
MAX_INVERSE_DEGREE = 80


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


def numeric_inverse(model: Model, kappa: sp.Matrix, xs: np.ndarray, y_grid: np.ndarray, y: sp.Symbol) -> tuple[sp.Expr, float, int] | None:
    """kappa^-1 as a Chebyshev interpolant on kappa(V), for one abstract state with kappa strictly monotone.

    kappa(xi) = y is solved by Brent's method at Chebyshev nodes of kappa(V); the degree is raised until
    max |m(kappa(xi)) - xi| on the grid of V is below ``LEFT_INVERSE_TOL``.

    Parameters
    ----------
    model : Model
    kappa : sympy Matrix (1, 1)
    xs, y_grid : ndarray (N,)
        A grid of V (increasing) and kappa on it.
    y : Symbol
        The output symbol m is written in.

    Returns
    -------
    (m_of_y, residual, degree), or None if kappa is not strictly monotone on V.
    """
    dk = np.diff(y_grid)
    if not (np.all(dk > 0) or np.all(dk < 0)):
        return None
    k_num = model.numeric(kappa, list(model.xi))
    lo, hi = float(xs[0]), float(xs[-1])
    box = np.array([[y_grid.min(), y_grid.max()]])
    nodes = chebyshev.nodes(box, MAX_INVERSE_DEGREE + 1)[0]
    roots = np.array([sopt.brentq(lambda s, target=t: float(k_num(s)[0, 0]) - target, lo, hi, xtol=1e-15, rtol=1e-15) for t in nodes])
    best = (None, np.inf, 0)
    for degree in range(1, MAX_INVERSE_DEGREE + 1):
        coeffs = chebyshev.fit(roots[None, :], box, nodes[None, :], degree)
        residual = float(np.abs(chebyshev.evaluate(coeffs, box, y_grid[None, :])[0] - xs).max())
        if residual < best[1]:
            best = (coeffs, residual, degree)
        if residual <= LEFT_INVERSE_TOL / 100:   # well inside the tolerance: condition (ii) inherits the error
            break
    coeffs, residual, degree = best
    return chebyshev.to_sympy(coeffs, box, [y])[0], residual, degree
