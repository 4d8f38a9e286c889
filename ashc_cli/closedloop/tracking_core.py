"""The tracking and m-relation loops of ``simulate`` and scipy's DOP853, compiled with numba.

Design-independent: the per-design kernels reach these functions as numba first-class functions
(:mod:`ashc_cli.closedloop.compiled` prints and caches them); numba caches this module's machine code
(``cache=True``)."""
import numpy as np
from numba import njit, types

from ashc_cli.closedloop.laws import feedback_of, pinv, saturate, setpoint, state_derivatives, weighted_norm2

F1 = types.float64[::1]
F2 = types.float64[:, ::1]
I1 = types.int64[::1]
#: eval_xi(xi, phi_bar, delta, l, dp/dxi delta, kappa, p) and eval_x(x, f_bar, g, h), filling their arrays.
XI_KERNEL = types.FunctionType(types.void(F1, F1, F2, F1, F2, F1, F1))
X_KERNEL = types.FunctionType(types.void(F1, F1, F2, F1))
#: eval_link(x, b, c, m) and eval_u([t], u): the m-relation's link and the spec's input signal.
LINK_KERNEL = types.FunctionType(types.void(F1, F1, F2, F1))
U_KERNEL = types.FunctionType(types.void(F1, F1))
OPTIONS = dict(cache=True, error_model='numpy')


@njit(**OPTIONS)
def design_at(eval_xi, eval_x, dims, z):
    """The kernels at z = [xi, x, ...], in fresh arrays: (phi_bar, delta, l, dp/dxi delta, kappa, p) of xi and
    (f_bar, g, h) of x."""
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
    eval_x(z[NH:NH + N].copy(), fb, g, h)
    return phi, delta, l, dpd, kap, pm, fb, g, h


@njit(inline="always", **OPTIONS)
def store_sample(k, v, u, kap, h, V, Uo, PSI, Y):
    """Row k of the sampled outputs: v, u, psi = kappa(xi) and y = h(x), element by element.

    Parameters
    ----------
    k : int
    v, u, kap, h : 1-D float arrays
        The values at the sample.
    V, Uo, PSI, Y : 2-D float arrays
        The tables (one row per sample).
    """
    for a in range(v.size):
        V[k, a] = v[a]
    for j in range(u.size):
        Uo[k, j] = u[j]
    for i in range(kap.size):
        PSI[k, i] = kap[i]
        Y[k, i] = h[i]


@njit(inline="always", **OPTIONS)
def _loop_at(phi, delta, l, dpd, pm, fb, g, dims, z, xi_ref, prm, L, K, U, q_ls, sat, v, u, dz):
    """:func:`closed_loop` given the design's values at z (``samples`` reuses them for psi and y)."""
    NH, N, M, MH = dims[0], dims[1], dims[2], dims[3]
    gain, v_max, lam, eps = prm[0], prm[1], prm[2], prm[3]
    xi = z[:NH].copy()
    x = z[NH:NH + N].copy()
    setpoint(delta, phi, xi, xi_ref, gain, v_max, v)
    # feedback = K (x - p); u_nominal = l + feedback; correction = feedback (+ q v)
    feedback = np.empty(M)
    feedback_of(K, x, pm, feedback)
    correction = feedback.copy()
    if q_ls == 1:
        # q = pinv(L^T g) (L^T dp/dxi delta), eq. egqLS
        Ltg = np.empty((N, M))
        Ltd = np.empty((N, MH))
        for i in range(N):
            for j in range(M):
                s = 0.0
                for k in range(N):
                    s += L[k, i] * g[k, j]
                Ltg[i, j] = s
            for a in range(MH):
                s = 0.0
                for k in range(N):
                    s += L[k, i] * dpd[k, a]
                Ltd[i, a] = s
        pg = pinv(Ltg)
        for j in range(M):
            s = 0.0
            for a in range(MH):
                qa = 0.0
                for i in range(N):
                    qa += pg[j, i] * Ltd[i, a]
                s += qa * v[a]
            correction[j] = feedback[j] + s
    saturate(l, 0, correction, 0, U, sat, u, M)          # u = SAT(l + correction)
    # dxi = phi_bar + delta v; dx = f_bar + g u; r = dp/dxi delta v - g (u - u_nominal)
    state_derivatives(phi, delta, v, fb, g, u, dz)
    r = np.empty(N)
    for i in range(N):
        s1 = 0.0
        for a in range(MH):
            s1 += dpd[i, a] * v[a]
        s2 = 0.0
        for j in range(M):
            s2 += g[i, j] * (u[j] - (l[j] + feedback[j]))
        r[i] = s1 - s2
    # w' = -(lambda - eps) w + |L^T r|^2 / eps
    dz[NH + N] = -(lam - eps) * z[NH + N] + weighted_norm2(L, r) / eps


