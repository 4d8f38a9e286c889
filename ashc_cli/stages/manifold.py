"""Stage 2: the invariant manifold x = p(xi), solving the invariance PDE (eq. SimuDesignCond1)

    dp/dxi (xi) phi_bar(xi) = f_bar(p(xi)) + g(p(xi)) l(xi)        for all xi in V.

With phi_bar = 0 (Remark solvePDE) the PDE is the algebraic equation f(p(xi), l(xi)) = 0: p(xi) is the
equilibrium of the concrete system under the constant input l(xi).  It is solved symbolically with the
parameters kept as symbols, so p reads like the paper's eq. egSimuDesign.

With phi_bar != 0 on a linear plant (f_bar(x) = A x + a, g = B constant) and affine phi_bar(xi) = S xi + s,
l(xi) = Q xi + q0, p(xi) = P xi + p0 where P solves the Sylvester equation A P + B Q = P S (Girard & Pappas
2009, Remark LinearCompare) and A p0 = P s - a - B q0; it has one solution when A and S share no eigenvalue.

Otherwise (phi_bar != 0, nonlinear plant, one abstract state) p is approximated by Chebyshev polynomials on V,
fitted by collocation (nonlinear least squares on the PDE residual at Chebyshev nodes), raising the degree
until the relative residual on an independent grid is below ``abstract.pde_tolerance`` (Remark solvePDE).  The residual of the PDE is
evaluated on a grid of V and stored, together with the check that l maps V into U (Theorem SimuDesign).
"""

from __future__ import annotations

import numpy as np
import numpy.polynomial.chebyshev as cheb
import scipy.linalg as sla
import scipy.optimize as sopt
import sympy as sp

from ..artefacts import Artefact, Check
from ..errors import DesignError, NumericalError
from ..grids import domain_grid
from ..model import Model

NAME = "manifold"
UPSTREAM: tuple[str, ...] = ()

GRID_POINTS = 2001
#: Largest PDE residual accepted, relative to the size of f_bar(p) + g(p) l along the manifold.
RESIDUAL_RTOL = 1e-9


def solve_algebraic(model: Model) -> tuple[sp.Matrix, int]:
    """Solve f_bar(p) + g(p) l(xi) = 0 for p (eq. SimuDesignCond1 with phi_bar = 0).

    Returns
    -------
    p : sympy Matrix (n x 1)
        The branch that is real and finite on all of V.
    branches : int
        How many solutions sympy found.

    Raises
    ------
    DesignError
        If no closed-form solution exists, or none is real and finite on V.
    """
    P = sp.Matrix(sp.symbols(f"_p0:{model.n}", real=True))
    equations = (model.f_bar + model.g * model.l).xreplace(dict(zip(model.x, P)))
    try:
        solutions = sp.solve(list(equations), list(P), dict=True)
    except NotImplementedError:
        solutions = []
    grid = domain_grid(model.V, 201)
    for sol in solutions:
        if set(sol) != set(P):
            continue  # a family of solutions: p is not determined
        p = sp.Matrix([sp.factor(sp.simplify(sol[s])) for s in P])
        values = model.numeric(p, list(model.xi))(*grid)
        if np.all(np.isfinite(values)):
            return p, len(solutions)
    raise DesignError("abstract.l", f"f_bar(p) + g(p) l(xi) = 0 has no closed-form solution p(xi) real and finite on V ({len(solutions)} found)",
                      "l(xi) giving an isolated equilibrium for every xi in V (or a different V)")


def _affine_parts(exprs: sp.Matrix, args: sp.Matrix, model: Model) -> tuple[np.ndarray, np.ndarray] | None:
    """(J, c) with exprs = J args + c numerically, or None if exprs is not affine in args."""
    J = exprs.jacobian(args)
    if any(e.free_symbols & set(args) for e in J):
        return None
    c = exprs.xreplace({a: 0 for a in args})
    return np.array(model.substitute(J), dtype=float), np.array(model.substitute(c), dtype=float).reshape(-1)


#: A and S must have eigenvalues at least this far apart for the Sylvester equation to be well posed.
SYLVESTER_SEPARATION = 1e-8


