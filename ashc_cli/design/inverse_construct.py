"""Constructions of the left inverse m for the inverse stage (Section IV-C): the closed-form branches of
kappa(m) = y that sympy finds; without one, kappa^-1 as a (piecewise) Chebyshev interpolant for one abstract state
(:func:`numeric_inverse`) and as a tensor Chebyshev series on Y from Newton solutions for several
(:func:`inverse_on_box`); and the tolerances of the checks of a hand-written m against a fitted p.
:mod:`ashc_cli.design.stages.inverse` chooses among them and checks what it chose."""

from __future__ import annotations

import dataclasses
from collections import namedtuple

import numpy as np
import sympy as sp

from ashc_cli.numerics import chebyshev
from ashc_cli.design.artefacts import Artefact
from ashc_cli.design.upstream import dp_function, p_function
from ashc_cli.errors import CoverError, DesignError, FitError
from ashc_cli.problem.grids import domain_grid
from ashc_cli.problem.model import Model, lambdify, sparse_jacobian, within_budget

__all__ = ["augment_outputs", "note_augmented", "LEFT_INVERSE_TOL", "CONDITION_II_RTOL", "COMPOSE_SAFETY", "SOLVE_MAX_OPS", "Branch", "closed_form_branches", "branch_residuals", "numeric_inverse",
           "composed_tolerances", "solve_kappa", "inverse_on_box", "kappa_inverse_on_Y"]

#: m(p(xi)) - xi must be below this on V (absolute, in units of xi).
LEFT_INVERSE_TOL = 1e-9
#: h(x) - kappa(m(x)) must be below this, relative to the size of Y, on samples of X_y.
CONDITION_II_RTOL = 1e-9
#: kappa is handed to sympy.solve only when it is this small (a fitted polynomial of high degree is not).
SOLVE_MAX_OPS = 300

#: The branch of kappa(m) = y that is p's left inverse (one output): m(y), the symbol y, how it was found, how many
#: branches there were, max |m(p(xi)) - xi| on V and kappa on V's grid.
Branch = namedtuple("Branch", "m_of_y y method branches left_residual y_grid")


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

    if model.numeric_paths is True or not all(solvable(e) for e in kappa):
        return []               # --numeric: the interpolant of kappa^-1, no sympy
    mus = [sp.Dummy(f"mu{k}", real=True) for k in range(model.n_hat)]
    equations = [sp.Eq(e.xreplace(dict(zip(model.xi, mus))), yk) for e, yk in zip(kappa, ys)]
    rational = all(sp.sympify(e).is_rational_function(*model.xi) for e in kappa)
    try:
        # check=False: every branch is verified numerically below (m(p(xi)) = xi on V), and sympy's own
        # check (checksol) took 0.7 of the 0.8 s of this stage on the Cuk converter.  A transcendental kappa
        # (tanh, exp of xi) runs under a safety stop: sympy may search for minutes without an answer.
        if rational:
            solutions = sp.solve(equations, mus, dict=True, check=False)
        else:
            solutions = within_budget(_solve_all, equations, mus)
    except (NotImplementedError, ValueError, TypeError):
        return []
    except TimeoutError as exc:
        raise DesignError("abstract.m", f"sympy.solve of kappa(xi) = y stopped ({exc}), a safety stop (a clock: the "
                          "numeric path is not taken silently, or the design would depend on the machine's load)",
                          "--numeric (an interpolant of kappa^-1, no sympy), or abstract.m written by hand (it is checked)") from None
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
    formula = m.to_sympy([y])[0] if m.kept_numeric else chebyshev.to_sympy(m.coeffs, m.box, [y])[0]
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


#: Largest degree per axis of the tensor series of kappa^-1 on Y (several abstract states).
BOX_MAX_DEGREE = {2: 40, 3: 16}
#: Newton iterations, and step halvings per iteration, for kappa(xi) = y.
NEWTON_STEPS, NEWTON_HALVINGS = 60, 40
#: |kappa(xi) - y| / max(1, |Y|) below this is a solution of kappa(xi) = y.
NEWTON_RTOL = 1e-13


