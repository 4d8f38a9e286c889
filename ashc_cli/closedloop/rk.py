"""The one Runge-Kutta engine of the closed loops: explicit embedded pairs as tableaus (data), one step, one error
norm, one step-size rule, dense output, a terminal event's root and a driver over sample times.

A tableau is the tuple ``(A, B, C, E, E3, D)`` of scipy's coefficients: DOP853 (E = E5, its second estimate E3,
D its dense output) or Dormand-Prince 5(4) (E3 empty, D = P).  The loop's right-hand side reaches the engine as
``call(t, y, K, row, ctx)`` (f(t, y) into K[row]), an inline adapter with the loop's arguments in the tuple ``ctx``; every function here is
inlined into its caller, so the compiled cores (tracking, governor, m-relation, falsify) are one engine
specialised for each loop, and numba still caches them (docs/guide.md, "Compiled closed loops").
"""
import math

import numpy as np
from numba import njit
from scipy.integrate._ivp import dop853_coefficients as _dop853, rk as _rk

__all__ = ["DOP853", "DP54", "RK4", "fixed_step", "stage_input", "stage_time", "attempt", "error_norm", "step_factor", "initial_step", "dense_prepare", "dense_eval",
           "event_root", "solve"]

INLINE = dict(inline="always", cache=True, error_model="numpy")


def _square(a: np.ndarray, size: int) -> np.ndarray:
    out = np.zeros((size, size))
    out[:a.shape[0], :a.shape[1]] = a
    return out


#: scipy's DOP853 (8th order, error estimates of orders 5 and 3, 7th-order dense output from three extra stages).
DOP853 = tuple(np.ascontiguousarray(a, dtype=float) for a in (_dop853.A, _dop853.B, _dop853.C, _dop853.E5, _dop853.E3, _dop853.D))
#: scipy's RK45, Dormand-Prince 5(4) (the 5th-order solution is the last stage, FSAL; 4th-order dense output).
DP54 = tuple(np.ascontiguousarray(a, dtype=float) for a in (_square(_rk.RK45.A, 7), _rk.RK45.B, _rk.RK45.C, _rk.RK45.E,
                                                             np.zeros(0), _rk.RK45.P))
#: The classical Runge-Kutta method of order 4, for plans stepped on a fixed grid in numpy (:func:`fixed_step`):
#: (A, weights, divisor), y_new = y + h / 6 (k1 + 2 k2 + 2 k3 + k4), the weights kept whole over their divisor so
#: that the sum is the textbook one, term by term.
RK4 = (np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 1.0]]), np.array([1.0, 2.0, 2.0, 1.0]), 6.0)
#: -1 / (order of the error estimate + 1), the exponent of the step-size rule.
DOP853_EXPONENT = -1.0 / 8.0
DP54_EXPONENT = -1.0 / 5.0


@njit(**INLINE)
def _combine(K, A, row, s, h, y, out):
    """out = y + (sum_{j < s} A[row, j] K[j]) h (no row views: a view's reference count costs a third of a
    falsify run)."""
    for i in range(y.size):
        acc = 0.0
        for j in range(s):
            acc += K[j, i] * A[row, j]
        out[i] = y[i] + acc * h


@njit(**INLINE)
def _combine_b(K, b, s, h, y, out):
    """out = y + (sum_{j < s} b[j] K[j]) h."""
    for i in range(y.size):
        acc = 0.0
        for j in range(s):
            acc += K[j, i] * b[j]
        out[i] = y[i] + acc * h


@njit(**INLINE)
def stage_input(tab, s, h, y, K, out):
    """Where stage s of a step of size h from y is evaluated: y + h sum_{j < s} A[s, j] K[j], for s = 1 .. n_stages
    (s = n_stages: the solution y_new, whose slope is the next step's first stage).

    Parameters
    ----------
    tab : tuple
        The tableau (A, B, C, E, E3, D).
    s : int
    h : float
    y : 1-D array
        The state at the step's start.
    K : 2-D array
        The stages' slopes, row j for stage j (rows below s filled).
    out : 1-D array
        Filled with the stage's state.
    """
    ns = tab[1].size
    if s == ns:
        _combine_b(K, tab[1], ns, h, y, out)
    else:
        _combine(K, tab[0], s, s, h, y, out)


@njit(**INLINE)
def stage_time(tab, s, t, h):
    """The time of stage s (t + h for s = n_stages).

    Parameters
    ----------
    tab : tuple
    s : int
    t, h : float
        The step's start and size.
    """
    return t + h if s == tab[1].size else t + tab[2][s] * h


