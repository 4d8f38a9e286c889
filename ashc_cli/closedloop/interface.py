"""The interface of the hierarchy, u = SAT(l(xi) + K (x - p(xi)) + s q(xi, x) v), written once in numba for every
compiled closed loop (tracking, signal, governor, falsification).

Eq. (15) is the interface u = l(xi) + q(xi, x) v with the feedback K (x - p(xi)) of ``feedback: linear_gain``;
eq. (43) the least-squares q = pinv(L^T g(x)) L^T dp/dxi delta(xi) (M = L L^T) or q = 0 as ``interface.q`` says;
eq. (44) the saturation SAT of ``interface.saturate``; ``s`` (1 everywhere but the governor, which scales v by it)
multiplies q v.  The comparison system (C) of the a-posteriori bound reads :func:`residual`,
r = dp/dxi delta s v - (f(x, u) - f(x, u_nominal)).

Each function works on 2-D arrays of the loop's own (falsification's flat work buffers are viewed as matrices once
per run) and is inlined into its caller.  Numpy callers use the same functions (:func:`apply_saturation` over rows,
:func:`interface_u` at a point), and ``ashc export`` prints them as C and Python (:mod:`ashc_cli.outputs.translate`):
the parameters are annotated with their kinds for that printer (``F1`` a vector, ``F2`` a matrix, ``int``,
``float``; numba ignores annotations), and the bodies stay within the subset it reads.
"""

import numpy as np
from numba import njit

from ashc_cli.closedloop.laws import F1, F2, INLINE, pinv_into
from ashc_cli.numerics.linalg import lower_bandwidth


@njit(**INLINE)
def saturate(lb: F1, lo: int, cb: F1, co: int, U: F2, sat: int, u: F1, m: int):
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
def feedback_of(K: F2, x: F1, pm: F1, feedback: F1):
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
def lt_times(L: F2, bw: int, X: F2, out: F2):
    """out = L^T X (the sums over L's rows in order), for L^T g and L^T dp/dxi delta of eq. (43).

    Only the band k = i .. i + bw of column i is summed: L is lower triangular with lower bandwidth ``bw`` (the
    entries left out are exact zeros, so the sums are the full ones bit for bit), O(n bw) instead of O(n^2).

    Parameters
    ----------
    L : 2-D float array (n, n)
        Lower triangular (the Cholesky factor of M).
    bw : int
        L's lower bandwidth (:func:`ashc_cli.numerics.linalg.lower_bandwidth`; n - 1 for a full L).
    X : 2-D float array (n, c)
    out : 2-D float array (n, c)
        Written.
    """
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            s = 0.0
            for k in range(i, min(X.shape[0], i + bw + 1)):
                s += L[k, i] * X[k, j]
            out[i, j] = s


