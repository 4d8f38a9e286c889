"""The manifold stage's numeric solvers of the invariance PDE (eq. (14a)) where p has no closed form: collocation by
Chebyshev polynomials on V for phi_bar != 0 (one abstract state), and Newton continuation on Chebyshev nodes for
phi_bar = 0 (the equilibria of f_bar(x) + g(x) l(xi) = 0, sparse Jacobians and LU), fitted by a Chebyshev series.
Used by :mod:`ashc_cli.design.stages.manifold`, which checks what they return."""

from __future__ import annotations


import itertools

import numpy as np
import scipy.optimize as sopt
import scipy.sparse as sps
import scipy.sparse.linalg as spla
import sympy as sp

from ashc_cli.numerics import chebyshev
from ashc_cli.errors import DesignError, FitError
from ashc_cli.problem.grids import domain_grid
from ashc_cli.problem.model import Model, compile_flat, sparse_jacobian

__all__ = ["ManifoldPlant", "manifold_field", "solve_collocation", "field_terms", "continuation", "solve_numeric_equilibria", "equilibrium_error",
           "resonance"]


def manifold_field(model: Model, valued: bool = False) -> sp.Matrix:
    """F(x, xi) = f_bar(x) + g(x) l(xi), or f(x, l(xi)) for a plant that is not input-affine (Remark 4): the right
    side of eq. (14a) before x = p(xi).

    Parameters
    ----------
    model : Model
    valued : bool
        Put the spec's parameter values in (for numbers); else they stay symbols.

    Returns
    -------
    sympy Matrix (n, 1)
    """
    if not model.affine:
        return model.f_on(model.x, model.valued["l"] if valued else model.l, valued=valued)
    if valued:
        return model.valued["f_bar"] + model.valued["g"] * model.valued["l"]
    return model.f_bar + model.g * model.l


def _residual_function(model: Model, jacobian: bool = False):
    """F(x, xi) (and dF/dx if asked), compiled for numpy (broadcasting)."""
    F = manifold_field(model)
    args = list(model.x) + list(model.xi)
    return (model.numeric(F, args), model.numeric(sparse_jacobian(F, model.x), args)) if jacobian else model.numeric(F, args)


#: The orders k of the resonance test: sum_i k_i mu_i (|k| <= RESONANCE_ORDER) against the plant's rates.
RESONANCE_ORDER = 4


def resonance(model: Model, x_c: np.ndarray | None = None) -> str:
    """Name a resonance of eq. (14a) at the centre of V: a combination sum_i k_i mu_i (k_i >= 0, 1 <= |k| <=
    RESONANCE_ORDER) of the rates mu of dphi_bar/dxi equal to a rate of dF/dx (F = f_bar + g l) at x_c.  There the
    PDE's homogeneous equation has a polynomial solution of degree |k| (p is not unique, and a fit can grow it
    without bound), or the equation has no polynomial solution at all.

    Parameters
    ----------
    model : Model
    x_c : ndarray (n,), optional
        The state to linearise at (p at V's centre); without it only a Jacobian free of x is read.

    Returns
    -------
    str
        "; ..." naming the rates, or "" when none matches (or the Jacobians cannot be evaluated).
    """
    try:
        xi_c = np.mean(np.asarray(model.V, dtype=float), axis=1)
        A_hat = np.asarray(model.numeric(sp.Matrix(model.phi_bar).jacobian(list(model.xi)), list(model.xi))(*xi_c), dtype=float)
        J_sym = sparse_jacobian(manifold_field(model, valued=True), model.x)
        if x_c is None and any(e.free_symbols & set(model.x) for e in J_sym):
            return ""
        x_c = np.zeros(model.n) if x_c is None else np.asarray(x_c, dtype=float)
        J = np.asarray(model.numeric(J_sym, list(model.x) + list(model.xi))(*x_c, *xi_c), dtype=float).reshape(model.n, model.n)
        mu, rates = np.linalg.eigvals(A_hat.reshape(model.n_hat, model.n_hat)), np.linalg.eigvals(J)
    except Exception:      # a Jacobian that is not finite at the centre: nothing to name
        return ""
    for order in range(1, RESONANCE_ORDER + 1):
        for k in itertools.combinations_with_replacement(range(model.n_hat), order):
            combo = complex(sum(mu[i] for i in k))
            for r in rates:
                if abs(combo - r) <= 1e-6 * max(1.0, abs(r)):
                    what = " + ".join(f"{complex(mu[i]).real:.6g}" for i in k)
                    return (f"; the PDE is resonant: phi_bar's rates at the centre of V ({what} = {combo.real:.6g}) equal a rate "
                            f"of the plant's df/dx there ({complex(r).real:.6g}), so its homogeneous equation has a polynomial solution "
                            f"of degree {order} (p is not unique or has no polynomial form); change phi_bar's rates")
    return ""