@njit(**INLINE)
def attempt(call, ctx, tab, t, y, h, K, ys, y_new):
    """One step of size h from (t, y) with K[0] = f(t, y) given: K[1 .. s-1], y_new and K[s] = f(t + h, y_new)
    (the first stage of the next step); returns the number of evaluations (s).  ``call(t, y, K, row, ctx)``
    writes f(t, y) into K[row].  (A loop whose right-hand side is cheap writes these lines out with
    :func:`stage_input`: unpacking ``ctx`` at every stage costs a reference count per array.)

    Parameters
    ----------
    call : inline njit function
    ctx : tuple
        The loop's arguments, passed to ``call``.
    tab : tuple
    t, h : float
    y : 1-D array
    K : 2-D array
        Rows 0 .. n_stages used.
    ys, y_new : 1-D array
        Work array of the stages; the solution.
    """
    ns = tab[1].size
    for s in range(1, ns):
        stage_input(tab, s, h, y, K, ys)
        call(stage_time(tab, s, t, h), ys, K, s, ctx)
    stage_input(tab, ns, h, y, K, y_new)
    call(t + h, y_new, K, ns, ctx)
    return ns


@njit(**INLINE)
def error_norm(tab, K, h, y, y_new, atol, rtol):
    """The step's error in the RMS norm scaled by atol[i] + rtol max(|y_i|, |y_new_i|): scipy's for DOP853 (its two
    estimates), else |h E K / scale|.

    Parameters
    ----------
    tab : tuple
    K : 2-D array
        The step's stages, the slope at y_new included.
    h : float
    y, y_new : 1-D array
    atol : 1-D array
        Absolute tolerance per component.
    rtol : float
    """
    E, E3 = tab[3], tab[4]
    d = y.size
    ns = E.size
    if E3.size > 0:
        e5 = 0.0
        e3 = 0.0
        for i in range(d):
            sc = atol[i] + max(abs(y[i]), abs(y_new[i])) * rtol
            a5 = 0.0
            a3 = 0.0
            for j in range(ns):
                a5 += K[j, i] * E[j]
                a3 += K[j, i] * E3[j]
            a5 /= sc
            a3 /= sc
            e5 += a5 * a5
            e3 += a3 * a3
        if e5 == 0 and e3 == 0:
            return 0.0
        return abs(h) * e5 / np.sqrt((e5 + 0.01 * e3) * d)
    e2 = 0.0
    for i in range(d):
        acc = 0.0
        for j in range(ns):
            acc += E[j] * K[j, i]
        sc = atol[i] + rtol * max(abs(y[i]), abs(y_new[i]))
        e2 += (h * acc / sc) ** 2
    return np.sqrt(e2 / d)


@njit(**INLINE)
def step_factor(err, exponent, safety, lo, hi):
    """The next step over this one: safety err^exponent within [lo, hi] (hi at err = 0; lo when it is NaN).

    Parameters
    ----------
    err : float
        The step's error (:func:`error_norm`).
    exponent : float
        -1 / (order of the error estimate + 1).
    safety, lo, hi : float
    """
    if err == 0:
        return hi
    factor = safety * err ** exponent
    if not (factor > lo):
        return lo
    if not (factor < hi):
        return hi
    return factor


@njit(**INLINE)
def initial_step(call, ctx, t, y, K, t_bound, rtol, atol, exponent, y1, F1):
    """scipy's select_initial_step from f = K[0] (one evaluation of the right-hand side, into F1[0]).

    Parameters
    ----------
    call, ctx
        As :func:`attempt`.
    t, t_bound : float
    y : 1-D array
    K : 2-D array
        K[0] = f(t, y).
    rtol : float
    atol : 1-D array
    exponent : float
    y1 : 1-D array
        Work array.
    F1 : 2-D array (1, len(y))
        Work array.
    """
    d = y.size
    interval = abs(t_bound - t)
    d0 = 0.0
    d1 = 0.0
    for i in range(d):
        sc = atol[i] + abs(y[i]) * rtol
        d0 += (y[i] / sc) ** 2
        d1 += (K[0, i] / sc) ** 2
    d0 = np.sqrt(d0) / np.sqrt(d)
    d1 = np.sqrt(d1) / np.sqrt(d)
    if d0 < 1e-5 or d1 < 1e-5:
        h0 = 1e-6
    else:
        h0 = 0.01 * d0 / d1
    h0 = min(h0, interval)
    for i in range(d):
        y1[i] = y[i] + h0 * K[0, i]
    call(t + h0, y1, F1, 0, ctx)
    d2 = 0.0
    for i in range(d):
        d2 += ((F1[0, i] - K[0, i]) / (atol[i] + abs(y[i]) * rtol)) ** 2
    d2 = np.sqrt(d2) / np.sqrt(d) / h0
    if d1 <= 1e-15 and d2 <= 1e-15:
        h1 = max(1e-6, h0 * 1e-3)
    else:
        h1 = (0.01 / max(d1, d2)) ** (-exponent)
    return min(100 * h0, h1, interval)