def solve_sylvester(model: Model) -> sp.Matrix | None:
    """p(xi) = P xi + p0 for a linear plant and affine phi_bar, l (Remark LinearCompare), or None.

    Raises
    ------
    DesignError
        If A and S share an eigenvalue (no unique solution) or A is singular where an offset is needed.
    """
    parts = [_affine_parts(model.f_bar, model.x, model), _affine_parts(model.phi_bar, model.xi, model), _affine_parts(model.l, model.xi, model)]
    if any(part is None for part in parts) or any(e.free_symbols & set(model.x) for e in model.g):
        return None
    (A, a), (S, s0), (Q, q0) = parts
    B = np.array(model.substitute(model.g), dtype=float)
    gap = np.abs(np.linalg.eigvals(A)[:, None] - np.linalg.eigvals(S)[None, :]).min()
    if gap < SYLVESTER_SEPARATION:
        raise DesignError("abstract.phi_bar", f"A and S share an eigenvalue (distance {gap:.3g}): the Sylvester equation A P + B Q = P S has no unique solution",
                          "a phi_bar whose eigenvalues differ from the plant's")
    P = sla.solve_sylvester(A, -S, -B @ Q)              # A P - P S = -B Q
    try:
        p0 = np.linalg.solve(A, P @ s0 - a - B @ q0)     # constant part: A p0 + a + B q0 = P s0
    except np.linalg.LinAlgError:
        raise DesignError("concrete.f_bar", "A is singular, so the offset p0 of p(xi) = P xi + p0 is not determined", "an invertible A, or offsets that vanish") from None
    return sp.Matrix(P.tolist()) * model.xi + sp.Matrix(p0.tolist())


#: Coefficients below this fraction of the largest are dropped from the fitted polynomial (round-off).
CHOP_RTOL = 1e-12


