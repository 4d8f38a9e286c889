"""Structured candidates for M of eq. (28), tried before any SDP on a large plant.

An LC ladder, a chain of masses or a converter has a metric that its structure gives away: the stored energy,
diagonal, makes every lossless coupling skew-symmetric (L_i i_i' = ... - v_j, C_j v_j' = i_i - ...: the pair
A_ij, A_ji cancels in A^T M + M A once d_i A_ij = -d_j A_ji).  Such an M is found from the vertex matrices by one
sparse least-squares solve on the logarithms, and checked exactly: the largest rate a given M certifies at every
vertex is a generalised eigenvalue (:func:`~ashc_cli.design.contraction.vertex.largest_decay_rate_for`), not an SDP.
A dense SDP at n = 256 takes about a minute and at n = 512 does not fit; these candidates take milliseconds.

Candidates, in order (:func:`candidates`): the diagonal that balances the skew couplings of the vertex mean, the
identity, and (for a full M) the Lyapunov solution of the vertex mean.  The first that certifies the requested
rate at every vertex is used (:func:`structured_M`); when none does, the SDP decides, as before.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sps
import scipy.sparse.linalg as spla

from ashc_cli.design.contraction.lyapunov import distinct, lyapunov_M
from ashc_cli.design.contraction.vertex import CERTIFIED_BACKOFF, largest_decay_rate_for

__all__ = ["BALANCE", "IDENTITY", "LYAPUNOV_MEAN", "balancing_diagonal", "candidates", "structured_M"]

BALANCE = "diagonal balancing the skew couplings of the vertex mean (d_i A_ij = -d_j A_ji)"
IDENTITY = "identity"
LYAPUNOV_MEAN = "Lyapunov solution of the vertex mean"
#: A coupling pair counts as skew when both entries are nonzero beyond this fraction of the largest entry.
COUPLING_RTOL = 1e-12
#: The dense Lyapunov candidate is formed up to this many states (an n x n dense solve; 0.3 s at n = 512).
LYAPUNOV_MAX_STATES = 1024


def _dense(A) -> np.ndarray:
    return np.asarray(A.toarray() if hasattr(A, "toarray") else A, dtype=float)


def balancing_diagonal(A: np.ndarray) -> np.ndarray | None:
    """d > 0 with d_i A_ij = -d_j A_ji for every skew pair of A (A_ij A_ji < 0), in the least-squares sense on
    log d (exact when the pairs are consistent, as a network's are), scaled to sum(d) = n; None without any pair.

    Parameters
    ----------
    A : ndarray (n, n) or sparse
        The matrix whose couplings are balanced (the vertex mean).

    Returns
    -------
    ndarray (n,) or None
    """
    S = sps.coo_matrix(A)
    n = S.shape[0]
    big = float(np.abs(S.data).max()) if S.nnz else 0.0
    keep = (S.row < S.col) & (np.abs(S.data) > COUPLING_RTOL * big)
    rows, cols, upper = S.row[keep], S.col[keep], S.data[keep]
    csr = sps.csr_matrix(A)
    lower = np.asarray(csr[cols, rows]).ravel()
    skew = upper * lower < 0
    if not skew.any():
        return None
    i, j = rows[skew], cols[skew]
    # log d_j - log d_i = log(-A_ij / A_ji): one row per pair of an incidence matrix
    k = np.arange(i.size)
    E = sps.csr_matrix((np.r_[np.ones(i.size), -np.ones(i.size)], (np.r_[k, k], np.r_[j, i])), shape=(i.size, n))
    rhs = np.log(-upper[skew] / lower[skew])
    log_d = spla.lsqr(E, rhs, atol=1e-14, btol=1e-14, iter_lim=20 * n)[0]     # minimum norm: a free component keeps d = 1
    d = np.exp(log_d - log_d.mean())
    if not np.all(np.isfinite(d)) or d.min() <= 0:
        return None
    return n * d / d.sum()


def candidates(A_list: list, lam: float, structure: str) -> list[tuple[str, np.ndarray]]:
    """The structured M to try, in order, for the vertex matrices (see the module docstring).

    Parameters
    ----------
    A_list : list of ndarray (n, n) or sparse
        The vertex matrices (scaled as the caller checks them).
    lam : float
        The requested rate, in the units of A_list (for the Lyapunov candidate).
    structure : str
        ``stabilisability.structure``: a ``diagonal`` choice gets the diagonal candidates only.

    Returns
    -------
    list of (name, M)
    """
    n = A_list[0].shape[0]
    mean = sum(_dense(A) for A in A_list) / len(A_list)
    out: list[tuple[str, np.ndarray]] = []
    d = balancing_diagonal(mean)
    if d is not None:
        out.append((BALANCE, np.diag(d)))
    out.append((IDENTITY, np.eye(n)))
    if structure != "diagonal" and n <= LYAPUNOV_MAX_STATES:
        M = lyapunov_M(mean, lam)
        if M is not None:
            out.append((LYAPUNOV_MEAN, M))
    return out


def structured_M(A_list: list, lam: float, structure: str) -> tuple[np.ndarray, str, list] | None:
    """The first candidate that certifies ``lam`` at every vertex (its exact rate strictly above ``lam``), or None.

    Parameters
    ----------
    A_list : list of ndarray (n, n)
        The vertex matrices, scaled.
    lam : float
        The requested rate, in their units.
    structure : str
        ``stabilisability.structure``.

    Returns
    -------
    (M, name, tried) or None
        tried: (name, largest rate it certifies) for each candidate checked, in order.
    """
    dense = [_dense(A) for A in distinct([_dense(A) for A in A_list])]
    tried = []
    for name, M in candidates(dense, lam, structure):
        rate = largest_decay_rate_for(dense, M)
        tried.append((name, rate))
        if rate * (1 - CERTIFIED_BACKOFF) > lam:
            return M, name, tried
    return None
