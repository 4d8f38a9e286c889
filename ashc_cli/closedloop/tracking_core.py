"""The tracking and m-relation loops of ``simulate``, compiled with numba and integrated by the engine of
:mod:`ashc_cli.closedloop.rk`.

Design-independent: the per-design kernels reach these functions as numba first-class functions
(:mod:`ashc_cli.closedloop.compiled` prints and caches them); numba caches this module's machine code
(``cache=True``)."""
from collections import namedtuple

import math

import numpy as np
from numba import njit, types

from ashc_cli.closedloop.interface import apply, feedback_of, q_of, residual, times
from ashc_cli.closedloop.laws import F1, F2, LAW_SIGNATURE, no_law, state_derivatives, weighted_norm2  # noqa: F401  (no_law: the m-relation runs pass core.no_law)
from ashc_cli.closedloop.rk import DOP853_EXPONENT, DP54_EXPONENT, solve

I1 = types.int64[::1]
#: eval_xi(xi, phi_bar, delta, l, dp/dxi delta, kappa, p) and eval_x([x, u], f_bar, g, h), filling their arrays.
XI_KERNEL = types.FunctionType(types.void(F1, F1, F2, F1, F2, F1, F1))
X_KERNEL = types.FunctionType(types.void(F1, F1, F2, F1))
#: eval_link([x, u], b, c, m) and eval_u([t], u): the m-relation's link and the spec's input signal.
LINK_KERNEL = types.FunctionType(types.void(F1, F1, F2, F1))
U_KERNEL = types.FunctionType(types.void(F1, F1))
#: An abstract controller's law (:data:`~ashc_cli.closedloop.laws.LAW_SIGNATURE`, :mod:`~ashc_cli.closedloop.controllers`).
LAW = types.FunctionType(LAW_SIGNATURE)
OPTIONS = dict(cache=True, error_model='numpy')

#: The closed loop's constants: dims = [n_hat, n, m, m_hat, p, affine, disturbed, bw] (affine: 1 for x' = f_bar + g u,
#: 0 for f(x, u); disturbed: 1 when the run applies its constant disturbance e(x) w0; bw: L's lower bandwidth, which
#: the sums over L keep to, :func:`ashc_cli.numerics.linalg.lower_bandwidth`); prm = [gain, v_max, lambda,
#: eps] (then, for the governor, governor.py's entries); L, K, U: the Cholesky factor of M (M = L L^T), the feedback
#: gain and the input box; q_ls = 1 for the least-squares q of eq. (43), 0 for q = 0; sat as
#: :func:`~ashc_cli.closedloop.interface.saturate`; lprm: the abstract controller's parameters (its law's prm).
Loop = namedtuple("Loop", "dims prm L K U q_ls sat lprm")
LOOP = types.NamedTuple((I1, F1, F2, F2, F2, types.int64, types.int64, F1), Loop)
#: The design's terms at z = [xi, x, ...] (:func:`design_at`): phi_bar, delta, l, dp/dxi delta, kappa, p of xi and
#: f_bar, g, h of x.
At = namedtuple("At", "phi delta l dpd kap pm fb g h")
#: A run's samples as the loops fill them: v, u, psi and y, one row per sample.
Samples = namedtuple("Samples", "V Uo PSI Y")
SAMPLES = types.NamedUniTuple(F2, 4, Samples)
#: One integration (:func:`integrate`): the start z0, the segments' spans t_bounds (segments, 2), the sample times
#: t_eval and each segment's rows offsets, the segments' references refs (segments, n_hat), the event's edges
#: ([lo, lo_margin, hi, hi_margin] or empty), rtol and atol.
Segments = namedtuple("Segments", "z0 t_bounds t_eval offsets refs edges rtol atol")
SEGMENTS = types.NamedTuple((F1, F2, F1, I1, F2, F1, types.float64, types.float64), Segments)
#: A tableau of :mod:`~ashc_cli.closedloop.rk` (A, B, C, E, E3, D).
TABLEAU = types.Tuple((F2, F1, F1, F1, F1, F2))


@njit(inline="always", **OPTIONS)
def _joined(x, u, extra):
    """[x, u] in a fresh array with ``extra`` entries after them (the kernels' state)."""
    N, M = x.size, u.size
    xu = np.empty(N + M + extra)
    for i in range(N):
        xu[i] = x[i]
    for j in range(M):
        xu[N + j] = u[j]
    return xu


