"""The laws every compiled closed loop shares, each written once in numba: the interface's saturation and the
pseudo-inverse of the set-point controller and of the least-squares q.  The numpy forms are
:func:`ashc_cli.problem.model.apply_saturation` and :func:`ashc_cli.numerics.linalg.pinv` (the same
arithmetic: the tests hold them to round-off)."""

import numpy as np
from numba import njit

OPTIONS = dict(cache=True, error_model="numpy")


@njit(**OPTIONS)
def saturate(l, correction, U, sat, u):
    """u = SAT(l + correction) into ``u``: the interface of eq. (15) with the saturation of eq. (44).

    Parameters
    ----------
    l, correction : 1-D float arrays of length m
        l(xi) and the correction K (x - p) + q v.
    U : 2-D float array (m, 2)
        The input box.
    sat : int
        0: no saturation; 1: clip each channel to U; 2: l + s correction with the largest s in [0, 1] that keeps
        u in U (one factor for every channel).
    u : 1-D float array of length m
        Filled with the input.
    """
    m = u.size
    if sat == 2:
        smin = np.inf
        for j in range(m):
            c = correction[j]
            if c > 0:
                room = (U[j, 1] - l[j]) / c
            elif c < 0:
                room = (U[j, 0] - l[j]) / c
            else:
                room = np.inf
            if room < smin or room != room:
                smin = room
        sf = min(max(smin, 0.0), 1.0)
        for j in range(m):
            u[j] = l[j] + sf * correction[j]
    elif sat == 1:
        for j in range(m):
            u[j] = min(max(l[j] + correction[j], U[j, 0]), U[j, 1])
    else:
        for j in range(m):
            u[j] = l[j] + correction[j]


@njit(**OPTIONS)
def pinv_into(a, out):
    """The Moore-Penrose pseudo-inverse of the 2-D array ``a`` (r x c) into ``out`` (c x r): a single column or
    row in closed form a^T / |a|^2 (zero where a is), else numpy's (SVD) pinv.  ``out`` may be a view into a
    larger buffer (falsify's flat work arrays)."""
    rows, cols = a.shape
    if rows == 1 or cols == 1:
        s = 0.0
        for i in range(rows):
            for j in range(cols):
                s += a[i, j] * a[i, j]
        for i in range(rows):
            for j in range(cols):
                out[j, i] = a[i, j] / s if s > 0 else 0.0
    else:
        out[:, :] = np.linalg.pinv(a)


@njit(**OPTIONS)
def pinv(a):
    """:func:`pinv_into` in a new array."""
    out = np.empty((a.shape[1], a.shape[0]))
    pinv_into(a, out)
    return out
