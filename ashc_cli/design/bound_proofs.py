"""Proofs of the bound stage's constants in ball arithmetic: alpha_h and L_h (eq. (6), Assumption 1) and the sups of
||sqrt(M) w|| over a box (dbar with q = 0, eq. (37); the disturbance's ebar), each a number or None / inf where no
proof is found (the stage then keeps its sampled value and says so)."""

from __future__ import annotations

import numpy as np
import sympy as sp

from ashc_cli.numerics import proofs
from ashc_cli.problem.model import Model, sparse_jacobian

__all__ = ["prove_alpha_h", "jacobian_norm_expr", "prove_sup_norm"]


def prove_alpha_h(model: Model, M: np.ndarray, alpha_h: float) -> tuple[float, float, str] | None:
    """alpha_h and L_h proved (eq. (6), Assumption 1), and how, or None where no proof is found.

    Linear h = C x: alpha' = alpha_h (1 - 1e-9) with M - alpha' C^T C >= 0 proved by an arb Cholesky (C
    formed in ball arithmetic); when M is diagonal and every output reads one state (C^T C diagonal), the
    matrix is diagonal and its entries are checked one by one, at any n (the Cholesky is skipped above
    ``proofs.MAX_PROOF_STATES`` states).  Nonlinear h (any number of outputs): L_h = a proved upper bound of
    sup ||dh/dx||_2 over ``concrete.state_box`` (:func:`jacobian_norm_expr`) and alpha' = (proved lower bound of
    lambda_min(M)) / L_h^2.

    Parameters
    ----------
    model, M : Model, ndarray (n, n)
        The spec's systems (h, C, ``concrete.state_box``) and the matrix of W.
    alpha_h : float
        The numpy value, proved less 1e-9 relative for a linear h (not used for a nonlinear h).

    Returns
    -------
    (alpha_h, L_h, how) : (float, float, str) or None
        The proved alpha_h and L_h (linear h: ||C||_2 in floating point) and how; None without a proof.
    """
    diagonal = model.C is not None and not np.any(M - np.diag(np.diag(M))) and np.all(np.count_nonzero(model.C, axis=1) <= 1)
    if model.n > proofs.MAX_PROOF_STATES and not diagonal:
        return None
    jac = sparse_jacobian(model.h, list(model.x))
    try:
        proof = _prove_alpha_h_diagonal(model, M, alpha_h, jac) if diagonal else None
        if proof is None and model.n <= proofs.MAX_PROOF_STATES:
            proof = _prove_alpha_h(model, M, alpha_h, jac)
        return proof
    except proofs.interval.UnsupportedExpression:
        return None


def _prove_alpha_h_diagonal(model: Model, M: np.ndarray, alpha_h: float, jac: sp.Matrix) -> tuple[float, float, str] | None:
    """M - alpha' C^T C >= 0 for a diagonal M and a C with at most one non-zero per row (both exactly, C in ball
    arithmetic): C^T C is then diagonal, so is the matrix, and it is PSD iff each diagonal entry is >= 0."""
    f = proofs.BoxFunction(model, {"C": jac}, list(model.x))
    Cb = f([proofs.arb(0)] * model.n)["C"]
    if any(sum(not c.is_zero() for c in row) > 1 for row in Cb):
        return None
    a = proofs.arb(alpha_h * (1.0 - 1e-9))
    for i in range(model.n):
        column = sum((row[i] ** 2 for row in Cb), proofs.arb(0))
        if not proofs.arb(float(M[i, i])) - a * column >= 0:
            return None
    return alpha_h * (1.0 - 1e-9), float(np.linalg.norm(model.C, 2)), "M diagonal and C^T C diagonal: each diagonal entry of M - alpha_h C^T C >= 0 in ball arithmetic"