def solve_polynomial(model: Model) -> tuple[sp.Matrix, int, float]:
    """Chebyshev collocation for eq. SimuDesignCond1 with one abstract state.

    Returns
    -------
    p : sympy Matrix
        Polynomials in xi (power basis, float coefficients).
    degree : int
        The degree that reached the tolerance.
    residual : float
        Relative residual on an independent grid.

    Raises
    ------
    DesignError
        If n_hat > 1, or no degree up to ``abstract.pde_max_degree`` reaches ``abstract.pde_tolerance``
        (the message gives the best residual reached).
    """
    if model.n_hat != 1:
        raise DesignError("abstract.states", "the polynomial solver of eq. SimuDesignCond1 handles one abstract state in this version",
                          "one abstract state, a linear plant (Sylvester), or phi_bar = 0")
    tol, max_degree = model.spec.abstract.pde_tolerance, model.spec.abstract.pde_max_degree
    a, b = model.V[0]
    fbar = model.numeric(model.f_bar, list(model.x))
    g = model.numeric(model.g, list(model.x))
    phi = model.numeric(model.phi_bar, list(model.xi))
    l = model.numeric(model.l, list(model.xi))
    n = model.n

    def residual(coeffs: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, float]:
        s = (2 * xs - (a + b)) / (b - a)
        P = cheb.chebval(s, coeffs.T)                                   # (n, N)
        dP = cheb.chebval(s, cheb.chebder(coeffs.T)) * 2 / (b - a) if coeffs.shape[1] > 1 else np.zeros_like(P)
        lhs = dP * phi(xs)[0, 0]
        rhs = fbar(*P)[:, 0, :] + np.einsum("ijN,jN->iN", g(*P), l(xs)[:, 0, :])
        return lhs - rhs, float(max(1.0, np.abs(lhs).max(), np.abs(rhs).max()))

    check = np.linspace(a, b, 1001)
    coeffs = np.zeros((n, 1))
    best = np.inf
    for degree in range(1, max_degree + 1):
        coeffs = np.c_[coeffs, np.zeros(n)]
        nodes = (a + b) / 2 + (b - a) / 2 * np.cos(np.pi * (np.arange(2 * (degree + 1)) + 0.5) / (2 * (degree + 1)))
        fit = sopt.least_squares(lambda c: residual(c.reshape(n, degree + 1), nodes)[0].ravel(), coeffs.ravel(), xtol=1e-15, ftol=1e-15, gtol=1e-15)
        coeffs = fit.x.reshape(n, degree + 1)
        r, scale = residual(coeffs, check)
        best = min(best, float(np.abs(r).max() / scale))
        if best <= tol:
            s = sp.Symbol("_s", real=True)
            xi = model.xi[0]
            rows = []
            for row in coeffs:
                power = cheb.cheb2poly(row)
                power[np.abs(power) < CHOP_RTOL * max(np.abs(power).max(), 1e-300)] = 0.0
                poly = sum(sp.Float(c) * s**k for k, c in enumerate(power) if c != 0)
                rows.append(sp.expand(sp.sympify(poly).xreplace({s: (2 * xi - (a + b)) / (b - a)})))
            return sp.Matrix(rows), degree, best
    raise DesignError("abstract.phi_bar", f"no polynomial of degree <= {max_degree} solves eq. SimuDesignCond1 on V to {tol:g}: the best relative residual is {best:.3g}",
                      "a smaller domain V, a larger abstract.pde_max_degree or pde_tolerance, or phi_bar = 0")


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Solve eq. SimuDesignCond1 for p and check it.

    Returns
    -------
    Artefact
        Expressions p (n x 1) and dp_dxi (n x n_hat); values xi_grid, p_grid, residual.

    Raises
    ------
    DesignError
        If the spec needs the PDE solver (phi_bar != 0; not in this version), no solution exists, or
        l(V) is not inside U.
    NumericalError
        If the residual of the PDE on V is above tolerance.
    """
    if model.V is None:
        raise DesignError("abstract.domain", "'auto' is not supported by this version", "a box [[lo, hi], ...] per abstract state")
    if all(sp.simplify(e) == 0 for e in model.phi_bar):
        p, branches = solve_algebraic(model)
        method = "closed form (sympy.solve of f(p, l(xi)) = 0)"
    else:
        p, branches = solve_sylvester(model), 1
        method = "Sylvester equation A P + B Q = P S (scipy.linalg.solve_sylvester)"
        if p is None:
            p, degree, fit_residual = solve_polynomial(model)
            method = f"Chebyshev collocation, degree {degree} (relative residual {fit_residual:.2g} on an independent grid)"
    dp = p.jacobian(model.xi)

    grid = domain_grid(model.V, GRID_POINTS)
    xi_args = list(model.xi)
    p_grid = model.numeric(p, xi_args)(*grid)[:, 0, :]                       # (n, N)
    dp_grid = model.numeric(dp, xi_args)(*grid)                              # (n, n_hat, N)
    phi_grid = model.numeric(model.phi_bar, xi_args)(*grid)[:, 0, :]         # (n_hat, N)
    l_grid = model.numeric(model.l, xi_args)(*grid)[:, 0, :]                 # (m, N)
    fbar = model.numeric(model.f_bar, list(model.x))(*p_grid)[:, 0, :]
    g = model.numeric(model.g, list(model.x))(*p_grid)                       # (n, m, N)
    rhs = fbar + np.einsum("ijk,jk->ik", g, l_grid)
    lhs = np.einsum("ijk,jk->ik", dp_grid, phi_grid)
    residual = float(np.abs(lhs - rhs).max())
    scale = float(max(1.0, np.abs(fbar).max(), np.abs(np.einsum("ijk,jk->ik", g, l_grid)).max()))
    if not np.isfinite(residual) or residual > RESIDUAL_RTOL * scale:
        raise NumericalError(NAME, f"residual of eq. SimuDesignCond1 on V is {residual:.3g} (scale {scale:.3g})", f"below {RESIDUAL_RTOL:g} relative")

    U = model.U
    l_lo, l_hi = l_grid.min(axis=1), l_grid.max(axis=1)
    l_inside = bool(np.all(l_lo >= U[:, 0] - 1e-12) and np.all(l_hi <= U[:, 1] + 1e-12))
    if not l_inside:
        raise DesignError("abstract.l", f"l(V) = {np.c_[l_lo, l_hi].tolist()} is not inside U = {U.tolist()}",
                          "l: V -> U (Theorem SimuDesign); shrink abstract.domain or change l", check="l_in_U")

    art = Artefact(stage=NAME, meta={"method": method, "branches": branches,
                                      "grid_points": int(grid.shape[1]), "residual_rtol": RESIDUAL_RTOL})
    art.exprs.update({"p": p, "dp_dxi": dp})
    art.values.update({"xi_grid": grid, "p_grid": p_grid, "residual": residual, "residual_scale": scale,
                       "l_range": np.c_[l_lo, l_hi]})
    art.checks["pde_residual"] = Check(residual, True, f"max over a {grid.shape[1]}-point grid of V of |dp/dxi phi_bar - f_bar(p) - g(p) l| (eq. SimuDesignCond1)")
    art.checks["l_in_U"] = Check(float(np.max(np.r_[U[:, 0] - l_lo, l_hi - U[:, 1]])), l_inside, "largest excursion of l(V) outside U (<= 0: l maps V into U)")
    return art


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``."""
    return {"p": [str(e) for e in art.exprs["p"]], "residual": float(art.values["residual"]), "method": art.meta.get("method")}


def headline(art: Artefact) -> str:
    """One progress line."""
    return f"p found ({art.meta.get('branches')} branch(es)), PDE residual = {art.values['residual']:.2g}"