@njit(inline="always", **OPTIONS)
def x_terms_at(eval_x, N, M, x, u, s, fb, g, h):
    """eval_x at (x, u) with the run's constant disturbance on (s = 1) or off (s = 0): the kernel's state is [x, u, s]
    and its fb is f_bar(x) + s e(x) w0 (f(x, u) + s e(x) w0 for a plant written as f(x, u), with g = 0).

    Parameters
    ----------
    eval_x : X_KERNEL
    N, M : int
        n and m.
    x, u : 1-D float arrays (n,), (m,)
    s : float
        1.0 (disturbance on) or 0.0.
    fb, g, h : float arrays (n,), (n, m), (p,)
        Written.
    """
    xu = _joined(x, u, 1)
    xu[N + M] = s
    eval_x(xu, fb, g, h)


@njit(inline="always", **OPTIONS)
def x_terms(eval_x, dims, x, u, fb, g, h):
    """eval_x at (x, u), filling fb, g and h: the kernel reads the state [x, u, s] (f_bar(x), g(x), h(x) of an
    input-affine plant do not read u; a plant written as f(x, u) gets fb = f(x, u) and g = 0; s = dims[6] switches
    the tracking run's constant disturbance e(x) w0 on).

    Parameters
    ----------
    eval_x : X_KERNEL
    dims : 1-D int64 array
        As :func:`design_at`.
    x, u : 1-D float arrays (n,), (m,)
    fb, g, h : float arrays (n,), (n, m), (p,)
        Written.
    """
    x_terms_at(eval_x, dims[1], dims[2], x, u, 1.0 if dims.size > 6 and dims[6] == 1 else 0.0, fb, g, h)


@njit(inline="always", **OPTIONS)
def link_terms(eval_link, dims, x, u, b, c, mx):
    """eval_link at (x, u), filling b, c and m(x): the link kernel reads the state [x, u] (b(x, u) of a plant
    written as f(x, u), with c = 0).

    Parameters
    ----------
    eval_link : LINK_KERNEL
    dims : 1-D int64 array
        As :func:`design_at`.
    x, u : 1-D float arrays (n,), (m,)
    b, c, mx : float arrays (m_hat,), (m_hat, m), (n_hat,)
        Written.
    """
    eval_link(_joined(x, u, 0), b, c, mx)


@njit(**OPTIONS)
def design_at(eval_xi, eval_x, dims, z):
    """The kernels at z = [xi, x, ...], in fresh arrays: (phi_bar, delta, l, dp/dxi delta, kappa, p) of xi and
    (f_bar, g, h) of x (for a plant written as f(x, u): fb = f(x, l(xi)), the loops evaluate it again at the input
    they apply).

    Parameters
    ----------
    eval_xi, eval_x : XI_KERNEL, X_KERNEL
        The design's kernels (:mod:`ashc_cli.closedloop.compiled`).
    dims : 1-D int64 array
        :class:`Loop`'s dims (entries after the seventh are not read).
    z : 1-D float array
        xi = z[:n_hat], x = z[n_hat:n_hat + n] (the rest is not read).

    Returns
    -------
    At
        phi_bar(xi), delta(xi), l(xi), dp/dxi delta, kappa(xi), p(xi) (shapes (n_hat,), (n_hat, m_hat), (m,),
        (n, m_hat), (p,), (n,)) and f_bar(x), g(x), h(x) ((n,), (n, m), (p,)).
    """
    NH, N, M, MH, P = dims[0], dims[1], dims[2], dims[3], dims[4]
    phi = np.empty(NH)
    delta = np.empty((NH, MH))
    l = np.empty(M)
    dpd = np.empty((N, MH))
    kap = np.empty(P)
    pm = np.empty(N)
    eval_xi(z[:NH].copy(), phi, delta, l, dpd, kap, pm)
    fb = np.empty(N)
    g = np.empty((N, M))
    h = np.empty(P)
    x_terms(eval_x, dims, z[NH:NH + N], l, fb, g, h)
    return At(phi, delta, l, dpd, kap, pm, fb, g, h)


@njit(inline="always", **OPTIONS)
def store_sample(k, v, u, kap, h, out):
    """Row k of the sampled outputs: v, u, psi = kappa(xi) and y = h(x), element by element.

    Parameters
    ----------
    k : int
    v, u, kap, h : 1-D float arrays
        The values at the sample.
    out : Samples
        The tables (one row per sample).
    """
    V, Uo, PSI, Y = out
    for a in range(v.size):
        V[k, a] = v[a]
    for j in range(u.size):
        Uo[k, j] = u[j]
    for i in range(kap.size):
        PSI[k, i] = kap[i]
        Y[k, i] = h[i]


