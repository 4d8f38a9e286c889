"""The runs of ``ashc falsify`` in numba: the batch's laws and adversaries, integrated hold by hold by the engine's
Dormand-Prince 5(4) (:mod:`ashc_cli.closedloop.rk`).

Design-independent: the per-design kernels reach these functions as numba first-class functions
(:mod:`ashc_cli.closedloop.compiled` prints and caches them); numba caches this module's machine code
(``cache=True``)."""
import math
import numpy as np
from numba import njit, types

from ashc_cli.closedloop.laws import pinv_flat, saturate
from ashc_cli.closedloop.rk import DP54, DP54_EXPONENT, error_norm, stage_input, step_factor

F1 = types.float64[::1]
F2 = types.float64[:, ::1]
F3 = types.float64[:, :, ::1]
I1 = types.int64[::1]
I2 = types.int64[:, ::1]
#: falsify_xi(z, A) and falsify_x(z, B), z = [xi, x]: A = [phi_bar, delta, l, dp/dxi delta, kappa, p, dp/dxi],
#: B = [f_bar, g, h, dh/dx], matrices row after row (one flat buffer each: few arrays cross a call).
XI_KERNEL = types.FunctionType(types.void(F1, F1))
X_KERNEL = types.FunctionType(types.void(F1, F1))
OPTIONS = dict(cache=True, error_model="numpy")

SETPOINT, TABLE, GREEDY = 0, 1, 2

#: Where each term lives in the flat buffers (indices into ``off``): A holds the xi kernel's output, B the x
#: kernel's, wk the loop's work (row-major matrices).
O_PHI, O_DEL, O_L, O_DPD, O_KAP, O_PM, O_DP, O_FB, O_G, O_H, O_DH, O_KX, O_Q, O_LTG, O_LTD, O_PG, O_DPLUS, O_CORR, O_VIN = range(19)


@njit(**OPTIONS)
def _norm(v):
    s = 0.0
    for i in range(v.size):
        s += v[i] * v[i]
    return math.sqrt(s)


@njit(**OPTIONS)
def _stays(z, dxi, step, lo, hi):
    """xi + step dxi inside [lo, hi], xi = z[:n_hat] (the guard of held inputs)."""
    for i in range(dxi.size):
        y = z[i] + step * dxi[i]
        if not (y >= lo[i] and y <= hi[i]):
            return False
    return True


@njit(**OPTIONS)
def _terms(exi, ex, z, dims, off, A, B, wk, K, L, q_ls):
    """The closed loop at z = [xi, x] that does not depend on v (strategies._interface): the kernels into A and B;
    kx = K (x - p) and q = pinv(L^T g) L^T dp/dxi delta (eq. (43)) or 0 into wk."""
    nh, n, m, mh = dims[0], dims[1], dims[2], dims[3]
    exi(z, A)
    ex(z, B)
    o_pm, o_g, o_dpd = off[O_PM], off[O_G], off[O_DPD]
    o_kx, o_q, o_ltg, o_ltd, o_pg = off[O_KX], off[O_Q], off[O_LTG], off[O_LTD], off[O_PG]
    for j in range(m):
        s = 0.0
        for i in range(n):
            s += (z[nh + i] - A[o_pm + i]) * K[j, i]
        wk[o_kx + j] = s
    if q_ls == 1:
        for i in range(n):
            for j in range(m):
                s = 0.0
                for k in range(n):
                    s += L[k, i] * B[o_g + k * m + j]
                wk[o_ltg + i * m + j] = s
            for a in range(mh):
                s = 0.0
                for k in range(n):
                    s += L[k, i] * A[o_dpd + k * mh + a]
                wk[o_ltd + i * mh + a] = s
        pinv_flat(wk, o_ltg, n, m, wk, o_pg)
        for j in range(m):
            for a in range(mh):
                s = 0.0
                for i in range(n):
                    s += wk[o_pg + j * n + i] * wk[o_ltd + i * mh + a]
                wk[o_q + j * mh + a] = s
    else:
        for k in range(m * mh):
            wk[o_q + k] = 0.0


