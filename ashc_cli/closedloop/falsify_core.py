"""The runs of ``ashc falsify`` in numba: the batch's laws and adversaries, integrated hold by hold by the engine's
Dormand-Prince 5(4) (:mod:`ashc_cli.closedloop.rk`).

The interface is :mod:`ashc_cli.closedloop.interface`'s; the kernels fill one flat buffer each, which every run
views as the design's terms once (:class:`Terms`).  The arguments travel in three named bundles: :class:`Design`
(the same for every run of a batch), :class:`Starts` (one row per run) and :class:`Outputs` (written).

Design-independent: the per-design kernels reach these functions as numba first-class functions
(:mod:`ashc_cli.closedloop.compiled` prints and caches them); numba caches this module's machine code
(``cache=True``)."""
import math
from collections import namedtuple

import numpy as np
from numba import carray, njit, types
from numba.extending import intrinsic

from ashc_cli.closedloop.interface import apply, feedback_of, q_of, times
from ashc_cli.closedloop.laws import F1, F2, LAW_SIGNATURE, pinv_into, setpoint_direction
from ashc_cli.closedloop.rk import DP54, DP54_EXPONENT, hold

F3 = types.float64[:, :, ::1]
I1 = types.int64[::1]
I2 = types.int64[:, ::1]
#: falsify_xi(z, A) and falsify_x(z, B), z = [xi, x]: A = [phi_bar, delta, l, dp/dxi delta, kappa, p, dp/dxi],
#: B = [f_bar, g, h, dh/dx], matrices row after row (one flat buffer each: few arrays cross a call).
XI_KERNEL = types.FunctionType(types.void(F1, F1))
X_KERNEL = types.FunctionType(types.void(F1, F1))
OPTIONS = dict(cache=True, error_model="numpy")
#: objective(t, z, err, bound, floor): a run's score at a hold boundary where it is active (the largest over the run
#: is its ``ratio``): :func:`bound_ratio` by default; the hook for scoring runs by something else (a task's robustness).
OBJECTIVE_SIGNATURE = types.float64(types.float64, F1, types.float64, types.float64, types.float64)
OBJECTIVE = types.FunctionType(OBJECTIVE_SIGNATURE)
#: A registered abstract controller's law (:data:`~ashc_cli.closedloop.laws.LAW_SIGNATURE`), run by the CONTROLLER
#: runs with the parameters ``Design.lprm`` (z = [xi, x]: falsify carries no w).
LAW = types.FunctionType(LAW_SIGNATURE)

#: How a run chooses v: the random strategy's set-point law, a table held per hold, the greedy adversary, or the
#: spec's registered controller (:mod:`~ashc_cli.closedloop.controllers`) as it is, its norm clipped to v_limit.
SETPOINT, TABLE, GREEDY, CONTROLLER = 0, 1, 2, 3

#: Where each term lives in the flat buffers (indices into ``off``): A holds the xi kernel's output, B the x
#: kernel's, wk the loop's work (row-major matrices).
O_PHI, O_DEL, O_L, O_DPD, O_KAP, O_PM, O_DP, O_FB, O_G, O_H, O_DH, O_KX, O_Q, O_LTG, O_LTD, O_PG, O_DPLUS, O_CORR, O_VIN = range(19)