@njit(**INLINE)
def q_of(L: F2, bw: int, g: F2, dpd: F2, q_ls: int, q: F2, ltg: F2, ltd: F2, pg: F2):
    """q(xi, x) of u* = q v (eq. (20)) into ``q``: the least-squares q = pinv(L^T g) (L^T dp/dxi delta) of eq. (43)
    when ``q_ls`` is 1, else 0.

    Parameters
    ----------
    L : 2-D float array (n, n)
        The Cholesky factor of M (M = L L^T).
    bw : int
        L's lower bandwidth (as :func:`lt_times`).
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
    lt_times(L, bw, g, ltg)
    lt_times(L, bw, dpd, ltd)
    pinv_into(ltg, pg)
    for j in range(M):
        for a in range(MH):
            s = 0.0
            for i in range(N):
                s += pg[j, i] * ltd[i, a]
            q[j, a] = s


@njit(**INLINE)
def times(A: F2, v: F1, out: F1):
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
def apply(l: F1, feedback: F1, qv: F1, s: float, U: F2, sat: int, corr: F1, u: F1):
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
def residual(dv: F1, s: float, g: F2, u: F1, l: F1, feedback: F1, shift: F1, r: F1):
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


#: The codes of ``interface.saturate`` that :func:`saturate` reads as ``sat``: no clipping, each channel, one scale.
SATURATE_CODES = {False: 0, True: 1, "scale": 2}


def interface_codes(q_kind: str, saturate_kind) -> tuple[int, int]:
    """The interface's choices as the integer codes the compiled loops read: (1 for the least-squares q of eq. (43),
    0 for q = 0; the saturation's code, :data:`SATURATE_CODES`).

    Parameters
    ----------
    q_kind : str
        ``interface.q``: ``least_squares`` or ``zero``.
    saturate_kind : bool or str
        ``interface.saturate``: True, False or ``scale``.

    Returns
    -------
    (int, int)

    Raises
    ------
    ValueError
        Naming the key whose value no compiled loop knows.
    """
    if q_kind not in ("least_squares", "zero"):
        raise ValueError(f"interface.q = {q_kind!r}")
    if not isinstance(saturate_kind, (bool, np.bool_, str)) or saturate_kind not in SATURATE_CODES:
        raise ValueError(f"interface.saturate = {saturate_kind!r}")
    return int(q_kind == "least_squares"), SATURATE_CODES[saturate_kind]


# --- from numpy: the same law over rows, and at one point ------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _saturate_rows(l, correction, U, sat, u):
    for k in range(l.shape[0]):
        saturate(l[k], 0, correction[k], 0, U, sat, u[k], l.shape[1])


def apply_saturation(l: np.ndarray, correction: np.ndarray, U: np.ndarray, mode) -> np.ndarray:
    """The interface's input u_w = SAT(l + correction) of eqs. (15), (44) for numpy callers: :func:`saturate`
    on each row.

    Parameters
    ----------
    l, correction : ndarray (..., m)
        l(xi) (inside U) and the correction K (x - p) + q v, for one point or a batch (leading axes).
    U : ndarray (m, 2)
        The input box.
    mode : True, False or "scale"
        ``interface.saturate``: clip each channel to U; one factor s in [0, 1] for every channel (the correction
        keeps its direction); no saturation.

    Returns
    -------
    ndarray (..., m)
    """
    l, correction = np.broadcast_arrays(np.asarray(l, dtype=float), np.asarray(correction, dtype=float))
    shape = l.shape
    m = shape[-1]
    rows_l = np.ascontiguousarray(l.reshape(-1, m))
    rows_c = np.ascontiguousarray(correction.reshape(-1, m))
    u = np.empty_like(rows_l)
    _saturate_rows(rows_l, rows_c, np.ascontiguousarray(U, dtype=float), SATURATE_CODES[mode], u)
    return u.reshape(shape)


def interface_u(l: np.ndarray, K: np.ndarray | None, x: np.ndarray, pm: np.ndarray, L: np.ndarray | None, g: np.ndarray,
                dpd: np.ndarray, v: np.ndarray, U: np.ndarray, codes: tuple[int, int]) -> np.ndarray:
    """u = SAT(l + K (x - p) + q v) at one point for numpy callers (``ashc eval DIR u_w``): the functions above in
    the order the compiled loops call them.

    Parameters
    ----------
    l, x, pm, v : ndarray (m,), (n,), (n,), (m_hat,)
        l(xi), the state, p(xi) and the abstract input.
    K : ndarray (m, n) or None
        The feedback gain (None: identity feedback).
    L : ndarray (n, n) or None
        M = L L^T (read when q is least squares).
    g, dpd : ndarray (n, m), (n, m_hat)
        g(x) and dp/dxi delta(xi) (read when q is least squares).
    U : ndarray (m, 2)
    codes : (int, int)
        (q_ls, sat) as the compiled loops read them (:func:`ashc_cli.closedloop.compiled.interface_codes`).

    Returns
    -------
    ndarray (m,)
    """
    q_ls, sat = codes
    f = np.asarray
    l, x, pm, v = (np.ascontiguousarray(f(a, dtype=float)) for a in (l, x, pm, v))
    M, N, MH = l.size, x.size, v.size
    feedback, qv = np.zeros(M), np.zeros(M)
    if K is not None:
        feedback_of(np.ascontiguousarray(K, dtype=float), x, pm, feedback)
    if q_ls == 1:
        q = np.empty((M, MH))
        L = np.ascontiguousarray(L, dtype=float)
        q_of(L, lower_bandwidth(L), np.ascontiguousarray(g, dtype=float), np.ascontiguousarray(dpd, dtype=float), 1, q,
             np.empty((N, M)), np.empty((N, MH)), np.empty((M, N)))
        times(q, v, qv)
    u = np.empty(M)
    apply(l, feedback, qv, 1.0, np.ascontiguousarray(U, dtype=float), sat, np.empty(M), u)
    return u