@njit(**OPTIONS)
def _apply(dims, off, A, B, wk, U, sat, v, u, dxi, dx):
    """u = SAT(l + K (x - p) + q v) (model.apply_saturation), xi' = phi_bar + delta v, x' = f_bar + g u."""
    nh, n, m, mh = dims[0], dims[1], dims[2], dims[3]
    o_l, o_kx, o_q, o_c = off[O_L], off[O_KX], off[O_Q], off[O_CORR]
    for j in range(m):
        s = 0.0
        for a in range(mh):
            s += wk[o_q + j * mh + a] * v[a]
        wk[o_c + j] = wk[o_kx + j] + s
    saturate(A, o_l, wk, o_c, U, sat, u, m)
    o_phi, o_del = off[O_PHI], off[O_DEL]
    for i in range(nh):
        s = 0.0
        for a in range(mh):
            s += A[o_del + i * mh + a] * v[a]
        dxi[i] = A[o_phi + i] + s
    o_fb, o_g = off[O_FB], off[O_G]
    for i in range(n):
        s = 0.0
        for j in range(m):
            s += B[o_g + i * m + j] * u[j]
        dx[i] = B[o_fb + i] + s


@njit(**OPTIONS)
def _setpoint_v(z, dims, off, A, wk, ref, gain, noise, v_limit, v):
    """The random strategy's law: v = delta^+ (gain (ref - xi) - phi_bar) + noise, its norm clipped to v_limit."""
    nh, mh = dims[0], dims[3]
    o_dp = off[O_DPLUS]
    pinv_flat(A, off[O_DEL], nh, mh, wk, o_dp)
    o_phi = off[O_PHI]
    for a in range(mh):
        s = 0.0
        for i in range(nh):
            s += wk[o_dp + a * nh + i] * (gain * (ref[i] - z[i]) - A[o_phi + i])
        v[a] = s + noise[a]
    shrink = min(1.0, v_limit / max(_norm(v), 1e-300))
    for a in range(mh):
        v[a] *= shrink


@njit(**OPTIONS)
def _isclose(a, b, rtol, atol):
    """numpy.isclose for two floats."""
    if a == b:
        return True
    if not (math.isfinite(a) and math.isfinite(b)):
        return False
    return abs(a - b) <= atol + rtol * abs(b)


@njit(**OPTIONS)
def _nan_to_num(v):
    big = 1.7976931348623157e308
    for a in range(v.size):
        if v[a] != v[a]:
            v[a] = 0.0
        elif v[a] == np.inf:
            v[a] = big
        elif v[a] == -np.inf:
            v[a] = -big


@njit(**OPTIONS)
def _greedy(dims, off, A, B, wk, M, U, sat, cand, Z, lo, hi, amp, rho, alpha_h, dt, lookahead, guarded, k, last_switch, prev, vc, u, dxi, dx,
            ee, choice, v_plan):
    """The greedy adversary at hold k (the terms of A and B at Z): among the candidates of norm ``amp`` (those that
    keep xi in V when ``guarded``), the one that maximises the one-hold look-ahead of rho W / alpha_h +
    (1 - rho) |dh/dx e|^2, e = p - x, into v_plan (NaN when none is allowed); ties keep the previous input.
    Returns the hold of the last switch."""
    nh, n, mh, p = dims[0], dims[1], dims[3], dims[4]
    o_pm, o_dp, o_dh = off[O_PM], off[O_DP], off[O_DH]
    best = -np.inf
    for a in range(mh):
        choice[a] = 0.0
    for c in range(cand.shape[0]):
        for a in range(mh):
            vc[a] = cand[c, a] * amp
        _apply(dims, off, A, B, wk, U, sat, vc, u, dxi, dx)
        for i in range(n):
            s = 0.0
            for j in range(nh):
                s += A[o_dp + i * nh + j] * dxi[j]
            ee[i] = (A[o_pm + i] - Z[nh + i]) + dt * (s - dx[i])
        quad = 0.0
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += M[i, j] * ee[j]
            quad += ee[i] * s
        out2 = 0.0
        for i in range(p):
            s = 0.0
            for j in range(n):
                s += B[o_dh + i * n + j] * ee[j]
            out2 += s * s
        J = rho * quad / alpha_h + (1 - rho) * out2
        if guarded and not _stays(Z, dxi, lookahead * dt, lo, hi):
            J = -np.inf
        thr = best
        if math.isfinite(best):
            thr = best + 1e-12 * abs(best)
        tie = _isclose(J, best, 1e-9, 0.0)
        if tie:
            for a in range(mh):
                if not _isclose(vc[a], prev[a], 1e-5, 1e-8):
                    tie = False
        if J > thr or tie:
            best = J
            for a in range(mh):
                choice[a] = vc[a]
    none = not math.isfinite(best)
    if none:
        for a in range(mh):
            choice[a] = 0.0
    for a in range(mh):
        if choice[a] != prev[a]:
            last_switch = k
    for a in range(mh):
        v_plan[a] = np.nan if none else choice[a]
    return last_switch