#: What every run of a batch shares.  dims = [n_hat, n, m, m_hat, p, H (holds), S (reference segments), record,
#: keep_v]; off: falsify_loop.layout; fprm = [dt (a hold), v_limit, lambda, eps, alpha_h, G, floor, rtol, divergence,
#: lookahead (in holds)]; iprm = [q_ls, sat, bw] (:mod:`~ashc_cli.closedloop.interface`; bw: L's lower bandwidth); M, L, K, U: the metric, its
#: Cholesky factor, the feedback gain, the input box; atol and scale per state (a run diverges where |z_i| >
#: divergence scale_i); lo, hi, centre: V's bounds and centre; cand: the greedy adversary's unit inputs (C, m_hat);
#: tgrid: the hold boundaries (H + 1,); lprm: the registered controller's parameters (CONTROLLER runs).
Design = namedtuple("Design", "dims off fprm iprm M L K U atol scale lo hi centre cand tgrid lprm")
DESIGN = types.NamedTuple((I1, I1, F1, I1, F2, F2, F2, F2, F1, F1, F1, F1, F1, F2, F1, F1), Design)
#: One row per run (N runs): the start xi0 (N, n_hat), x0 (N, n) and W0 = W(xi0, x0) (N,); mode SETPOINT, TABLE, GREEDY or
#: GREEDY; vtab (N, H, m_hat) the input held at each hold (TABLE); the greedy adversary's weight rho (it maximises
#: rho e^T M e / alpha_h + (1 - rho) |dh/dx e|^2, e = p - x a hold ahead), the fewest holds between its switches
#: (dwell, int) and its input norm (and the guard's) as a fraction of v_limit (amp); guard != 0: a held input that
#: would carry xi out of V is reversed, else turned to V's centre; refs (N, S, n_hat), gains (N,), noise (N, S, m_hat):
#: the set-point law's reference of each segment, its gain and the noise added to v (SETPOINT).
Starts = namedtuple("Starts", "xi0 x0 mode vtab rho dwell amp guard refs gains noise W0")
STARTS = types.NamedTuple((F2, F2, I1, F3, F1, I1, F1, I1, F3, F1, F3, F1), Starts)
#: Written at each run's row: fout (N, 6) = [ratio, ratio_late, max_error, vsup, at_limit, largest_bound], iout (N, 6)
#: = [k_at, left_V, diverged, forced, accepted steps, rejected steps]; with keep_v, vused (N, H, m_hat) the input of
#: each hold; with record, recZ (N, H + 1, n_hat + n), recE, recB (N, H + 1), recV (N, H + 1, m_hat): z, the error
#: |kappa(xi) - h(x)|, the bound and v at each hold boundary (N = 0 in the arrays not kept).
Outputs = namedtuple("Outputs", "fout iout vused recZ recE recB recV")
OUTPUTS = types.NamedTuple((F2, I2, F3, F3, F2, F2, F3), Outputs)
#: A run's view of the kernels' buffers A, B and its work buffer as the design's terms (made once per run); ``owners``
#: holds the buffers themselves, so that they live as long as the views (which carry no reference count).
Terms = namedtuple("Terms", "phi delta l dpd kap pm dp fb g h dh kx q ltg ltd pg dplus corr vin qv owners")
#: A run's scratch arrays.
Work = namedtuple("Work", "u dxi dxi_r dx ee vc choice plan0 neg")


@intrinsic
def _address(typingctx, buf, o):
    """The address of buf[o] (a pointer numba's ``carray`` can view)."""
    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.gep(ary.data, [args[1]])
    return types.CPointer(buf.dtype)(buf, o), codegen


@njit(inline="always", **OPTIONS)
def _vec(buf, o, r):
    """buf[o:o + r] as a view that carries no reference count: ``buf`` must outlive it (:class:`Terms` holds the
    run's buffers for its views; numba frees an array after the last use of its variable, not at the end of the scope).
    Views of the buffer itself cost falsify's 3000 Cuk runs 2.2x the time: every call that binds one pays an
    atomic increment and decrement of the buffer's count, and the interface's calls bind twenty."""
    return carray(_address(buf, o), r)


@njit(inline="always", **OPTIONS)
def _mat(buf, o, r, c):
    """The r x c matrix stored row after row at buf[o:], as a view without a reference count (as :func:`_vec`)."""
    return carray(_address(buf, o), (r, c))


@njit(**OPTIONS)
def _views(D, A, B, wk, qv):
    """The run's :class:`Terms`: A, B and wk viewed at the offsets of ``D.off`` (qv: the run's own q v)."""
    nh, n, m, mh, p = D.dims[0], D.dims[1], D.dims[2], D.dims[3], D.dims[4]
    o = D.off
    return Terms(_vec(A, o[O_PHI], nh), _mat(A, o[O_DEL], nh, mh), _vec(A, o[O_L], m), _mat(A, o[O_DPD], n, mh),
                 _vec(A, o[O_KAP], p), _vec(A, o[O_PM], n), _mat(A, o[O_DP], n, nh),
                 _vec(B, o[O_FB], n), _mat(B, o[O_G], n, m), _vec(B, o[O_H], p), _mat(B, o[O_DH], p, n),
                 _vec(wk, o[O_KX], m), _mat(wk, o[O_Q], m, mh), _mat(wk, o[O_LTG], n, m), _mat(wk, o[O_LTD], n, mh),
                 _mat(wk, o[O_PG], m, n), _mat(wk, o[O_DPLUS], mh, nh), _vec(wk, o[O_CORR], m),
                 _vec(wk, o[O_VIN], mh), _vec(qv, 0, m), (A, B, wk, qv))


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


