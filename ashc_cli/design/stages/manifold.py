"""Stage 2: the invariant manifold x = p(xi), solving the invariance PDE (eq. SimuDesignCond1)

    dp/dxi (xi) phi_bar(xi) = f_bar(p(xi)) + g(p(xi)) l(xi)        for all xi in V.

With phi_bar = 0 (Remark solvePDE) the PDE is the algebraic equation f(p(xi), l(xi)) = 0: p(xi) is the
equilibrium of the concrete system under the constant input l(xi).  It is solved symbolically with the
parameters kept as symbols, so p reads like the paper's eq. egSimuDesign.  Without a closed form (or above
``model.NUMERIC_THRESHOLD`` states) the equilibria are found by Newton continuation on Chebyshev nodes (sparse
Jacobians, sparse LU) and fitted by a Chebyshev series, which the artefact keeps numeric
(:class:`~ashc_cli.numerics.chebyshev.Series`: the later stages evaluate it with numpy; its formula, Horner's scheme,
is built only for the readers that need one, and the residual check covers both).

With phi_bar != 0 on a linear plant (f_bar(x) = A x + a, g = B constant) and affine phi_bar(xi) = S xi + s,
l(xi) = Q xi + q0, p(xi) = P xi + p0 where P solves the Sylvester equation A P + B Q = P S (Girard & Pappas
2009, Remark LinearCompare) and A p0 = P s - a - B q0; it has one solution when A and S share no eigenvalue.

Otherwise (phi_bar != 0, nonlinear plant, one abstract state) p is approximated by Chebyshev polynomials on V,
fitted by collocation (nonlinear least squares on the PDE residual at Chebyshev nodes), raising the degree
until the relative residual on an independent grid is below ``abstract.pde_tolerance`` (Remark solvePDE).  The residual of the PDE is
evaluated on a grid of V and stored, together with the check that l maps V into U (Theorem SimuDesign).
"""

from __future__ import annotations

import itertools

import numpy as np
import scipy.linalg as sla
import scipy.optimize as sopt
import scipy.sparse as sps
import scipy.sparse.linalg as spla
import sympy as sp

