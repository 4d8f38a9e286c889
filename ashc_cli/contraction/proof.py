"""The proof of eq. (28) in ball arithmetic: the vertex argument with an arb Cholesky at every vertex matrix."""

from __future__ import annotations

import itertools

import numpy as np
import sympy as sp
from flint import arb

from .. import proofs
from ..model import Model


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

