"""Small linear algebra shared by the stages, the closed loops and the exported code."""

from __future__ import annotations

import numpy as np


def pinv(a: np.ndarray) -> np.ndarray:
    """Moore-Penrose pseudo-inverse of a matrix (r, c) or of a stack (N, r, c): a single column or row in closed
    form a^T / |a|^2 (zero where a is), else numpy's (SVD) pinv; the same arithmetic as the compiled loops'
    :func:`ashc_cli.closedloop.laws.pinv`.

    Parameters
    ----------
    a : ndarray (r, c) or (N, r, c)

    Returns
    -------
    ndarray (c, r) or (N, c, r)
    """
    if a.shape[-2] == 1 or a.shape[-1] == 1:
        if a.ndim == 2:
            v = a.reshape(-1)
            s = float(v @ v)
            return a.T / s if s > 0 else np.zeros_like(a.T)
        norm2 = np.sum(a * a, axis=(-2, -1), keepdims=True)
        return np.where(norm2 > 0, np.swapaxes(a, -2, -1) / np.where(norm2 > 0, norm2, 1.0), 0.0)
    return np.linalg.pinv(a)


def lower_bandwidth(L: np.ndarray) -> int:
    """The lower bandwidth of a lower-triangular L: the largest i - k with L[i, k] != 0 (0 for a diagonal L, n - 1
    at most).  The compiled loops sum L^T r over this band only; entries outside it are exact zeros, so nothing
    is rounded differently.

    Parameters
    ----------
    L : ndarray (n, n)

    Returns
    -------
    int

    Raises
    ------
    ValueError
        L has a nonzero above its diagonal (it is not a Cholesky factor).
    """
    L = np.asarray(L)
    i, k = np.nonzero(L)
    if np.any(k > i):
        raise ValueError("L is not lower triangular")
    return int((i - k).max()) if i.size else 0


def least_squares_q(L: np.ndarray, g: np.ndarray, dpd: np.ndarray) -> np.ndarray:
    """The least-squares q(xi, x) = pinv(L^T g) (L^T dp/dxi delta) of eq. (43) (M = L L^T): the q that makes
    sqrt(M) (dp/dxi delta - g q) smallest; the numpy form of :func:`ashc_cli.closedloop.interface.q_of`, for one
    point or a stack.

    Parameters
    ----------
    L : ndarray (n, n)
        A factor of M = L L^T.
    g, dpd : ndarray (..., n, m), (..., n, m_hat)
        g(x) and dp/dxi delta(xi), with the same leading axes (or broadcastable ones).

    Returns
    -------
    ndarray (..., m, m_hat)
    """
    return pinv(L.T @ g) @ (L.T @ dpd)


def sqrt_M_times(L: np.ndarray, w: np.ndarray) -> np.ndarray:
    """L^T w at N points: w of shape (n, k, N) -> (N, n, k); ||L^T w|| = ||sqrt(M) w|| with M = L L^T.

    One matrix product over all points (BLAS), or a scaling when L is diagonal (a diagonal M, as found for large
    plants): ``einsum`` without BLAS took 8 s for n = 512 on 20001 points.

    Parameters
    ----------
    L : ndarray (n, n)
        A factor of M = L L^T (the stages pass the Cholesky factor).
    w : ndarray (n, k, N)
        k columns at each of N points (e.g. dp/dxi delta on a grid of V).

    Returns
    -------
    ndarray (N, n, k)
    """
    n, k, N = w.shape
    d = np.diag(L)
    if not np.any(L - np.diag(d)):
        return np.moveaxis(d[:, None, None] * w, -1, 0)
    return np.moveaxis((L.T @ w.reshape(n, k * N)).reshape(n, k, N), -1, 0)