def solve_kappa(kappa_fn, dkappa_fn, y: np.ndarray, start: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Damped Newton for kappa(xi) = y at every column of y at once (as many outputs as abstract states).

    A step is halved (up to ``NEWTON_HALVINGS`` times) until it lowers |kappa(xi) - y| and keeps kappa finite.

    Parameters
    ----------
    kappa_fn, dkappa_fn : callable
        kappa (values (p, 1, N)) and dkappa/dxi (values (p, n_hat, N)), one array per abstract state.
    y : ndarray (p, N)
        The outputs.
    start : ndarray (n_hat, N)
        The starting points (e.g. the nearest point of kappa's grid of V).
    scale : float
        Residuals are measured relative to max(1, scale).

    Returns
    -------
    (xi, residual) : ndarray (n_hat, N), ndarray (N,)
        The points reached and max_k |kappa_k(xi) - y_k| / max(1, scale) there.
    """
    n_hat, N = start.shape

    def residual_at(z):
        r = np.asarray(kappa_fn(*z), dtype=float).reshape(-1, N) - y
        return r, np.where(np.all(np.isfinite(r), axis=0), np.abs(r).max(axis=0), np.inf) / max(1.0, scale)

    xi = np.array(start, dtype=float)
    r, size = residual_at(xi)
    for _ in range(NEWTON_STEPS):
        active = size > NEWTON_RTOL
        if not active.any():
            break
        J = np.moveaxis(np.broadcast_to(np.asarray(dkappa_fn(*xi), dtype=float), (y.shape[0], n_hat, N)), -1, 0)
        with np.errstate(all="ignore"):
            try:
                delta = np.linalg.solve(J, r.T[..., None])[..., 0].T
            except np.linalg.LinAlgError:
                delta = np.stack([np.linalg.lstsq(Jk, rk, rcond=None)[0] for Jk, rk in zip(J, r.T)], axis=1)
        delta = np.where(np.isfinite(delta), delta, 0.0)
        t = np.where(active, 1.0, 0.0)
        for _ in range(NEWTON_HALVINGS):
            trial = xi - t * delta
            r_new, size_new = residual_at(trial)
            worse = active & ~(size_new < size)
            if not worse.any():
                break
            t = np.where(worse, t / 2, t)
        better = size_new < size
        xi = np.where(better, trial, xi)
        r = np.where(better, r_new, r)
        size = np.where(better, size_new, size)
    return xi, size


def inverse_on_box(kappa_fn, dkappa_fn, xi_grid: np.ndarray, kappa_grid: np.ndarray, Y: np.ndarray, V: np.ndarray,
                   ys: list[sp.Symbol]) -> dict:
    """kappa^-1 on the output box Y as a tensor Chebyshev series, for several abstract states and as many outputs
    (the paper's m = kappa^-1(h(x)) of Section IV-C where sympy finds no closed form).

    kappa(xi) = y is solved by Newton (:func:`solve_kappa`, from the nearest point of kappa's grid of V) at the
    Chebyshev nodes of Y; the lowest even degree per axis whose series and formula both stay within
    ``LEFT_INVERSE_TOL`` / 100 of the Newton solutions on an independent grid of Y (corners and edges included) is
    kept.  Every solution must lie in V: that is eq. (10), kappa(V) covers Y, on the nodes and the grid.

    Parameters
    ----------
    kappa_fn, dkappa_fn : callable
        kappa and its Jacobian for numpy (one array per abstract state).
    xi_grid, kappa_grid : ndarray (n_hat, N), (p, N)
        The grid of V and kappa on it (starting points).
    Y, V : ndarray (p, 2), (n_hat, 2)
        The output box and the domain.
    ys : list of Symbol
        The output symbols the formula is written in.

    Returns
    -------
    dict
        m_of_y (sympy Matrix (n_hat, 1)), series (the Chebyshev series it is the formula of), dm_dy (n_hat, p: the formula of the series' own derivative, so that a
        clipped cosine form is never differentiated), degree, error (max deviation of the formula from the Newton solutions on
        the check grid), check_points, check_xi (the solutions there, (n_hat, k)) and excursion (largest distance
        of a solution outside V, <= 0 inside).

    Raises
    ------
    CoverError
        If Newton finds no solution in V for some y of Y.
    ashc_cli.errors.FitError
        If no degree up to ``BOX_MAX_DEGREE`` reaches the tolerance.
    """
    n_hat = len(V)
    scale = float(np.ptp(Y, axis=1).max())
    max_degree = BOX_MAX_DEGREE.get(n_hat, 8)

    def preimages(y: np.ndarray) -> tuple[np.ndarray, float]:
        nearest = np.argmin(((kappa_grid[:, :, None] - y[:, None, :]) ** 2).sum(axis=0), axis=0)
        xi, size = solve_kappa(kappa_fn, dkappa_fn, y, xi_grid[:, nearest], scale)
        excursion = np.max(np.r_[V[:, :1] - xi, xi - V[:, 1:]], axis=0)
        bad = ~(size <= NEWTON_RTOL * 100) | ~(excursion <= 1e-12 * max(1.0, float(np.ptp(V, axis=1).max())))
        if bad.any():
            k = int(np.argmax(bad))
            raise CoverError(y[:, k], float(size[k]), float(excursion[k]) if np.isfinite(excursion[k]) else np.inf)
        return xi, float(excursion.max())

    check_y = domain_grid(Y, 41 ** n_hat if n_hat == 2 else 13 ** n_hat)
    check_xi, excursion = preimages(check_y)
    best = (np.inf, None)
    for degree in range(4, max_degree + 1, 2):
        z = chebyshev.nodes(Y, degree + 1)
        xi_nodes, exc = preimages(z)
        excursion = max(excursion, exc)
        coeffs = chebyshev.fit(xi_nodes, Y, z, degree)
        series_error = float(np.abs(chebyshev.evaluate(coeffs, Y, check_y) - check_xi).max())
        if series_error > LEFT_INVERSE_TOL / 100:
            best = min(best, (series_error, degree), key=lambda b: b[0])
            continue
        series = chebyshev.Series.column(coeffs, Y)
        # The series' own formula: the cosine form at a high degree (a power basis lost the digits), expanded at a low one.
        m_of_y = series.to_sympy(ys)
        formula = np.broadcast_to(lambdify(m_of_y, ys)(*check_y)[:, 0, :], check_xi.shape)
        error = float(np.abs(formula - check_xi).max())
        if error <= LEFT_INVERSE_TOL / 100:
            return {"m_of_y": m_of_y, "series": series, "dm_dy": series.jacobian().to_sympy(ys), "degree": degree, "error": error, "check_points": check_y.shape[1],
                    "check_xi": check_xi, "check_y": check_y, "excursion": excursion}
        best = min(best, (error, degree), key=lambda b: b[0])
    raise FitError(tuple(map(tuple, Y.tolist())), best[0], f"degree {max_degree} per axis is not enough (best {best[0]:.3g} at degree {best[1]})")


def kappa_inverse_on_Y(model: Model, man: Artefact, kap: Artefact, ys: list, y_grid: np.ndarray, closed_residual: float) -> dict:
    """m = kappa^-1(h(x)) as a tensor Chebyshev series on Y (:func:`inverse_on_box`) for several abstract states
    without a closed form, and its left-inverse residual where it is used.

    Parameters
    ----------
    model : Model
    man, kap : Artefact
        The manifold (xi_grid, p_grid, p) and kappa (kappa, dkappa_dxi, its series) artefacts.
    ys : list of Symbol
        The output symbols m_of_y is written in.
    y_grid : ndarray (p, N)
        kappa on V's grid.
    closed_residual : float
        The best residual of sympy's branches (for the messages).

    Returns
    -------
    dict
        :func:`inverse_on_box`'s result, with left_residual (max |m(p(xi)) - xi| at the points of V's grid with
        kappa(xi) in Y and at the Newton solutions on the check grid) and p_points (p at those points: where
        condition (i) is measured).

    Raises
    ------
    DesignError
        Naming ``abstract.domain`` (no preimage in V, or p not injective there) or ``abstract.m`` (no fit).
    """
    grid = np.asarray(man.value("xi_grid"))
    kappa_fn = kap.series["kappa"] if "kappa" in kap.series else model.numeric(kap.expr("kappa"), list(model.xi))
    dkappa_fn = kap.series["dkappa_dxi"] if "dkappa_dxi" in kap.series else model.numeric(kap.expr("dkappa_dxi"), list(model.xi))
    closed = f"sympy finds no closed form of m (best residual {closed_residual:.3g})"
    try:
        fit = inverse_on_box(kappa_fn, dkappa_fn, grid, y_grid, model.Y, model.V, ys)
    except CoverError as exc:
        where = (f"the nearest solution lies {exc.excursion:.3g} outside V" if exc.residual <= 1e-11 and np.isfinite(exc.excursion)
                 else f"Newton from the nearest point of kappa's grid stops at |kappa(xi) - y| = {exc.residual:.3g}")
        raise DesignError("abstract.domain", f"{closed}, and kappa(xi) = y has no solution xi in V for y = {np.round(exc.y, 6).tolist()} of Y ({where}): "
                          "kappa(V) does not cover Y (eq. (10)), or kappa is not invertible there",
                          "a larger domain V or a smaller output_set; or abstract.m written by hand (checked, not trusted)", check="V_covers_Y") from None
    except FitError as exc:
        raise DesignError("abstract.m", f"{closed}, and a tensor Chebyshev series of kappa^-1 on Y misses it by {exc.measure:.3g} ({exc.reason})",
                          "abstract.m written by hand (it is checked, not trusted), or a smaller output_set", check="left_inverse") from None
    m_fn = model.numeric(fit["m_of_y"], ys)
    scale = max(1.0, float(np.ptp(model.V, axis=1).max()))
    inside = np.all((y_grid >= model.Y[:, :1] - 1e-12 * scale) & (y_grid <= model.Y[:, 1:] + 1e-12 * scale), axis=0)
    back_v = np.broadcast_to(m_fn(*y_grid[:, inside])[:, 0, :], (model.n_hat, int(inside.sum())))
    back_y = np.broadcast_to(m_fn(*fit["check_y"])[:, 0, :], fit["check_xi"].shape)
    left = max(float(np.abs(back_v - grid[:, inside]).max(initial=0.0)), float(np.abs(back_y - fit["check_xi"]).max()))
    if not left <= LEFT_INVERSE_TOL:
        worst = grid[:, inside][:, int(np.argmax(np.abs(back_v - grid[:, inside]).max(axis=0)))] if inside.any() else fit["check_xi"][:, 0]
        raise DesignError("abstract.domain", f"p is not injective where kappa(xi) is in Y: the series of kappa^-1 gives max |m(p(xi)) - xi| = {left:.3g} "
                          f"(at xi = {np.round(worst, 6).tolist()})",
                          "a domain V on which kappa is one-to-one, or abstract.m written by hand (checked, not trusted)", check="left_inverse")
    p_num = p_function(man, model)
    points = np.c_[np.asarray(man.value("p_grid"))[:, inside], np.broadcast_to(p_num(*fit["check_xi"])[:, 0, :], (model.n, fit["check_xi"].shape[1]))]
    return {**fit, "left_residual": left, "p_points": points}


def augment_outputs(model: Model, man: Artefact, kap: Artefact) -> tuple[Model, Artefact, list[sp.Symbol]]:
    """More abstract states than outputs (n_hat > p) with a nonlinear p: the outputs augmented with n_hat - p states
    x_J, so that m = Phi^-1(h(x), x_J) with Phi(xi) = (kappa(xi), p_J(xi)) square (Theorem 6 with the outputs
    (h, x_J)).

    m(p(xi)) = xi wherever Phi is injective on V, and h(p(m(x))) = kappa(m(x)) = h(x) for every x with (h(x), x_J)
    in Phi(V): conditions (i) and (ii) for the augmented outputs imply those for h.  The states are chosen greedily
    at V's centre, each the one that keeps the smallest singular value of [dkappa/dxi; dp_J/dxi] (rows normalised)
    largest; the augmented output box is Y times the range of p_J over V's grid.

    Parameters
    ----------
    model : Model
    man, kap : Artefact
        The manifold (p, its grid) and kappa artefacts.

    Returns
    -------
    model_aug : Model
        ``model`` with h = (h, x_J) and Y = (Y, range of p_J on V).
    kap_aug : Artefact
        kappa = (kappa, p_J) and its Jacobian.
    added : list of Symbol
        The states x_J.
    """
    xi_c = np.mean(np.asarray(model.V, dtype=float), axis=1)
    dp = np.asarray(dp_function(man, model)(*xi_c), dtype=float).reshape(model.n, model.n_hat)
    dk = np.asarray(model.numeric(kap.expr("dkappa_dxi"), list(model.xi))(*xi_c), dtype=float).reshape(model.p, model.n_hat)

    def rows_normalised(A: np.ndarray) -> np.ndarray:
        return A / np.maximum(np.linalg.norm(A, axis=1, keepdims=True), 1e-300)

    def smallest_sv(rows: list[int]) -> float:
        return float(np.linalg.svd(rows_normalised(np.vstack([dk, dp[rows]])), compute_uv=False).min())

    chosen: list[int] = []
    for _ in range(model.n_hat - model.p):
        j = max((k for k in range(model.n) if k not in chosen), key=lambda k: (smallest_sv(chosen + [k]), -k))   # ties: the first state
        if not smallest_sv(chosen + [j]) > 1e-9:
            raise DesignError("abstract.states", f"no {model.n_hat - model.p} states complete the outputs' kappa to an invertible map at V's centre "
                              f"(xi = {xi_c.tolist()}): dkappa/dxi and dp/dxi have rank < n_hat there",
                              "a p injective on V (full-rank dp/dxi), or abstract.m written by hand (checked, not trusted)", check="left_inverse")
        chosen.append(j)
    p_grid = np.asarray(man.value("p_grid"), dtype=float)
    added = [model.x[j] for j in chosen]
    p_expr = man.expr("p")
    kappa_aug = sp.Matrix(list(kap.expr("kappa")) + [p_expr[j] for j in chosen])
    dkappa_aug = sp.Matrix.vstack(kap.expr("dkappa_dxi"), sp.Matrix([list(p_expr[j:j + 1, :].jacobian(model.xi)) for j in chosen]))
    Y_aug = np.vstack([model.Y, np.c_[p_grid[chosen].min(axis=1), p_grid[chosen].max(axis=1)]])
    model_aug = dataclasses.replace(model, h=sp.Matrix(list(model.h) + added), Y=Y_aug)
    return model_aug, Artefact(stage="kappa", exprs={"kappa": kappa_aug, "dkappa_dxi": dkappa_aug}), added


def note_augmented(art: Artefact, added: list[sp.Symbol]) -> Artefact:
    """Record on the inverse's artefact that its outputs were augmented (:func:`augment_outputs`): ``meta/augmented_outputs``,
    the method, and the certified set's meaning (m_domain has a row per augmented output, ``exprs/h`` evaluates them).

    Parameters
    ----------
    art : Artefact
        The inverse stage's artefact, changed in place.
    added : list of Symbol
        The states x_J the outputs were augmented with.

    Returns
    -------
    Artefact
        ``art``.
    """
    names = ", ".join(map(str, added))
    art.meta.update(augmented_outputs=[str(s) for s in added], method=f"{art.meta['method']}; outputs augmented with {names} (n_hat > p)",
                    m_domain_set=f"(h, {names})", m_domain=f"(h(x), {names}) in the box: the outputs augmented with {names}, so that kappa and p_J form a square map; "
                    + str(art.meta.get("m_domain", "")))
    return art