@njit(inline="always", **OPTIONS)
def _terms(exi, ex, z, x, A, B, T, D):
    """The closed loop at z = [xi, x] (x the view z[n_hat:]) that does not depend on v (strategies._interface): the
    kernels into A and B; K (x - p) and q (eq. (43), or 0) into T.kx and T.q."""
    exi(z, A)
    ex(z, B)
    feedback_of(D.K, x, T.pm, T.kx)
    q_of(D.L, D.iprm[2], T.g, T.dpd, D.iprm[0], T.q, T.ltg, T.ltd, T.pg)


@njit(inline="always", **OPTIONS)
def _apply(T, D, v, u, dxi, dx):
    """u = SAT(l + K (x - p) + q v) (the interface), xi' = phi_bar + delta v, x' = f_bar + g u."""
    times(T.q, v, T.qv)
    apply(T.l, T.kx, T.qv, 1.0, D.U, D.iprm[1], T.corr, u)
    times(T.delta, v, dxi)
    for i in range(dxi.size):
        dxi[i] = T.phi[i] + dxi[i]
    times(T.g, u, dx)
    for i in range(dx.size):
        dx[i] = T.fb[i] + dx[i]


@njit(inline="always", **OPTIONS)
def _setpoint_v(z, T, ref, gain, noise, v_limit, v):
    """The random strategy's law: v = delta^+ (gain (ref - xi) - phi_bar) + noise, its norm clipped to v_limit."""
    pinv_into(T.delta, T.dplus)
    setpoint_direction(T.dplus, T.phi, z, ref, gain, v)
    for a in range(v.size):
        v[a] = v[a] + noise[a]
    _clip_norm(v, v_limit)


@njit(inline="always", **OPTIONS)
def _clip_norm(v, v_limit):
    """v scaled down to |v| <= v_limit (the limit the bound is certified for)."""
    shrink = min(1.0, v_limit / max(_norm(v), 1e-300))
    for a in range(v.size):
        v[a] *= shrink


@njit(inline="always", **OPTIONS)
def _controller_v(t, z, T, ref, law, lprm, v_limit, v):
    """A CONTROLLER run's v: the registered law at (t, z = [xi, x]) with the segment's reference, |v| clipped to
    v_limit."""
    law(t, z, ref, T.phi, T.delta, lprm, v)
    _clip_norm(v, v_limit)


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
def _greedy(T, D, W, Z, amp, rho, guarded, k, last_switch, prev, v_plan):
    """The greedy adversary at hold k (the terms T at Z): among the candidates of norm ``amp`` (those that keep xi in
    V when ``guarded``), the one that maximises the one-hold look-ahead of rho W / alpha_h + (1 - rho) |dh/dx e|^2,
    e = p - x, into v_plan (NaN when none is allowed); ties keep the previous input.  Returns the hold of the last
    switch."""
    nh, n, mh, p = D.dims[0], D.dims[1], D.dims[3], D.dims[4]
    M, cand, alpha_h, dt, lookahead = D.M, D.cand, D.fprm[4], D.fprm[0], D.fprm[9]
    vc, u, dxi, dx, ee, choice = W.vc, W.u, W.dxi, W.dx, W.ee, W.choice
    best = -np.inf
    for a in range(mh):
        choice[a] = 0.0
    for c in range(cand.shape[0]):
        for a in range(mh):
            vc[a] = cand[c, a] * amp
        _apply(T, D, vc, u, dxi, dx)
        for i in range(n):
            s = 0.0
            for j in range(nh):
                s += T.dp[i, j] * dxi[j]
            ee[i] = (T.pm[i] - Z[nh + i]) + dt * (s - dx[i])
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
                s += T.dh[i, j] * ee[j]
            out2 += s * s
        J = rho * quad / alpha_h + (1 - rho) * out2
        if guarded and not _stays(Z, dxi, lookahead * dt, D.lo, D.hi):
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
def _output_error(T):
    """|psi - y| = |kappa(xi) - h(x)| from the run's terms."""
    err = 0.0
    for i in range(T.kap.size):
        err += (T.kap[i] - T.h[i]) ** 2
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


@njit(OBJECTIVE_SIGNATURE, **OPTIONS)
def bound_ratio(t, z, err, bound, floor):
    """The default objective: (|psi - y| - floor) / bound (Theorem 2's bound), 0 below the floor, inf where the bound
    is 0 and the error is not.

    Parameters
    ----------
    t : float
    z : 1-D float array
        [xi, x] (not read).
    err, bound, floor : float
        |kappa(xi) - h(x)|, the guaranteed bound and the floor of the integrator's accuracy.
    """
    if err > floor:
        return (err - floor) / max(bound, 1e-300) if bound > 0 else np.inf
    return 0.0