@njit(**INLINE)
def dense_prepare(call, ctx, tab, t_old, h, y, y_new, K, ys, F):
    """The dense output of the step from (t_old, y) to y_new, into F; returns the evaluations it cost (DOP853's
    three extra stages).

    Parameters
    ----------
    call, ctx, tab
        As :func:`attempt`.
    t_old, h : float
    y, y_new : 1-D array
    K : 2-D array
        The step's stages (DOP853's extra ones are added).
    ys : 1-D array
        Work array.
    F : 2-D array (7, len(y))
        The polynomial's coefficients.
    """
    A, C, D = tab[0], tab[2], tab[5]
    d = y.size
    ns = tab[1].size
    if tab[4].size == 0:                       # Q = K^T P: y(t_old + x h) = y + h sum_r Q_r x^(r + 1)
        for r in range(D.shape[1]):
            for i in range(d):
                acc = 0.0
                for j in range(ns + 1):
                    acc += K[j, i] * D[j, r]
                F[r, i] = acc
        return 0
    n_ext = A.shape[0]
    for s in range(ns + 1, n_ext):
        _combine(K, A, s, s, h, y, ys)
        call(t_old + C[s] * h, ys, K, s, ctx)
    for i in range(d):
        dlt = y_new[i] - y[i]
        F[0, i] = dlt
        F[1, i] = h * K[0, i] - dlt
        F[2, i] = 2 * dlt - h * (K[ns, i] + K[0, i])
    for r in range(D.shape[0]):
        for i in range(d):
            acc = 0.0
            for j in range(n_ext):
                acc += D[r, j] * K[j, i]
            F[3 + r, i] = h * acc
    return n_ext - ns - 1


@njit(**INLINE)
def dense_eval(tab, F, y, h, x, out):
    """The dense output at t_old + x h (scipy's order of operations).

    Parameters
    ----------
    tab : tuple
    F : 2-D array
        From :func:`dense_prepare`.
    y : 1-D array
        The state at t_old.
    h, x : float
    out : 1-D array
    """
    d = y.size
    if tab[4].size == 0:
        R = tab[5].shape[1]
        for i in range(d):
            acc = 0.0
            p = 1.0
            for r in range(R):
                p *= x
                acc += F[r, i] * p
            out[i] = h * acc + y[i]
        return
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


@njit(**INLINE)
def event_root(event, ectx, tab, F, y, t_old, t, z):
    """The time in [t_old, t] where event(z, ectx) crosses zero on the dense output: scipy.optimize.brentq (its C
    code, xtol = rtol = 4 eps, 100 iterations) as solve_ivp's solve_event_equation calls it; z = the state there.

    Parameters
    ----------
    event : inline njit function
        event(z, ectx), a float.
    ectx : tuple
    tab : tuple
    F : 2-D array
        The step's dense output.
    y : 1-D array
        The state at t_old.
    t_old, t : float
    z : 1-D array
        Filled with the state at the root.
    """
    xtol = 4 * 2.220446049250313e-16     # scipy: 4 * np.finfo(float).eps
    rtol = xtol
    hs = t - t_old
    xpre = t_old
    xcur = t
    dense_eval(tab, F, y, hs, (xpre - t_old) / hs, z)
    fpre = event(z, ectx)
    dense_eval(tab, F, y, hs, (xcur - t_old) / hs, z)
    fcur = event(z, ectx)
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
            dense_eval(tab, F, y, hs, (xcur - t_old) / hs, z)
            fcur = event(z, ectx)
        root = xcur
    dense_eval(tab, F, y, hs, (root - t_old) / hs, z)
    return root