@njit(inline="always", **OPTIONS)
def _loop_at(eval_x, at, loop, z, v, u, dz):
    """:func:`closed_loop` given the design's values at z and the abstract input v (``samples`` reuses them for
    psi and y)."""
    phi, delta, l, dpd, _, pm, fb, g, _ = at
    dims, prm, L, K, U, q_ls, sat, _ = loop
    NH, N, M, MH = dims[0], dims[1], dims[2], dims[3]
    lam, eps = prm[2], prm[3]
    x = z[NH:NH + N].copy()
    # u = SAT(l + K (x - p) + q v), eqs. (15), (43), (44)
    feedback = np.empty(M)
    feedback_of(K, x, pm, feedback)
    q = np.empty((M, MH))
    q_of(L, dims[7], g, dpd, q_ls, q, np.empty((N, M)), np.empty((N, MH)), np.empty((M, N)))
    qv = np.empty(M)
    times(q, v, qv)
    apply(l, feedback, qv, 1.0, U, sat, np.empty(M), u)
    # dxi = phi_bar + delta v; dx = f_bar + g u; r = dp/dxi delta v - g (u - u_nominal)
    # (a plant written as f(x, u): dx = f(x, u), r = dp/dxi delta v - (f(x, u) - f(x, u_nominal)))
    shift = np.zeros(N)
    if dims[5] == 0:
        nominal = np.empty(M)
        for j in range(M):
            nominal[j] = l[j] + feedback[j]
        g0 = np.empty((N, M))
        h0 = np.empty(dims[4])
        fb_nominal = np.empty(N)
        x_terms(eval_x, dims, x, nominal, fb_nominal, g0, h0)
        fb = np.empty(N)
        x_terms(eval_x, dims, x, u, fb, g0, h0)
        for i in range(N):
            shift[i] = fb[i] - fb_nominal[i]
    if dims.size > 6 and dims[6] == 1:
        # the disturbance e(x) w0 enters dx and, with the opposite sign, r: r = ... - e w0
        g1 = np.empty((N, M))
        h1 = np.empty(dims[4])
        fb_on = np.empty(N)
        fb_off = np.empty(N)
        x_terms_at(eval_x, N, M, x, u, 1.0, fb_on, g1, h1)
        x_terms_at(eval_x, N, M, x, u, 0.0, fb_off, g1, h1)
        for i in range(N):
            shift[i] += fb_on[i] - fb_off[i]
    state_derivatives(phi, delta, v, fb, g, u, dz)
    dv = np.empty(N)
    times(dpd, v, dv)
    r = np.empty(N)
    residual(dv, 1.0, g, u, l, feedback, shift, r)
    # w' = -(lambda - eps) w + (|L^T r| + rho_bar)^2 / eps (rho_bar: a fitted p's PDE residual, docs/guaranteed.md)
    rho = prm[4] if prm.size > 4 else 0.0
    q2 = weighted_norm2(L, dims[7], r)
    dz[NH + N] = -(lam - eps) * z[NH + N] + (q2 if rho == 0.0 else (math.sqrt(q2) + rho) ** 2) / eps


@njit(types.void(XI_KERNEL, X_KERNEL, LAW, LOOP, types.float64, F1, F1, F1, F1, F1), **OPTIONS)
def closed_loop(eval_xi, eval_x, law, loop, t, z, xi_ref, v, u, dz):
    """The abstract controller's law, the interface and the comparison system at (t, z = [xi, x, w]) (with the
    set-point law: tests/oracle.py ``tracking_law``); fills v, u and dz = [dxi, dx, dw].

    Parameters
    ----------
    eval_xi, eval_x
        As :func:`design_at`.
    law : LAW
        The abstract controller (:mod:`~ashc_cli.closedloop.controllers`), called with loop.lprm.
    loop : Loop
        The closed loop's constants.
    t : float
    z : 1-D float array (n_hat + n + 1,)
        [xi, x, w].
    xi_ref : 1-D float array (n_hat,)
        The controller's reference.
    v, u, dz : 1-D float arrays (m_hat,), (m,), (n_hat + n + 1,)
        Written: the abstract input, the concrete input and [dxi, dx, dw].
    """
    at = design_at(eval_xi, eval_x, loop.dims, z)
    law(t, z, xi_ref, at.phi, at.delta, loop.lprm, v)
    _loop_at(eval_x, at, loop, z, v, u, dz)