@njit(types.void(XI_KERNEL, X_KERNEL, I1, F1, F1, F1, F2, F2, F2, types.int64, types.int64, F1, F1, F1), **OPTIONS)
def closed_loop(eval_xi, eval_x, dims, z, xi_ref, prm, L, K, U, q_ls, sat, v, u, dz):
    """reference.tracking_law and the comparison system at z = [xi, x, w]; fills v, u and dz = [dxi, dx, dw].

    dims = [n_hat, n, m, m_hat, p]; prm = [gain, v_max, lambda, eps]; q_ls = 1 for the least-squares q, 0 for
    q = 0; sat = 0 (no saturation), 1 (clip each channel to U) or 2 (scale the correction).
    """
    phi, delta, l, dpd, kap, pm, fb, g, h = design_at(eval_xi, eval_x, dims, z)
    _loop_at(phi, delta, l, dpd, pm, fb, g, dims, z, xi_ref, prm, L, K, U, q_ls, sat, v, u, dz)


@njit(types.void(XI_KERNEL, X_KERNEL, LINK_KERNEL, U_KERNEL, I1, types.float64, F1, F1, F1, F1), **OPTIONS)
def link_loop(eval_xi, eval_x, eval_link, eval_u, dims, t, z, v, u, dz):
    """simulate.run_m_relation's right-hand side at (t, z = [xi, x]); fills u = u(t), v and dz = [dxi, dx].

    v = b(x) + c(x) u (eq. mRelateLink); dxi = phi_bar(xi) + delta(xi) v; dx = f_bar(x) + g(x) u.
    """
    NH, N, M, MH = dims[0], dims[1], dims[2], dims[3]
    tt = np.empty(1)
    tt[0] = t
    eval_u(tt, u)
    x = z[NH:NH + N].copy()
    phi, delta, l, dpd, kap, pm, fb, g, h = design_at(eval_xi, eval_x, dims, z)
    b = np.empty(MH)
    c = np.empty((MH, M))
    mx = np.empty(NH)
    eval_link(x, b, c, mx)
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
    """The eval_link of the tracking runs (``integrate`` takes one; it is never called there)."""


@njit(types.void(F1, F1), **OPTIONS)
def no_signal(t, u):
    """The eval_u of the tracking runs (never called there)."""


#: rhs(t, z, dz, eval_xi, eval_x, eval_link, eval_u, dims, ref, prm, L, K, U, q_ls, sat, v, u): the right-hand side
#: of either loop behind one signature, so that one integrate runs both (an indirect call: integrate is compiled
#: once and small, instead of inlining both loops at each of its calls).
RHS_SIGNATURE = types.void(types.float64, F1, F1, XI_KERNEL, X_KERNEL, LINK_KERNEL, U_KERNEL, I1, F1, F1, F2, F2, F2, types.int64,
                           types.int64, F1, F1)
RHS = types.FunctionType(RHS_SIGNATURE)


@njit(RHS_SIGNATURE, **OPTIONS)
def tracking_rhs(t, z, dz, eval_xi, eval_x, eval_link, eval_u, dims, ref, prm, L, K, U, q_ls, sat, v, u):
    """closed_loop behind the RHS signature (t, eval_link and eval_u unused)."""
    closed_loop(eval_xi, eval_x, dims, z, ref, prm, L, K, U, q_ls, sat, v, u, dz)