@njit(**INLINE)
def _advance(call, ctx, method, span, y, h_abs, min_step, work, tol):
    """scipy's RungeKutta._step_impl: attempts from h_abs until one is accepted; returns (accepted, t_new, h, the
    next h_abs, evaluations), not accepted when the step fell below min_step.  method = (tab, exponent), span =
    (t, t_bound), work = (K, ys, y_new), tol = (rtol, atol) (as :func:`solve`)."""
    (tab, exponent), (t, t_bound), (K, ys, y_new), (rtol, atol) = method, span, work, tol
    SAFETY = 0.9
    MIN_FACTOR = 0.2
    MAX_FACTOR = 10.0
    rejected = False
    nfev = 0
    while True:
        if not (h_abs >= min_step):        # scipy: h_abs < min_step (a NaN step, where scipy loops for ever, fails too)
            return False, t, 0.0, h_abs, nfev
        t_new = t + h_abs
        if t_new - t_bound > 0:
            t_new = t_bound
        h = t_new - t
        h_abs = abs(h)
        nfev += attempt(call, ctx, tab, t, y, h, K, ys, y_new)
        err = error_norm(tab, K, h, y, y_new, atol, rtol)
        factor = step_factor(err, exponent, SAFETY, MIN_FACTOR, MAX_FACTOR)
        if err < 1:
            if rejected and not (factor < 1.0):
                factor = 1.0
            return True, t_new, h, h_abs * factor, nfev
        rejected = True
        h_abs *= factor


@njit(**INLINE)
def hold(call, ctx, method, span, y, h, control, work, tol):
    """Integrate y from span[0] to span[1] (one hold of falsify, whose input changes at its ends) with a step control
    of its own: a step of h_min is accepted even when its error exceeds the tolerance (``forced``: a run whose
    interface kinks would otherwise stall), a non-finite error norm counts as 0 (the caller's state checks stop a
    diverged run), and a step cut within the hold grows back to the one before the cut when its error was at
    most 0.5 (the hold's end is not the run's).  K[0] must hold f(span[0], y) (FSAL: it holds f at the end on
    return).

    Parameters
    ----------
    call, ctx
        As :func:`attempt`.
    method : (tab, exponent)
    span : (float, float)
        (t, t_end).
    y : 1-D array
        The state at t; written: at t_end.
    h : float
        The first step to try.
    control : (float, float, float, float, float)
        (h_min, h_max, safety, min_factor, max_factor) of :func:`step_factor`.
    work : (K, ys, y_new)
        As :func:`attempt`.
    tol : (float, 1-D array)
        (rtol, atol per component).

    Returns
    -------
    h, accepted, rejected, forced : float, int, int, int
        The step to try next, and the steps accepted, rejected and accepted by force.
    """
    (tab, exponent), (t, t_end), (K, ys, y_new), (rtol, atol), (h_min, h_max, safety, lo, hi) = method, span, work, tol, control
    ns = tab[1].size
    accepted = 0
    rejected = 0
    forced = 0
    while t < t_end - 1e-14 * max(1.0, t_end):
        h_nat = h
        h = min(h, t_end - t)
        attempt(call, ctx, tab, t, y, h, K, ys, y_new)
        E = error_norm(tab, K, h, y, y_new, atol, rtol)
        if not math.isfinite(E):
            E = 0.0
        if E <= 1.0 or h <= h_min:
            if E > 1.0:
                forced += 1
            accepted += 1
            for i in range(y.size):
                y[i] = y_new[i]
                K[0, i] = K[ns, i]
            t += h
            h = h * step_factor(E, exponent, safety, lo, hi)
            restore = h_nat if (h < h_nat and E <= 0.5) else 0.0
            h = min(max(h, h_min, restore), h_max)
        else:
            rejected += 1
            h = max(h_min, h * step_factor(E, exponent, safety, lo, hi))
    return h, accepted, rejected, forced


