"""The abstract controllers' laws and the small linear algebra every compiled closed loop shares, each written once
in numba and inlined into its callers: the pseudo-inverse (of the set-point controller's delta and of the
least-squares q), the set-point controller, the state derivatives and the comparison system's |L^T r|^2.  The
interface itself is :mod:`ashc_cli.closedloop.interface`.  The numpy form of :func:`pinv` is
:func:`ashc_cli.numerics.linalg.pinv` (the same arithmetic: the tests hold them to round-off).

They work on 2-D arrays.  Falsification views its flat per-run buffers as matrices once per run, with views that
carry no reference count (``falsify_core._vec``): views made by slicing cost its 3000 Cuk runs 2.2x, every call
that binds one paying an atomic count (docs/guide.md, "Compiled closed loops").
"""

import numpy as np
from numba import njit, types

OPTIONS = dict(cache=True, error_model="numpy")
#: A vector and a matrix of floats (C order): the cores' signatures, and the annotations of the laws that ``ashc
#: export`` prints (:mod:`ashc_cli.outputs.translate` reads F1, F2, int and float; numba ignores annotations).
F1 = types.float64[::1]
F2 = types.float64[:, ::1]
#: law(t, z, ref, phi, delta, prm, v): an abstract controller's law (:mod:`ashc_cli.closedloop.controllers`) at time
#: t and state z = [xi, x, ...] with the reference xi_ref, phi_bar(xi), delta(xi) and its parameters prm; fills v.
LAW_SIGNATURE = types.void(types.float64, F1, F1, F1, F2, F1, F1)
#: Inlined into the caller by numba (its IR, not LLVM's: a function loaded from numba's cache is machine code that
#: LLVM cannot inline), so the hot loops pay no call.
INLINE = dict(OPTIONS, inline="always")


@njit(**INLINE)
def pinv_into(a: F2, out: F2):
    """out = the Moore-Penrose pseudo-inverse (c x r) of the r x c matrix ``a``: a single column or row in closed form
    a^T / |a|^2 (zero where a is), else numpy's (SVD) pinv.

    Parameters
    ----------
    a : 2-D float array (r, c)
    out : 2-D float array (c, r)
        Written.
    """
    r, c = a.shape
    if r == 1 or c == 1:
        s = 0.0
        for i in range(r):
            for j in range(c):
                s += a[i, j] * a[i, j]
        for i in range(r):
            for j in range(c):
                out[j, i] = a[i, j] / s if s > 0 else 0.0
    else:
        pa = np.linalg.pinv(a)
        for j in range(c):
            for i in range(r):
                out[j, i] = pa[j, i]


@njit(**OPTIONS)
def pinv(a):
    """:func:`pinv_into` in a new array.

    Parameters
    ----------
    a : 2-D float array (r, c)

    Returns
    -------
    2-D float array (c, r)
        The Moore-Penrose pseudo-inverse of ``a``.
    """
    r, c = a.shape
    out = np.empty((c, r))
    pinv_into(a, out)
    return out


@njit(**INLINE)
def setpoint_direction(dplus: F2, phi: F1, xi: F1, xi_ref: F1, gain: float, v: F1):
    """The set-point law before its limit into ``v``: delta^+ (gain (xi_ref - xi) - phi_bar), so that xi' = gain
    (xi_ref - xi) where delta has full row rank.  :func:`setpoint` clips it; falsify's random strategy adds noise
    and scales it to its norm limit.

    Parameters
    ----------
    dplus : 2-D float array (m_hat, n_hat)
        delta(xi)^+ (:func:`pinv_into`).
    phi : 1-D float array (n_hat,)
        phi_bar(xi).
    xi : 1-D float array
        The abstract state in its first n_hat entries (a longer state [xi, x, ...] may be passed).
    xi_ref : 1-D float array (n_hat,)
        The reference.
    gain : float
    v : 1-D float array (m_hat,)
        Filled.
    """
    for a in range(v.size):
        s = 0.0
        for i in range(xi_ref.size):
            s += dplus[a, i] * (gain * (xi_ref[i] - xi[i]) - phi[i])
        v[a] = s


