"""The manifold stage's numeric solvers of the invariance PDE (eq. (14a)) where p has no closed form: collocation by
Chebyshev polynomials on V for phi_bar != 0 (one abstract state), and Newton continuation on Chebyshev nodes for
phi_bar = 0 (the equilibria of f_bar(x) + g(x) l(xi) = 0, sparse Jacobians and LU), fitted by a Chebyshev series.
Used by :mod:`ashc_cli.design.stages.manifold`, which checks what they return."""

from __future__ import annotations


import numpy as np
import scipy.optimize as sopt
import scipy.sparse as sps
import scipy.sparse.linalg as spla
import sympy as sp

from ashc_cli.numerics import chebyshev
from ashc_cli.errors import DesignError
from ashc_cli.problem.grids import domain_grid
from ashc_cli.problem.model import Model, compile_flat, sparse_jacobian

__all__ = ["ManifoldPlant", "manifold_field", "solve_collocation", "field_terms", "continuation", "solve_numeric_equilibria"]


def manifold_field(model: Model, valued: bool = False) -> sp.Matrix:
    """F(x, xi) = f_bar(x) + g(x) l(xi): the right side of eq. (14a) before x = p(xi).

    Parameters
    ----------
    model : Model
    valued : bool
        Put the spec's parameter values in (for numbers); else they stay symbols.

    Returns
    -------
    sympy Matrix (n, 1)
    """
    if valued:
        return model.valued["f_bar"] + model.valued["g"] * model.valued["l"]
    return model.f_bar + model.g * model.l


def _residual_function(model: Model, jacobian: bool = False):
    """F(x, xi) (and dF/dx if asked), compiled for numpy (broadcasting)."""
    F = manifold_field(model)
    args = list(model.x) + list(model.xi)
    return (model.numeric(F, args), model.numeric(sparse_jacobian(F, model.x), args)) if jacobian else model.numeric(F, args)


class ManifoldPlant:
    """f_bar(x), g(x) and l(xi) compiled once for numpy (broadcasting), for the residuals of fits and of p."""

    def __init__(self, model: Model):
        x, xi = list(model.x), list(model.xi)
        self.fbar = model.numeric(model.valued["f_bar"], x)
        self.g = model.numeric(model.valued["g"], x)
        self.l = model.numeric(model.valued["l"], xi)

    def sides(self, P: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """f_bar(P) and g(P) l(z) at the points P (n, N) and z (n_hat, N), each (n, N)."""
        return self.fbar(*P)[:, 0, :], np.einsum("ijk,jk->ik", self.g(*P), self.l(*z)[:, 0, :])


def _relative_residual(model: Model, coeffs: np.ndarray, box: np.ndarray, z: np.ndarray, plant: ManifoldPlant, phi: np.ndarray) -> float:
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


def _stalled(history: list[float]) -> bool:
    """True when the best residual has not halved over the last ``STALL_DEGREES`` raises of the degree.

    A smooth (analytic) manifold gains a constant factor per degree, so a fit that stalls is fitting a
    manifold with a kink or a near-singularity on V, where a higher degree only costs time.
    """
    if len(history) <= STALL_DEGREES:
        return False
    return history[-1] > STALL_FACTOR * history[-1 - STALL_DEGREES]


def solve_collocation(model: Model, plant: ManifoldPlant | None = None) -> tuple[sp.Matrix, int, float]:
    """Tensor Chebyshev collocation for eq. (14a) (phi_bar != 0), any number of abstract states.

    The coefficients minimise the PDE residual at 2 (degree + 1) Chebyshev nodes per axis (Gauss-Newton with
    the exact Jacobian: the residual is linear in p's coefficients through dp/dxi and nonlinear through
    F(p, xi)); the degree is raised from 1 until the relative residual on an independent grid is below
    ``abstract.pde_tolerance``.

    Parameters
    ----------
    model : Model
        The spec's systems (V, the abstract maps and ``abstract.pde_*`` are read).
    plant : ManifoldPlant, optional
        f_bar, g and l compiled once (built here when None).

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
    plant = plant or ManifoldPlant(model)
    phi_num = model.numeric(model.phi_bar, list(model.xi))
    check = _check_grid(box)
    phi_check = phi_num(*check)[:, 0, :]
    coeffs = np.zeros((n,) + (1,) * nh)
    best, history = np.inf, []
    for degree in range(1, max_degree + 1):
        if _stalled(history):
            raise DesignError("abstract.phi_bar", f"the polynomial fit of eq. (14a) stopped improving at degree {degree - 1} (relative residual "
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
    raise DesignError("abstract.phi_bar", f"no polynomial of degree <= {max_degree} solves eq. (14a) on V to {tol:g}: the best relative residual is {best:.3g}",
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

    Parameters
    ----------
    model : Model
        The spec's systems (f_bar, g, l with the parameter values put in).

    Returns
    -------
    callable
        ``terms(x, xi)`` -> (F (n,), dF/dx (n x n, scipy.sparse CSC), dF/dxi (n, n_hat) dense).
    """
    n, nh = model.n, model.n_hat
    F = manifold_field(model, valued=True)
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

    Parameters
    ----------
    model : Model
        The spec's systems (V fixed; ``abstract.manifold_guess`` and ``concrete.state_box`` give starts).
    z : ndarray (n_hat, N)
        Points of V, visited nearest-first.

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


def solve_numeric_equilibria(model: Model, plant: ManifoldPlant | None = None) -> tuple[chebyshev.Series, int, float]:
    """p for phi_bar = 0 without a closed form: Newton continuation on Chebyshev nodes, then a Chebyshev fit.

    The equilibria are found at Chebyshev nodes (31 first, twice as many whenever the degree outgrows
    them); the fitted degree is raised until the relative residual of f(p(xi), l(xi)) = 0 on an independent
    grid (:func:`_relative_residual`) is below ``pde_tolerance``, or the fit stops improving
    (:func:`_stalled`), or the safety cap ``pde_max_degree`` is reached.

    Parameters
    ----------
    model, plant : Model, ManifoldPlant or None
        As :func:`solve_collocation`.

    Returns
    -------
    p : Series
        The fitted series (n x 1), kept numeric.
    degree, residual : as :func:`solve_collocation`
    """
    tol, max_degree = model.spec.abstract.pde_tolerance, model.spec.abstract.pde_max_degree
    box = model.V
    plant = plant or ManifoldPlant(model)
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
        if _stalled(history):
            raise DesignError("abstract.domain", f"the Chebyshev fit of the numeric equilibrium manifold stopped improving at degree {degree} "
                              f"(relative residual {best:.3g}, tolerance {tol:g}): p is not smooth enough on V for a polynomial",
                              "a smaller domain V, or a larger abstract.pde_tolerance")
    raise DesignError("abstract.domain", f"the numeric equilibrium manifold is not fitted to {tol:g} by Chebyshev polynomials of degree <= {max_degree}: the best relative residual is {best:.3g}",
                      "a smaller domain V, or a larger abstract.pde_max_degree or pde_tolerance")
