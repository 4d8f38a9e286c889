"""``method: given``: a metric M (and a gain K) the engineer gives, or computes from the linearisation, proved over the
state box by a test whose cost grows with the number of Jacobian entries, not with 2^terms.

M is a matrix of the spec or ``lyapunov``: the solution of (A_cl + s/2 I)^T M + M (A_cl + s/2 I) = -I for the closed
loop A_cl = A0 + B K linearised at ``stabilisability.linearise_at`` (default: the centres of the state box and of U),
with the shift s halfway between the rate asked for and the linearisation's supremum -2 max Re eig(A_cl) (half the
supremum for ``maximise``).  K is a matrix or ``lqr`` (the Riccati gain of the linearisation, Q = I, R = I).

**The norm-bound test** (:class:`NormBound`): every entry of df/dx(x, u) over ``state_box`` x U is enclosed in ball
arithmetic (:func:`~ashc_cli.design.contraction.terms.enclose_term`), so df/dx = A0 + Delta with |Delta_ij| <= C_ij.
With M = T^T T (T = L^T, L the Cholesky factor), T^-T (Delta^T M + M Delta) T^-1 is the symmetric part of twice
T Delta T^-1, whose norm is at most that of the nonnegative matrix |T| C |T^-1| (entrywise absolute values); so

    Delta^T M + M Delta <= 2 beta M,   beta = || |T| C |T^-1| ||_2,

and eq. (28) holds on the whole box once  A_cl^T M + M A_cl + (lambda + 2 beta) M <= 0.  The largest such lambda is a
generalised eigenvalue less 2 beta.  The proof (:func:`prove`) forms T in ball arithmetic, bounds beta by the
Collatz-Wielandt quotient max_i (Y v)_i / v_i of Y = X^T X at a positive vector v (X the upper bounds of |T| C |T^-1|),
and proves the inequality by an arb Cholesky.  Cost: one enclosure per nonzero entry and a few n x n matrix products,
whatever the number of distinct nonlinear terms.  For ``M: lyapunov`` the shift is chosen among a few fractions of
the supremum as the one whose M the test proves the largest rate for.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from flint import arb

from ashc_cli.design.contraction.lyapunov import lyapunov_M
from ashc_cli.design.contraction.terms import Polytope, enclose_entry
from ashc_cli.errors import DesignError, SpecError
from ashc_cli.numerics import proofs
from ashc_cli.problem.model import Model, nonzero_entries

__all__ = ["NormBound", "linearisation_point", "linearise", "input_matrix", "gain", "metric", "norm_bound", "beta",
           "largest_rate", "prove", "norm_polytope"]

#: The rate reported is this much below the largest the test allows (a strictly negative proved margin).
BACKOFF = 1e-6


@dataclass
class NormBound:
    """df/dx = A0 + Delta over state_box x U with |Delta| <= C entrywise (C rounded up; ``proved`` when every
    entry was enclosed in ball arithmetic)."""

    A0: np.ndarray
    C: np.ndarray
    proved: bool
    entries: int


def linearisation_point(model: Model, st) -> tuple[np.ndarray, np.ndarray]:
    """(x0, u0): ``stabilisability.linearise_at``, else the centres of ``concrete.state_box`` (0 without one) and of U.

    Parameters
    ----------
    model : Model
    st : Stabilisability
        The spec's section.

    Returns
    -------
    (ndarray (n,), ndarray (m,))
    """
    if st.linearise_at is not None:
        return np.array(st.linearise_at.x, dtype=float), np.array(st.linearise_at.u, dtype=float)
    x0 = model.state_box.mean(axis=1) if model.state_box is not None else np.zeros(model.n)
    return x0, model.U.mean(axis=1)


def linearise(model: Model, J, x0: np.ndarray, u0: np.ndarray) -> np.ndarray:
    """df/dx at (x0, u0), as floats.

    Parameters
    ----------
    model : Model
    J : sympy Matrix (n, n)
        df/dx(x, u).
    x0, u0 : ndarray
        The point.

    Returns
    -------
    ndarray (n, n)
    """
    A0 = np.asarray(model.numeric(J, list(model.x) + list(model.u))(*x0, *u0), dtype=float).reshape(model.n, model.n)
    if not np.all(np.isfinite(A0)):
        raise DesignError("stabilisability.linearise_at", f"df/dx is not finite at x = {x0.tolist()}, u = {u0.tolist()}",
                          "a point where f is differentiable")
    return A0


def input_matrix(model: Model) -> np.ndarray:
    """The constant g as floats (``feedback: linear_gain`` needs it).

    Parameters
    ----------
    model : Model

    Returns
    -------
    ndarray (n, m)
    """
    if not model.affine or any(e.free_symbols & set(model.x) for e in model.g):
        raise DesignError("concrete.g", "feedback linear_gain needs a constant input matrix g (the closed loop's g(z) K would vary with the state)",
                          "g independent of x, or feedback identity", check="lmi_margin")
    return np.array(model.substitute(model.g), dtype=float)


def gain(st, A0: np.ndarray, B: np.ndarray) -> np.ndarray:
    """K of ``stabilisability.K``: the given matrix, or ``lqr`` (K = -B^T P, P the stabilising solution of
    A0^T P + P A0 - P B B^T P + I = 0).

    Parameters
    ----------
    st : Stabilisability
    A0, B : ndarray
        The linearisation and the input matrix.

    Returns
    -------
    ndarray (m, n)
    """
    if st.K != "lqr":
        return np.array(st.K, dtype=float)
    try:
        P = sla.solve_continuous_are(A0, B, np.eye(A0.shape[0]), np.eye(B.shape[1]))
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise DesignError("stabilisability.K", f"lqr: the Riccati equation of the linearisation has no stabilising solution ({exc})",
                          "a stabilisable linearisation (stabilisability.linearise_at), or K given as a matrix") from None
    return -B.T @ P


#: ``M: lyapunov`` on the norm-bound route: the shifts tried, as fractions of the way from the rate asked for (0 for
#: ``maximise``) to the linearisation's supremum; the M the test proves the largest rate for is kept.
SHIFTS = (0.25, 0.5, 0.75, 0.9)


def metric(st, A_cl: np.ndarray, nb: NormBound | None = None, BK: np.ndarray | None = None) -> tuple[np.ndarray, float | None]:
    """M of ``stabilisability.M`` and the shift s of ``lyapunov`` (None for a given matrix).

    Parameters
    ----------
    st : Stabilisability
    A_cl : ndarray (n, n)
        The closed loop's linearisation A0 + B K.
    nb : NormBound, optional
        On the norm-bound route: ``lyapunov`` tries :data:`SHIFTS` and the identity, and keeps the M with the
        largest proved rate (else the shift halfway).
    BK : ndarray (n, n), optional
        B K, for the rates of the norm-bound route (zeros when absent).

    Returns
    -------
    (ndarray (n, n), float or None)
        M and the shift of its Lyapunov equation (0.0 for the identity, None for a given M).
    """
    if st.M != "lyapunov":
        M = np.array(st.M, dtype=float)
        if not np.allclose(M, M.T, rtol=0, atol=1e-12 * max(1.0, np.abs(M).max())):
            raise SpecError("stabilisability.M", "is not symmetric", "a symmetric positive definite matrix")
        if np.linalg.eigvalsh(M).min() <= 0:
            raise DesignError("stabilisability.M", f"is not positive definite (smallest eigenvalue {np.linalg.eigvalsh(M).min():.4g})", "M > 0",
                              check="M_positive")
        return M, None
    sup = -2.0 * float(np.linalg.eigvals(A_cl).real.max())
    if not sup > 0:
        raise DesignError("stabilisability.M", f"lyapunov: the linearised closed loop is not stable (-2 max Re eig = {sup:.4g})",
                          "a stabilising K (K: lqr with feedback: linear_gain), or another stabilisability.linearise_at")
    rate = 0.0 if st.decay_rate == "maximise" else float(st.decay_rate)
    if not rate < sup:
        raise DesignError("stabilisability.decay_rate", f"{rate:g} is not below the linearisation's supremum {sup:.6g} (-2 max Re eig of A0 + B K)",
                          f"decay_rate below {sup:.6g}, or maximise")
    found = []
    for fraction in (SHIFTS if nb is not None else (0.5,)):
        shift = rate + fraction * (sup - rate)
        M = lyapunov_M(A_cl, shift)
        if M is not None:
            found.append((largest_rate(nb, M, BK if BK is not None else np.zeros_like(A_cl)) if nb is not None else 0.0, shift, M))
    if nb is not None:   # the identity too: a plant contracting in the Euclidean norm is proved best by it
        found.append((largest_rate(nb, np.eye(len(A_cl)), BK if BK is not None else np.zeros_like(A_cl)), 0.0, np.eye(len(A_cl))))
    if not found:
        raise DesignError("stabilisability.M", f"lyapunov: no positive definite solution at the shifts tried up to {sup:.6g}", "a given M")
    _, shift, M = max(found, key=lambda f: f[0])
    return M, shift


def norm_bound(model: Model, J, A0: np.ndarray) -> NormBound:
    """The middle A_mid of the enclosure of each entry of df/dx over ``concrete.state_box`` x U and C >= |df/dx - A_mid|
    entrywise (one ball-arithmetic enclosure per nonzero entry).

    Parameters
    ----------
    model : Model
        Supplies the state box, U and the parameter values.
    J : sympy Matrix (n, n)
        df/dx(x, u).
    A0 : ndarray (n, n)
        The linearisation (its shape; the test is centred on the enclosures' middles, where C is smallest).

    Returns
    -------
    NormBound
        ``A0`` is the middle of the enclosures.
    """
    if model.state_box is None:
        raise DesignError("concrete.state_box", "missing: the norm-bound test encloses df/dx over a box of states", "one [lo, hi] pair per state")
    args = list(model.x) + list(model.u)
    box = np.r_[model.state_box, model.U]
    C, centre = np.zeros_like(A0), np.zeros_like(A0)
    entries = nonzero_entries(J)
    for (i, j), e in entries.items():
        enclosed = enclose_entry(model, e, args, box)
        if enclosed is None:
            raise DesignError("concrete", f"df{i + 1}/d{model.x[j]} = {e} cannot be enclosed over state_box x U in ball arithmetic",
                              "df/dx of functions ball arithmetic encloses (polynomials, exp, log, sin, cos, tanh, sqrt, ...)", check="lmi_margin")
        lo, hi = enclosed
        # the centre of the test is the middle of the enclosure (the smallest C), not the linearisation
        centre[i, j] = 0.5 * (lo + hi)
        C[i, j] = np.nextafter(max(hi - centre[i, j], centre[i, j] - lo, 0.0), np.inf)
    return NormBound(centre, C, True, len(entries))     # every entry enclosed, or refused above


def beta(M: np.ndarray, C: np.ndarray) -> float:
    """|| |T| C |T^-1| ||_2 with M = T^T T: Delta^T M + M Delta <= 2 beta M for every |Delta| <= C (module docstring).

    Parameters
    ----------
    M, C : ndarray (n, n)

    Returns
    -------
    float
    """
    T = np.linalg.cholesky(M).T
    return float(np.linalg.norm(np.abs(T) @ C @ np.abs(np.linalg.inv(T)), 2))


def largest_rate(nb: NormBound, M: np.ndarray, BK: np.ndarray) -> float:
    """The largest lambda with A_cl^T M + M A_cl + (lambda + 2 beta) M <= 0, A_cl = nb.A0 + B K (a generalised
    eigenvalue; <= 0: none).

    Parameters
    ----------
    nb : NormBound
    M : ndarray (n, n)
    BK : ndarray (n, n)
        B K (zeros for identity feedback).

    Returns
    -------
    float
    """
    A_cl = nb.A0 + BK
    S = -(A_cl.T @ M + M @ A_cl)
    return float(sla.eigh(0.5 * (S + S.T), M, eigvals_only=True).min()) - 2.0 * beta(M, nb.C)


def prove(model: Model, nb: NormBound, M: np.ndarray, K: np.ndarray, lam: float) -> tuple[float, str]:
    """A proved upper bound of the largest eigenvalue of A_cl^T M + M A_cl + lambda M + gamma I (<= 0: eq. (28) holds
    for every df/dx the enclosures hold), in ball arithmetic, or inf.

    Parameters
    ----------
    model : Model
        Supplies g (constant with a gain: formed in ball arithmetic, its parameters exact doubles).
    nb : NormBound
    M : ndarray (n, n)
    K : ndarray (m, n)
        The gain (zeros for identity feedback): B K is formed in ball arithmetic, not rounded.
    lam : float

    Returns
    -------
    (float, str)
    """
    if not nb.proved:
        return np.inf, "an entry of df/dx was not enclosed in ball arithmetic"
    n = M.shape[0]
    Mb = proofs.matrix_balls(M)
    b = _beta_upper(Mb, nb.C)
    if not np.isfinite(b):
        return np.inf, "the ball Cholesky factor of M or its inverse could not be formed"
    A = [[arb(float(nb.A0[i, j])) for j in range(n)] for i in range(n)]
    if np.any(K != 0):      # B K in ball arithmetic (as the vertex proof forms it), not the rounded float product
        B = proofs.BoxFunction(model, {"g": model.g}, list(model.x))([arb(0)] * n)["g"]
        Kb = proofs.matrix_balls(K)
        A = [[A[i][j] + sum((B[i][k] * Kb[k][j] for k in range(K.shape[0])), arb(0)) for j in range(n)] for i in range(n)]
    MA = [[sum((Mb[i][k] * A[k][j] for k in range(n)), arb(0)) for j in range(n)] for i in range(n)]
    S = [[-(MA[j][i] + MA[i][j] + (arb(lam) + 2 * arb(b)) * Mb[i][j]) for j in range(n)] for i in range(n)]
    bound = -proofs.psd_lower_bound_balls(S)
    return float(bound), (f"norm-bound test: |df/dx - A0| <= C over state_box x U ({nb.entries} entries enclosed in ball arithmetic), "
                          f"beta = || |T| C |T^-1| ||_2 <= {b:.4g} (M = T^T T in ball arithmetic, Collatz-Wielandt), "
                          "A_cl^T M + M A_cl + (lambda + 2 beta) M <= 0 by an arb Cholesky")


def _beta_upper(Mb: list, C: np.ndarray) -> float:
    """A proved upper bound of || |T| C |T^-1| ||_2 (M = T^T T, T upper triangular): T by a Cholesky in ball arithmetic
    (its balls hold the exact factor), T^-1 by arb_mat's inverse, X the upper ends of the entrywise product, and
    ||X||_2^2 <= max_i (X^T X v)_i / v_i for any v > 0 (Collatz-Wielandt), v from a float power iteration."""
    from flint import arb_mat

    n = len(Mb)
    L = [[arb(0)] * n for _ in range(n)]
    for j in range(n):
        d = Mb[j][j] - sum((L[j][k] ** 2 for k in range(j)), arb(0))
        if not d > 0:
            return np.inf
        L[j][j] = d.sqrt()
        for i in range(j + 1, n):
            L[i][j] = (Mb[i][j] - sum((L[i][k] * L[j][k] for k in range(j)), arb(0))) / L[j][j]
    T = arb_mat([[L[j][i] for j in range(n)] for i in range(n)])
    try:
        Ti = T.inv()
    except ZeroDivisionError:
        return np.inf
    absT = np.array([[proofs.upper(abs(T[i, j])) for j in range(n)] for i in range(n)])
    absTi = np.array([[proofs.upper(abs(Ti[i, j])) for j in range(n)] for i in range(n)])
    if not (np.all(np.isfinite(absT)) and np.all(np.isfinite(absTi))):
        return np.inf
    Xb = arb_mat(absT.tolist()) * arb_mat(C.tolist()) * arb_mat(absTi.tolist())
    X = np.array([[proofs.upper(Xb[i, j]) for j in range(n)] for i in range(n)])
    Y = X.T @ X
    v = np.ones(n)
    for _ in range(200):
        w = Y @ v + 1e-300
        v = w / w.max()
    v = np.maximum(v, 1e-12)
    Yb = arb_mat(X.T.tolist()) * arb_mat(X.tolist()) * arb_mat([[float(x)] for x in v])
    rho = max(proofs.upper(Yb[i, 0] / arb(float(v[i]))) for i in range(n))
    if not np.isfinite(rho):
        return np.inf
    return float(np.nextafter(np.sqrt(rho), np.inf)) if rho > 0 else 0.0


def norm_polytope(nb: NormBound, why: str) -> Polytope:
    """The centre as a one-vertex 'polytope' carrying the norm bound (the stage's re-checks sample df/dx over the box).

    Parameters
    ----------
    nb : NormBound
    why : str
        Why this route was taken (recorded).

    Returns
    -------
    Polytope
    """
    meta = {"_normbound": nb, "norm_bound": f"|df/dx - A0| <= C entrywise over state_box x U, {nb.entries} entries enclosed; {why}",
            "norm_bound_C_max": float(nb.C.max())}
    return Polytope("norm bound", [nb.A0], ["the linearisation point"], nb.proved, None, meta)
