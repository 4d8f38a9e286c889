"""The guaranteed governor of the tracking scenario (docs/guaranteed.md), compiled with numba: the same law as
``governor_law`` of tests/oracle.py (its numpy form), run by the
engine of :mod:`ashc_cli.closedloop.rk` through :func:`governor_rhs`.

v = s v_sp with the largest s in [0, 1] such that |L^T r(s)|^2 / eps <= (lambda - eps) W_max + c (W_max - w),
r(s) through the actual interface (saturation included); then w <= W_max is invariant.  ``prm`` holds
[gain, v_max, lambda, eps, W_max, c, 1 (a slot not read), grid, bisections, backoff...] (the GOVERNOR_* constants of
closedloop/plan.py).
"""

from collections import namedtuple

import math

import numpy as np
from numba import njit, types

from ashc_cli.closedloop.interface import apply, feedback_of, q_of, residual, times
from ashc_cli.closedloop.laws import setpoint, state_derivatives, weighted_norm2
from ashc_cli.closedloop.tracking_core import F1, F2, LOOP, RHS_SIGNATURE, SAMPLES, I1, X_KERNEL, XI_KERNEL, design_at, store_sample

OPTIONS = dict(cache=True, error_model="numpy")
#: The interface at one point, all of u(s) and r(s) but the scale s: L (M = L L^T), l(xi), K e = K (x - p(xi)),
#: q v_sp, dp/dxi delta v_sp, g(x), the input box U, the saturation code sat and L's lower bandwidth bw.
Point = namedtuple("Point", "L l feedback qv dv g U sat bw")


@njit(**OPTIONS)
def interface_at(s, P, u, r, corr):
    """u(s) = SAT(l + K e + s q v_sp) and r(s) = s dp/dxi delta v_sp - g (u(s) - (l + K e)) into u and r; returns
    |L^T r(s)|^2 (the oracle's interface_r at one s).

    Parameters
    ----------
    s : float
    P : Point
        The interface at the point (sat as :func:`~ashc_cli.closedloop.interface.saturate`).
    u, r : 1-D float arrays (m,), (n,)
        Written: u(s) and r(s).
    corr : 1-D float array (m,)
        Work array (left holding K e + s q v_sp).

    Returns
    -------
    float
        |L^T r(s)|^2.
    """
    apply(P.l, P.feedback, P.qv, s, P.U, P.sat, corr, u)
    residual(P.dv, s, P.g, u, P.l, P.feedback, np.zeros(P.dv.size), r)
    return weighted_norm2(P.L, P.bw, r)


@njit(**OPTIONS)
def breakpoints(P, ends):
    """The s in (0, 1) where the interface changes form, sorted and distinct, into ``ends``; returns (count,
    affine) as the oracle's breakpoints.

    Parameters
    ----------
    P : Point
        As :func:`interface_at`.
    ends : 1-D float array
        Written: the breakpoints in ends[:count]; room for 2 m of them (sat = 1; one for sat = 2).

    Returns
    -------
    count : int
    affine : bool
        Whether r(s) is affine between the breakpoints (not for sat = 2 with K e != 0, then count = 0).
    """
    l, feedback, qv, U, sat = P.l, P.feedback, P.qv, P.U, P.sat
    if sat == 0:
        return 0, True
    M = l.size
    if sat == 2:
        for j in range(M):
            if feedback[j] != 0.0:
                return 0, False
    count, s_c = 0, np.inf
    for j in range(M):
        d = qv[j]
        if d == 0.0:
            continue
        lo = (U[j, 0] - l[j] - feedback[j]) / d
        hi = (U[j, 1] - l[j] - feedback[j]) / d
        if sat == 1:
            if 0.0 < lo < 1.0:
                ends[count] = lo
                count += 1
            if 0.0 < hi < 1.0:
                ends[count] = hi
                count += 1
        else:
            s_c = min(s_c, hi if d > 0 else lo)
    if sat == 2 and 0.0 < s_c < 1.0:
        ends[count] = s_c
        count += 1
    ends[:count] = np.sort(ends[:count])
    distinct = 0
    for k in range(count):
        if distinct == 0 or ends[k] != ends[distinct - 1]:
            ends[distinct] = ends[k]
            distinct += 1
    return distinct, True