def _prove_alpha_h(model: Model, M: np.ndarray, alpha_h: float, jac: sp.Matrix) -> tuple[float, float, str] | None:
    if model.C is not None:
        f = proofs.BoxFunction(model, {"C": jac}, list(model.x))
        a = alpha_h * (1.0 - 1e-9)
        Cb = f([proofs.arb(0)] * model.n)["C"]
        CtC = proofs.quadratic_form_terms(np.eye(len(Cb)), Cb)
        Mb = proofs.matrix_balls(M)
        S = [[Mb[i][j] - proofs.arb(a) * CtC[i][j] for j in range(model.n)] for i in range(model.n)]
        return (a, float(np.linalg.norm(model.C, 2)), "M - alpha_h C^T C >= 0 proved by an arb Cholesky") if proofs.psd_lower_bound_balls(S) >= 0 else None
    if model.state_box is None:
        return None
    norm, how = jacobian_norm_expr(jac)
    lip, ok, _ = proofs.sup_on_box(proofs.compile_claims(model, [norm], list(model.x)), model.state_box)
    m_low = proofs.lambda_min_lower(M)
    if not ok or not m_low > 0:
        return None
    return float(m_low / lip**2), float(lip), f"lambda_min(M) and L_h = sup ||dh/dx||_2 ({how}) bounded by ball arithmetic"


def jacobian_norm_expr(jac: sp.Matrix) -> tuple[sp.Expr, str]:
    """An expression >= ||dh/dx||_2 everywhere, for any number of outputs, and what it is.

    One output: the gradient's Euclidean norm (exact).  Two outputs or two states: sqrt of the largest
    eigenvalue of the 2 x 2 Gram matrix in closed form (exact).  Otherwise the Frobenius norm, an upper bound
    within a factor sqrt(min(p, n)).

    Parameters
    ----------
    jac : sympy Matrix (p, n)
        dh/dx.

    Returns
    -------
    expr, how : sympy Expr, str
        The bound (in x) and which bound it is.
    """
    p, n = jac.shape
    if p == 1:
        return sp.sqrt(sum(e**2 for e in jac)), "the gradient's norm"
    if min(p, n) <= 2:
        w = jac.T if p <= 2 else jac           # two columns: ||w||_2 = ||dh/dx||_2
        return proofs.norm_expr(np.eye(w.shape[0]), w), "closed-form 2 x 2 Gram eigenvalue"
    return sp.sqrt(sum(e**2 for e in jac)), "Frobenius norm, >= the 2-norm"


def prove_sup_norm(model: Model, M: np.ndarray, dp_delta: sp.Matrix, V: np.ndarray, seed: np.ndarray, args: list | None = None) -> float:
    """A proved upper bound of sup over V of ||sqrt(M) dp/dxi delta|| (dbar with q = 0, eq. (37)), inf if none; with
    ``args`` (default the abstract states) the sup of ||sqrt(M) w|| for any matrix w of those variables over the box V
    (the disturbance's ebar: w = e(x) over concrete.state_box).

    Parameters
    ----------
    model : Model
    M : ndarray (n, n)
    dp_delta : sympy Matrix (n, k)
        The matrix w.
    V : ndarray (d, 2)
        The box of ``args``.
    seed : ndarray (d,)
        Where the grid maximum is (branch and bound starts there).
    args : list of Symbol, optional
        The variables of w (default ``model.xi``).

    Returns
    -------
    float

    Branch and bound over V in ball arithmetic, seeded with the grid maximum; ||sqrt(M) w||_2 is the square
    root of the largest eigenvalue of the Gram matrix w^T M w, in closed form for one or two abstract inputs,
    bounded through Gershgorin's discs for more.
    """
    # above MAX_PROOF_STATES only a diagonal M: ||sqrt(M) w||^2 = sum_i M_ii w_i^2 has n terms, not n^2
    if model.n > proofs.MAX_PROOF_STATES and (np.any(M - np.diag(np.diag(M))) or dp_delta.shape[1] > 2):
        return np.inf
    try:
        if dp_delta.shape[1] <= 2:
            fun = proofs.compile_claims(model, [proofs.norm_expr(M, dp_delta)], list(model.xi) if args is None else list(args))
        else:
            f = proofs.BoxFunction(model, {"w": dp_delta}, list(model.xi) if args is None else list(args))
            fun = lambda b: [proofs.norm_sqrt_M(M, f(b)["w"])]   # noqa: E731 (Gershgorin on the Gram matrix)
        upper_bound, ok, _ = proofs.sup_on_box(fun, V, seeds=seed.reshape(1, -1))
    except proofs.interval.UnsupportedExpression:
        return np.inf
    return upper_bound if ok else np.inf