@njit(RHS_SIGNATURE, **OPTIONS)
def link_rhs(t, z, dz, eval_xi, eval_x, eval_link, eval_u, dims, ref, prm, L, K, U, q_ls, sat, v, u):
    """link_loop behind the RHS signature (ref, prm, L, K, U, q_ls and sat unused)."""
    link_loop(eval_xi, eval_x, eval_link, eval_u, dims, t, z, v, u, dz)


@njit(**OPTIONS)
def _leaves(eval_x, dims, z, edges):
    """simulate's leaves_certified_set: min(y - lo - lo_margin, hi - hi_margin - y), y = h(x), edges = [lo,
    lo_margin, hi, hi_margin]; Python's min of the two (the first unless the second is smaller)."""
    NH, N, M, P = dims[0], dims[1], dims[2], dims[4]
    x = z[NH:NH + N].copy()
    fb = np.empty(N)
    g = np.empty((N, M))
    h = np.empty(P)
    eval_x(x, fb, g, h)
    below = h[0] - edges[0] - edges[1]
    above = edges[2] - edges[3] - h[0]
    return above if above < below else below


@njit(**OPTIONS)
def _rms(x):
    s = 0.0
    for i in range(x.size):
        s += x[i] * x[i]
    return np.sqrt(s) / np.sqrt(x.size)


@njit(**OPTIONS)
def _combine(K, coef, s, h, y, out):
    """out = y + (sum_{j < s} coef[j] K[j]) h  (scipy: y + np.dot(K[:s].T, coef[:s]) * h)."""
    for i in range(K.shape[1]):
        acc = 0.0
        for j in range(s):
            acc += K[j, i] * coef[j]
        out[i] = y[i] + acc * h


@njit(**OPTIONS)
def _dense(F, y, x, out):
    """Dop853DenseOutput at x = (t - t_old) / h: out = y + the 7th-order polynomial of F (scipy's order)."""
    d = y.size
    for i in range(d):
        out[i] = 0.0
    for q in range(7):
        for i in range(d):
            out[i] += F[6 - q, i]
            if q % 2 == 0:
                out[i] *= x
            else:
                out[i] *= 1 - x
    for i in range(d):
        out[i] += y[i]


@njit(**OPTIONS)
def _event_root(eval_x, dims, edges, F, y, t_old, t, z):
    """The time in [t_old, t] where the event crosses zero on the dense output: scipy.optimize.brentq (its C
    code, xtol = rtol = 4 eps, 100 iterations) as solve_ivp's solve_event_equation calls it; z = the state there."""
    xtol = 4 * 2.220446049250313e-16     # scipy: 4 * np.finfo(float).eps
    rtol = xtol
    hs = t - t_old
    xpre = t_old
    xcur = t
    _dense(F, y, (xpre - t_old) / hs, z)
    fpre = _leaves(eval_x, dims, z, edges)
    _dense(F, y, (xcur - t_old) / hs, z)
    fcur = _leaves(eval_x, dims, z, edges)
    root = xcur
    if fpre == 0:
        root = xpre
    elif fcur != 0 and (fpre < 0) == (fcur < 0):
        root = xcur     # no sign change on the dense output (scipy raises): the step's end, where the event was seen
    elif fcur != 0:
        xblk = 0.0
        fblk = 0.0
        spre = 0.0
        scur = 0.0
        for _ in range(100):
            if fpre != 0 and fcur != 0 and (fpre < 0) != (fcur < 0):
                xblk = xpre
                fblk = fpre
                spre = xcur - xpre
                scur = spre
            if abs(fblk) < abs(fcur):
                xpre = xcur
                xcur = xblk
                xblk = xpre
                fpre = fcur
                fcur = fblk
                fblk = fpre
            tol = (xtol + rtol * abs(xcur)) / 2
            sbis = (xblk - xcur) / 2
            if fcur == 0 or abs(sbis) < tol:
                break
            if abs(spre) > tol and abs(fcur) < abs(fpre):
                if xpre == xblk:        # interpolate
                    stry = -fcur * (xcur - xpre) / (fcur - fpre)
                else:                   # extrapolate
                    dpre = (fpre - fcur) / (xpre - xcur)
                    dblk = (fblk - fcur) / (xblk - xcur)
                    stry = -fcur * (fblk * dblk - fpre * dpre) / (dblk * dpre * (fblk - fpre))
                if 2 * abs(stry) < min(abs(spre), 3 * abs(sbis) - tol):
                    spre = scur         # good short step
                    scur = stry
                else:
                    spre = sbis         # bisect
                    scur = sbis
            else:
                spre = sbis
                scur = sbis
            xpre = xcur
            fpre = fcur
            if abs(scur) > tol:
                xcur += scur
            else:
                xcur += tol if sbis > 0 else -tol
            _dense(F, y, (xcur - t_old) / hs, z)
            fcur = _leaves(eval_x, dims, z, edges)
        root = xcur
    _dense(F, y, (root - t_old) / hs, z)
    return root