from ashc_cli.numerics import chebyshev
from ashc_cli.numerics import proofs
from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.errors import DesignError, NumericalError
from ashc_cli.problem.grids import domain_grid
from ashc_cli.problem.model import Model, compile_flat, sparse_jacobian

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
    equations = _manifold_field(model).xreplace(dict(zip(model.x, P)))
    # sympy.solve is given rational systems only: on transcendental ones (tanh, exp, sqrt of the unknowns) it
    # can run for minutes, depending on the hash seed, before giving up; those go to Newton continuation.
    rational = all(sp.sympify(e).is_rational_function(*P) for e in equations)
    try:
        solutions = sp.solve(list(equations), list(P), dict=True) if rational else []
    except NotImplementedError:
        solutions = []
    # With domain: auto, V is not known yet: keep the branch real and finite on most of the search interval.
    grid = domain_grid(model.V if model.V is not None else auto_search_box(model), 201)
    best, best_score = None, 0.0
    for sol in solutions:
        if set(sol) != set(P):
            continue  # a family of solutions: p is not determined
        p = sp.Matrix([sp.factor(sp.simplify(sol[s])) for s in P])
        values = model.numeric(p, list(model.xi))(*grid)
        score = float(np.mean(np.all(np.isfinite(values), axis=(0, 1))))
        if score == 1.0 and model.V is not None:
            return p, len(solutions)
        if model.V is None and score > best_score:
            best, best_score = p, score
    if best is not None:
        return best, len(solutions)
    what = "is not rational in x (sympy not tried)" if not rational else f"has no closed-form solution p(xi) real and finite on V ({len(solutions)} found)"
    raise DesignError("abstract.l", f"f_bar(p) + g(p) l(xi) = 0 {what}",
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
    exact = solve_sylvester_exact(model)
    if exact is not None:
        return exact
    return sp.Matrix(P.tolist()) * model.xi + sp.Matrix(p0.tolist())


#: Coefficients of a fitted polynomial p within this (relative) distance of a simple rational are tried as it.
RECOGNISE_RTOL = 1e-10


def recognise_exact(model: Model, p: sp.Matrix) -> sp.Matrix | None:
    """The fitted polynomial p with each coefficient replaced by the nearest simple rational (sympy's nsimplify,
    RECOGNISE_RTOL), if that p solves eq. (14a) exactly (the residual, in exact rationals, simplifies to 0); else None.

    A collocation that has found an exact polynomial solution (p = [xi, xi^2] of a bilinear cascade) then
    carries it exactly, and the PDE row is proved instead of sampled; a p that is only close is never changed.
    """
    floats = set().union(*(e.atoms(sp.Float) for e in p))
    if not floats:
        return None
    swap = {}
    for f in floats:
        value = float(f)
        r = sp.nsimplify(value, rational=True, tolerance=RECOGNISE_RTOL * max(1.0, abs(value)))
        if not isinstance(r, sp.Rational) or r.q > 10**6:
            return None
        swap[f] = r
    candidate = sp.Matrix([sp.expand(e.xreplace(swap)) for e in p])
    return candidate if proofs.symbolic_zero(list(proofs.exact(model, pde_residual_expr(model, candidate)))) else None


#: The Sylvester equation is solved in exact rationals up to this many unknowns n x n_hat.
EXACT_SYLVESTER_UNKNOWNS = 64


def solve_sylvester_exact(model: Model) -> sp.Matrix | None:
    """p(xi) = P xi + p0 solving A P + B Q = P S and A p0 + a + B q0 = P s0 in exact rationals (every parameter
    and number the exact rational of its double), or None above EXACT_SYLVESTER_UNKNOWNS unknowns.

    Then p solves eq. (14a) exactly, and sympy proves it (the residual simplifies to 0), as for a closed form.
    """
    if model.n * model.n_hat > EXACT_SYLVESTER_UNKNOWNS:
        return None
    unknowns = sp.symbols(f"_p0:{model.n * (model.n_hat + 1)}")
    Pm = sp.Matrix(model.n, model.n_hat, unknowns[:model.n * model.n_hat])
    p0 = sp.Matrix(unknowns[model.n * model.n_hat:])
    p = Pm * model.xi + p0
    residual = proofs.exact(model, pde_residual_expr(model, p))
    equations = []
    for r in residual:
        poly = sp.Poly(sp.expand(r), *model.xi)
        equations += poly.coeffs()
    try:
        solution = sp.solve(equations, unknowns, dict=True)
    except (NotImplementedError, ValueError):
        return None
    if len(solution) != 1 or set(solution[0]) != set(unknowns):
        return None
    return p.xreplace(solution[0])


def _manifold_field(model: Model, valued: bool = False) -> sp.Matrix:
    """F(x, xi) = f_bar(x) + g(x) l(xi): the right side of eq. SimuDesignCond1 before x = p(xi) (with the
    parameter values put in if ``valued``, for numbers)."""
    if valued:
        return model.valued["f_bar"] + model.valued["g"] * model.valued["l"]
    return model.f_bar + model.g * model.l


def _residual_function(model: Model, jacobian: bool = False):
    """F(x, xi) (and dF/dx if asked), compiled for numpy (broadcasting)."""
    F = _manifold_field(model)
    args = list(model.x) + list(model.xi)
    return (model.numeric(F, args), model.numeric(sparse_jacobian(F, model.x), args)) if jacobian else model.numeric(F, args)


class _Plant:
    """f_bar(x), g(x) and l(xi) compiled once for numpy (broadcasting), for the residuals of fits and of p."""

    def __init__(self, model: Model):
        x, xi = list(model.x), list(model.xi)
        self.fbar = model.numeric(model.valued["f_bar"], x)
        self.g = model.numeric(model.valued["g"], x)
        self.l = model.numeric(model.valued["l"], xi)

    def sides(self, P: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """f_bar(P) and g(P) l(z) at the points P (n, N) and z (n_hat, N), each (n, N)."""
        return self.fbar(*P)[:, 0, :], np.einsum("ijk,jk->ik", self.g(*P), self.l(*z)[:, 0, :])


def _relative_residual(model: Model, coeffs: np.ndarray, box: np.ndarray, z: np.ndarray, plant: _Plant, phi: np.ndarray) -> float:
    """max |dp/dxi phi_bar - f_bar(p) - g(p) l| on z (phi = phi_bar on z), relative to the size of its terms,
    max(1, |dp/dxi phi_bar|, |f_bar(p)|, |g(p) l|, |f_bar(p) + g(p) l|).

    The terms, not their sum: with phi_bar = 0 the sum is the residual itself, and a plant whose terms are
    large (the ladder's v / L, 1e5 at n = 512) could never meet an absolute tolerance.  ``run`` judges the
    stored p against the same scale.
    """
    P = chebyshev.evaluate(coeffs, box, z)
    lhs = sum(chebyshev.evaluate(chebyshev.derivative(coeffs, box, k), box, z) * phi[k] for k in range(model.n_hat))
    fbar, gl = plant.sides(P, z)
    rhs = fbar + gl
    scale = max(1.0, np.abs(lhs).max(), np.abs(rhs).max(), np.abs(fbar).max(), np.abs(gl).max())
    return float(np.abs(lhs - rhs).max() / scale)


def _check_grid(box: np.ndarray) -> np.ndarray:
    """An independent grid (not the collocation nodes) on which a fit's residual is judged."""
    return domain_grid(box, 1001 if len(box) == 1 else 41 ** len(box) if len(box) == 2 else 4096)


#: The numeric equilibria are first found at this many + 1 Chebyshev nodes (enough for degree 30).
FIRST_NODES_DEGREE = 30
#: A fit has stopped improving when its best residual fell by less than STALL_FACTOR over STALL_DEGREES degrees.
STALL_DEGREES = 6
STALL_FACTOR = 0.5


def stalled(history: list[float]) -> bool:
    """True when the best residual has not halved over the last ``STALL_DEGREES`` raises of the degree.

    A smooth (analytic) manifold gains a constant factor per degree, so a fit that stalls is fitting a
    manifold with a kink or a near-singularity on V, where a higher degree only costs time.
    """
    if len(history) <= STALL_DEGREES:
        return False
    return history[-1] > STALL_FACTOR * history[-1 - STALL_DEGREES]


def solve_collocation(model: Model, plant: _Plant | None = None) -> tuple[sp.Matrix, int, float]:
    """Tensor Chebyshev collocation for eq. SimuDesignCond1 (phi_bar != 0), any number of abstract states.

    The coefficients minimise the PDE residual at 2 (degree + 1) Chebyshev nodes per axis (Gauss-Newton with
    the exact Jacobian: the residual is linear in p's coefficients through dp/dxi and nonlinear through
    F(p, xi)); the degree is raised from 1 until the relative residual on an independent grid is below
    ``abstract.pde_tolerance``.

    Returns
    -------
    p : sympy Matrix
        Polynomials in xi.
    degree : int
        The degree per axis that reached the tolerance.
    residual : float
        Relative residual on the independent grid.

    Raises
    ------
    DesignError
        If no degree up to ``abstract.pde_max_degree`` reaches ``abstract.pde_tolerance`` (the message
        gives the best residual reached).
    """
    tol, max_degree = model.spec.abstract.pde_tolerance, model.spec.abstract.pde_max_degree
    box, n, nh = model.V, model.n, model.n_hat
    F, F_x = _residual_function(model, jacobian=True)
    plant = plant or _Plant(model)
    phi_num = model.numeric(model.phi_bar, list(model.xi))
    check = _check_grid(box)
    phi_check = phi_num(*check)[:, 0, :]
    coeffs = np.zeros((n,) + (1,) * nh)
    best, history = np.inf, []
    for degree in range(1, max_degree + 1):
        if stalled(history):
            raise DesignError("abstract.phi_bar", f"the polynomial fit of eq. SimuDesignCond1 stopped improving at degree {degree - 1} (relative residual "
                              f"{best:.3g}, tolerance {tol:g}): p is not smooth enough on V for a polynomial", "a smaller domain V, a larger pde_tolerance, or phi_bar = 0")
        grown = np.zeros((n,) + (degree + 1,) * nh)
        grown[(slice(None),) + tuple(slice(0, degree) for _ in range(nh))] = coeffs
        z = chebyshev.nodes(box, 2 * (degree + 1))
        K = (degree + 1) ** nh
        basis = np.eye(K).reshape((K,) + (degree + 1,) * nh)
        V = chebyshev.evaluate(basis, box, z).T                                   # (N, K)
        phi = phi_num(*z)[:, 0, :]                                                # (n_hat, N)
        E = sum(chebyshev.evaluate(chebyshev.derivative(basis, box, k), box, z).T * phi[k][:, None] for k in range(nh))

        def residual(c: np.ndarray) -> np.ndarray:
            C = c.reshape(n, K)
            return (C @ E.T - F(*(C @ V.T), *z)[:, 0, :]).ravel()

        def jacobian(c: np.ndarray) -> np.ndarray:
            Fx = F_x(*(c.reshape(n, K) @ V.T), *z)                               # (n, n, N)
            J = np.einsum("ij,NK->iNjK", np.eye(n), E) - np.einsum("ijN,NK->iNjK", Fx, V)
            return J.reshape(n * len(V), n * K)

        fit = sopt.least_squares(residual, grown.ravel(), jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        coeffs = fit.x.reshape(grown.shape)
        best = min(best, _relative_residual(model, coeffs, box, check, plant, phi_check))
        history.append(best)
        if best <= tol:
            return chebyshev.to_sympy(coeffs, box, list(model.xi)), degree, best
    raise DesignError("abstract.phi_bar", f"no polynomial of degree <= {max_degree} solves eq. SimuDesignCond1 on V to {tol:g}: the best relative residual is {best:.3g}",
                      "a smaller domain V, a larger abstract.pde_max_degree or pde_tolerance, or phi_bar = 0")


#: Newton's method at a node has converged when |F(x, xi)| is below this, relative to max(1, |f_bar|, |g l|).
NEWTON_RTOL = 1e-13
#: The Jacobian dF/dx must have a reciprocal condition number above this (an isolated equilibrium), estimated in
#: the 1-norm from the sparse LU factors Newton's step uses anyway (an SVD per step cost 0.2 s at n = 512).
SINGULAR_RCOND = 1e-12


def field_terms(model: Model):
    """F(x, xi) = f_bar(x) + g(x) l(xi), dF/dx and dF/dxi at one point, from one compiled function.

    Only the non-zero entries of the Jacobians are compiled (with their positions): a plant's states are
    coupled sparsely, and compiling all n^2 entries of the ladder's dF/dx took most of this stage at n = 256.

    Returns
    -------
    callable
        ``terms(x, xi)`` -> (F (n,), dF/dx (n x n, scipy.sparse CSC), dF/dxi (n, n_hat) dense).
    """
    n, nh = model.n, model.n_hat
    F = _manifold_field(model, valued=True)
    column = {s: j for j, s in enumerate(model.x)}
    column.update({s: n + k for k, s in enumerate(model.xi)})
    where, entries = [], []
    for i, e in enumerate(F):
        for sym in sorted(e.free_symbols & set(column), key=column.get):
            d = e.diff(sym)
            if d != 0:
                where.append((i, column[sym]))
                entries.append(d)
    positions = np.array(where, dtype=int).reshape(-1, 2)
    in_x = positions[:, 1] < n
    # Point-wise evaluation (one call per Newton step): compiled flat, without the broadcasting wrapper.
    flat = compile_flat(list(F) + entries, list(model.x) + list(model.xi), model.values)

    def terms(x: np.ndarray, at: np.ndarray):
        values = np.array(flat(*x, *at), dtype=float)
        jac = values[n:]
        Fx = sps.csc_matrix((jac[in_x], (positions[in_x, 0], positions[in_x, 1])), shape=(n, n))
        Fxi = np.zeros((n, nh))
        Fxi[positions[~in_x, 0], positions[~in_x, 1] - n] = jac[~in_x]
        return values[:n], Fx, Fxi

    return terms


def _factor(Fx):
    """The sparse LU factors of dF/dx (scipy.sparse.linalg.splu), or None where it is singular to working
    precision: its reciprocal condition number in the 1-norm, estimated as LAPACK's gecon does (Hager's
    method, :func:`_inverse_norm1`), below ``SINGULAR_RCOND``."""
    try:
        lu = spla.splu(sps.csc_matrix(Fx))
    except RuntimeError:   # exactly singular
        return None
    norm = float(abs(Fx).sum(axis=0).max())
    inverse_norm = _inverse_norm1(lu, Fx.shape[0])
    return lu if np.isfinite(inverse_norm) and norm * inverse_norm * SINGULAR_RCOND < 1 else None


def _inverse_norm1(lu, n: int, steps: int = 5) -> float:
    """A lower estimate of ||A^-1||_1 from the LU factors of A (Hager 1984, Higham's LAPACK xLACON, deterministic):
    a few solves with A and A^T instead of the inverse."""
    x = np.full(n, 1.0 / n)
    estimate = 0.0
    for _ in range(steps):
        y = lu.solve(x)
        value = float(np.abs(y).sum())
        if not np.isfinite(value):
            return np.inf
        if value <= estimate:
            break
        estimate = value
        z = lu.solve(np.where(y >= 0, 1.0, -1.0), trans="T")
        j = int(np.argmax(np.abs(z)))
        if abs(z[j]) <= z @ x:
            break
        x = np.zeros(n)
        x[j] = 1.0
    return estimate


def continuation(model: Model, z: np.ndarray) -> np.ndarray:
    """Equilibria x with F(x, xi) = f_bar(x) + g(x) l(xi) = 0 at the points z, by Newton continuation.

    Starts at the point nearest the centre of V (from ``abstract.manifold_guess``, else the origin, else
    the centre of ``concrete.state_box``), then visits each next-nearest point, predicting from the nearest
    solved one along the tangent dp/dxi = -(dF/dx)^-1 dF/dxi and correcting by Newton's method.

    Returns
    -------
    ndarray, shape (n, N)
        The equilibria.

    Raises
    ------
    DesignError
        If no start converges, or the branch turns (dF/dx singular) or is lost at some xi.
    """
    n, N = model.n, z.shape[1]
    terms = field_terms(model)
    centre = model.V.mean(axis=1)
    first = int(np.argmin(np.linalg.norm(z - centre[:, None], axis=0)))

    def newton(guess: np.ndarray, at: np.ndarray) -> np.ndarray | None:
        x = guess.astype(float).copy()
        for _ in range(50):
            value, Fx, _ = terms(x, at)
            if not (np.all(np.isfinite(Fx.data)) and np.all(np.isfinite(value))):
                return None
            lu = _factor(Fx)
            if lu is None:
                return None
            # |F| is judged against the size of its terms, |dF/dx| |x|: round-off, not 1, is the floor.
            scale = max(1.0, float(abs(Fx).max() * np.abs(x).max()))
            if np.abs(value).max() <= NEWTON_RTOL * scale:
                return x
            x = x + lu.solve(-value)
        value, Fx, _ = terms(x, at)
        return x if np.abs(value).max() <= 1e3 * NEWTON_RTOL * max(1.0, float(abs(Fx).max() * np.abs(x).max())) else None

    starts = []
    if model.spec.abstract.manifold_guess is not None:
        starts.append(np.array(model.spec.abstract.manifold_guess, dtype=float))
    starts.append(np.zeros(n))
    if model.state_box is not None:
        starts.append(model.state_box.mean(axis=1))
    x0 = next((x for x in (newton(s, z[:, first]) for s in starts) if x is not None), None)
    if x0 is None:
        raise DesignError("abstract.manifold_guess", f"Newton's method finds no equilibrium f_bar(x) + g(x) l(xi) = 0 at xi = {np.round(z[:, first], 6).tolist()} from {len(starts)} start(s)",
                          "a manifold_guess: n numbers near the equilibrium at the centre of V")
    X = np.full((n, N), np.nan)
    X[:, first] = x0
    solved = np.zeros(N, dtype=bool)
    solved[first] = True
    distance = np.linalg.norm(z - z[:, [first]], axis=0)
    nearest = np.full(N, first)
    for _ in range(N - 1):
        k = int(np.argmin(np.where(solved, np.inf, distance)))
        j = nearest[k]
        _, Fx, Fxi = terms(X[:, j], z[:, j])
        lu = _factor(Fx)
        x = None if lu is None else newton(X[:, j] - lu.solve(Fxi) @ (z[:, k] - z[:, j]), z[:, k])
        if x is None:
            raise DesignError("abstract.domain", f"the equilibrium branch is lost at xi = {np.round(z[:, k], 6).tolist()} (dF/dx singular or Newton diverges): p is not defined on all of V",
                              "a smaller domain V, on which f_bar(x) + g(x) l(xi) = 0 has an isolated solution", check="pde_residual")
        X[:, k], solved[k] = x, True
        to_k = np.linalg.norm(z - z[:, [k]], axis=0)
        closer = to_k < distance
        distance, nearest = np.where(closer, to_k, distance), np.where(closer, k, nearest)
    return X


def solve_numeric_equilibria(model: Model, plant: _Plant | None = None) -> tuple[chebyshev.Series, int, float]:
    """p for phi_bar = 0 without a closed form: Newton continuation on Chebyshev nodes, then a Chebyshev fit.

    The equilibria are found at Chebyshev nodes (31 first, twice as many whenever the degree outgrows
    them); the fitted degree is raised until the relative residual of f(p(xi), l(xi)) = 0 on an independent
    grid (:func:`_relative_residual`) is below ``pde_tolerance``, or the fit stops improving
    (:func:`stalled`), or the safety cap ``pde_max_degree`` is reached.

    Returns
    -------
    p : Series
        The fitted series (n x 1), kept numeric.
    degree, residual : as :func:`solve_collocation`
    """
    tol, max_degree = model.spec.abstract.pde_tolerance, model.spec.abstract.pde_max_degree
    box = model.V
    plant = plant or _Plant(model)
    check = _check_grid(box)
    phi_check = np.zeros((model.n_hat, check.shape[1]))   # phi_bar = 0 here
    best, history = np.inf, []
    nodes_degree = min(max_degree, FIRST_NODES_DEGREE)
    z = chebyshev.nodes(box, nodes_degree + 1)
    X = continuation(model, z)
    degree = 0
    while degree < max_degree:
        degree += 1
        if degree > nodes_degree:
            # More nodes for a higher degree: the equilibria are found again at twice as many.
            nodes_degree = min(max_degree, 2 * nodes_degree)
            z = chebyshev.nodes(box, nodes_degree + 1)
            X = continuation(model, z)
        coeffs = chebyshev.fit(X, box, z, degree)
        best = min(best, _relative_residual(model, coeffs, box, check, plant, phi_check))
        history.append(best)
        if best <= tol:
            return chebyshev.Series.column(coeffs, box), degree, best
        if stalled(history):
            raise DesignError("abstract.domain", f"the Chebyshev fit of the numeric equilibrium manifold stopped improving at degree {degree} "
                              f"(relative residual {best:.3g}, tolerance {tol:g}): p is not smooth enough on V for a polynomial",
                              "a smaller domain V, or a larger abstract.pde_tolerance")
    raise DesignError("abstract.domain", f"the numeric equilibrium manifold is not fitted to {tol:g} by Chebyshev polynomials of degree <= {max_degree}: the best relative residual is {best:.3g}",
                      "a smaller domain V, or a larger abstract.pde_max_degree or pde_tolerance")


#: ``domain: auto`` grows V while ||dp/dxi|| stays below this many times its largest value on kappa^-1(Y).
AUTO_SLOPE_RATIO = 10.0
AUTO_GRID = 20001


def auto_search_box(model: Model) -> np.ndarray:
    """Where ``domain: auto`` searches: the interval of xi with l(xi) in U (one abstract state, l affine).

    Raises
    ------
    DesignError
        For several abstract states, or an l that is not affine or does not bound xi.
    """
    if model.n_hat != 1 or model.p != 1:
        raise DesignError("abstract.domain", f"'auto' handles one abstract state and one output (n_hat = {model.n_hat}, p = {model.p})", "a box [[lo, hi], ...] per abstract state")
    xi = model.xi[0]
    lo, hi = -np.inf, np.inf
    for k, (e, (u_lo, u_hi)) in enumerate(zip(model.l, model.U)):
        slope = sp.diff(e, xi)
        if slope.free_symbols & {xi} or model.substitute(slope) == 0:
            raise DesignError("abstract.l", f"'auto' needs each l_i affine and not constant in xi (l[{k}] = {e})", "a box for abstract.domain")
        a, b = float(model.substitute(slope)), float(model.substitute(e.xreplace({xi: 0})))
        ends = sorted(((u_lo - b) / a, (u_hi - b) / a))
        lo, hi = max(lo, ends[0]), min(hi, ends[1])
    if not lo < hi:
        raise DesignError("abstract.l", "no xi has l(xi) in U", "l mapping some interval into U")
    return np.array([[lo, hi]])


def auto_domain(model: Model, p: sp.Matrix) -> np.ndarray:
    """``abstract.domain: auto`` for one abstract state: the largest interval V around kappa^-1(Y) on which
    l(xi) is in U, p is finite and C^1, kappa = h o p is strictly monotone (so p is injective and kappa(V)
    covers Y), and the manifold is no steeper than ``AUTO_SLOPE_RATIO`` times its steepest point over
    kappa^-1(Y) (beyond that dbar, hence the error bound, grows without helping the outputs in Y).

    The search runs over the interval where l(xi) is in U (l affine in xi).

    Raises
    ------
    DesignError
        For several abstract states or outputs, an l that does not bound xi, or a Y that kappa does not
        reach monotonically from a point of that interval.
    """
    lo, hi = auto_search_box(model)[0]
    xi = model.xi[0]
    xs = np.linspace(lo, hi, AUTO_GRID)
    kappa = model.h.xreplace(dict(zip(model.x, p)))
    k = model.numeric(kappa, [xi])(xs)[0, 0]
    dk = model.numeric(kappa.diff(xi), [xi])(xs)[0, 0]
    slope = np.linalg.norm(model.numeric(p.diff(xi), [xi])(xs)[:, 0, :], axis=0)
    ok = np.isfinite(k) & np.isfinite(dk) & np.isfinite(slope) & (dk != 0)
    Y = model.Y[0]
    inside = ok & (k >= Y[0]) & (k <= Y[1])
    if not inside.any():
        raise DesignError("abstract.domain", f"'auto': kappa(xi) never enters Y = {Y.tolist()} for xi in [{lo:.6g}, {hi:.6g}] (where l(xi) is in U)",
                          "an output_set that the equilibria reach, or a box for abstract.domain", check="V_covers_Y")
    # The run of admissible points with one sign of dkappa that contains the first point in Y.
    start = int(np.flatnonzero(inside)[0])
    sign = np.sign(dk[start])
    good = ok & (np.sign(dk) == sign)
    left, right = start, start
    while left > 0 and good[left - 1]:
        left -= 1
    while right < len(xs) - 1 and good[right + 1]:
        right += 1
    run_k = k[left:right + 1]
    if not (run_k.min() <= Y[0] and Y[1] <= run_k.max()):
        raise DesignError("abstract.domain", f"'auto': kappa is monotone only on [{xs[left]:.6g}, {xs[right]:.6g}], where it spans [{run_k.min():.6g}, {run_k.max():.6g}], not all of Y = {Y.tolist()}",
                          "a smaller output_set, or a box for abstract.domain", check="V_covers_Y")
    need = (k >= Y[0]) & (k <= Y[1]) & good
    need[:left] = need[right + 1:] = False
    cap = AUTO_SLOPE_RATIO * slope[need].max()
    need_idx = np.flatnonzero(need)
    a_idx, b_idx = need_idx[0], need_idx[-1]
    while a_idx > left and slope[a_idx - 1] <= cap:
        a_idx -= 1
    while b_idx < right and slope[b_idx + 1] <= cap:
        b_idx += 1
    # Stay one grid cell inside an inadmissible neighbour (a pole or a turning point of kappa).
    a_idx += a_idx > 0 and not good[a_idx - 1]
    b_idx -= b_idx < len(xs) - 1 and not good[b_idx + 1]
    return np.array([[xs[a_idx], xs[b_idx]]])


def run(model: Model, upstream: dict[str, Artefact]) -> Artefact:
    """Solve eq. (14a) for p and check it.

    Parameters
    ----------
    model : Model
        The spec's systems.
    upstream : dict of str to Artefact
        Unused (the manifold reads only the spec).

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
    plant = _Plant(model)
    p, series, branches, method, tolerance = _solve(model, plant)
    V = model.V if model.V is not None else auto_domain(model, p)
    on = _on_grid(model, plant, p, series, V, tolerance)
    l_range, excursion, l_proved, grid_excursion, l_inside = _l_in_U(model, V, on["l_grid"])
    art = Artefact(stage=NAME, meta={"method": method, "branches": branches,
                                      "grid_points": int(on["grid"].shape[1]), "residual_rtol": tolerance,
                                      "domain": "auto" if model.V is None else "spec"})
    if series is not None:
        art.set_series("p", series, model.xi)
        art.set_series("dp_dxi", on["dp_series"], model.xi)
        art.values["p_formula_deviation"] = on["deviation"]
    else:
        art.exprs.update({"p": p, "dp_dxi": on["dp"]})
    art.values.update({"V": V, "xi_grid": on["grid"], "p_grid": on["p_grid"], "residual": on["residual"], "residual_scale": on["scale"],
                       "l_range": l_range})
    points = on["grid"].shape[1]
    if series is None and not p.atoms(sp.Float) and proofs.symbolic_zero(list(proofs.exact(model, pde_residual_expr(model, p)))):
        art.checks["pde_residual"] = Check(0.0, True, "dp/dxi phi_bar - f_bar(p) - g(p) l simplifies to 0 (sympy): p solves eq. (14a) exactly", proofs.PROVED)
    else:
        which = f" (the Chebyshev series and its formula; they differ by {on['deviation']:.2g})" if series is not None else ""
        art.checks["pde_residual"] = Check(on["residual"], True, f"max over a {points}-point grid of V of |dp/dxi phi_bar - f_bar(p) - g(p) l| (eq. (14a)){which}")
    if l_proved:
        how = ("l affine: its values at the corners of V, in exact rationals" if proofs.affine_in(model.l, list(model.xi))
               else "the ball-arithmetic enclosure of l(V)")
        art.checks["l_in_U"] = Check(excursion, True, f"largest excursion of l(V) outside U, {how} (<= 0: l maps V into U)", proofs.PROVED)
    else:
        art.checks["l_in_U"] = Check(grid_excursion, l_inside, f"largest excursion of l(V) outside U on a {points}-point grid (<= 0: l maps V into U)")
    return art


def _solve(model: Model, plant: _Plant):
    """(p, series, branches, method, tolerance): p by the first method that applies (a closed form, Newton
    continuation with a Chebyshev fit, the Sylvester equation, Chebyshev collocation), its coefficients
    recognised as exact where they are; ``series`` is p kept numeric (then p is that series too); tolerance is
    the residual p must meet (round-off for a closed form, the spec's pde_tolerance for a fit)."""
    # A closed form must solve the PDE to round-off; a fitted p to the spec's pde_tolerance.
    tolerance, fitted_tolerance = RESIDUAL_RTOL, max(RESIDUAL_RTOL, model.spec.abstract.pde_tolerance)
    if all(sp.simplify(e) == 0 for e in model.phi_bar):
        p, closed_form_failure = None, "numeric fast path chosen (sympy not tried)"
        if not (model.use_numeric and model.V is not None):
            try:
                p, branches = solve_algebraic(model)
                method = "closed form (sympy.solve of f(p, l(xi)) = 0)"
            except DesignError as exc:
                if model.V is None:
                    raise
                closed_form_failure = exc.what
        if p is None:
            try:
                p, degree, fit_residual = solve_numeric_equilibria(model, plant)
            except DesignError as numeric_failure:
                raise DesignError(numeric_failure.where, f"{closed_form_failure}; numerically: {numeric_failure.what}", numeric_failure.expected,
                                  check=numeric_failure.check) from None
            branches, tolerance = 1, fitted_tolerance
            method = f"Newton continuation on Chebyshev nodes + Chebyshev fit, degree {degree} (relative residual {fit_residual:.2g} on an independent grid)"
    else:
        p, branches = solve_sylvester(model), 1
        method = "Sylvester equation A P + B Q = P S (scipy.linalg.solve_sylvester)"
        if p is None:
            if model.V is None:
                raise DesignError("abstract.domain", "'auto' needs a p defined independently of V (phi_bar = 0 with a closed form, or a linear plant)",
                                  "a box [[lo, hi], ...] per abstract state for the PDE solver")
            p, degree, fit_residual = solve_collocation(model, plant)
            tolerance = fitted_tolerance
            method = f"Chebyshev collocation, degree {degree} (relative residual {fit_residual:.2g} on an independent grid)"
    series = None
    if isinstance(p, chebyshev.Series):
        if p.horner:
            series = p
        else:   # a low degree: the expanded, chopped polynomial (an exact solution reads as one) is p
            p = p.to_sympy(list(model.xi))
    if series is None and p.atoms(sp.Float):
        exact_p = recognise_exact(model, p)
        if exact_p is not None:
            p, tolerance = exact_p, RESIDUAL_RTOL
            method += "; its coefficients recognised as rationals that solve eq. (14a) exactly (sympy)"
    return p, series, branches, method, tolerance


def _on_grid(model: Model, plant: _Plant, p, series, V: np.ndarray, tolerance: float) -> dict:
    """p, dp/dxi, phi_bar and l on a grid of V, and the PDE residual there (the series and its formula both);
    a NumericalError if the residual is above ``tolerance`` relative to the size of its terms."""
    grid = domain_grid(V, GRID_POINTS)
    xi_args = list(model.xi)
    on = {"grid": grid, "deviation": 0.0}
    phi_grid = model.numeric(model.phi_bar, xi_args)(*grid)[:, 0, :]         # (n_hat, N)
    on["l_grid"] = l_grid = model.numeric(model.l, xi_args)(*grid)[:, 0, :]  # (m, N)
    if series is not None:
        # Kept numeric (Chebyshev series, evaluated by numpy): no sympy Jacobian or compiled formula of p.
        on["dp_series"] = dp_series = series.jacobian()
        p_grid, dp_grid = series.at(grid)[:, 0, :], dp_series.at(grid)      # (n, N), (n, n_hat, N)
    else:
        on["dp"] = dp = p.jacobian(model.xi)
        p_grid = model.numeric(p, xi_args)(*grid)[:, 0, :]                   # (n, N)
        dp_grid = model.numeric(dp, xi_args)(*grid)                          # (n, n_hat, N)
    residual, scale = _grid_residual(plant, p_grid, dp_grid, phi_grid, l_grid)
    if series is not None:
        # Readers of the artefact get p's formula (Horner on power coefficients), which differs from the series
        # by the round-off of that conversion: it must solve the PDE too, and the check covers both.
        p_formula = series.formula_at(grid)[:, 0, :]
        on["deviation"] = float(np.abs(p_formula - p_grid).max())
        formula_residual, formula_scale = _grid_residual(plant, p_formula, dp_series.formula_at(grid), phi_grid, l_grid)
        residual, scale = max(residual, formula_residual), max(scale, formula_scale)
    if not np.isfinite(residual) or residual > tolerance * scale:
        raise NumericalError(NAME, f"residual of eq. (14a) on V is {residual:.3g} (scale {scale:.3g})", f"below {tolerance:g} relative")
    on.update(p_grid=p_grid, residual=residual, scale=scale)
    return on


def _l_in_U(model: Model, V: np.ndarray, l_grid: np.ndarray):
    """(l_range, excursion, proved, grid_excursion, inside): l(V) inside U, proved (exactly for an affine l, in
    ball arithmetic otherwise) or on the grid; a DesignError if l(V) leaves U."""
    U = model.U
    l_lo, l_hi = l_grid.min(axis=1), l_grid.max(axis=1)
    excursion, l_proved = prove_l_in_U(model, V)
    # Proved inside, proved outside, or (no proof) inside on the grid with no slack.
    grid_excursion = float(np.max(np.r_[U[:, 0] - l_lo, l_hi - U[:, 1]]))
    decided = l_proved or (np.isfinite(excursion) and proofs.affine_in(model.l, list(model.xi)))
    l_inside = l_proved if decided else grid_excursion <= 0
    if not l_inside:
        by = excursion if decided else grid_excursion
        tiny = " (at the level of rounding: shrink abstract.domain by that much)" if by <= 1e-12 * max(1.0, float(np.abs(U).max())) else ""
        raise DesignError("abstract.l", f"l(V) = {np.c_[l_lo, l_hi].tolist()} is not inside U = {U.tolist()}: it leaves U by {by:.3g}"
                          f"{' (decided exactly)' if decided else ' on a grid of V'}{tiny}",
                          "l: V -> U (Theorem 4); shrink abstract.domain or change l", check="l_in_U")
    return np.c_[l_lo, l_hi], excursion, l_proved, grid_excursion, l_inside


def _grid_residual(plant: _Plant, p_grid: np.ndarray, dp_grid: np.ndarray, phi_grid: np.ndarray, l_grid: np.ndarray) -> tuple[float, float]:
    """max |dp/dxi phi_bar - f_bar(p) - g(p) l| over a grid, and the size of its terms max(1, |f_bar(p)|, |g(p) l|)."""
    fbar = plant.fbar(*p_grid)[:, 0, :]
    gl = np.einsum("ijk,jk->ik", plant.g(*p_grid), l_grid)
    residual = float(np.abs(np.einsum("ijk,jk->ik", dp_grid, phi_grid) - (fbar + gl)).max())
    return residual, float(max(1.0, np.abs(fbar).max(), np.abs(gl).max()))


def pde_residual_expr(model: Model, p: sp.Matrix) -> sp.Matrix:
    """dp/dxi phi_bar - f_bar(p) - g(p) l(xi), symbolically (eq. SimuDesignCond1 as a residual)."""
    on_p = dict(zip(model.x, p))
    return p.jacobian(model.xi) * model.phi_bar - model.f_bar.xreplace(on_p) - model.g.xreplace(on_p) * model.l


def prove_l_in_U(model: Model, V: np.ndarray) -> tuple[float, bool]:
    """The largest excursion of l(V) outside U, from proved bounds of each l_i over V; and whether l(V) is inside U.

    An affine l is decided exactly: its extremes are at the corners of V, evaluated in rationals (the spec's
    decimals, :func:`proofs.exact`), so an l that meets the end of U exactly is inside, and one that leaves it by
    2e-16 is outside.  Otherwise each l_i is enclosed by branch and bound in ball arithmetic.
    """
    if proofs.affine_in(model.l, list(model.xi)):
        l_exact = proofs.exact(model, model.l)
        corners = itertools.product(*[(proofs.exact_number(lo), proofs.exact_number(hi)) for lo, hi in V])
        at = [l_exact.xreplace(dict(zip(model.xi, c))) for c in corners]
        excursion = max(max(proofs.exact_number(model.U[i, 0]) - a[i], a[i] - proofs.exact_number(model.U[i, 1])) for a in at for i in range(model.m))
        return float(excursion), bool(excursion <= 0)
    try:
        f = proofs.compile_claims(model, list(model.l), list(model.xi))
    except proofs.interval.UnsupportedExpression:
        return np.inf, False
    excursion = -np.inf
    for i in range(model.m):
        lo, hi, ok = proofs.range_on_box(f, V, index=i)
        if not ok:
            return np.inf, False
        excursion = max(excursion, model.U[i, 0] - lo, hi - model.U[i, 1])
    return float(excursion), bool(excursion <= 0)


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``."""
    return {"p": [str(e) for e in art.exprs["p"]], "residual": float(art.values["residual"]), "method": art.meta.get("method")}


def headline(art: Artefact) -> str:
    """One progress line."""
    return f"p found ({art.meta.get('branches')} branch(es)), PDE residual = {art.values['residual']:.2g}"
