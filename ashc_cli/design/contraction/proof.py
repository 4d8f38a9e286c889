"""The proof of eq. (28) in ball arithmetic: the vertex argument with an arb Cholesky at every vertex matrix."""

from __future__ import annotations

import numpy as np
from flint import arb

from ashc_cli.numerics import proofs
from ashc_cli.problem.model import Model
from ashc_cli.design.contraction.terms import Polytope


def _ball_lmi(A: list[list], M: np.ndarray, lam: float) -> list[list]:
    """-(A^T M + M A + lambda M) with A a ball matrix (eq. (28) as a matrix that must be >= 0)."""
    n = len(A)
    Mb = proofs.matrix_balls(M)
    MA = [[sum((Mb[i][k] * A[k][j] for k in range(n)), arb(0)) for j in range(n)] for i in range(n)]
    return [[-(MA[j][i] + MA[i][j] + arb(lam) * Mb[i][j]) for j in range(n)] for i in range(n)]


def sym_diagonal_product(d: list, A: dict) -> dict:
    """M A + A^T M for M = diag(d) and a sparse A, both as balls: {(i, j): arb} (both triangles).

    Parameters
    ----------
    d : list of arb
        The diagonal of M.
    A : dict of (int, int) to arb
        The nonzero entries of A.

    Returns
    -------
    dict of (int, int) to arb
    """
    S: dict = {}
    for (i, j), v in A.items():
        S[(i, j)] = S.get((i, j), arb(0)) + d[i] * v
        S[(j, i)] = S.get((j, i), arb(0)) + d[i] * v
    return S


def _prove_sparse(model: Model, polytope: Polytope, M: np.ndarray, lam: float) -> tuple[float, str]:
    """eq. (28) above ``proofs.MAX_PROOF_STATES`` states for a diagonal M: at each vertex, -(A^T M + M A + lambda M)
    from the nonzero entries of A in ball arithmetic, proved positive definite by a float banded Cholesky factor with
    its residual bounded in ball arithmetic (:func:`ashc_cli.numerics.proofs.sparse_psd_lower_bound`; n w^2 work
    for bandwidth w: a ladder's is tridiagonal)."""
    d = [arb(float(v)) for v in np.diag(M)]
    worst = -np.inf
    for A in polytope.sparse_balls():
        S = sym_diagonal_product(d, A)
        for i in range(model.n):
            S[(i, i)] = S.get((i, i), arb(0)) + arb(lam) * d[i]
        worst = max(worst, -proofs.sparse_psd_lower_bound({key: -v for key, v in S.items()}, model.n))
    return float(worst), "banded Cholesky of -(A^T M + M A + lambda M), M diagonal, with its residual bounded in ball arithmetic"


def prove_lmi(model: Model, polytope: Polytope, K: np.ndarray, M: np.ndarray, lam: float) -> tuple[float, str]:
    """A proved upper bound of the largest eigenvalue of A_cl^T M + M A_cl + lambda M over the polytope's hull:
    the LMI of eq. (28) (Theorem 1's eq. (5b) for the quadratic V of eq. (30)), proved.

    The vertex argument: the LMI is affine in A_cl = A + B K, so it holds on the convex hull of the vertex
    matrices once it holds at each of them, and the hull contains every df/dx the certificate covers when the
    polytope is proved (A(u) affine in u at the vertices of U, or ranges enclosed by ball arithmetic).  Each vertex
    matrix is formed in ball arithmetic from the formulas (parameters exact as doubles) and its LMI proved by an
    arb Cholesky.

    Parameters
    ----------
    model : Model
        Supplies g (B = g at x = 0: linear_gain needs g constant) and the parameter values.
    polytope : Polytope
        Its ``balls()`` are the vertex matrices; an unproved polytope is not attempted.
    K : ndarray (m, n)
        The feedback gain (zeros for identity feedback).
    M : ndarray (n, n)
        The certificate.
    lam : float
        The decay rate, in the plant's units.

    Returns
    -------
    margin : float
        The proved bound (inf when no proof was found).
    how : str
        What was proved, or why not.
    """
    if not polytope.proved:
        why = ("A(u) is not affine in u, so its vertices do not bound it" if polytope.kind == "affine in u" else
               "the ranges over state_box x U were only sampled (ball arithmetic could not enclose them)")
        return np.inf, why
    if model.n > proofs.MAX_PROOF_STATES:
        diagonal = not np.any(M - np.diag(np.diag(M)))
        if not diagonal or np.any(K != 0) or polytope.sparse_balls is None:
            why = "M is not diagonal" if not diagonal else ("a gain K" if np.any(K != 0) else f"the {polytope.kind} polytope")
            return np.inf, f"not attempted above {proofs.MAX_PROOF_STATES} states for {why} (the sparse proof takes a diagonal M, K = 0, A(u) at the vertices of U)"
        try:
            return _prove_sparse(model, polytope, M, lam)
        except proofs.interval.UnsupportedExpression as exc:
            return np.inf, f"ball arithmetic cannot enclose A ({exc})"
    try:
        corners = polytope.balls()
        BK = None
        if np.any(K != 0):
            fB = proofs.BoxFunction(model, {"g": model.g}, list(model.x))
            B = fB([arb(0)] * model.n)["g"]
            Kb = proofs.matrix_balls(K)
            BK = [[sum((B[i][k] * Kb[k][j] for k in range(model.m)), arb(0)) for j in range(model.n)] for i in range(model.n)]
        worst = -np.inf
        for A in corners:
            Acl = A if BK is None else [[A[i][j] + BK[i][j] for j in range(model.n)] for i in range(model.n)]
            worst = max(worst, -proofs.psd_lower_bound_balls(_ball_lmi(Acl, M, lam)))
    except proofs.interval.UnsupportedExpression as exc:
        return np.inf, f"ball arithmetic cannot enclose A ({exc})"
    where = {"affine in u": "the vertices of U (A(u) affine in u)",
             "Jacobian entries": "the corners of the enclosed Jacobian entry ranges over state_box x U",
             "Jacobian terms": "the corners of the enclosed ranges of the plant's nonlinear terms over state_box x U"}[polytope.kind]
    return float(worst), f"arb Cholesky of -(A^T M + M A + lambda M) at {where}"