@njit(inline="always", **OPTIONS)
def _account(k, k_at, score, active, err, bound, acc):
    """Sample k into the run's tallies ``acc`` (fout's row: the largest score, the largest after t = 0, the largest
    error and, at acc[5], bound while the run is active); the sample of the largest score is returned.  A local
    row, copied to fout at the end: threads writing neighbouring rows of fout every hold share cache lines."""
    ratio = score if active else 0.0
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
def _guard(T, D, W, Z, step, v_max, v_plan):
    """The guard of a held input: v_plan is kept if it keeps xi in V over ``step``, else reversed, else turned to
    V's centre at |v| = v_max (NaN entries count as 0)."""
    nh, mh = D.dims[0], D.dims[3]
    plan0, neg = W.plan0, W.neg
    any_nan = False
    for a in range(mh):
        plan0[a] = v_plan[a]
        if v_plan[a] != v_plan[a]:
            any_nan = True
    _nan_to_num(plan0)
    _apply(T, D, plan0, W.u, W.dxi, W.dx)
    if not any_nan and _stays(Z, W.dxi, step, D.lo, D.hi):
        return
    nonzero = False
    for a in range(mh):
        neg[a] = -plan0[a]
        if plan0[a] != 0:
            nonzero = True
    _apply(T, D, neg, W.u, W.dxi_r, W.dx)
    if nonzero and _stays(Z, W.dxi_r, step, D.lo, D.hi):
        for a in range(mh):
            v_plan[a] = neg[a]
        return
    pinv_into(T.delta, T.dplus)
    nin = 0.0
    for a in range(mh):
        s = 0.0
        for i in range(nh):
            s += T.dplus[a, i] * (D.centre[i] - Z[i])
        T.vin[a] = s
        nin += s * s
    nin = math.sqrt(nin)
    for a in range(mh):
        v_plan[a] = T.vin[a] * (v_max / max(nin, 1e-300))


#: The step control of a hold (rk.hold): the least step as a fraction of the hold (accepted by force), and the
#: safety factor and the bounds of a step's change.
H_MIN_HOLDS, SAFETY, MIN_FACTOR, MAX_FACTOR = 1.0 / 4096.0, 0.9, 0.2, 5.0


@njit(inline="always", **OPTIONS)
def _v1(a):
    """The whole 1-D array ``a`` as a view without a reference count (:func:`_vec`; ``a`` must outlive it)."""
    return _vec(a, 0, a.size)


@njit(inline="always", **OPTIONS)
def _v2(a):
    """The whole 2-D (C-order) array ``a`` as a view without a reference count (:func:`_mat`)."""
    return _mat(a, 0, a.shape[0], a.shape[1])


@njit(inline="always", **OPTIONS)
def _stage_context(exi, ex, A, B, T, D, W, law):
    """rk.hold's ctx for :func:`_stage`, every array in it a view without a reference count: the engine unpacks
    the context at every stage, and with the arrays themselves each paid its count (1.53x the time of a campaign).
    The arrays are the run's, alive for the whole hold (A, B, T, W, the law's v) or the caller's (D, the starts)."""
    Dv = Design(_v1(D.dims), _v1(D.off), _v1(D.fprm), _v1(D.iprm), _v2(D.M), _v2(D.L), _v2(D.K), _v2(D.U), _v1(D.atol),
                _v1(D.scale), _v1(D.lo), _v1(D.hi), _v1(D.centre), _v2(D.cand), _v1(D.tgrid), _v1(D.lprm))
    Wv = Work(_v1(W.u), _v1(W.dxi), _v1(W.dxi_r), _v1(W.dx), _v1(W.ee), _v1(W.vc), _v1(W.choice), _v1(W.plan0), _v1(W.neg))
    Tv = Terms(T.phi, T.delta, T.l, T.dpd, T.kap, T.pm, T.dp, T.fb, T.g, T.h, T.dh, T.kx, T.q, T.ltg, T.ltd, T.pg, T.dplus,
               T.corr, T.vin, T.qv, 0)
    md, ref, gain, nz, v_limit, v, v_now, kernel = law
    return (exi, ex, _v1(A), _v1(B), Tv, Dv, Wv, (md, _v1(ref), gain, _v1(nz), v_limit, _v1(v), _v1(v_now), kernel))


