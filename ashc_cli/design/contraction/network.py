"""Networks of dissipative terms: a diagonal M under which every nonlinear term only helps, at any size.

A network's Jacobian is A0 + sum_k theta_k b_k c_k^T with one rank-one term per element (a diode between nodes
i and j: b = -c = e_i - e_j up to the node capacitances).  For a diagonal M with M b_k = -gamma_k c_k (gamma_k >= 0),
the term's part of A^T M + M A is -2 gamma_k theta_k c_k c_k^T: negative semidefinite, so the LMI of eq. (28) is
hardest at the lower end a_k of every theta_k, and

    A_lo^T M + M A_lo + lambda M <= 0,   A_lo = A0 + sum_k a_k A_k

certifies the whole box, whatever the upper ends (an exponential's slope over a state box can be 10^4 times its
lowest).  That M is the network's stored energy (the capacitances); it is found from the terms alone, as the solution
of the linear equations log d_i - log gamma_k = log(-c_ki / b_ki) (one per node of each term), and the largest rate
is then an eigenvalue problem, not an SDP: lambda = lambda_min of D^-1/2 (-(A_lo^T D + D A_lo)) D^-1/2, computed
sparse.  Terms that are not dissipative under that M (a few at most) are enumerated as corners.

The proof (:func:`prove`): each term's T_k = M A_k + A_k^T M is bounded above by Gershgorin in ball arithmetic
(0 up to rounding), so A(theta)^T M + M A(theta) + lambda M <= S_lo + sum_k (hi_k - lo_k) max(0, lambda_max(T_k)) I,
and S_lo is proved negative definite by a float banded Cholesky factor whose residual is bounded in ball arithmetic
(:func:`ashc_cli.numerics.proofs.sparse_psd_lower_bound`; a ladder's matrix is tridiagonal: linear in n).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sps
import scipy.sparse.linalg as spla
from flint import arb

from ashc_cli.numerics import proofs
from ashc_cli.problem.model import Model
from ashc_cli.design.contraction.proof import sym_diagonal_product
from ashc_cli.design.contraction.terms import MAX_VERTEX_TERMS, Polytope, Terms

__all__ = ["Network", "dissipative_storage", "network_polytope", "largest_rate", "prove"]

#: Relative tolerance of the consistency of the log-equations, and of a term's rank one.
RANK_RTOL = 1e-10
#: The rate reported is this much below the largest eigenvalue bound (a strictly negative margin).
BACKOFF = 1e-6


@dataclass
class Network:
    """A diagonal M = diag(d) and the terms it makes dissipative (M b_k = -gamma_k c_k)."""

    d: np.ndarray
    dissipative: list
    gamma: np.ndarray
    others: list


def _rank_one(A: sps.csr_matrix) -> tuple[np.ndarray, np.ndarray] | None:
    """(b, c) with A = b c^T (dense vectors), or None if A is not of rank one."""
    coo = A.tocoo()
    rows, cols = np.unique(coo.row), np.unique(coo.col)
    sub = A[rows][:, cols].toarray()
    u, s, vt = np.linalg.svd(sub)
    if s.size == 0 or s[0] == 0 or (s.size > 1 and s[1] > RANK_RTOL * s[0]):
        return None
    n = A.shape[0]
    b, c = np.zeros(n), np.zeros(n)
    b[rows], c[cols] = s[0] * u[:, 0], vt[0]
    return b, c


def dissipative_storage(terms: Terms, n: int) -> Network | None:
    """The diagonal M (normalised to mean log d = 0) under which the most terms are dissipative, or None if none is.

    A term is a candidate when it is of rank one, b and c have the same support, and -c_i / b_i > 0 there; the
    candidates' log-equations must be consistent (a network's are: one capacitance per node).

    Parameters
    ----------
    terms : Terms
        The Jacobian's decomposition (:func:`~ashc_cli.design.contraction.terms.decompose`).
    n : int
        The number of states.

    Returns
    -------
    Network or None
        d (n,), entries rounded to 12 digits; None when no term is a candidate or their equations are inconsistent.
    """
    rows, cols, vals, rhs, members = [], [], [], [], []
    eq = 0
    for k, A in enumerate(terms.A):
        bc = _rank_one(A)
        if bc is None:
            continue
        b, c = bc
        support = np.flatnonzero(b)
        if not np.array_equal(support, np.flatnonzero(c)):
            continue
        ratio = -c[support] / b[support]
        if np.any(ratio <= 0):
            continue
        for i, r in zip(support, ratio):
            rows += [eq, eq]
            cols += [int(i), n + len(members)]
            vals += [1.0, -1.0]
            rhs.append(np.log(r))
            eq += 1
        members.append((k, b, c))
    if not members:
        return None
    system = sps.csr_matrix((vals, (rows, cols)), shape=(eq, n + len(members)))
    sol = spla.lsqr(system, np.array(rhs), atol=1e-14, btol=1e-14, iter_lim=20 * (n + len(members)))[0]
    if np.abs(system @ sol - np.array(rhs)).max() > 1e-8:
        return None                     # inconsistent: no single diagonal M makes all of them dissipative
    logd = sol[:n]
    touched = np.zeros(n, dtype=bool)
    for _, b, _ in members:
        touched |= b != 0
    logd = logd - logd[touched].mean()
    # Rounded to 12 digits, so that the nodes of a uniform network get exactly equal weights (1.0) and each term's
    # part of A^T M + M A is exactly rank-one semidefinite in ball arithmetic (no rounding slack in the proof).
    d = np.array([float(f"{v:.12g}") for v in np.exp(logd)])
    # gamma_k from M b_k = -gamma_k c_k at one node of the term (the equations hold at all of them)
    gamma = np.array([float(-(d * b)[np.flatnonzero(b)][0] / c[np.flatnonzero(b)][0]) for _, b, c in members])
    diss = [k for k, _, _ in members]
    return Network(d=d, dissipative=diss, gamma=gamma, others=[k for k in range(len(terms)) if k not in diss])


def _corners(terms: Terms, net: Network) -> list[tuple[np.ndarray, str]]:
    """The matrices A_lo (dissipative terms at their lower ends) at every corner of the other terms, with labels."""
    A_lo = sps.csr_matrix(terms.A0) + sum((terms.ranges[k, 0] * terms.A[k] for k in net.dissipative), sps.csr_matrix(terms.A0.shape))
    out = []
    for corner in itertools.product(*[tuple(terms.ranges[k]) for k in net.others]):
        A = A_lo + sum((t * terms.A[k] for t, k in zip(corner, net.others)), sps.csr_matrix(terms.A0.shape))
        label = ", ".join(f"{terms.thetas[k]} = {t:.6g}" for t, k in zip(corner, net.others)) or "every term at its lower end"
        out.append((A.tocsr(), label))
    return out


def largest_rate(A: sps.csr_matrix, d: np.ndarray) -> float:
    """The largest lambda with A^T M + M A + lambda M <= 0 for M = diag(d): lambda_min of D^-1/2 (-(A^T D + D A)) D^-1/2.

    Parameters
    ----------
    A : scipy.sparse.csr_matrix (n, n)
        One matrix of the network polytope.
    d : ndarray (n,)
        The diagonal of M (positive).

    Returns
    -------
    float
        In the units of A; <= 0 when M certifies no positive rate.
    """
    Dh = sps.diags(1.0 / np.sqrt(d))
    D = sps.diags(d)
    N = (Dh @ (-(A.T @ D + D @ A)) @ Dh).tocsc()
    N = 0.5 * (N + N.T)
    n = N.shape[0]
    if n <= 400:
        return float(np.linalg.eigvalsh(N.toarray()).min())
    try:
        return float(spla.eigsh(N, k=1, which="SA", return_eigenvectors=False, tol=1e-10, maxiter=20 * n)[0])
    except spla.ArpackNoConvergence:
        return float(np.linalg.eigvalsh(N.toarray()).min())


def network_polytope(model: Model, terms: Terms) -> tuple[Polytope, Network] | None:
    """The network certificate's matrices (as a polytope over the non-dissipative terms' corners) and its M, or None
    when no diagonal M makes the terms dissipative or too many others remain.

    Parameters
    ----------
    model : Model
        Supplies n.
    terms : Terms
        The Jacobian's decomposition over state_box x U.

    Returns
    -------
    tuple of (Polytope, Network) or None
        The polytope (dense matrices up to 400 states, sparse above; no ``balls``, ``meta["_network"]`` is the
        Network) and the Network; None when :func:`dissipative_storage` finds none or more than MAX_VERTEX_TERMS
        terms are not dissipative.
    """
    net = dissipative_storage(terms, model.n)
    if net is None or len(net.others) > MAX_VERTEX_TERMS:
        return None
    corners = _corners(terms, net)
    meta = {"jacobian_terms": [str(t) for t in terms.thetas], "term_ranges": terms.ranges.tolist(), "ranges_proved": terms.proved,
            "network": f"diagonal M under which {len(net.dissipative)} of {len(terms)} terms are dissipative (M b_k = -gamma_k c_k); "
                       f"those enter at their lower ends, {len(net.others)} others at their corners",
            "range_method": "ball-arithmetic enclosure of each term over box x U by branch and bound (rigorous)" if terms.proved else "sampled"}
    dense = model.n <= 400
    poly = Polytope("Jacobian terms (network)", [A.toarray() if dense else A for A, _ in corners], [label for _, label in corners],
                    terms.proved, None, meta)
    poly.meta["_network"] = net
    return poly, net


def prove(model: Model, terms: Terms, net: Network, lam: float) -> tuple[float, str]:
    """A proved upper bound of the largest eigenvalue of A(theta)^T M + M A(theta) + lambda M over the term box, for
    M = diag(d) (inf when no proof is found); see the module docstring.

    Parameters
    ----------
    model : Model
        Supplies n.
    terms : Terms
        The decomposition the network was found from (its ranges must be proved).
    net : Network
        M = diag(net.d) and which terms are dissipative.
    lam : float
        The decay rate, in the plant's units.

    Returns
    -------
    bound : float
        The proved bound (<= 0: eq. (28) holds on the term box), or inf.
    how : str
        What was proved, or why not.
    """
    if not terms.proved:
        return np.inf, "the term ranges over state_box x U were only sampled"
    n = model.n
    d = [arb(float(v)) for v in net.d]
    try:
        coef = [_ball_dict(model, c) for c in terms.coefficients]
    except proofs.interval.UnsupportedExpression as exc:
        return np.inf, f"ball arithmetic cannot enclose a coefficient ({exc})"
    # slack from the dissipative terms: (hi_k - lo_k) max(0, lambda_max(M A_k + A_k^T M))
    slack = arb(0)
    for k in net.dissipative:
        T = sym_diagonal_product(d, coef[k + 1])
        top = _gershgorin_upper(T)
        width = arb(float(terms.ranges[k, 1])) - arb(float(terms.ranges[k, 0]))
        slack += width * arb(max(0.0, top))
    worst = -np.inf
    for corner in itertools.product(*[tuple(terms.ranges[k]) for k in net.others]):
        A = dict(coef[0])
        for k in net.dissipative:
            _add(A, coef[k + 1], arb(float(terms.ranges[k, 0])))
        for t, k in zip(corner, net.others):
            _add(A, coef[k + 1], arb(float(t)))
        S = sym_diagonal_product(d, A)
        for i in range(n):
            S[(i, i)] = S.get((i, i), arb(0)) + arb(lam) * d[i]
        # lambda_max(S) <= -tau where tau is a proved lower bound of lambda_min(-S)
        neg = {key: -v for key, v in S.items()}
        tau = proofs.sparse_psd_lower_bound(neg, n)
        worst = max(worst, -tau + proofs.upper(slack))
    if not np.isfinite(worst):
        return np.inf, "the banded Cholesky with its ball-arithmetic residual did not prove -S > 0"
    return float(worst), ("banded Cholesky of -(A_lo^T M + M A_lo + lambda M) with its residual bounded in ball arithmetic, plus the "
                          "dissipative terms' Gershgorin bounds times their widths")


def _ball_dict(model: Model, coefficients: dict) -> dict:
    """{(i, j): exact expression} as {(i, j): arb} (parameters exact as doubles)."""
    keys = list(coefficients)
    if not keys:
        return {}
    f = proofs.compile_claims(model, [coefficients[k] for k in keys], [])
    return dict(zip(keys, f([])))


def _add(A: dict, B: dict, t: arb) -> None:
    for key, v in B.items():
        A[key] = A.get(key, arb(0)) + t * v


def _gershgorin_upper(S: dict) -> float:
    """An upper bound of lambda_max of the symmetric ball matrix S (Gershgorin, rounded up)."""
    rows: dict = {}
    for (i, j), v in S.items():
        if i == j:
            rows.setdefault(i, [arb(0), arb(0)])[0] += v
        else:
            rows.setdefault(i, [arb(0), arb(0)])[1] += abs(v)
    return max((proofs.upper(diag + off) for diag, off in rows.values()), default=0.0)
