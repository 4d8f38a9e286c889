"""The interface of the hierarchy, u = SAT(l(xi) + K (x - p(xi)) + s q(xi, x) v), written once in numba for every
compiled closed loop (tracking, signal, governor, falsification).

Eq. (15) is the interface u = l(xi) + q(xi, x) v with the feedback K (x - p(xi)) of ``feedback: linear_gain``;
eq. (43) the least-squares q = pinv(L^T g(x)) L^T dp/dxi delta(xi) (M = L L^T) or q = 0 as ``interface.q`` says;
eq. (44) the saturation SAT of ``interface.saturate``; ``s`` (1 everywhere but the governor, which scales v by it)
multiplies q v.  The comparison system (C) of the a-posteriori bound reads :func:`residual`,
r = dp/dxi delta s v - (f(x, u) - f(x, u_nominal)).

Each function works on 2-D arrays of the loop's own (falsification's flat work buffers are viewed as matrices once
per run) and is inlined into its caller.  The numpy forms are :func:`ashc_cli.problem.model.apply_saturation` and
:func:`ashc_cli.numerics.linalg.pinv` (the same arithmetic: the tests hold them to round-off), and the printers of
``ashc export`` (:mod:`ashc_cli.outputs.printers`) write the same steps in C and Python.
"""

import numpy as np
from numba import njit

from ashc_cli.closedloop.laws import INLINE, pinv_into


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
def feedback_of(K, x, pm, feedback):
    """K (x - p(xi)) into ``feedback``: the feedback term of the interface (eq. (15) with ``feedback: linear_gain``;
    K = 0 for identity feedback).

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
def q_of(L, g, dpd, q_ls, q, ltg, ltd, pg):
    """q(xi, x) of u* = q v (eq. (20)) into ``q``: the least-squares q = pinv(L^T g) (L^T dp/dxi delta) of eq. (43)
    when ``q_ls`` is 1, else 0.

    Parameters
    ----------
    L : 2-D float array (n, n)
        The Cholesky factor of M (M = L L^T).
    g, dpd : 2-D float arrays (n, m), (n, m_hat)
        g(x) and dp/dxi delta(xi).
    q_ls : int
        1 for the least-squares q, 0 for q = 0.
    q : 2-D float array (m, m_hat)
        Written.
    ltg, ltd, pg : 2-D float arrays (n, m), (n, m_hat), (m, n)
        Work: L^T g, L^T dp/dxi delta and pinv(L^T g).
    """
    N, M, MH = g.shape[0], g.shape[1], dpd.shape[1]
    if q_ls != 1:
        for j in range(M):
            for a in range(MH):
                q[j, a] = 0.0
        return
    for i in range(N):
        for j in range(M):
            s = 0.0
            for k in range(N):
                s += L[k, i] * g[k, j]
            ltg[i, j] = s
        for a in range(MH):
            s = 0.0
            for k in range(N):
                s += L[k, i] * dpd[k, a]
            ltd[i, a] = s
    pinv_into(ltg, pg)
    for j in range(M):
        for a in range(MH):
            s = 0.0
            for i in range(N):
                s += pg[j, i] * ltd[i, a]
            q[j, a] = s


@njit(**INLINE)
def times(A, v, out):
    """out = A v (the rows of A summed in order), for q v and dp/dxi delta v.

    Parameters
    ----------
    A : 2-D float array (r, c)
    v : 1-D float array (c,)
    out : 1-D float array (r,)
        Written.
    """
    for j in range(A.shape[0]):
        s = 0.0
        for a in range(A.shape[1]):
            s += A[j, a] * v[a]
        out[j] = s


@njit(**INLINE)
def apply(l, feedback, qv, s, U, sat, corr, u):
    """u = SAT(l + K e + s q v) into ``u`` (eqs. (15), (44); the example's eq. (42) is l(xi) = xi, K = 0); ``corr``
    is left holding K e + s q v.

    Parameters
    ----------
    l, feedback, qv : 1-D float arrays (m,)
        l(xi), K e = K (x - p(xi)) (:func:`feedback_of`) and q v (:func:`q_of`, :func:`times`).
    s : float
        The scale of v: 1, or the governor's.
    U : 2-D float array (m, 2)
        The input box.
    sat : int
        As :func:`saturate`.
    corr, u : 1-D float arrays (m,)
        Written.
    """
    M = l.size
    for j in range(M):
        corr[j] = feedback[j] + s * qv[j]
    saturate(l, 0, corr, 0, U, sat, u, M)


@njit(**INLINE)
def residual(dv, s, g, u, l, feedback, shift, r):
    """r = s dp/dxi delta v - (shift + g (u - (l + K e))) into ``r``: what the interface leaves of the manifold's
    motion, the input of the comparison system (C) (eq. (37) applied to the saturated u).

    Parameters
    ----------
    dv : 1-D float array (n,)
        dp/dxi delta v.
    s : float
        The scale of v (as :func:`apply`).
    g : 2-D float array (n, m)
        g(x) (zero for a plant written as f(x, u), whose input's effect is in ``shift``).
    u, l, feedback : 1-D float arrays (m,)
        The applied input, l(xi) and K e.
    shift : 1-D float array (n,)
        f(x, u) - f(x, u_nominal) for a plant written as f(x, u), plus the disturbance e(x) w0 of a disturbed run;
        zero otherwise.
    r : 1-D float array (n,)
        Written.
    """
    N, M = g.shape[0], g.shape[1]
    for i in range(N):
        s2 = shift[i]
        for j in range(M):
            s2 += g[i, j] * (u[j] - (l[j] + feedback[j]))
        r[i] = s * dv[i] - s2