@njit(inline="always", **OPTIONS)
def _output_error(A, B, o_kap, o_h, p):
    """|psi - y| = |kappa(xi) - h(x)| from the kernels' buffers."""
    err = 0.0
    for i in range(p):
        err += (A[o_kap + i] - B[o_h + i]) ** 2
    return math.sqrt(err)


@njit(inline="always", **OPTIONS)
def _state_checks(Z, nh, scale, diverge, lo, hi):
    """(finite, inside): every entry of Z finite and within ``diverge`` times its scale; xi = Z[:nh] in V (1e-9 slack)."""
    finite = True
    for i in range(Z.size):
        if not (math.isfinite(Z[i]) and abs(Z[i]) <= diverge * scale[i]):
            finite = False
    inside = True
    for i in range(nh):
        if not (Z[i] >= lo[i] - 1e-9 and Z[i] <= hi[i] + 1e-9):
            inside = False
    return finite, inside


@njit(inline="always", **OPTIONS)
def _account(k, k_at, active, err, floor, bound, acc):
    """Sample k into the run's tallies ``acc`` (fout's row: the largest error / bound ratio, the largest after t = 0,
    the largest error and, at acc[5], bound while the run is active); the sample of the largest ratio is returned.
    A local row, copied to fout at the end: threads writing neighbouring rows of fout every hold share cache lines."""
    ratio = 0.0
    if active and err > floor:
        ratio = (err - floor) / max(bound, 1e-300) if bound > 0 else np.inf
    if ratio > acc[0]:
        acc[0] = ratio
        k_at = k
    if k > 0:
        acc[1] = max(acc[1], ratio)
    if active:
        acc[2] = max(acc[2], err if math.isfinite(err) else 0.0)
        acc[5] = max(acc[5], bound)
    return k_at


@njit(inline="always", **OPTIONS)
def _record(r, k, Z, err, bound, v_now, recZ, recE, recB, recV):
    """Sample k of run r into the records (``record`` runs only)."""
    for i in range(Z.size):
        recZ[r, k, i] = Z[i]
    recE[r, k] = err
    recB[r, k] = bound
    for a in range(v_now.size):
        recV[r, k, a] = v_now[a]


@njit(inline="always", **OPTIONS)
def _guard(dims, off, A, B, wk, U, sat, Z, lo, hi, centre, step, v_max, v_plan, plan0, neg, u, dxi, dxi_r, dx):
    """The guard of a held input: v_plan is kept if it keeps xi in V over ``step``, else reversed, else turned to
    V's centre at |v| = v_max (NaN entries count as 0)."""
    nh, mh = dims[0], dims[3]
    any_nan = False
    for a in range(mh):
        plan0[a] = v_plan[a]
        if v_plan[a] != v_plan[a]:
            any_nan = True
    _nan_to_num(plan0)
    _apply(dims, off, A, B, wk, U, sat, plan0, u, dxi, dx)
    if not any_nan and _stays(Z, dxi, step, lo, hi):
        return
    nonzero = False
    for a in range(mh):
        neg[a] = -plan0[a]
        if plan0[a] != 0:
            nonzero = True
    _apply(dims, off, A, B, wk, U, sat, neg, u, dxi_r, dx)
    if nonzero and _stays(Z, dxi_r, step, lo, hi):
        for a in range(mh):
            v_plan[a] = neg[a]
        return
    o_dplus, o_del, o_vin = off[O_DPLUS], off[O_DEL], off[O_VIN]
    pinv_flat(A, o_del, nh, mh, wk, o_dplus)
    nin = 0.0
    for a in range(mh):
        s = 0.0
        for i in range(nh):
            s += wk[o_dplus + a * nh + i] * (centre[i] - Z[i])
        wk[o_vin + a] = s
        nin += s * s
    nin = math.sqrt(nin)
    for a in range(mh):
        v_plan[a] = wk[o_vin + a] * (v_max / max(nin, 1e-300))