@njit(types.void(XI_KERNEL, X_KERNEL, LINK_KERNEL, U_KERNEL, I1, types.float64, F1, F1, F1, F1), **OPTIONS)
def link_loop(eval_xi, eval_x, eval_link, eval_u, dims, t, z, v, u, dz):
    """simulate.run_m_relation's right-hand side at (t, z = [xi, x]); fills u = u(t), v and dz = [dxi, dx].

    v = b(x) + c(x) u (eq. (22)); dxi = phi_bar(xi) + delta(xi) v; dx = f_bar(x) + g(x) u.

    Parameters
    ----------
    eval_xi, eval_x, dims
        As :func:`design_at`.
    eval_link, eval_u : LINK_KERNEL, U_KERNEL
        The m-relation's kernels: b(x), c(x), m(x) and u(t).
    t : float
    z : 1-D float array (n_hat + n,)
        [xi, x].
    v, u, dz : 1-D float arrays (m_hat,), (m,), (n_hat + n,)
        Written.
    """
    NH, N, M, MH = dims[0], dims[1], dims[2], dims[3]
    tt = np.empty(1)
    tt[0] = t
    eval_u(tt, u)
    x = z[NH:NH + N].copy()
    phi, delta, l, dpd, kap, pm, fb, g, h = design_at(eval_xi, eval_x, dims, z)
    if dims[5] == 0:
        x_terms(eval_x, dims, x, u, fb, g, h)       # f(x, u) at the applied input
    b = np.empty(MH)
    c = np.empty((MH, M))
    mx = np.empty(NH)
    link_terms(eval_link, dims, x, u, b, c, mx)
    for a in range(MH):
        s = 0.0
        for j in range(M):
            s += c[a, j] * u[j]
        v[a] = b[a] + s
    for i in range(NH):
        s = 0.0
        for a in range(MH):
            s += delta[i, a] * v[a]
        dz[i] = phi[i] + s
    for i in range(N):
        s = 0.0
        for j in range(M):
            s += g[i, j] * u[j]
        dz[NH + i] = fb[i] + s


@njit(types.void(F1, F1, F2, F1), **OPTIONS)
def no_link(x, b, c, m):
    """The eval_link of the tracking runs (``integrate`` takes one; it is never called there).

    Parameters
    ----------
    x, b, c, m : float arrays, 1-D, 1-D, 2-D, 1-D
        eval_link's arguments, neither read nor written.
    """


@njit(types.void(F1, F1), **OPTIONS)
def no_signal(t, u):
    """The eval_u of the tracking runs (never called there).

    Parameters
    ----------
    t, u : 1-D float arrays
        eval_u's arguments, neither read nor written.
    """


#: rhs(t, z, dz, eval_xi, eval_x, eval_link, eval_u, law, loop, ref, v, u): the right-hand side of either loop
#: behind one signature, so that one integrate runs both (an indirect call: integrate is compiled once and small,
#: instead of inlining both loops at each of its calls).
RHS_SIGNATURE = types.void(types.float64, F1, F1, XI_KERNEL, X_KERNEL, LINK_KERNEL, U_KERNEL, LAW, LOOP, F1, F1, F1)
RHS = types.FunctionType(RHS_SIGNATURE)


@njit(RHS_SIGNATURE, **OPTIONS)
def tracking_rhs(t, z, dz, eval_xi, eval_x, eval_link, eval_u, law, loop, ref, v, u):
    """closed_loop behind the RHS signature (eval_link and eval_u unused).

    Parameters
    ----------
    t : float
    z, dz : 1-D float arrays (n_hat + n + 1,)
        [xi, x, w]; written: [dxi, dx, dw].
    eval_xi, eval_x, law, loop, v, u
        As :func:`closed_loop`.
    eval_link, eval_u : LINK_KERNEL, U_KERNEL
    ref : 1-D float array (n_hat,)
        closed_loop's xi_ref.
    """
    closed_loop(eval_xi, eval_x, law, loop, t, z, ref, v, u, dz)