@njit(types.UniTuple(types.int64, 5)(RHS, XI_KERNEL, X_KERNEL, LINK_KERNEL, U_KERNEL, I1, F1, F2, F1, I1, F2, F1, F2, F2, F2,
                                     types.int64, types.int64, F1, types.float64, types.float64, F2, F1, F1, F1, F1, F2, F2, F1),
      **OPTIONS)
def integrate(rhs, eval_xi, eval_x, eval_link, eval_u, dims, z0, t_bounds, t_eval, offsets, refs, prm, L, K, U, q_ls, sat, edges,
              rtol, atol, A, B, C, E3, E5, D, out, hit):
    """scipy's DOP853 (solve_ivp with t_eval, max_step = inf, at most one terminal event), segment after segment.

    ``rhs`` is tracking_rhs (refs[k], prm, L, K, U, q_ls and sat used; eval_link and eval_u not, pass no_link
    and no_signal) or link_rhs (those unused).  Segment k runs from t_bounds[k, 0] to t_bounds[k, 1] with the
    reference refs[k] and writes its samples t_eval[offsets[k]:offsets[k + 1]] to the same rows of out; the
    next segment starts from its last sample.  With edges = [lo, lo_margin, hi, hi_margin] (empty: no event)
    the run stops where h(x) leaves [lo + lo_margin, hi - hi_margin] (simulate's leaves_certified_set,
    direction -1, terminal): hit = [t, z] there.  Returns (status, rows written, segment, nfev, accepted steps): status 0 on success,
    1 at the event, -1 when the step fell below ten times the spacing of floating-point numbers (scipy's
    failure), -2 at a sample that is not finite.
    """
    SAFETY = 0.9
    MIN_FACTOR = 0.2
    MAX_FACTOR = 10.0
    n_stages = 12
    n_ext = 16
    exponent = -1.0 / 8.0            # -1 / (error_estimator_order + 1), error_estimator_order = 7
    d = z0.size
    nfev = 0
    steps = 0
    written = 0
    y = z0.copy()
    Kx = np.empty((n_ext, d))
    f = np.empty(d)
    f1 = np.empty(d)
    y1 = np.empty(d)
    ys = np.empty(d)
    yk = np.empty(d)
    F = np.empty((7, d))
    v = np.empty(dims[3])
    u = np.empty(dims[2])
    watch = edges.size > 0
    g_old = 0.0
    for seg in range(t_bounds.shape[0]):
        t = t_bounds[seg, 0]
        t_bound = t_bounds[seg, 1]
        ref = refs[seg]
        i_eval = offsets[seg]
        i_end = offsets[seg + 1]
        rhs(t, y, f, eval_xi, eval_x, eval_link, eval_u, dims, ref, prm, L, K, U, q_ls, sat, v, u)
        nfev += 1
        if watch:
            g_old = _leaves(eval_x, dims, y, edges)
        # select_initial_step (scipy.integrate._ivp.common), error_estimator_order 7
        interval = abs(t_bound - t)
        d0 = 0.0
        d1 = 0.0
        for i in range(d):
            sc = atol + abs(y[i]) * rtol
            d0 += (y[i] / sc) ** 2
            d1 += (f[i] / sc) ** 2
        d0 = np.sqrt(d0) / np.sqrt(d)
        d1 = np.sqrt(d1) / np.sqrt(d)
        if d0 < 1e-5 or d1 < 1e-5:
            h0 = 1e-6
        else:
            h0 = 0.01 * d0 / d1
        h0 = min(h0, interval)
        for i in range(d):
            y1[i] = y[i] + h0 * f[i]
        rhs(t + h0, y1, f1, eval_xi, eval_x, eval_link, eval_u, dims, ref, prm, L, K, U, q_ls, sat, v, u)
        nfev += 1
        d2 = 0.0
        for i in range(d):
            d2 += ((f1[i] - f[i]) / (atol + abs(y[i]) * rtol)) ** 2
        d2 = np.sqrt(d2) / np.sqrt(d) / h0
        if d1 <= 1e-15 and d2 <= 1e-15:
            h1 = max(1e-6, h0 * 1e-3)
        else:
            h1 = (0.01 / max(d1, d2)) ** (1.0 / 8.0)
        h_abs = min(100 * h0, h1, interval)
        finished = t == t_bound
        if finished:                           # a zero-length segment: every sample is its start
            for k in range(i_eval, i_end):
                for i in range(d):
                    out[k, i] = y[i]
            written = i_end
            i_eval = i_end
        y_new = np.empty(d)
        while not finished:
            # RungeKutta._step_impl
            min_step = 10 * abs(np.nextafter(t, np.inf) - t)
            if h_abs < min_step:
                h_abs = min_step
            accepted = False
            rejected = False
            t_new = t
            h = 0.0
            while not accepted:
                if not (h_abs >= min_step):    # scipy: h_abs < min_step (a NaN step, where scipy loops for ever, fails too)
                    return -1, written, seg, nfev, steps
                h = h_abs
                t_new = t + h
                if t_new - t_bound > 0:
                    t_new = t_bound
                h = t_new - t
                h_abs = abs(h)
                # rk_step (rows copied element by element: a row assignment, Kx[0] = f, makes numba compile its
                # error-message formatting, 1.6 s of the core's first compilation)
                for i in range(d):
                    Kx[0, i] = f[i]
                for s in range(1, n_stages):
                    _combine(Kx, A[s], s, h, y, ys)
                    rhs(t + C[s] * h, ys, Kx[s], eval_xi, eval_x, eval_link, eval_u, dims, ref, prm, L, K, U, q_ls, sat, v, u)
                nfev += n_stages - 1
                for i in range(d):
                    acc = 0.0
                    for j in range(n_stages):
                        acc += Kx[j, i] * B[j]
                    y_new[i] = y[i] + h * acc
                rhs(t + h, y_new, Kx[n_stages], eval_xi, eval_x, eval_link, eval_u, dims, ref, prm, L, K, U, q_ls, sat, v, u)
                nfev += 1
                # DOP853._estimate_error_norm
                e5 = 0.0
                e3 = 0.0
                for i in range(d):
                    sc = atol + max(abs(y[i]), abs(y_new[i])) * rtol
                    a5 = 0.0
                    a3 = 0.0
                    for j in range(n_stages + 1):
                        a5 += Kx[j, i] * E5[j]
                        a3 += Kx[j, i] * E3[j]
                    a5 /= sc
                    a3 /= sc
                    e5 += a5 * a5
                    e3 += a3 * a3
                if e5 == 0 and e3 == 0:
                    err = 0.0
                else:
                    err = abs(h) * e5 / np.sqrt((e5 + 0.01 * e3) * d)
                if err < 1:
                    if err == 0:
                        factor = MAX_FACTOR
                    else:
                        factor = SAFETY * err ** exponent
                        if not (factor < MAX_FACTOR):     # min(MAX_FACTOR, .) as Python evaluates it
                            factor = MAX_FACTOR
                    if rejected and not (factor < 1.0):
                        factor = 1.0
                    h_abs *= factor
                    accepted = True
                else:
                    factor = SAFETY * err ** exponent
                    if not (factor > MIN_FACTOR):         # max(MIN_FACTOR, .), NaN included
                        factor = MIN_FACTOR
                    h_abs *= factor
                    rejected = True
            steps += 1
            t_old = t
            t = t_new
            finished = t - t_bound >= 0
            # the event (solve_ivp checks it before sampling the step), then the samples in (t_old, t] (and t_old
            # itself at the first step); both read the dense output, built once per step and only when needed
            crossed = False
            if watch:
                g_new = _leaves(eval_x, dims, y_new, edges)
                crossed = g_old >= 0 and g_new <= 0
                g_old = g_new
            i_new = i_eval
            while i_new < i_end and t_eval[i_new] <= t:
                i_new += 1
            if crossed or i_new > i_eval:
                for s in range(n_stages + 1, n_ext):
                    _combine(Kx, A[s], s, h, y, ys)
                    rhs(t_old + C[s] * h, ys, Kx[s], eval_xi, eval_x, eval_link, eval_u, dims, ref, prm, L, K, U, q_ls, sat, v, u)
                nfev += n_ext - n_stages - 1
                for i in range(d):
                    dlt = y_new[i] - y[i]
                    F[0, i] = dlt
                    F[1, i] = h * Kx[0, i] - dlt
                    F[2, i] = 2 * dlt - h * (Kx[n_stages, i] + Kx[0, i])
                for r in range(4):
                    for i in range(d):
                        acc = 0.0
                        for j in range(n_ext):
                            acc += D[r, j] * Kx[j, i]
                        F[3 + r, i] = h * acc
            if crossed:
                hit[0] = _event_root(eval_x, dims, edges, F, y, t_old, t, yk)
                for i in range(d):
                    hit[1 + i] = yk[i]
                return 1, written, seg, nfev, steps
            if i_new > i_eval:
                hs = t - t_old
                for k in range(i_eval, i_new):
                    _dense(F, y, (t_eval[k] - t_old) / hs, yk)
                    for i in range(d):
                        out[k, i] = yk[i]
                        if not np.isfinite(out[k, i]):
                            return -2, k + 1, seg, nfev, steps
                written = i_new
                i_eval = i_new
            for i in range(d):
                y[i] = y_new[i]
            for i in range(d):
                f[i] = Kx[n_stages, i]
        if i_end > i_eval:                     # not reached: the last sample is t_bound
            return -1, written, seg, nfev, steps
        for i in range(d):
            y[i] = out[i_end - 1, i]
    return 0, written, t_bounds.shape[0], nfev, steps