class ManifoldPlant:
    """f_bar(x), g(x) and l(xi) compiled once for numpy (broadcasting), for the residuals of fits and of p; f(x, u)
    and l(xi) for a plant that is not input-affine."""

    def __init__(self, model: Model):
        x, xi = list(model.x), list(model.xi)
        self.affine = model.affine
        if self.affine:
            self.fbar = model.numeric(model.valued["f_bar"], x)
            self.g = model.numeric(model.valued["g"], x)
        else:
            self.f = model.numeric(model.valued["f"], x + list(model.u))
        self.l = model.numeric(model.valued["l"], xi)
        # the size of each row's terms: sum of |additive part| of F_i(x, xi) = f_bar_i + (g l)_i (top-level expanded,
        # so that (v_k - v_k+1) / L counts as |v_k / L| + |v_k+1 / L|, not as its small difference)
        size = [sp.Add(*[sp.Abs(part) for part in sp.Add.make_args(sp.expand(F, deep=False, power_exp=False, power_base=False,
                                                                               log=False, multinomial=False))])
                for F in manifold_field(model, valued=True)]
        self.size = model.numeric(size, x + xi)

    def sizes(self, P: np.ndarray, z: np.ndarray) -> np.ndarray:
        """The size of each row's terms at the points P (n, N) and z (n_hat, N): (n, N)."""
        return np.broadcast_to(self.size(*P, *z)[:, 0, :], P.shape)

    def sides(self, P: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """f_bar(P) and g(P) l(z) at the points P (n, N) and z (n_hat, N), each (n, N); f(P, l(z)) and zeros for a
        plant that is not input-affine."""
        return self.sides_at(P, self.l(*z)[:, 0, :])

    def sides_at(self, P: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`sides` with the inputs L (m, N) = l(z) already evaluated."""
        if not self.affine:
            return self.f(*P, *L)[:, 0, :], np.zeros_like(P)
        return self.fbar(*P)[:, 0, :], np.einsum("ijk,jk->ik", self.g(*P), L)


def _residual_terms(p, z: np.ndarray, plant: ManifoldPlant, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|dp/dxi phi_bar - f_bar(p) - g(p) l| at each point of z, row by row, for a fitted p (a Series or
    PiecewiseSeries; phi = phi_bar on z), and the size of each row's terms there, max(1, |dp/dxi phi_bar|_i,
    |f_bar(p)|_i, |g(p) l|_i, |f_bar(p) + g(p) l|_i, the sum of the row's additive parts :meth:`ManifoldPlant.sizes`).

    The terms, not their sum: with phi_bar = 0 the sum is the residual itself, and a plant whose terms are
    large (the ladder's v / L, 1e5 at n = 512) could never meet an absolute tolerance.  Each row against its own
    terms: one row of size 6e7 (a resonant row's homogeneous solution) must not make the other rows' residual of
    0.3 look relative 1e-9.  ``run`` judges the stored p the same way.

    Returns
    -------
    residual : ndarray (n, N)
    scale : ndarray (n,)
    """
    P = p.at(z)[:, 0, :]
    lhs = np.einsum("ikN,kN->iN", p.jacobian().at(z), phi) if np.any(phi) else np.zeros_like(P)
    fbar, gl = plant.sides(P, z)
    rhs = fbar + gl
    scale = np.max(np.abs(np.stack([lhs, rhs, fbar, gl, plant.sizes(P, z)])), axis=(0, 2), initial=1.0)
    return np.abs(lhs - rhs), scale


def _relative_residual(model: Model, p, z: np.ndarray, plant: ManifoldPlant, phi: np.ndarray, scale: np.ndarray | None = None) -> float:
    """max over the rows of :func:`_residual_terms` on z relative to the size of that row's terms there, or to
    ``scale`` when given (the size of the terms on all of V, for a piece: one number, or one per row)."""
    residual, own = _residual_terms(p, z, plant, phi)
    by = np.asarray(own if scale is None else scale, dtype=float)
    return float((residual / (by[:, None] if by.ndim else by)).max())


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


#: Evaluations of one degree's Levenberg-Marquardt fit at most (the problem is nearly linear in the coefficients:
#: it converges in a few; the bound keeps a degree that does not from running on).
LM_MAX_STEPS = 100


def solve_collocation(model: Model, plant: ManifoldPlant | None = None, seed: np.ndarray | None = None) -> tuple[chebyshev.Series | chebyshev.PiecewiseSeries, int, float]:
    """Tensor Chebyshev collocation for eq. (14a) (phi_bar != 0), any number of abstract states.

    The coefficients minimise the PDE residual at 2 (degree + 1) Chebyshev nodes per axis (Gauss-Newton with
    the exact Jacobian: the residual is linear in p's coefficients through dp/dxi and nonlinear through
    F(p, xi)); the degree is raised from 1 until the relative residual on an independent grid is below
    ``abstract.pde_tolerance``.  With one abstract state the degree stops at ``chebyshev.PIECE_MAX_DEGREE``,
    or where the fit stops improving, and V is then split into pieces (:func:`_collocate_pieces`).

    Parameters
    ----------
    model : Model
        The spec's systems (V, the abstract maps and ``abstract.pde_*`` are read).
    plant : ManifoldPlant, optional
        f_bar, g and l compiled once (built here when None).
    seed : ndarray (n, n_hat), optional
        Start the degree-1 fit from p(xi) = seed xi instead of p = 0 (where eq. (14a) has several solutions).

    Returns
    -------
    p : Series or PiecewiseSeries
        The fitted series (n x 1), kept numeric.
    degree : int
        The degree per axis (the highest of a piece) that reached the tolerance.
    residual : float
        Relative residual on the independent grid.
    work : float
        The least-squares work spent (rows x columns^2 summed over the Jacobian evaluations; ``abstract.pde_work``).

    Raises
    ------
    DesignError
        If no degree up to ``abstract.pde_max_degree`` reaches ``abstract.pde_tolerance`` (the message
        gives the best residual reached, and where on V for pieces).
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
    top = min(max_degree, chebyshev.PIECE_MAX_DEGREE) if nh == 1 else max_degree
    budget, work = float(model.spec.abstract.pde_work), 0.0
    for degree in range(1, top + 1):
        if _stalled(history):
            if nh == 1:
                break
            raise DesignError("abstract.phi_bar", f"the polynomial fit of eq. (14a) stopped improving at degree {degree - 1} (relative residual "
                              f"{best:.3g}, tolerance {tol:g}): p is not smooth enough on V for a polynomial"
                              f"{resonance(model, chebyshev.Series.column(coeffs, box).at(np.mean(box, axis=1)[:, None])[:, 0, 0])}",
                              "a smaller domain V, a larger pde_tolerance, or phi_bar = 0")
        grown = np.zeros((n,) + (degree + 1,) * nh)
        grown[(slice(None),) + tuple(slice(0, degree) for _ in range(nh))] = coeffs
        z = chebyshev.nodes(box, 2 * (degree + 1))
        if seed is not None and degree == 1:
            grown = chebyshev.fit(np.asarray(seed, dtype=float) @ z, box, z, 1)
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

        # The work of one step: rows x columns^2 of the Jacobian (a QR).  Counted, not timed (deterministic).
        per_step = float(n * z.shape[1]) * float(n * K) ** 2
        steps = int((budget - work) // per_step)
        if steps < 1:
            raise DesignError("abstract.pde_work", f"the collocation of eq. (14a) spent {work:.3g} of its work budget {budget:.3g} up to degree "
                              f"{degree - 1} (best relative residual {best:.3g}, tolerance {tol:g}); degree {degree} needs {per_step:.3g} a step",
                              "a larger abstract.pde_work, a larger pde_tolerance, a smaller domain V, or abstract.p written by hand (checked)")
        fit = sopt.least_squares(residual, grown.ravel(), jac=jacobian, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15,
                                 max_nfev=min(steps, LM_MAX_STEPS))
        work += per_step * int(fit.njev if fit.njev is not None else fit.nfev)      # a QR per Jacobian
        coeffs = fit.x.reshape(grown.shape)
        series = chebyshev.Series.column(coeffs, box)
        best = min(best, _relative_residual(model, series, check, plant, phi_check))
        history.append(best)
        if best <= tol:
            return series, degree, best, work
    if nh == 1:
        p = _collocate_pieces(model, F, F_x, phi_num, plant, top)
        return p, p.degree, _relative_residual(model, p, check, plant, phi_check), work
    raise DesignError("abstract.phi_bar", f"no polynomial of degree <= {max_degree} solves eq. (14a) on V to {tol:g}: the best relative residual is {best:.3g}"
                      f"{resonance(model, series.at(np.mean(box, axis=1)[:, None])[:, 0, 0])}",
                      "a smaller domain V, a larger abstract.pde_max_degree or pde_tolerance, or phi_bar = 0")


def _collocate_pieces(model: Model, F, F_x, phi_num, plant: ManifoldPlant, degree: int) -> chebyshev.PiecewiseSeries:
    """Piecewise Chebyshev collocation for eq. (14a) with one abstract state: V is halved where the PDE residual
    of a piece (on an independent grid of it, against the size of the terms on all of V) is above
    ``pde_tolerance``, and all pieces are solved together, the PDE at 2 (degree + 1) nodes of each and p and
    dp/dxi continuous at the breaks (weighted rows of the same least-squares problem).

    Raises
    ------
    DesignError
        If ``chebyshev.MAX_PIECES`` pieces, or pieces ``chebyshev.MIN_PIECE_FRACTION`` of V wide, are not
        enough (the message names where on V the residual stays high).
    """
    tol = model.spec.abstract.pde_tolerance
    lo, hi = (float(v) for v in model.V[0])
    zeros = _zeros_of_phi(phi_num, lo, hi)
    breaks = np.array([lo, _split_point(lo, hi, zeros), hi])
    while True:
        p = _solve_pieces(model, F, F_x, phi_num, breaks, degree)
        check = _check_grid(model.V)
        _, scale = _residual_terms(p, check, plant, phi_num(*check)[:, 0, :])
        failing, best = [], {}
        for k, piece in enumerate(p.pieces):
            grid = domain_grid(piece.box, PIECE_CHECK_POINTS)
            residual, _ = _residual_terms(p, grid, plant, phi_num(*grid)[:, 0, :])
            best[k] = float((residual / scale[:, None]).max())
            # Half the tolerance on the piece's grid: between its points, and at the breaks, the residual is higher
            # (the stage judges p on a finer grid of V).
            if best[k] > tol / 2:
                failing.append(k)
        if not failing:
            return p
        widths = np.diff(breaks)
        worst = max(failing, key=best.get)
        too_many = len(breaks) - 1 + len(failing) > chebyshev.MAX_PIECES
        if too_many or widths[failing].min() / 2 < (hi - lo) * chebyshev.MIN_PIECE_FRACTION:
            why = (f"{chebyshev.MAX_PIECES} pieces are not enough" if too_many else
                   "the pieces there are already too narrow: p has a kink or a near-singularity there")
            raise DesignError("abstract.phi_bar", f"no piecewise polynomial ({len(breaks) - 1} pieces of degree {degree}) solves eq. (14a) to {tol:g}: "
                              f"near xi in [{breaks[worst]:.6g}, {breaks[worst + 1]:.6g}] the relative residual is {best[worst]:.3g}; {why}"
                              f"{resonance(model, p.at(np.mean(model.V, axis=1)[:, None])[:, 0, 0])}",
                              "a domain V that stops short of it, a larger abstract.pde_tolerance or pde_max_degree, or phi_bar = 0")
        breaks = np.sort(np.r_[breaks, [_split_point(breaks[k], breaks[k + 1], zeros) for k in failing]])


def _zeros_of_phi(phi_num, lo: float, hi: float) -> np.ndarray:
    """Where phi_bar (one abstract state) vanishes or changes sign on [lo, hi], to the spacing of a 20001-point grid."""
    xs = np.linspace(lo, hi, 20001)
    phi = np.asarray(phi_num(xs), dtype=float).reshape(-1)
    change = np.flatnonzero((phi[:-1] == 0) | (np.sign(phi[:-1]) * np.sign(phi[1:]) < 0))
    return 0.5 * (xs[change] + xs[change + 1])


def _split_point(a: float, b: float, zeros: np.ndarray) -> float:
    """Where [a, b] is halved: its midpoint, unless phi_bar vanishes within a quarter of the width of it; then a
    quarter of the width from that zero, so that the zero stays inside a piece.

    At a zero of phi_bar eq. (14a) is singular, and beside the smooth p it has solutions p + c |xi - xi0|^r
    (r from the plant's eigenvalues), continuous with their first derivatives: a break there lets the
    collocation choose one of them (on a DC motor, |p| = 3e3 instead of 40)."""
    mid = 0.5 * (a + b)
    near = zeros[np.abs(zeros - mid) < (b - a) / 4]
    if not near.size:
        return mid
    z0 = float(near[np.argmin(np.abs(near - mid))])
    return z0 + (b - a) / 4 if z0 <= mid else z0 - (b - a) / 4


def _solve_pieces(model: Model, F, F_x, phi_num, breaks: np.ndarray, degree: int) -> chebyshev.PiecewiseSeries:
    """The least-squares collocation of :func:`_collocate_pieces` on the pieces between ``breaks``."""
    n, K, d1 = model.n, len(breaks) - 1, degree + 1
    basis = np.eye(d1)
    blocks = []
    for a, b in zip(breaks[:-1], breaks[1:]):
        box = np.array([[a, b]])
        z = chebyshev.nodes(box, 2 * d1)
        V = chebyshev.evaluate(basis, box, z).T                                                  # (N, d + 1)
        E = chebyshev.evaluate(chebyshev.derivative(basis, box, 0), box, z).T * phi_num(*z)[0, 0][:, None]
        blocks.append((box, z, V, E))
    # p and dp/dxi at the ends of each piece: T_j(+-1) and T_j'(+-1) (scaled to xi).
    j = np.arange(d1)
    ends = [(np.ones(d1), (-1.0) ** j, j**2 * 2.0 / (b - a), (-1.0) ** (j + 1) * j**2 * 2.0 / (b - a)) for a, b in zip(breaks[:-1], breaks[1:])]
    # Continuity rows weighted like the PDE rows: a jump of p by e costs about |dp/dxi phi| would.
    w_value = max(float(np.abs(E).max()) for *_, E in blocks)
    w_slope = max(1.0, max(float(np.abs(phi_num(*z)[0, 0]).max()) for _, z, *_ in blocks))

    def unpack(c: np.ndarray) -> np.ndarray:
        return c.reshape(K, n, d1)

    def residual(c: np.ndarray) -> np.ndarray:
        C = unpack(c)
        out = [(C[k] @ E.T - F(*(C[k] @ V.T), *z)[:, 0, :]).ravel() for k, (_, z, V, E) in enumerate(blocks)]
        for k in range(K - 1):
            out.append(w_value * (C[k] @ ends[k][0] - C[k + 1] @ ends[k + 1][1]))
            out.append(w_slope * (C[k] @ ends[k][2] - C[k + 1] @ ends[k + 1][3]))
        return np.concatenate(out)

    def jacobian(c: np.ndarray) -> sps.csc_matrix:
        C = unpack(c)
        parts, row = [], 0
        for k, (_, z, V, E) in enumerate(blocks):
            Fx = F_x(*(C[k] @ V.T), *z)                                                         # (n, n, N)
            Jk = (np.einsum("ij,NK->iNjK", np.eye(n), E) - np.einsum("ijN,NK->iNjK", Fx, V)).reshape(n * len(V), n * d1)
            parts.append((sps.csr_matrix(Jk), row, k * n * d1))
            row += n * len(V)
        eye = np.eye(n)
        for k in range(K - 1):
            for weight, left, right in ((w_value, ends[k][0], ends[k + 1][1]), (w_slope, ends[k][2], ends[k + 1][3])):
                parts.append((sps.csr_matrix(weight * np.kron(eye, left[None, :])), row, k * n * d1))
                parts.append((sps.csr_matrix(-weight * np.kron(eye, right[None, :])), row, (k + 1) * n * d1))
                row += n
        coo = [(m.tocoo(), r0, c0) for m, r0, c0 in parts]
        rows = np.concatenate([m.row + r0 for m, r0, _ in coo])
        cols = np.concatenate([m.col + c0 for m, _, c0 in coo])
        data = np.concatenate([m.data for m, _, _ in coo])
        return sps.csc_matrix((data, (rows, cols)), shape=(row, K * n * d1))

    # From zero, not from the last fit: away from the zeros of phi_bar eq. (14a) is an ODE whose homogeneous
    # solutions (growing like |xi|^r, r up to the plant's fastest rate) barely change the residual, and Gauss-Newton
    # keeps whatever part of them its start holds (|p| reached 1.8e5 on a DC motor from a warm start).
    C = unpack(_gauss_newton(residual, jacobian, np.zeros(K * n * d1)))
    return chebyshev.PiecewiseSeries(tuple(chebyshev.Series.column(C[k], blocks[k][0]) for k in range(K)))


#: Gauss-Newton on the pieces stops after this many steps, or when a step no longer lowers the residual.
GAUSS_NEWTON_STEPS = 30


def _gauss_newton(residual, jacobian, c: np.ndarray) -> np.ndarray:
    """Minimise |residual(c)| by damped Gauss-Newton steps, each the sparse least-squares solution of
    J dc = -r through the augmented system [[I, J], [J^T, -mu I]] (sparse LU: QR-like accuracy, unlike the
    normal equations; mu, 1e-14 of |J|^2, steadies the directions the collocation leaves nearly free)."""
    r = residual(c)
    cost = float(r @ r)
    for _ in range(GAUSS_NEWTON_STEPS):
        J = jacobian(c)
        m, N = J.shape
        mu = 1e-14 * float(abs(J).power(2).sum(axis=0).max())
        A = sps.bmat([[sps.identity(m), J], [J.T, -mu * sps.identity(N)]], format="csc")
        dc = spla.splu(A).solve(np.r_[-r, np.zeros(N)])[m:]
        step = 1.0
        while step >= 1.0 / 64:
            trial = c + step * dc
            r_trial = residual(trial)
            if np.all(np.isfinite(r_trial)) and float(r_trial @ r_trial) < cost:
                break
            step /= 2
        else:
            return c
        improvement = cost - float(r_trial @ r_trial)
        c, r, cost = trial, r_trial, float(r_trial @ r_trial)
        if improvement <= 1e-12 * cost or np.abs(step * dc).max() <= 1e-15 * max(1.0, np.abs(c).max()):
            return c
    return c


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


def _newton(terms, guess: np.ndarray, at: np.ndarray) -> np.ndarray | None:
    """Newton's method for F(x, xi) = 0 at xi = ``at`` from ``guess`` (``terms`` from :func:`field_terms`), or None
    where dF/dx is singular or it does not converge in 50 steps."""
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
        step = lu.solve(-value)
        # Halve the step while it leaves where F is finite (a tank's outflow sqrt(h) at h < 0).
        for _ in range(30):
            if np.all(np.isfinite(terms(x + step, at)[0])):
                break
            step = step / 2
        x = x + step
    value, Fx, _ = terms(x, at)
    return x if np.abs(value).max() <= 1e3 * NEWTON_RTOL * max(1.0, float(abs(Fx).max() * np.abs(x).max())) else None


#: Continuation from a solved point to the next splits the step in up to this many parts where Newton fails.
MAX_SUBSTEPS = 64


def _walk(terms, x: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray | None:
    """The equilibrium at ``end``, continued from the equilibrium x at ``start``: a tangent prediction and Newton,
    in 1, 2, 4, ... ``MAX_SUBSTEPS`` equal steps until every step converges (a steep term such as tanh(200 w)
    bends the branch within one step); None where even the finest fails."""
    parts = 1
    while parts <= MAX_SUBSTEPS:
        here, at = x, start
        for s in range(1, parts + 1):
            nxt = start + (end - start) * s / parts
            _, Fx, Fxi = terms(here, at)
            lu = _factor(Fx)
            here = None if lu is None else _newton(terms, here - lu.solve(Fxi) @ (nxt - at), nxt)
            if here is None:
                break
            at = nxt
        if here is not None:
            return here
        parts *= 2
    return None


def equilibrium_error(model: Model, p, z: np.ndarray) -> np.ndarray:
    """How far a fitted p is from the equilibria it stands for: per state, max over the points z of |x*(xi) - p(xi)|,
    x* the equilibrium Newton's method reaches from p(xi) (inf where it does not).

    The checks downstream that compose p with something exact (a hand-written m) inherit this error.

    Parameters
    ----------
    model : Model
        The spec's systems.
    p : callable
        p for numpy (``p(*xi)`` of shape (n, 1, N)): a series, or a compiled formula.
    z : ndarray (n_hat, N)
        Points of V.

    Returns
    -------
    ndarray (n,)
    """
    terms = field_terms(model)
    P = np.asarray(p(*z), dtype=float)[:, 0, :]
    error = np.zeros(model.n)
    for k in range(z.shape[1]):
        x = _newton(terms, P[:, k], z[:, k])
        if x is None:
            return np.full(model.n, np.inf)
        error = np.maximum(error, np.abs(x - P[:, k]))
    return error


def continuation(model: Model, z: np.ndarray, known: tuple[np.ndarray, np.ndarray] | None = None, terms=None) -> np.ndarray:
    """Equilibria x with F(x, xi) = f_bar(x) + g(x) l(xi) = 0 at the points z, by Newton continuation.

    Without ``known`` it starts at the point nearest the centre of V (from ``abstract.manifold_guess``, else
    the origin, else the centre of ``concrete.state_box``); then it visits each next-nearest point, predicting
    from the nearest solved one along the tangent dp/dxi = -(dF/dx)^-1 dF/dxi and correcting by Newton's method.

    Parameters
    ----------
    model : Model
        The spec's systems (V fixed; ``abstract.manifold_guess`` and ``concrete.state_box`` give starts).
    z : ndarray (n_hat, N)
        Points of V, visited nearest-first.
    known : (ndarray (n_hat, K), ndarray (n, K)), optional
        Points already solved on the branch and their equilibria: the walk starts from them (the same branch).
    terms : callable, optional
        :func:`field_terms` of the model (compiled here when None).

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
    terms = terms or field_terms(model)

    def newton(guess: np.ndarray, at: np.ndarray) -> np.ndarray | None:
        return _newton(terms, guess, at)

    if known is not None:
        # Continue from the solved points: they join the walk as solved, and only z's points are returned.
        z_known, x_known = known
        z, K = np.concatenate([z_known, z], axis=1), z_known.shape[1]
        X = np.concatenate([x_known, np.full((n, N), np.nan)], axis=1)
        solved = np.r_[np.ones(K, dtype=bool), np.zeros(N, dtype=bool)]
    else:
        centre = model.V.mean(axis=1)
        first = int(np.argmin(np.linalg.norm(z - centre[:, None], axis=0)))
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
        K, X = 0, np.full((n, N), np.nan)
        X[:, first] = x0
        solved = np.zeros(N, dtype=bool)
        solved[first] = True
    # The distance of every point to its nearest solved point, and which one that is.
    distance, nearest = np.full(z.shape[1], np.inf), np.zeros(z.shape[1], dtype=int)
    for j in np.flatnonzero(solved):
        to_j = np.linalg.norm(z - z[:, [j]], axis=0)
        closer = to_j < distance
        distance, nearest = np.where(closer, to_j, distance), np.where(closer, j, nearest)
    for _ in range(int((~solved).sum())):
        k = int(np.argmin(np.where(solved, np.inf, distance)))
        j = nearest[k]
        x = _walk(terms, X[:, j], z[:, j], z[:, k])
        if x is None:
            raise DesignError("abstract.domain", f"the equilibrium branch is lost at xi = {np.round(z[:, k], 6).tolist()} (dF/dx singular or Newton diverges): p is not defined on all of V",
                              "a smaller domain V, on which f_bar(x) + g(x) l(xi) = 0 has an isolated solution", check="pde_residual")
        X[:, k], solved[k] = x, True
        to_k = np.linalg.norm(z - z[:, [k]], axis=0)
        closer = to_k < distance
        distance, nearest = np.where(closer, to_k, distance), np.where(closer, k, nearest)
    return X[:, K:]


def solve_numeric_equilibria(model: Model, plant: ManifoldPlant | None = None) -> tuple[chebyshev.Series | chebyshev.PiecewiseSeries, int, float]:
    """p for phi_bar = 0 without a closed form: Newton continuation on Chebyshev nodes, then a Chebyshev fit.

    One abstract state: :func:`ashc_cli.numerics.chebyshev.fit_adaptive` interpolates the equilibria at the
    Chebyshev nodes of V (and of its pieces, where one series of degree <= ``chebyshev.PIECE_MAX_DEGREE`` is not
    enough), keeping on each interval the lowest degree whose relative residual of f(p(xi), l(xi)) = 0 on an
    independent grid of it (:func:`_relative_residual`, against the size of the terms on all of V) is below
    ``pde_tolerance``.  Several abstract states: one tensor series, its degree raised until that residual on
    an independent grid of V is met, or the fit stops improving (:func:`_stalled`), or ``pde_max_degree``.

    Parameters
    ----------
    model, plant : Model, ManifoldPlant or None
        As :func:`solve_collocation`.

    Returns
    -------
    p : Series or PiecewiseSeries
        The fitted series (n x 1), kept numeric.
    degree : int
        The highest degree of a piece.
    residual : float
        The relative residual on an independent grid of V.

    Raises
    ------
    DesignError
        If no fit meets ``pde_tolerance`` (the message says where on V, and what to change).
    """
    tol, max_degree = model.spec.abstract.pde_tolerance, model.spec.abstract.pde_max_degree
    box = model.V
    plant = plant or ManifoldPlant(model)
    terms = field_terms(model)
    check = _check_grid(box)
    phi_check = np.zeros((model.n_hat, check.shape[1]))   # phi_bar = 0 here
    if model.n_hat == 1:
        solved: list[tuple[np.ndarray, np.ndarray]] = []
        scale = []

        def sample(z: np.ndarray) -> np.ndarray:
            X = continuation(model, z, _stacked(solved), terms)
            solved.append((z, X))
            if not scale:   # the size of the terms on all of V, from the first (whole-V) nodes: one number for all rows
                # here (the equilibria come from Newton at each node, so no homogeneous solution can grow in one row
                # and hide another's residual; the stage's own check then judges each row against its terms)
                fbar, gl = plant.sides(X, z)
                scale.append(float(np.max(np.abs(np.stack([fbar, gl])), initial=1.0)))
            return X

        def accept(piece: chebyshev.Series) -> tuple[bool, float]:
            grid = domain_grid(piece.box, PIECE_CHECK_POINTS)
            measure = _relative_residual(model, piece, grid, plant, np.zeros((1, grid.shape[1])), scale[0])
            # Half the tolerance on the piece's grid: the stage judges p on a finer grid of V (at 1e-9 a fit accepted
            # at the tolerance itself missed it there by 20%).
            return measure <= tol / 2, measure

        try:
            p = chebyshev.fit_adaptive(sample, box[0], accept, max_degree=min(max_degree, chebyshev.PIECE_MAX_DEGREE))
        except FitError as exc:
            raise DesignError("abstract.domain", f"the Chebyshev fit of the numeric equilibrium manifold does not reach {tol:g} near xi in "
                              f"[{exc.interval[0]:.6g}, {exc.interval[1]:.6g}] (best relative residual {exc.measure:.3g}; {exc.reason}): p has a kink "
                              "or a near-singularity there", "a domain V that stops short of it, or a larger abstract.pde_tolerance") from None
        return p, p.degree, _relative_residual(model, p, check, plant, phi_check)
    best, history = np.inf, []
    nodes_degree = min(max_degree, FIRST_NODES_DEGREE)
    z = chebyshev.nodes(box, nodes_degree + 1)
    X = continuation(model, z, terms=terms)
    degree = 0
    while degree < max_degree:
        degree += 1
        if degree > nodes_degree:
            # More nodes for a higher degree: the equilibria are found again at twice as many.
            nodes_degree = min(max_degree, 2 * nodes_degree)
            z = chebyshev.nodes(box, nodes_degree + 1)
            X = continuation(model, z, terms=terms)
        series = chebyshev.Series.column(chebyshev.fit(X, box, z, degree), box)
        best = min(best, _relative_residual(model, series, check, plant, phi_check))
        history.append(best)
        if best <= tol:
            return series, degree, best
        if _stalled(history):
            raise DesignError("abstract.domain", f"the Chebyshev fit of the numeric equilibrium manifold stopped improving at degree {degree} "
                              f"(relative residual {best:.3g}, tolerance {tol:g}): p is not smooth enough on V for a polynomial",
                              "a smaller domain V, or a larger abstract.pde_tolerance")
    raise DesignError("abstract.domain", f"the numeric equilibrium manifold is not fitted to {tol:g} by Chebyshev polynomials of degree <= {max_degree}: the best relative residual is {best:.3g}",
                      "a smaller domain V, or a larger abstract.pde_max_degree or pde_tolerance")


#: Points of the independent grid on which one piece of a fit is judged.
PIECE_CHECK_POINTS = 201


def _stacked(solved: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray] | None:
    """The points solved so far and their equilibria, side by side (None before the first)."""
    if not solved:
        return None
    return np.concatenate([z for z, _ in solved], axis=1), np.concatenate([X for _, X in solved], axis=1)