@njit(**OPTIONS)
def run_one(exi, ex, r, dims, off, fprm, iprm, M, L, K, U, atol, scale, lo, hi, centre, cand, tgrid,
            xi0, x0, mode, vtab, rho, dwell, amp, guard, refs, gains, noise, W0,
            fout, iout, vused, recZ, recE, recB, recV):
    """Run r, hold by hold, with its own step-size control: the error / bound ratio at each hold boundary, xi in V.

    Parameters
    ----------
    r : int, the run: its row of the per-run arrays and of the outputs; the other arguments as :func:`run_batch`."""
    nh, n, m, mh, p, H, S, record, keep_v = dims[0], dims[1], dims[2], dims[3], dims[4], dims[5], dims[6], dims[7], dims[8]
    q_ls, sat = iprm[0], iprm[1]
    dt, v_limit, lam, eps, alpha_h, G, floor, diverge, lookahead = fprm[0], fprm[1], fprm[2], fprm[3], fprm[4], fprm[5], fprm[6], fprm[8], fprm[9]
    d = nh + n
    A, B, wk = np.empty(off[19]), np.empty(off[20]), np.empty(off[21])     # the kernels' buffers and the loop's work
    v, v_plan, plan0, neg, vc, choice = np.empty(mh), np.empty(mh), np.empty(mh), np.empty(mh), np.empty(mh), np.empty(mh)
    v_now, prev = np.zeros(mh), np.zeros(mh)
    u, dxi, dxi_r, dx, ee = np.empty(m), np.empty(nh), np.empty(nh), np.empty(n), np.empty(n)
    Z, Zs, zs, ks = np.empty(d), np.empty(d), np.empty(d), np.empty((DP54[0].shape[0], d))
    for i in range(nh):
        Z[i] = xi0[r, i]
    for i in range(n):
        Z[nh + i] = x0[r, i]
    md = mode[r]
    held = md != SETPOINT
    greedy = md == GREEDY
    setpoint = md == SETPOINT
    guarded = guard[r] != 0
    w0 = W0[r]
    gain = gains[r]
    active = True
    left = 0
    diverged = 0
    vsup = 0.0
    at_limit = 0.0
    forced = 0
    accepted = 0
    rejected = 0
    h_min = dt / 4096.0
    rtol = fprm[7]
    last_switch = -(10 ** 9)
    acc = np.zeros(6)                # ratio, ratio_late, max_err, vsup, at_limit, largest_bound (fout's row)
    k_at = 0
    h_step = dt
    for k in range(H + 1):
        seg = min(k * S // H, S - 1)
        ref = refs[r, seg]
        nz = noise[r, seg]
        finite, inside = _state_checks(Z, nh, scale, diverge, lo, hi)
        if active and not finite:
            diverged = 1
        active = active and finite
        if active and not inside:
            left = 1
        active = active and inside
        for i in range(d):
            Zs[i] = Z[i] if math.isfinite(Z[i]) else 0.0
        _terms(exi, ex, Zs, dims, off, A, B, wk, K, L, q_ls)
        err = _output_error(A, B, off[O_KAP], off[O_H], p)

        v_now[:] = 0.0
        if k < H:
            if held:
                v_plan[:] = vtab[r, k]
                if greedy and not (active and k - last_switch >= dwell[r]):
                    v_plan[:] = prev                      # the adversary keeps its choice for dwell holds after a switch
                elif greedy:
                    last_switch = _greedy(dims, off, A, B, wk, M, U, sat, cand, Z, lo, hi, v_limit * amp[r], rho[r], alpha_h, dt, lookahead,
                                          guarded, k, last_switch, prev, vc, u, dxi, dx, ee, choice, v_plan)
                if guarded and active:                    # out of V: the input reversed, else turned to V's centre
                    _guard(dims, off, A, B, wk, U, sat, Z, lo, hi, centre, lookahead * dt, v_limit * amp[r], v_plan, plan0, neg, u, dxi, dxi_r, dx)
                _nan_to_num(v_plan)
                if greedy:
                    prev[:] = v_plan
                v_now[:] = v_plan
            if setpoint:
                _setpoint_v(Zs, dims, off, A, wk, ref, gain, nz, v_limit, v_now)
            if keep_v:
                for a in range(mh):
                    vused[r, k, a] = v_now[a]
        elif setpoint:
            _setpoint_v(Zs, dims, off, A, wk, ref, gain, nz, v_limit, v_now)
        vn = _norm(v_now)
        if active:
            vsup = max(vsup, vn)
            if vn >= v_limit * (1 - 1e-9):
                at_limit += 1.0
        bound = math.sqrt(w0 * math.exp(-(lam - eps) * tgrid[k]) / alpha_h) + G * vsup
        k_at = _account(k, k_at, active, err, floor, bound, acc)
        if record:
            _record(r, k, Z, err, bound, v_now, recZ, recE, recB, recV)
        if k == H:
            break
        if not active:
            continue

        t = tgrid[k]
        t_end = tgrid[k + 1]
        tab = DP54
        ns = tab[1].size
        first = 0
        while t < t_end - 1e-14 * max(1.0, t_end):
            h_nat = h_step
            h_step = min(h_step, t_end - t)
            for s in range(first, ns + 1):
                # [xi', x'] at zs, held input or set-point law, non-finite entries 0.  Stage 0 runs at the hold's start
                # only: zs = Z, and the terms in A, B and wk are still those of the hold-start check.
                if s == 0:
                    zs[:] = Z
                else:
                    stage_input(tab, s, h_step, Z, ks, zs)
                    _terms(exi, ex, zs, dims, off, A, B, wk, K, L, q_ls)
                if setpoint:
                    _setpoint_v(zs, dims, off, A, wk, ref, gain, nz, v_limit, v)
                else:
                    for a in range(mh):
                        v[a] = v_now[a]
                _apply(dims, off, A, B, wk, U, sat, v, u, dxi, dx)
                for i in range(nh):
                    ks[s, i] = dxi[i] if math.isfinite(dxi[i]) else 0.0
                for i in range(n):
                    ks[s, nh + i] = dx[i] if math.isfinite(dx[i]) else 0.0
            first = 1
            E = error_norm(tab, ks, h_step, Z, zs, atol, rtol)
            if not math.isfinite(E):
                E = 0.0
            if E <= 1.0 or h_step <= h_min:
                if E > 1.0:
                    forced += 1
                accepted += 1
                for i in range(d):
                    Z[i] = zs[i]
                    ks[0, i] = ks[ns, i]
                t += h_step
                h_step = h_step * step_factor(E, DP54_EXPONENT, 0.9, 0.2, 5.0)
                restore = h_nat if (h_step < h_nat and E <= 0.5) else 0.0
                h_step = min(max(h_step, h_min, restore), dt)
            else:
                rejected += 1
                h_step = max(h_min, h_step * step_factor(E, DP54_EXPONENT, 0.9, 0.2, 5.0))
    acc[3], acc[4] = vsup, at_limit
    fout[r, :6] = acc
    iout[r, 0] = k_at
    iout[r, 1] = left
    iout[r, 2] = diverged
    iout[r, 3] = forced
    iout[r, 4] = accepted
    iout[r, 5] = rejected


@njit(types.void(XI_KERNEL, X_KERNEL, I1, I1, F1, I1, F2, F2, F2, F2, F1, F1, F1, F1, F1, F2, F1, I1,
                 F2, F2, I1, F3, F1, I1, F1, I1, F3, F1, F3, F1,
                 F2, I2, F3, F3, F2, F2, F3), nogil=True, **OPTIONS)
def run_batch(exi, ex, dims, off, fprm, iprm, M, L, K, U, atol, scale, lo, hi, centre, cand, tgrid, rows,
              xi0, x0, mode, vtab, rho, dwell, amp, guard, refs, gains, noise, W0,
              fout, iout, vused, recZ, recE, recB, recV):
    """The runs ``rows`` (indices into the per-run arrays); without the GIL, so that threads share the runs.

    Parameters
    ----------
    exi, ex : XI_KERNEL, X_KERNEL
        The design's falsify_xi(z, A) and falsify_x(z, B) (:mod:`ashc_cli.closedloop.falsify_loop`).
    dims : 1-D int64 array (9,)
        [n_hat, n, m, m_hat, p, H (holds), S (reference segments), record, keep_v] (the last two 0 or 1).
    off : 1-D int64 array (22,)
        falsify_loop.layout: the terms' offsets in A, B and wk (indexed by the O_* constants), then the lengths of A, B, wk.
    fprm : 1-D float array (10,)
        [dt (a hold), v_limit, lambda, eps, alpha_h, G, floor, rtol, divergence, lookahead (in holds)].
    iprm : 1-D int64 array (2,)
        [q_ls, sat]: 1 for the least-squares q of eq. (43), else 0; sat as :func:`~ashc_cli.closedloop.laws.saturate`.
    M, L, K, U : 2-D float arrays (n, n), (n, n), (m, n), (m, 2)
        The metric, its Cholesky factor, the feedback gain and the input box.
    atol, scale : 1-D float arrays (n_hat + n,)
        The absolute tolerance per state; the states' scale (a run diverges where |z_i| > divergence scale_i).
    lo, hi, centre : 1-D float arrays (n_hat,)
        V's bounds and its centre.
    cand : 2-D float array (C, m_hat)
        The greedy adversary's unit inputs.
    tgrid : 1-D float array (H + 1,)
        The hold boundaries.
    rows : 1-D int64 array
        The runs to integrate.
    xi0, x0, W0 : float arrays (N, n_hat), (N, n), (N,)
        Per run: the start and W(xi0, x0).
    mode, vtab : int64 array (N,), float array (N, H, m_hat)
        Per run: SETPOINT, TABLE or GREEDY; the input held at each hold (TABLE).
    rho, dwell, amp, guard : arrays (N,), float, int64, float, int64
        Per run: the greedy adversary's weight (rho e^T M e / alpha_h + (1 - rho) |dh/dx e|^2, e = p - x a hold ahead),
        the fewest holds between its switches, its input norm (and the guard's) as a fraction of v_limit; guard != 0:
        a held input that would carry xi out of V is reversed, else turned to V's centre.
    refs, gains, noise : float arrays (N, S, n_hat), (N,), (N, S, m_hat)
        Per run: the set-point law's reference of each segment, its gain and the noise added to v (SETPOINT).
    fout, iout : 2-D float array (N, 6), 2-D int64 array (N, 6)
        Written at the rows ``rows``: [ratio, ratio_late, max_error, vsup, at_limit, largest_bound] and
        [k_at, left_V, diverged, forced, accepted steps, rejected steps].
    vused : 3-D float array (N, H, m_hat), or (0, H, m_hat) without keep_v
        Written with keep_v: the input of each hold.
    recZ, recE, recB, recV : float arrays (N, H + 1, n_hat + n), (N, H + 1), (N, H + 1), (N, H + 1, m_hat), N = 0 without record
        Written with record: z, the error |kappa(xi) - h(x)|, the bound and v at each hold boundary.
    """
    for j in range(rows.size):
        run_one(exi, ex, rows[j], dims, off, fprm, iprm, M, L, K, U, atol, scale, lo, hi, centre, cand, tgrid,
                xi0, x0, mode, vtab, rho, dwell, amp, guard, refs, gains, noise, W0,
                fout, iout, vused, recZ, recE, recB, recV)