@njit(RHS_SIGNATURE, **OPTIONS)
def link_rhs(t, z, dz, eval_xi, eval_x, eval_link, eval_u, law, loop, ref, v, u):
    """link_loop behind the RHS signature (law, ref and all of loop but its dims unused).

    Parameters
    ----------
    t : float
    z, dz : 1-D float arrays (n_hat + n,)
        [xi, x]; written: [dxi, dx].
    eval_xi, eval_x, eval_link, eval_u, v, u
        As :func:`link_loop`.
    law : LAW
        Not called (:func:`no_law`).
    loop : Loop
        Its dims are link_loop's.
    ref : 1-D float array
        Not read.
    """
    link_loop(eval_xi, eval_x, eval_link, eval_u, loop.dims, t, z, v, u, dz)


@njit(**OPTIONS)
def _leaves(eval_x, dims, z, edges):
    """simulate's leaves_certified_set: min(y - lo - lo_margin, hi - hi_margin - y), y = h(x), edges = [lo,
    lo_margin, hi, hi_margin]; Python's min of the two (the first unless the second is smaller)."""
    NH, N, M, P = dims[0], dims[1], dims[2], dims[4]
    x = z[NH:NH + N].copy()
    fb = np.empty(N)
    g = np.empty((N, M))
    h = np.empty(P)
    x_terms(eval_x, dims, x, np.zeros(M), fb, g, h)      # h(x) only
    below = h[0] - edges[0] - edges[1]
    above = edges[2] - edges[3] - h[0]
    return above if above < below else below


@njit(inline="always", **OPTIONS)
def _call(t, y, D, row, ctx):
    """The engine's call(t, y, D, row, ctx) for either loop: ctx = (rhs, eval_xi, eval_x, eval_link, eval_u, law,
    loop, ref, v, u)."""
    rhs, eval_xi, eval_x, eval_link, eval_u, law, loop, ref, v, u = ctx
    rhs(t, y, D[row], eval_xi, eval_x, eval_link, eval_u, law, loop, ref, v, u)


@njit(inline="always", **OPTIONS)
def _leaves_event(z, ectx):
    """The engine's event(z, ectx): :func:`_leaves` with ectx = (eval_x, dims, edges)."""
    return _leaves(ectx[0], ectx[1], z, ectx[2])


@njit(types.UniTuple(types.int64, 5)(RHS, XI_KERNEL, X_KERNEL, LINK_KERNEL, U_KERNEL, LAW, LOOP, SEGMENTS, TABLEAU, F2, F1), nogil=True, **OPTIONS)
def integrate(rhs, eval_xi, eval_x, eval_link, eval_u, law, loop, run, tab, out, hit):
    """The engine's :func:`~ashc_cli.closedloop.rk.solve` with the tableau ``tab``, segment after segment.

    ``rhs`` is tracking_rhs or governor_rhs (the loop's constants and, for tracking_rhs, the law used; eval_link and
    eval_u not: pass no_link and no_signal) or link_rhs (only loop.dims used; pass no_law).  Segment k runs from
    run.t_bounds[k, 0] to run.t_bounds[k, 1] with the reference run.refs[k] and writes its samples
    run.t_eval[run.offsets[k]:run.offsets[k + 1]] to the same rows of out; the next segment starts from its last
    sample.  With run.edges = [lo, lo_margin, hi, hi_margin] (empty: no event) the run stops where h(x) leaves
    [lo + lo_margin, hi - hi_margin] (simulate's leaves_certified_set, direction -1, terminal): hit = [t, z]
    there.  Returns (status, rows written, segment, nfev, accepted steps), status as rk.solve's.

    Parameters
    ----------
    rhs : RHS
        tracking_rhs, governor_rhs (:mod:`ashc_cli.closedloop.governor`) or link_rhs.
    eval_xi, eval_x, eval_link, eval_u
        As :func:`link_loop`.
    law : LAW
        The abstract controller of tracking_rhs.
    loop : Loop
        The closed loop's constants (for governor_rhs prm goes on with [W_max, c, 1.0 (not read), grid,
        bisections, backoffs...]).
    run : Segments
        The start ([xi0, x0, W0], or [xi0, x0] for link_rhs), the segments, their sample times and references, the
        event's edges and the tolerances (atol for every component).
    tab : tuple
        The tableau (:data:`~ashc_cli.closedloop.rk.DOP853`, or DP54 with E3 empty).
    out : 2-D float array (N, d)
        Written: row i the state at run.t_eval[i].
    hit : 1-D float array (1 + d,)
        Written at the event.

    Returns
    -------
    status, written, segment, nfev, steps : int
        0 (every sample written), 1 (the event), -1 (the step fell below the spacing of floating-point numbers, or a
        backward span) or -2 (a sample is not finite); the rows of out written are those before ``written``;
        the segment it stopped in (the number of segments when it did not); evaluations and accepted steps.
    """
    dims, t_bounds, offsets = loop.dims, run.t_bounds, run.offsets
    method = (tab, DOP853_EXPONENT if tab[4].size > 0 else DP54_EXPONENT)
    y = run.z0.copy()
    tol = (run.rtol, np.full(y.size, run.atol))
    v = np.empty(dims[3])
    u = np.empty(dims[2])
    ectx = (eval_x, dims, run.edges)
    nfev = 0
    steps = 0
    written = 0
    for seg in range(t_bounds.shape[0]):
        ctx = (rhs, eval_xi, eval_x, eval_link, eval_u, law, loop, run.refs[seg], v, u)
        status, written, n_f, n_s = solve(_call, ctx, _leaves_event, ectx, run.edges.size > 0, method, (t_bounds[seg, 0], t_bounds[seg, 1]),
                                          y, (run.t_eval, offsets[seg], offsets[seg + 1]), tol, out, hit)
        nfev += n_f
        steps += n_s
        if status != 0:
            return status, written, seg, nfev, steps
        for i in range(y.size):
            y[i] = out[offsets[seg + 1] - 1, i]
    return 0, written, t_bounds.shape[0], nfev, steps