@njit(types.void(XI_KERNEL, X_KERNEL, I1, F2, I1, F2, F1, F2, F2, F2, types.int64, types.int64, F2, F2, F2, F2), **OPTIONS)
def samples(eval_xi, eval_x, dims, Z, seg_of_row, refs, prm, L, K, U, q_ls, sat, V, Uo, PSI, Y):
    """At every row of Z: v and u (tracking_law), psi = kappa(xi) and y = h(x)."""
    NH, N, M, MH = dims[0], dims[1], dims[2], dims[3]
    dz = np.empty(NH + N + 1)
    v = np.empty(MH)
    u = np.empty(M)
    for k in range(Z.shape[0]):
        z = Z[k]
        phi, delta, l, dpd, kap, pm, fb, g, h = design_at(eval_xi, eval_x, dims, z)
        _loop_at(phi, delta, l, dpd, pm, fb, g, dims, z, refs[seg_of_row[k]], prm, L, K, U, q_ls, sat, v, u, dz)
        store_sample(k, v, u, kap, h, V, Uo, PSI, Y)


@njit(types.void(XI_KERNEL, X_KERNEL, LINK_KERNEL, U_KERNEL, I1, F1, F2, F2, F2, F2, F2, F2), **OPTIONS)
def link_samples(eval_xi, eval_x, eval_link, eval_u, dims, t, Z, V, Uo, PSI, Y, MX):
    """At every row of Z = [xi, x] (time t[k]): v and u (link_loop), psi = kappa(xi), y = h(x) and m(x)."""
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
        phi, delta, l, dpd, kap, pm, fb, g, h = design_at(eval_xi, eval_x, dims, z)
        x = z[NH:NH + N].copy()
        eval_link(x, b, c, mx)
        store_sample(k, v, u, kap, h, V, Uo, PSI, Y)
        for i in range(NH):
            MX[k, i] = mx[i]