@njit(**OPTIONS)
def _largest_verified(lo, hi, bound, prm, P, u, r, ut, rt, corr):
    """The largest s in [lo, hi] found admissible by evaluation (hi a few roundings lower, else bisection from
    lo), with u(s) and r(s) in u and r; (False, 0) when not even lo is admissible."""
    for b in range(9, prm.size):
        s_try = max(lo, hi * (1.0 - prm[b]))
        if interface_at(s_try, P, u, r, corr) <= bound:
            return True, s_try
    if not interface_at(lo, P, u, r, corr) <= bound:
        return False, 0.0
    good = lo
    for _ in range(int(prm[8])):
        mid = 0.5 * (good + hi)
        if not (good < mid < hi):
            break
        if interface_at(mid, P, ut, rt, corr) <= bound:
            good = mid
            u[:] = ut
            r[:] = rt
        else:
            hi = mid
    return True, good


@njit(**OPTIONS)
def governor_scale(P, bound, prm, u, r):
    """The oracle's governor_scale: the largest s in [0, 1] with |L^T r(s)|^2 <= bound, u(s) and r(s) into u and r;
    returns (s, admissible).  Closed-form roots on the pieces where r is affine in s, else a grid of prm[7] + 1
    values of s and bisection.

    Parameters
    ----------
    P : Point
        As :func:`interface_at`.
    bound : float
        eps ((lambda - eps) W_max + c (W_max - w)).
    prm : 1-D float array
        The governor's parameters (:func:`governor_rhs`): prm[7] the grid, prm[8] the bisections, prm[9:] the
        back-offs b (s = (1 - b) s_hi is tried first, s_hi the upper end found, then bisection).
    u, r : 1-D float arrays (m,), (n,)
        Written: u(s) and r(s).

    Returns
    -------
    s : float
    admissible : bool
        False when not even s = 0 meets the bound (s is then 0).
    """
    M, N = P.l.size, P.dv.size
    ends = np.empty(2 * M + 1)
    count, affine = breakpoints(P, ends)
    if affine:
        G = count + 2
        grid = np.empty(G)
        grid[0] = 0.0
        grid[1:G - 1] = ends[:count]
        grid[G - 1] = 1.0
    else:
        G = int(prm[7]) + 1
        grid = np.linspace(0.0, 1.0, G)
    Ug, Rg, q2 = np.empty((G, M)), np.empty((G, N)), np.empty(G)
    corr, ut, rt = np.empty(M), np.empty(M), np.empty(N)
    for k in range(G):
        q2[k] = interface_at(grid[k], P, Ug[k], Rg[k], corr)
    if q2[G - 1] <= bound:
        u[:] = Ug[G - 1]
        r[:] = Rg[G - 1]
        return 1.0, True
    if affine:
        R = Rg @ P.L
        for k in range(G - 2, -1, -1):
            s0, s1 = grid[k], grid[k + 1]
            if q2[k + 1] <= bound:
                u[:] = Ug[k + 1]
                r[:] = Rg[k + 1]
                return s1, True
            h = s1 - s0
            D = (R[k + 1] - R[k]) / h
            a, b, c0 = D @ D, R[k] @ D, R[k] @ R[k] - bound
            if a <= 0.0:
                continue                                    # constant on the piece and inadmissible at its end
            disc = b * b - a * c0
            if disc < 0.0:
                continue
            root = np.sqrt(disc)
            upper = -c0 / (b + root) if b > 0 else (root - b) / a         # the larger root, without cancellation
            if b > 0:
                lower = (-b - root) / a
            else:
                lower = c0 / (a * upper) if upper != 0 else (-b - root) / a
            if upper < 0.0 or lower > h:
                continue
            found, s = _largest_verified(s0 + max(lower, 0.0), s0 + min(upper, h), bound, prm, P, u, r, ut, rt, corr)
            if found:
                return s, True
    else:
        last = -1
        for k in range(G):
            if q2[k] <= bound:
                last = k
        if last >= 0:
            found, s = _largest_verified(grid[last], grid[last + 1], bound, prm, P, u, r, ut, rt, corr)
            if found:
                return s, True
    u[:] = Ug[0]
    r[:] = Rg[0]
    return 0.0, q2[0] <= bound