@njit(types.void(XI_KERNEL, X_KERNEL, LAW, LOOP, F1, F2, I1, F2, SAMPLES), nogil=True, **OPTIONS)
def samples(eval_xi, eval_x, law, loop, t, Z, seg_of_row, refs, out):
    """At every row of Z (time t[k]): v (the law) and u (the interface), psi = kappa(xi) and y = h(x).

    Parameters
    ----------
    eval_xi, eval_x, law, loop
        As :func:`closed_loop`.
    t : 1-D float array (N,)
        The sample times.
    Z : 2-D float array (N, n_hat + n + 1)
        The samples [xi, x, w] (integrate's out).
    seg_of_row : 1-D int64 array (N,)
        Each row's segment, its row of refs.
    refs : 2-D float array (segments, n_hat)
        Each segment's xi_ref.
    out : Samples
        Written: v, u, psi and y (shapes (N, m_hat), (N, m), (N, p), (N, p)), row k at Z[k].
    """
    dims = loop.dims
    NH, N, M, MH = dims[0], dims[1], dims[2], dims[3]
    dz = np.empty(NH + N + 1)
    v = np.empty(MH)
    u = np.empty(M)
    for k in range(Z.shape[0]):
        z = Z[k]
        at = design_at(eval_xi, eval_x, dims, z)
        law(t[k], z, refs[seg_of_row[k]], at.phi, at.delta, loop.lprm, v)
        _loop_at(eval_x, at, loop, z, v, u, dz)
        store_sample(k, v, u, at.kap, at.h, out)


@njit(types.void(XI_KERNEL, X_KERNEL, LINK_KERNEL, U_KERNEL, I1, F1, F2, SAMPLES, F2), nogil=True, **OPTIONS)
def link_samples(eval_xi, eval_x, eval_link, eval_u, dims, t, Z, out, MX):
    """At every row of Z = [xi, x] (time t[k]): v and u (link_loop), psi = kappa(xi), y = h(x) and m(x).

    Parameters
    ----------
    eval_xi, eval_x, eval_link, eval_u, dims
        As :func:`link_loop`.
    t : 1-D float array (N,)
        The sample times.
    Z : 2-D float array (N, n_hat + n)
        The samples (integrate's out).
    out : Samples
        Written: v, u, psi and y, row k at Z[k].
    MX : 2-D float array (N, n_hat)
        Written: m(x), row k at Z[k].
    """
    NH, N, M, MH = dims[0], dims[1], dims[2], dims[3]
    dz = np.empty(NH + N)
    v = np.empty(MH)
    u = np.empty(M)
    b = np.empty(MH)
    c = np.empty((MH, M))
    mx = np.empty(NH)
    for k in range(Z.shape[0]):
        z = Z[k]
        link_loop(eval_xi, eval_x, eval_link, eval_u, dims, t[k], z, v, u, dz)
        at = design_at(eval_xi, eval_x, dims, z)
        x = z[NH:NH + N].copy()
        link_terms(eval_link, dims, x, u, b, c, mx)
        store_sample(k, v, u, at.kap, at.h, out)
        for i in range(NH):
            MX[k, i] = mx[i]