@njit(inline="always", **OPTIONS)
def _derivative(t, z, K, row, T, D, W, law):
    """[xi', x'] at (t, z) into K[row] (non-finite entries 0), the terms T already at z: the input is the set-point
    law or the registered controller at z, or the held v (law = (mode, ref, gain, noise, v_limit, v, v_now, kernel))."""
    md, ref, gain, nz, v_limit, v, v_now, kernel = law
    nh, n = D.dims[0], D.dims[1]
    if md == SETPOINT:
        _setpoint_v(z, T, ref, gain, nz, v_limit, v)
    elif md == CONTROLLER:
        _controller_v(t, z, T, ref, kernel, D.lprm, v_limit, v)
    else:
        for a in range(v.size):
            v[a] = v_now[a]
    _apply(T, D, v, W.u, W.dxi, W.dx)
    for i in range(nh):
        K[row, i] = W.dxi[i] if math.isfinite(W.dxi[i]) else 0.0
    for i in range(n):
        K[row, nh + i] = W.dx[i] if math.isfinite(W.dx[i]) else 0.0


@njit(inline="always", **OPTIONS)
def _stage(t, y, K, row, ctx):
    """rk.hold's call: the terms at the stage y, then :func:`_derivative` (ctx = (exi, ex, A, B, T, D, W, law))."""
    exi, ex, A, B, T, D, W, law = ctx
    _terms(exi, ex, y, _vec(y, D.dims[0], D.dims[1]), A, B, T, D)
    _derivative(t, y, K, row, T, D, W, law)


@njit(inline="always", **OPTIONS)
def _held_v(T, D, W, Z, S, r, k, active, last_switch, prev, v_plan):
    """v_plan: the input run r holds over hold k (TABLE or GREEDY), the greedy adversary's choice and the guard
    applied; returns the adversary's last switch (prev: its choice, kept for dwell holds after a switch)."""
    v_limit, dt, lookahead = D.fprm[1], D.fprm[0], D.fprm[9]
    greedy, guarded = S.mode[r] == GREEDY, S.guard[r] != 0
    v_plan[:] = S.vtab[r, k]
    if greedy and not (active and k - last_switch >= S.dwell[r]):
        v_plan[:] = prev                          # the adversary keeps its choice for dwell holds after a switch
    elif greedy:
        last_switch = _greedy(T, D, W, Z, v_limit * S.amp[r], S.rho[r], guarded, k, last_switch, prev, v_plan)
    if guarded and active:                        # out of V: the input reversed, else turned to V's centre
        _guard(T, D, W, Z, lookahead * dt, v_limit * S.amp[r], v_plan)
    _nan_to_num(v_plan)
    if greedy:
        prev[:] = v_plan
    return last_switch