@njit(inline="always", **OPTIONS)
def _governed_at(at, loop, z, xi_ref, v, u, dz, out):
    """:func:`_governed_loop` given the design's values at z (``governor_samples`` reuses them for psi and y)."""
    phi, delta, l, dpd, _, pm, fb, g, _ = at
    dims, prm, L, K, U, q_ls, sat, _ = loop
    NH, N, M, MH = dims[0], dims[1], dims[2], dims[3]
    gain, v_max, lam, eps, w_level, rate = prm[0], prm[1], prm[2], prm[3], prm[4], prm[5]
    xi = z[:NH].copy()
    x = z[NH:NH + N].copy()
    w = z[NH + N]
    v_sp = np.empty(MH)
    setpoint(delta, np.empty((MH, NH)), phi, xi, xi_ref, gain, v_max, v_sp)
    feedback = np.empty(M)
    feedback_of(K, x, pm, feedback)
    q = np.empty((M, MH))
    q_of(L, dims[7], g, dpd, q_ls, q, np.empty((N, M)), np.empty((N, MH)), np.empty((M, N)))
    qv = np.empty(M)
    times(q, v_sp, qv)
    dv = np.empty(N)
    times(dpd, v_sp, dv)
    room = (lam - eps) * w_level + rate * (w_level - w)
    # (|L^T r| + rho_bar)^2 / eps <= room, i.e. |L^T r| <= sqrt(eps room) - rho_bar (rho_bar: a fitted p's residual)
    rho = prm[6]
    reach = math.sqrt(max(eps * room, 0.0)) - rho
    bound = eps * room if rho == 0.0 else (reach * reach if reach > 0.0 else 0.0)
    r = np.empty(N)
    scale, _ = governor_scale(Point(L, l, feedback, qv, dv, g, U, sat, dims[7]), bound, prm, u, r)
    for a in range(MH):
        v[a] = scale * v_sp[a]
    state_derivatives(phi, delta, v, fb, g, u, dz)
    q2 = weighted_norm2(L, dims[7], r)
    q = q2 if rho == 0.0 else (math.sqrt(q2) + rho) ** 2
    dz[NH + N] = -(lam - eps) * w + q / eps
    out[0] = scale
    out[1] = room - q / eps


@njit(types.void(XI_KERNEL, X_KERNEL, LOOP, F1, F1, F1, F1, F1, F1), **OPTIONS)
def _governed_loop(eval_xi, eval_x, loop, z, xi_ref, v, u, dz, out):
    """The oracle's governor_law and the comparison system at z = [xi, x, w]: fills v, u, dz = [dxi, dx, dw] and
    out = [s, slack]."""
    _governed_at(design_at(eval_xi, eval_x, loop.dims, z), loop, z, xi_ref, v, u, dz, out)


@njit(RHS_SIGNATURE, **OPTIONS)
def governor_rhs(t, z, dz, eval_xi, eval_x, eval_link, eval_u, law, loop, ref, v, u):
    """_governed_loop behind the tracking core's RHS signature.

    Parameters
    ----------
    t : float
        Not read.
    z, dz : 1-D float arrays (n_hat + n + 1,)
        [xi, x, w]; written: [dxi, dx, dw].
    eval_xi, eval_x, v, u
        As :func:`~ashc_cli.closedloop.tracking_core.closed_loop` (v = s v_sp).
    eval_link, eval_u, law : LINK_KERNEL, U_KERNEL, LAW
        Not read (v_sp is the set-point law, :func:`~ashc_cli.closedloop.laws.setpoint`).
    loop : Loop
        As closed_loop's, with prm = [gain, v_max, lambda, eps, W_max, c, rho_bar, grid, bisections, backoffs...].
    ref : 1-D float array (n_hat,)
        The reference xi_ref.
    """
    _governed_loop(eval_xi, eval_x, loop, z, ref, v, u, dz, np.empty(2))


@njit(types.void(XI_KERNEL, X_KERNEL, LOOP, F2, I1, F2, SAMPLES, F1, F1), nogil=True, **OPTIONS)
def governor_samples(eval_xi, eval_x, loop, Z, seg_of_row, refs, out, SCALE, SLACK):
    """At every row of Z: v, u, s and slack (_governed_loop), psi = kappa(xi) and y = h(x).

    Parameters
    ----------
    eval_xi, eval_x, Z, seg_of_row, refs, out
        As :func:`~ashc_cli.closedloop.tracking_core.samples`.
    loop : Loop
        As :func:`governor_rhs`.
    SCALE, SLACK : 1-D float arrays (N,)
        Written: s and (lambda - eps) W_max + c (W_max - w) - |L^T r(s)|^2 / eps, row k at Z[k].
    """
    dims = loop.dims
    NH, N, M, MH = dims[0], dims[1], dims[2], dims[3]
    dz = np.empty(NH + N + 1)
    v = np.empty(MH)
    u = np.empty(M)
    sl = np.empty(2)
    for k in range(Z.shape[0]):
        z = Z[k]
        at = design_at(eval_xi, eval_x, dims, z)
        _governed_at(at, loop, z, refs[seg_of_row[k]], v, u, dz, sl)
        store_sample(k, v, u, at.kap, at.h, out)
        SCALE[k] = sl[0]
        SLACK[k] = sl[1]