@njit(**INLINE)
def solve(call, ctx, event, ectx, watch, method, span, y, samples, tol, out, hit):
    """solve_ivp(call, (t, t_bound), y, t_eval=t_eval[i_eval:i_end], max_step = inf) with at most one terminal
    event (direction -1, watched when ``watch``): scipy's RungeKutta step for step.

    The span must run forward (t <= t_bound; a backward one fails at once); on a span of length zero every
    sample is the start.  The samples are written to the same rows of ``out``; y is left at t_bound.  Returns (status, rows written,
    evaluations, accepted steps): status 0 on success, 1 at the event (hit = [t, z] there), -1 when the step fell
    below ten times the spacing of floating-point numbers (scipy's failure), -2 at a sample that is not finite.

    Parameters
    ----------
    call, ctx
        As :func:`attempt`.
    event, ectx
        As :func:`event_root`.
    watch : bool
    method : tuple
        (tab, exponent): the tableau (:data:`DOP853` or :data:`DP54`) and its step-size exponent.
    span : tuple
        (t, t_bound), floats.
    y : 1-D array
    samples : tuple
        (t_eval, i_eval, i_end): the sample times and the rows of t_eval (and out) of this run.
    tol : tuple
        (rtol, atol): a float and a 1-D array.
    out : 2-D array
    hit : 1-D array (1 + len(y))
    """
    (tab, exponent), (t, t_bound), (t_eval, i_eval, i_end), (rtol, atol) = method, span, samples, tol
    d = y.size
    ns = tab[1].size
    K = np.empty((tab[0].shape[0], d))
    F1 = np.empty((1, d))
    ys = np.empty(d)
    yk = np.empty(d)
    y_new = np.empty(d)
    F = np.empty((7, d))
    steps = 0
    written = i_eval
    if not (t_bound >= t):                     # forward spans only (scipy would integrate backwards)
        return -1, written, 0, steps
    call(t, y, K, 0, ctx)
    nfev = 1
    if t == t_bound:                           # a zero-length segment: every sample is its start
        for k in range(i_eval, i_end):
            for i in range(d):
                out[k, i] = y[i]
        return 0, i_end, nfev, steps
    g_old = event(y, ectx) if watch else 0.0
    h_abs = initial_step(call, ctx, t, y, K, t_bound, rtol, atol, exponent, ys, F1)
    nfev += 1
    finished = False
    while not finished:
        min_step = 10 * abs(np.nextafter(t, np.inf) - t)
        if h_abs < min_step:
            h_abs = min_step
        ok, t_new, h, h_abs, n_f = _advance(call, ctx, method, (t, t_bound), y, h_abs, min_step, (K, ys, y_new), tol)
        nfev += n_f
        if not ok:
            return -1, written, nfev, steps
        steps += 1
        t_old = t
        t = t_new
        finished = t - t_bound >= 0
        # the event (solve_ivp checks it before sampling the step), then the samples in (t_old, t] (and t_old
        # itself at the first step); both read the dense output, built once per step and only when needed
        crossed = False
        if watch:
            g_new = event(y_new, ectx)
            crossed = g_old >= 0 and g_new <= 0
            g_old = g_new
        i_new = i_eval
        while i_new < i_end and t_eval[i_new] <= t:
            i_new += 1
        if crossed or i_new > i_eval:
            nfev += dense_prepare(call, ctx, tab, t_old, h, y, y_new, K, ys, F)
        if crossed:
            hit[0] = event_root(event, ectx, tab, F, y, t_old, t, yk)
            for i in range(d):
                hit[1 + i] = yk[i]
            return 1, written, nfev, steps
        if i_new > i_eval:
            hs = t - t_old
            for k in range(i_eval, i_new):
                dense_eval(tab, F, y, hs, (t_eval[k] - t_old) / hs, yk)
                for i in range(d):
                    out[k, i] = yk[i]
                    if not np.isfinite(out[k, i]):
                        return -2, k + 1, nfev, steps
            written = i_new
            i_eval = i_new
        for i in range(d):
            y[i] = y_new[i]
        for i in range(d):
            K[0, i] = K[ns, i]
    if i_end > i_eval:                         # not reached: the last sample is t_bound
        return -1, written, nfev, steps
    return 0, written, nfev, steps


def fixed_step(f, y: np.ndarray, h: float, k1: np.ndarray, tab=RK4) -> np.ndarray:
    """One explicit Runge-Kutta step of fixed size h in numpy, for an autonomous f (a plan on the abstraction,
    whose field is numpy code, not a compiled loop): y + h / divisor sum_s w_s k_s, k_s = f(y + h sum_j A[s, j] k_j).

    Parameters
    ----------
    f : callable
        y -> y' (1-D arrays).
    y : 1-D array
        The state at the step's start.
    h : float
        The step.
    k1 : 1-D array
        f(y), which the caller has (it samples the plan there).
    tab : tuple
        (A, weights, divisor), :data:`RK4` by default.

    Returns
    -------
    1-D array
        The state after the step.
    """
    if tab is RK4:
        # the classic tableau written out, the same operations in the same order as the loop below (bit for bit), at a
        # third of its cost: the plans take hundreds of thousands of these steps
        k2 = f(y + h * (0.5 * k1))
        k3 = f(y + h * (0.5 * k2))
        k4 = f(y + h * (1.0 * k3))
        return y + h / 6.0 * (1.0 * k1 + 2.0 * k2 + 2.0 * k3 + 1.0 * k4)
    A, w, divisor = tab
    ks = [k1]
    for s in range(1, w.size):
        acc = None
        for j in range(s):
            if A[s, j] != 0.0:
                term = A[s, j] * ks[j]
                acc = term if acc is None else acc + term
        ks.append(f(y if acc is None else y + h * acc))
    acc = w[0] * ks[0]
    for s in range(1, w.size):
        acc = acc + w[s] * ks[s]
    return y + h / divisor * acc