@njit(**OPTIONS)
def run_one(exi, ex, objective, kernel, r, D, S, O):
    """Run r, hold by hold, with its own step-size control: the error / bound ratio at each hold boundary, xi in V.

    Parameters
    ----------
    r : int, the run: its row of the per-run arrays and of the outputs; the other arguments as :func:`run_batch`."""
    dims, fprm = D.dims, D.fprm
    nh, n, m, mh, H, SEG, record, keep_v = dims[0], dims[1], dims[2], dims[3], dims[5], dims[6], dims[7], dims[8]
    dt, v_limit, lam, eps, alpha_h, G, floor, diverge = fprm[0], fprm[1], fprm[2], fprm[3], fprm[4], fprm[5], fprm[6], fprm[8]
    d = nh + n
    A, B, wk = np.empty(D.off[19]), np.empty(D.off[20]), np.empty(D.off[21])     # the kernels' buffers and the loop's work
    T = _views(D, A, B, wk, np.empty(m))
    W = Work(np.empty(m), np.empty(nh), np.empty(nh), np.empty(n), np.empty(n), np.empty(mh), np.empty(mh), np.empty(mh), np.empty(mh))
    v, v_plan = np.empty(mh), np.empty(mh)
    v_now, prev = np.zeros(mh), np.zeros(mh)
    Z, Zs, zs, z_new, ks = np.empty(d), np.empty(d), np.empty(d), np.empty(d), np.empty((DP54[0].shape[0], d))
    xs = Zs[nh:]                              # x of the hold start (a view made once)
    for i in range(nh):
        Z[i] = S.xi0[r, i]
    for i in range(n):
        Z[nh + i] = S.x0[r, i]
    md = S.mode[r]
    held = md == TABLE or md == GREEDY
    w0 = S.W0[r]
    gain = S.gains[r]
    active = True
    left = 0
    diverged = 0
    vsup = 0.0
    at_limit = 0.0
    forced = 0
    accepted = 0
    rejected = 0
    control = (dt * H_MIN_HOLDS, dt, SAFETY, MIN_FACTOR, MAX_FACTOR)
    tol = (fprm[7], D.atol)
    last_switch = -(10 ** 9)
    acc = np.zeros(6)                # ratio, ratio_late, max_err, vsup, at_limit, largest_bound (fout's row)
    k_at = 0
    h_step = dt
    for k in range(H + 1):
        seg = min(k * SEG // H, SEG - 1)
        ref = S.refs[r, seg]
        nz = S.noise[r, seg]
        finite, inside = _state_checks(Z, nh, D.scale, diverge, D.lo, D.hi)
        if active and not finite:
            diverged = 1
        active = active and finite
        if active and not inside:
            left = 1
        active = active and inside
        for i in range(d):
            Zs[i] = Z[i] if math.isfinite(Z[i]) else 0.0
        _terms(exi, ex, Zs, xs, A, B, T, D)
        err = _output_error(T)

        v_now[:] = 0.0
        if k < H and held:
            last_switch = _held_v(T, D, W, Z, S, r, k, active, last_switch, prev, v_plan)
            v_now[:] = v_plan
        elif md == SETPOINT:
            _setpoint_v(Zs, T, ref, gain, nz, v_limit, v_now)
        elif md == CONTROLLER:
            _controller_v(D.tgrid[k], Zs, T, ref, kernel, D.lprm, v_limit, v_now)
        if k < H and keep_v:
            for a in range(mh):
                O.vused[r, k, a] = v_now[a]
        vn = _norm(v_now)
        if active:
            vsup = max(vsup, vn)
            if vn >= v_limit * (1 - 1e-9):
                at_limit += 1.0
        bound = math.sqrt(w0 * math.exp(-(lam - eps) * D.tgrid[k]) / alpha_h) + G * vsup
        k_at = _account(k, k_at, objective(D.tgrid[k], Z, err, bound, floor) if active else 0.0, active, err, bound, acc)
        if record:
            _record(r, k, Z, err, bound, v_now, O.recZ, O.recE, O.recB, O.recV)
        if k == H:
            break
        if not active:
            continue

        # the hold: its first stage at the hold's start, with the terms of the hold-start check (the same point)
        law = (md, ref, gain, nz, v_limit, v, v_now, kernel)
        _derivative(D.tgrid[k], Z, ks, 0, T, D, W, law)
        h_step, n_acc, n_rej, n_forced = hold(_stage, _stage_context(exi, ex, A, B, T, D, W, law), (DP54, DP54_EXPONENT),
                                             (D.tgrid[k], D.tgrid[k + 1]), Z, h_step, control, (ks, zs, z_new), tol)
        accepted += n_acc
        rejected += n_rej
        forced += n_forced
    acc[3], acc[4] = vsup, at_limit
    O.fout[r, :6] = acc
    O.iout[r, 0] = k_at
    O.iout[r, 1] = left
    O.iout[r, 2] = diverged
    O.iout[r, 3] = forced
    O.iout[r, 4] = accepted
    O.iout[r, 5] = rejected


@njit(types.void(XI_KERNEL, X_KERNEL, OBJECTIVE, LAW, DESIGN, STARTS, I1, OUTPUTS), nogil=True, **OPTIONS)
def run_batch(exi, ex, objective, law, design, starts, rows, outputs):
    """The runs ``rows`` (indices into the per-run arrays); without the GIL, so that threads share the runs.

    Parameters
    ----------
    exi, ex : XI_KERNEL, X_KERNEL
        The design's falsify_xi(z, A) and falsify_x(z, B) (:mod:`ashc_cli.closedloop.falsify_loop`).
    objective : OBJECTIVE
        A run's score at each hold boundary (:func:`bound_ratio`, or another of the signature).
    law : LAW
        The registered controller the CONTROLLER runs close the loop with (any law where no run is one).
    design : Design
        What every run shares (:class:`Design`).
    starts : Starts
        Per run: its start, its law and its adversary (:class:`Starts`).
    rows : 1-D int64 array
        The runs to integrate.
    outputs : Outputs
        Written at the rows ``rows`` (:class:`Outputs`).
    """
    for j in range(rows.size):
        run_one(exi, ex, objective, law, rows[j], design, starts, outputs)