@njit(**INLINE)
def setpoint(delta: F2, dplus: F2, phi: F1, xi: F1, xi_ref: F1, gain: float, v_max: float, v: F1):
    """The set-point controller into ``v``: clip(delta^+ (gain (xi_ref - xi) - phi_bar), -v_max, v_max).

    Parameters
    ----------
    delta : 2-D float array (n_hat, m_hat)
    dplus : 2-D float array (m_hat, n_hat)
        Work: delta^+.
    phi, xi, xi_ref : 1-D float arrays (n_hat,)
        phi_bar(xi), the abstract state and its reference.
    gain, v_max : float
    v : 1-D float array (m_hat,)
        Filled with the abstract input.
    """
    pinv_into(delta, dplus)
    setpoint_direction(dplus, phi, xi, xi_ref, gain, v)
    for a in range(v.size):
        v[a] = min(max(v[a], -v_max), v_max)


@njit(LAW_SIGNATURE, **OPTIONS)
def setpoint_law(t: float, z: F1, ref: F1, phi: F1, delta: F2, prm: F1, v: F1):
    """The set-point controller as a registered law (prm = [gain, v_max]): :func:`setpoint` at xi = z[:n_hat].

    Parameters
    ----------
    t : float
        Not read.
    z : 1-D float array
        [xi, x, ...].
    ref, phi : 1-D float arrays (n_hat,)
        xi_ref and phi_bar(xi).
    delta : 2-D float array (n_hat, m_hat)
    prm : 1-D float array (2,)
        gain, v_max.
    v : 1-D float array (m_hat,)
        Filled.
    """
    dplus = np.empty((v.size, ref.size))
    setpoint(delta, dplus, phi, z, ref, prm[0], prm[1], v)


@njit(LAW_SIGNATURE, **OPTIONS)
def held_law(t: float, z: F1, ref: F1, phi: F1, delta: F2, prm: F1, v: F1):
    """The grid planner's table as the loop runs it (prm = [v_max]): v = the input the table chose at the period's
    sample, held over the period, which the run carries as the segment's reference (its first m_hat entries), within
    |v_a| <= v_max.

    Parameters
    ----------
    t : float
        Not read.
    z : 1-D float array
        Not read.
    ref, phi : 1-D float arrays (n_hat,)
        The held input (first m_hat entries) and phi_bar(xi) (not read).
    delta : 2-D float array (n_hat, m_hat)
        Not read.
    prm : 1-D float array (1,)
        v_max.
    v : 1-D float array (m_hat,)
        Filled.
    """
    for a in range(v.size):
        v[a] = min(max(ref[a], -prm[0]), prm[0])


@njit(LAW_SIGNATURE, **OPTIONS)
def no_law(t: float, z: F1, ref: F1, phi: F1, delta: F2, prm: F1, v: F1):
    """The law of runs that close no loop with one (the m-relation's runs, falsify's batches without a registered
    controller): a law's arguments, never called there.

    Parameters
    ----------
    t, z, ref, phi, delta, prm, v
        A law's arguments, neither read nor written.
    """


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
def weighted_norm2(L, bw, r):
    """|L^T r|^2 = |sqrt(M) r|^2 with M = L L^T (the comparison system's input), over L's band only (as
    :func:`ashc_cli.closedloop.interface.lt_times`: the same sum, O(n bw)).

    Parameters
    ----------
    L : 2-D float array (n, n)
        The Cholesky factor of M (lower triangular).
    bw : int
        L's lower bandwidth (n - 1 for a full L).
    r : 1-D float array (n,)
    """
    q2 = 0.0
    for i in range(r.size):
        s = 0.0
        for k in range(i, min(r.size, i + bw + 1)):
            s += L[k, i] * r[k]
        q2 += s * s
    return q2
