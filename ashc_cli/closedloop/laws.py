"""The laws every compiled closed loop shares, each written once in numba: the interface's saturation and the
pseudo-inverse of the set-point controller and of the least-squares q.  The numpy forms are
:func:`ashc_cli.problem.model.apply_saturation` and :func:`ashc_cli.numerics.linalg.pinv` (the same
arithmetic: the tests hold them to round-off).

Both work on flat buffers at an offset, as falsify's work arrays hold them, and are inlined into their callers.
Measured on falsify's 3000 Cuk runs against the laws written out in each core (31.7 s): views per call (a
slice, a reshape: a reference count on a buffer the threads share) 46.7 s; flat buffers 36.2 s; inlined, with m
passed, 32.9 s (+3.6%).
"""

import numpy as np
from numba import njit

OPTIONS = dict(cache=True, error_model="numpy")
#: Inlined into the caller by numba (its IR, not LLVM's: a function loaded from numba's cache is machine code that
#: LLVM cannot inline), so the hot loops pay no call.
INLINE = dict(OPTIONS, inline="always")


@njit(**INLINE)
def saturate(lb, lo, cb, co, U, sat, u, m):
    """u = SAT(l + correction) into ``u``: the interface of eq. (15) with the saturation of eq. (44).

    Parameters
    ----------
    lb, lo : 1-D float array, int
        l(xi) is ``lb[lo:lo + m]``.
    cb, co : 1-D float array, int
        The correction K (x - p) + q v is ``cb[co:co + m]``.
    U : 2-D float array (m, 2)
        The input box.
    sat : int
        0: no saturation; 1: clip each channel to U; 2: l + s correction with the largest s in [0, 1] that keeps
        u in U (one factor for every channel).
    u : 1-D float array of length m
        Filled with the input.
    m : int
        The number of inputs.
    """
    if sat == 2:
        smin = np.inf
        for j in range(m):
            c = cb[co + j]
            if c > 0:
                room = (U[j, 1] - lb[lo + j]) / c
            elif c < 0:
                room = (U[j, 0] - lb[lo + j]) / c
            else:
                room = np.inf
            if room < smin or room != room:
                smin = room
        sf = min(max(smin, 0.0), 1.0)
        for j in range(m):
            u[j] = lb[lo + j] + sf * cb[co + j]
    elif sat == 1:
        for j in range(m):
            u[j] = min(max(lb[lo + j] + cb[co + j], U[j, 0]), U[j, 1])
    else:
        for j in range(m):
            u[j] = lb[lo + j] + cb[co + j]


@njit(**INLINE)
def pinv_flat(src, so, r, c, dst, do):
    """dst[do:do + c r] = the Moore-Penrose pseudo-inverse (c x r, row-major) of the r x c matrix src[so:so + r c]
    (row-major): a single column or row in closed form a^T / |a|^2 (zero where a is), else numpy's (SVD) pinv.

    Parameters
    ----------
    src, so : 1-D float array, int
        The matrix is ``src[so:so + r c]``, row-major.
    r, c : int
        Its rows and columns.
    dst, do : 1-D float array, int
        The pseudo-inverse (c x r, row-major) is written to ``dst[do:do + c r]`` (may be ``src``, at a range that does
        not overlap).
    """
    if r == 1 or c == 1:
        s = 0.0
        for k in range(r * c):
            s += src[so + k] * src[so + k]
        for i in range(r):
            for j in range(c):
                dst[do + j * r + i] = src[so + i * c + j] / s if s > 0 else 0.0
    else:
        a = np.empty((r, c))
        for i in range(r):
            for j in range(c):
                a[i, j] = src[so + i * c + j]
        pa = np.linalg.pinv(a)
        for j in range(c):
            for i in range(r):
                dst[do + j * r + i] = pa[j, i]


@njit(**OPTIONS)
def pinv(a):
    """:func:`pinv_flat` of a 2-D C-contiguous array, in a new array.

    Parameters
    ----------
    a : 2-D float array (r, c)
        C-contiguous (it is reshaped to a flat view).

    Returns
    -------
    2-D float array (c, r)
        The Moore-Penrose pseudo-inverse of ``a``.
    """
    r, c = a.shape
    out = np.empty((c, r))
    pinv_flat(a.reshape(r * c), 0, r, c, out.reshape(c * r), 0)
    return out


@njit(**INLINE)
def setpoint(delta, phi, xi, xi_ref, gain, v_max, v):
    """The set-point controller into ``v``: clip(delta^+ (gain (xi_ref - xi) - phi_bar), -v_max, v_max).

    Parameters
    ----------
    delta : 2-D float array (n_hat, m_hat)
    phi, xi, xi_ref : 1-D float arrays (n_hat,)
        phi_bar(xi), the abstract state and its reference.
    gain, v_max : float
    v : 1-D float array (m_hat,)
        Filled with the abstract input.
    """
    dplus = pinv(delta)
    for a in range(v.size):
        s = 0.0
        for i in range(xi.size):
            s += dplus[a, i] * (gain * (xi_ref[i] - xi[i]) - phi[i])
        v[a] = min(max(s, -v_max), v_max)


@njit(**INLINE)
def feedback_of(K, x, pm, feedback):
    """K (x - p(xi)) into ``feedback`` (0 for identity feedback).

    Parameters
    ----------
    K : 2-D float array (m, n)
    x, pm : 1-D float arrays (n,)
        The concrete state and p(xi).
    feedback : 1-D float array (m,)
        Filled with K (x - p(xi)).
    """
    for j in range(feedback.size):
        s = 0.0
        for i in range(x.size):
            s += K[j, i] * (x[i] - pm[i])
        feedback[j] = s


@njit(**INLINE)
def state_derivatives(phi, delta, v, fb, g, u, dz):
    """dz[:n_hat] = phi_bar + delta v and dz[n_hat:n_hat + n] = f_bar + g u.

    Parameters
    ----------
    phi, delta, v : float arrays (n_hat,), (n_hat, m_hat), (m_hat,)
    fb, g, u : float arrays (n,), (n, m), (m,)
    dz : 1-D float array
        Filled from its start (a longer dz keeps its tail).
    """
    NH, N = phi.size, fb.size
    for i in range(NH):
        s = 0.0
        for a in range(v.size):
            s += delta[i, a] * v[a]
        dz[i] = phi[i] + s
    for i in range(N):
        s = 0.0
        for j in range(u.size):
            s += g[i, j] * u[j]
        dz[NH + i] = fb[i] + s


@njit(**INLINE)
def weighted_norm2(L, r):
    """|L^T r|^2 = |sqrt(M) r|^2 with M = L L^T (the comparison system's input).

    Parameters
    ----------
    L : 2-D float array (n, n)
        The Cholesky factor of M.
    r : 1-D float array (n,)
    """
    q2 = 0.0
    for i in range(r.size):
        s = 0.0
        for k in range(r.size):
            s += L[k, i] * r[k]
        q2 += s * s
    return q2
