"""The tracking closed loop of ``simulate`` as compiled (numba) code, with its own DOP853 integrator.

``simulate.run_tracking`` integrates the loop with scipy's ``solve_ivp`` and a Python right-hand side (about
0.05 ms a call through :class:`~ashc_cli.stages.simulate._Plant`; 69 000 calls on the Cuk converter's 30 s
run).  This module runs the same loop in compiled code:

* **the design's expressions** (f_bar, g, h from the model; phi_bar, l; delta, p, dp/dxi delta and kappa
  from the artefacts) are printed from sympy, common subexpressions eliminated and the parameter values put in
  as :func:`ashc_cli.model.compile_flat` does, into two small numba functions (the *kernels*)
  ``eval_xi(xi, phi_bar, delta, l, dp/dxi delta, kappa, p)`` and ``eval_x(x, f_bar, g, h)``.  sympy stays the
  single source of truth;
* **the core** (the same for every design) holds the control law, :func:`ashc_cli.stages.simulate.tracking_law`
  written out in loops (the set-point controller v = clip(delta^+ (gain (xi_ref - xi) - phi_bar), -v_max,
  v_max); the interface u = SAT(l + K (x - p) + q v) with q the least-squares q of eq. egqLS or 0 and SAT as
  :func:`ashc_cli.model.apply_saturation`; the comparison system w' = -(lambda - eps) w + |L^T r|^2 / eps,
  r = dp/dxi delta v - g (u - l - K (x - p))), and the integrator: scipy's DOP853 (scipy's coefficients, from
  ``scipy.integrate._ivp.dop853_coefficients``) with scipy's initial step, error norm, step-size control and
  7th-order dense output at the sample times.  The right-hand side is bit for bit scipy's (tests), and a run
  takes the steps ``solve_ivp`` takes (on the Cuk converter the same right-hand-side calls per segment); the
  samples differ by the round-off of the stage sums (BLAS's order against a plain loop) as the loop amplifies
  it: 1e-9 of the scale on the Cuk run (v, steeper, 3e-7 of v_max).  On a stiff loop (unstable_linear, K =
  [-1168, -484]) the step sequence depends on the last bit, for scipy too.  The kernels reach the core as
  first-class functions (numba ``FunctionType``), so the core is compiled once per machine and a new design
  compiles only its kernels.

Both are written to files in the cache directory (``$ASHC_CACHE/compiled``, else ``~/.cache/ashc/compiled``),
named by a SHA-256 (of the core's text; of the kernels' sympy input), and imported from there with numba's
``cache=True``: a later process loads the machine code instead of compiling.  ``ASHC_COMPILED=0`` turns the
compiled path off (:class:`Unsupported` is raised and the caller uses scipy).

Entry points: :func:`tracking_loop` (the compiled loop of a design) and :meth:`TrackingLoop.run` (the tracking
scenario's segments, as ``run_tracking``'s loop integrates them).
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sympy as sp
from sympy.printing.pycode import PythonCodePrinter

from .errors import NumericalError

__all__ = ["Unsupported", "TrackingLoop", "TrackingRun", "tracking_loop", "cache_dir", "available", "kernel_source", "kernel_key",
           "load_source", "CORE_SOURCE"]


#: Bump when the kernels' printing changes (it is part of their cache key; the core is keyed by its text).
KERNEL_VERSION = 1


class Unsupported(Exception):
    """The compiled path cannot run this design (numba is missing, or an expression has no numba form).

    The caller uses the scipy path.
    """


def available() -> bool:
    """Whether the compiled path may run: numba can be imported and ``$ASHC_COMPILED`` is not ``0``."""
    if os.environ.get("ASHC_COMPILED", "1").strip() == "0":
        return False
    try:
        import numba  # noqa: F401
    except Exception:
        return False
    return True


def cache_dir() -> Path:
    """Where the generated modules (and numba's cache of them) live: ``$ASHC_CACHE/compiled``, else
    ``$XDG_CACHE_HOME/ashc/compiled`` or ``~/.cache/ashc/compiled``; created as needed (a folder under the
    temporary directory if that one cannot be written)."""
    root = os.environ.get("ASHC_CACHE")
    base = Path(root) if root else Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "ashc"
    for path in (base / "compiled", Path(tempfile.gettempdir()) / f"ashc-{os.getuid() if hasattr(os, 'getuid') else 'user'}" / "compiled"):
        try:
            path.mkdir(parents=True, exist_ok=True)
            if os.access(path, os.W_OK):
                return path
        except OSError:
            pass
    raise Unsupported(f"no writable cache directory for compiled code ({base / 'compiled'})")


# --- the design's kernels, printed from sympy -------------------------------------------------------------


class _Printer(PythonCodePrinter):
    """Python source for numba's nopython mode: ``math`` functions; min and max of floats, two at a time."""

    def __init__(self):
        super().__init__({"fully_qualified_modules": True, "strict": True})

    def _minmax(self, expr, name):
        args = [f"float({self._print(a)})" for a in expr.args]
        out = args[0]
        for a in args[1:]:
            out = f"{name}({out}, {a})"
        return out

    def _print_Min(self, expr):
        return self._minmax(expr, "min")

    def _print_Max(self, expr):
        return self._minmax(expr, "max")


_KERNEL_SIGNATURES = {"eval_xi": "types.void(F1, F1, F2, F1, F2, F1, F1)", "eval_x": "types.void(F1, F1, F2, F1)"}


def _emit_kernel(name: str, state: str, symbols: Sequence[sp.Symbol], outputs: Sequence[tuple[str, sp.MatrixBase, bool]], values) -> str:
    """The numba function ``name(state, *outputs)`` filling its output arrays from the matrices.

    ``outputs``: (array name, matrix, as_vector); a column written to a 1-D array when ``as_vector``.
    """
    subs = {k: sp.Float(v) for k, v in (values or {}).items()}
    local = {s: sp.Symbol(f"_{state}{i}", real=True) for i, s in enumerate(symbols)}
    lines = [f"    _{state}{i} = {state}[{i}]" for i in range(len(symbols))]
    targets, exprs = [], []
    for arr, matrix, as_vector in outputs:
        rows, cols = matrix.shape
        for i in range(rows):
            for j in range(cols):
                targets.append(f"{arr}[{i}]" if as_vector else f"{arr}[{i}, {j}]")
                exprs.append(sp.sympify(matrix[i, j]).xreplace(subs).xreplace(local))
    free = set().union(*(e.free_symbols for e in exprs)) - set(local.values())
    if free:
        raise Unsupported(f"{name}: the expressions depend on {sorted(map(str, free))}, which are not states")
    replacements, reduced = sp.cse(exprs, symbols=sp.numbered_symbols("_c"))
    printer = _Printer()
    try:
        lines += [f"    {sym} = {printer.doprint(e)}" for sym, e in replacements]
        lines += [f"    {target} = {printer.doprint(e)}" for target, e in zip(targets, reduced)]
    except Exception as exc:  # a function numba cannot run (sympy's PrintMethodNotImplementedError and kin)
        raise Unsupported(f"{name}: {exc}") from exc
    args = ", ".join([state] + [a for a, _, _ in outputs])
    head = f"@njit({_KERNEL_SIGNATURES[name]}, cache=True, error_model='numpy')\ndef {name}({args}):\n"
    return head + "\n".join(lines) + "\n"


def _design_terms(model, up):
    xi_terms = [("phi", model.phi_bar, True), ("delta", up["delta"].expr("delta"), False), ("l", model.l, True),
                ("dpd", up["bound"].expr("dp_delta"), False), ("kap", up["kappa"].expr("kappa"), True),
                ("pm", up["manifold"].expr("p"), True)]
    x_terms = [("fb", model.f_bar, True), ("g", model.g, False), ("h", model.h, True)]
    nh, n, m, mh, p = model.n_hat, model.n, model.m, model.m_hat, model.p
    expected = {"phi": (nh, 1), "delta": (nh, mh), "l": (m, 1), "dpd": (n, mh), "kap": (p, 1), "pm": (n, 1),
                "fb": (n, 1), "g": (n, m), "h": (p, 1)}
    for name, matrix, _ in xi_terms + x_terms:
        if tuple(matrix.shape) != expected[name]:
            raise Unsupported(f"{name} has shape {tuple(matrix.shape)}, expected {expected[name]}")
    return xi_terms, x_terms


def kernel_source(model, up) -> str:
    """The numba module of a design's expressions: ``eval_xi`` and ``eval_x`` (Python source).

    The matrices are those ``simulate._Plant`` compiles: phi_bar, l and f_bar, g, h from the model; delta
    (delta stage), p (manifold), dp/dxi delta (bound) and kappa (kappa stage).
    """
    xi_terms, x_terms = _design_terms(model, up)
    parts = [f'"""Generated by ashc_cli.compiled (first for design {model.spec.name!r}): the expressions of a design; do not edit."""',
             "import math", "from numba import njit, types", "", "F1 = types.float64[::1]", "F2 = types.float64[:, ::1]", "", "",
             _emit_kernel("eval_xi", "xi", list(model.xi), xi_terms, model.values), "",
             _emit_kernel("eval_x", "x", list(model.x), x_terms, model.values)]
    return "\n".join(parts)


# --- the core: closed loop, integrator, sampling (the same text for every design) ---------------------------

CORE_SOURCE = '''"""Generated by ashc_cli.compiled (core): the tracking loop and scipy's DOP853 in numba; do not edit."""
import math
import numpy as np
from numba import njit, types

F1 = types.float64[::1]
F2 = types.float64[:, ::1]
I1 = types.int64[::1]
#: eval_xi(xi, phi_bar, delta, l, dp/dxi delta, kappa, p) and eval_x(x, f_bar, g, h), filling their arrays.
XI_KERNEL = types.FunctionType(types.void(F1, F1, F2, F1, F2, F1, F1))
X_KERNEL = types.FunctionType(types.void(F1, F1, F2, F1))
OPTIONS = dict(cache=True, error_model='numpy')


@njit(**OPTIONS)
def _pinv(a):
    """simulate._pinv: a single column in closed form a^T / |a|^2 (zero where the column is), else numpy's pinv."""
    rows, cols = a.shape
    if cols == 1:
        s = 0.0
        for i in range(rows):
            s += a[i, 0] * a[i, 0]
        out = np.zeros((1, rows))
        if s > 0:
            for i in range(rows):
                out[0, i] = a[i, 0] / s
        return out
    return np.linalg.pinv(a)


@njit(types.void(XI_KERNEL, X_KERNEL, I1, F1, F1, F1, F2, F2, F2, types.int64, types.int64, F1, F1, F1), **OPTIONS)
def closed_loop(eval_xi, eval_x, dims, z, xi_ref, prm, L, K, U, q_ls, sat, v, u, dz):
    """simulate.tracking_law and the comparison system at z = [xi, x, w]; fills v, u and dz = [dxi, dx, dw].

    dims = [n_hat, n, m, m_hat, p]; prm = [gain, v_max, lambda, eps]; q_ls = 1 for the least-squares q, 0 for
    q = 0; sat = 0 (no saturation), 1 (clip each channel to U) or 2 (scale the correction).
    """
    NH, N, M, MH, P = dims[0], dims[1], dims[2], dims[3], dims[4]
    gain, v_max, lam, eps = prm[0], prm[1], prm[2], prm[3]
    xi = z[:NH].copy()
    x = z[NH:NH + N].copy()
    phi = np.empty(NH)
    delta = np.empty((NH, MH))
    l = np.empty(M)
    dpd = np.empty((N, MH))
    kap = np.empty(P)
    pm = np.empty(N)
    eval_xi(xi, phi, delta, l, dpd, kap, pm)
    fb = np.empty(N)
    g = np.empty((N, M))
    h = np.empty(P)
    eval_x(x, fb, g, h)
    # v = clip(delta^+ (gain (xi_ref - xi) - phi_bar), -v_max, v_max)
    dplus = _pinv(delta)
    for a in range(MH):
        s = 0.0
        for i in range(NH):
            s += dplus[a, i] * (gain * (xi_ref[i] - xi[i]) - phi[i])
        v[a] = min(max(s, -v_max), v_max)
    # feedback = K (x - p); u_nominal = l + feedback; correction = feedback (+ q v)
    feedback = np.empty(M)
    for j in range(M):
        s = 0.0
        for i in range(N):
            s += K[j, i] * (x[i] - pm[i])
        feedback[j] = s
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
        pg = _pinv(Ltg)
        for j in range(M):
            s = 0.0
            for a in range(MH):
                qa = 0.0
                for i in range(N):
                    qa += pg[j, i] * Ltd[i, a]
                s += qa * v[a]
            correction[j] = feedback[j] + s
    # u = SAT(l + correction), model.apply_saturation
    if sat == 2:
        smin = np.inf
        for j in range(M):
            c = correction[j]
            if c > 0:
                room = (U[j, 1] - l[j]) / c
            elif c < 0:
                room = (U[j, 0] - l[j]) / c
            else:
                room = np.inf
            if room < smin or room != room:
                smin = room
        sf = min(max(smin, 0.0), 1.0)
        for j in range(M):
            u[j] = l[j] + sf * correction[j]
    elif sat == 1:
        for j in range(M):
            u[j] = min(max(l[j] + correction[j], U[j, 0]), U[j, 1])
    else:
        for j in range(M):
            u[j] = l[j] + correction[j]
    # dxi = phi_bar + delta v; dx = f_bar + g u; r = dp/dxi delta v - g (u - u_nominal)
    for i in range(NH):
        s = 0.0
        for a in range(MH):
            s += delta[i, a] * v[a]
        dz[i] = phi[i] + s
    r = np.empty(N)
    for i in range(N):
        s = 0.0
        for j in range(M):
            s += g[i, j] * u[j]
        dz[NH + i] = fb[i] + s
        s1 = 0.0
        for a in range(MH):
            s1 += dpd[i, a] * v[a]
        s2 = 0.0
        for j in range(M):
            s2 += g[i, j] * (u[j] - (l[j] + feedback[j]))
        r[i] = s1 - s2
    # w' = -(lambda - eps) w + |L^T r|^2 / eps
    q2 = 0.0
    for i in range(N):
        s = 0.0
        for k in range(N):
            s += L[k, i] * r[k]
        q2 += s * s
    dz[NH + N] = -(lam - eps) * z[NH + N] + q2 / eps


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


@njit(types.UniTuple(types.int64, 5)(XI_KERNEL, X_KERNEL, I1, F1, F2, F1, I1, F2, F1, F2, F2, F2, types.int64, types.int64,
                                     types.float64, types.float64, F2, F1, F1, F1, F2, F2), **OPTIONS)
def integrate(eval_xi, eval_x, dims, z0, t_bounds, t_eval, offsets, refs, prm, L, K, U, q_ls, sat, rtol, atol,
              A, B, E3, E5, D, out):
    """scipy's DOP853 (solve_ivp with t_eval, max_step = inf), segment after segment.

    Segment k runs from t_bounds[k, 0] to t_bounds[k, 1] with the reference refs[k] and writes its samples
    t_eval[offsets[k]:offsets[k + 1]] to the same rows of out; the next segment starts from its last sample.
    Returns (status, rows written, segment, nfev, accepted steps): status 0 on success, -1 when the step
    fell below ten times the spacing of floating-point numbers (scipy's failure), -2 at a sample that is
    not finite.
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
    for seg in range(t_bounds.shape[0]):
        t = t_bounds[seg, 0]
        t_bound = t_bounds[seg, 1]
        ref = refs[seg]
        i_eval = offsets[seg]
        i_end = offsets[seg + 1]
        closed_loop(eval_xi, eval_x, dims, y, ref, prm, L, K, U, q_ls, sat, v, u, f)
        nfev += 1
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
        closed_loop(eval_xi, eval_x, dims, y1, ref, prm, L, K, U, q_ls, sat, v, u, f1)
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
                out[k] = y
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
                # rk_step
                Kx[0] = f
                for s in range(1, n_stages):
                    _combine(Kx, A[s], s, h, y, ys)
                    closed_loop(eval_xi, eval_x, dims, ys, ref, prm, L, K, U, q_ls, sat, v, u, Kx[s])
                nfev += n_stages - 1
                for i in range(d):
                    acc = 0.0
                    for j in range(n_stages):
                        acc += Kx[j, i] * B[j]
                    y_new[i] = y[i] + h * acc
                closed_loop(eval_xi, eval_x, dims, y_new, ref, prm, L, K, U, q_ls, sat, v, u, Kx[n_stages])
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
            # the samples in (t_old, t] (and t_old itself at the first step): dense output, as solve_ivp
            i_new = i_eval
            while i_new < i_end and t_eval[i_new] <= t:
                i_new += 1
            if i_new > i_eval:
                for s in range(n_stages + 1, n_ext):
                    _combine(Kx, A[s], s, h, y, ys)
                    closed_loop(eval_xi, eval_x, dims, ys, ref, prm, L, K, U, q_ls, sat, v, u, Kx[s])
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
                hs = t - t_old
                for k in range(i_eval, i_new):
                    xk = (t_eval[k] - t_old) / hs
                    for i in range(d):
                        yk[i] = 0.0
                    for q in range(7):
                        for i in range(d):
                            yk[i] += F[6 - q, i]
                            if q % 2 == 0:
                                yk[i] *= xk
                            else:
                                yk[i] *= 1 - xk
                    for i in range(d):
                        out[k, i] = yk[i] + y[i]
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
    NH, N, M, MH, P = dims[0], dims[1], dims[2], dims[3], dims[4]
    dz = np.empty(NH + N + 1)
    v = np.empty(MH)
    u = np.empty(M)
    phi = np.empty(NH)
    delta = np.empty((NH, MH))
    l = np.empty(M)
    dpd = np.empty((N, MH))
    kap = np.empty(P)
    pm = np.empty(N)
    fb = np.empty(N)
    g = np.empty((N, M))
    h = np.empty(P)
    for k in range(Z.shape[0]):
        z = Z[k]
        closed_loop(eval_xi, eval_x, dims, z, refs[seg_of_row[k]], prm, L, K, U, q_ls, sat, v, u, dz)
        V[k] = v
        Uo[k] = u
        eval_xi(z[:NH].copy(), phi, delta, l, dpd, kap, pm)
        eval_x(z[NH:NH + N].copy(), fb, g, h)
        PSI[k] = kap
        Y[k] = h
'''


_MODULES: dict[str, object] = {}


def load_source(source, prefix: str, key: str | None = None):
    """Import generated source from the cache directory, once per process.

    The file is ``<prefix>_<key>.py``, ``key`` defaulting to the SHA-256 of the text; ``source`` may be a
    function returning the text, called only when the file is missing (the kernels are keyed by their sympy
    input, so a second run skips common-subexpression elimination too).  A file is written atomically and never
    rewritten, since numba's cache is keyed on its time stamp.
    """
    if key is None:
        key = hashlib.sha256(source.encode()).hexdigest()[:24]
    name = f"{prefix}_{key}"
    if name in _MODULES:
        return _MODULES[name]
    if not available():
        raise Unsupported("numba is not installed (or ASHC_COMPILED=0)")
    folder = cache_dir()
    path = folder / f"{name}.py"
    if not path.exists():
        text = source() if callable(source) else source
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{name}.", suffix=".tmp")
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except Exception:
        sys.modules.pop(name, None)
        raise
    _MODULES[name] = module
    return module


def kernel_key(model, up) -> str:
    """What a design's kernels are made from, hashed: the matrices (``srepr``, every digit), the state
    symbols, the parameter values, the generator's version and sympy's."""
    xi_terms, x_terms = _design_terms(model, up)
    digest = hashlib.sha256(f"ashc kernels {KERNEL_VERSION} sympy {sp.__version__}".encode())
    for arr, matrix, as_vector in xi_terms + x_terms:
        digest.update(f"|{arr}|{as_vector}|{sp.srepr(matrix)}".encode())
    digest.update(f"|{sp.srepr(list(model.xi))}|{sp.srepr(list(model.x))}".encode())
    digest.update("|".join(f"{sp.srepr(k)}={float(v)!r}" for k, v in sorted(model.values.items(), key=lambda kv: str(kv[0]))).encode())
    return digest.hexdigest()[:24]


def _dop853_tables() -> tuple[np.ndarray, ...]:
    """scipy's DOP853 coefficients: A (16 x 16, the three extra stages of the dense output included), B, E3,
    E5 and D (4 x 16)."""
    from scipy.integrate._ivp import dop853_coefficients as c

    return tuple(np.ascontiguousarray(a, dtype=float) for a in (c.A, c.B, c.E3, c.E5, c.D))


@dataclass
class TrackingRun:
    """A compiled tracking run in run_tracking's shapes (N samples, the repeated segment starts dropped).

    Attributes
    ----------
    t : ndarray (N,)
        Sample times.
    xi, x : ndarray (n_hat, N), (n, N)
        Abstract and concrete state.
    w : ndarray (N,)
        The comparison system of the a-posteriori bound.
    v, u : ndarray (m_hat, N), (m, N)
        Abstract and concrete input (tracking_law at each sample).
    psi, y : ndarray (p, N)
        kappa(xi) and h(x).
    reference_index : ndarray (N,) of int
        The reference (index into ``refs``) each sample was integrated with.
    psi_end : ndarray (segments, p)
        psi at the end of each segment.
    nfev, steps : int
        Right-hand-side calls and accepted steps.
    """

    t: np.ndarray
    xi: np.ndarray
    x: np.ndarray
    w: np.ndarray
    v: np.ndarray
    u: np.ndarray
    psi: np.ndarray
    y: np.ndarray
    reference_index: np.ndarray
    psi_end: np.ndarray
    nfev: int
    steps: int


_SATURATE = {False: 0, True: 1, "scale": 2}


class TrackingLoop:
    """The compiled tracking closed loop of one design (build it with :func:`tracking_loop`)."""

    def __init__(self, core, kernels, model, up):
        self.core, self.kernels = core, kernels
        self.nh, self.n, self.m, self.mh, self.p = model.n_hat, model.n, model.m, model.m_hat, model.p
        self.dims = np.array([self.nh, self.n, self.m, self.mh, self.p], dtype=np.int64)
        self.L = np.ascontiguousarray(np.asarray(up["bound"].value("L"), dtype=float).reshape(self.n, self.n))
        K = up["stabilise"].values.get("K", np.zeros((model.m, model.n)))
        self.K = np.ascontiguousarray(np.asarray(K, dtype=float).reshape(self.m, self.n))
        self.U = np.ascontiguousarray(np.asarray(model.U, dtype=float).reshape(self.m, 2))
        self.lam = float(up["bound"].value("lambda"))
        self.eps = float(up["bound"].value("epsilon"))
        self._tables = _dop853_tables()

    @staticmethod
    def _flags(q_kind: str, saturate) -> tuple[int, int]:
        if q_kind not in ("least_squares", "zero"):
            raise Unsupported(f"interface.q = {q_kind!r}")
        if not isinstance(saturate, (bool, np.bool_, str)) or saturate not in _SATURATE:
            raise Unsupported(f"interface.saturate = {saturate!r}")
        return int(q_kind == "least_squares"), _SATURATE[saturate]

    def _prm(self, gain: float, v_max: float) -> np.ndarray:
        return np.array([gain, v_max, self.lam, self.eps], dtype=float)

    def law(self, xi, x, xi_ref, gain: float, v_max: float, q_kind: str, saturate, w: float = 0.0):
        """(v, u, dz) at one point: the compiled tracking_law, dz = [dxi, dx, dw]."""
        q_ls, sat = self._flags(q_kind, saturate)
        z = np.ascontiguousarray(np.r_[np.ravel(xi), np.ravel(x), w], dtype=float)
        v, u, dz = np.empty(self.mh), np.empty(self.m), np.empty(z.size)
        self.core.closed_loop(self.kernels.eval_xi, self.kernels.eval_x, self.dims, z, np.ascontiguousarray(xi_ref, dtype=float).reshape(self.nh),
                              self._prm(gain, v_max), self.L, self.K, self.U, q_ls, sat, v, u, dz)
        return v, u, dz

    def run(self, z0: np.ndarray, segments: Sequence[tuple[float, float, np.ndarray, int]], refs: Sequence[np.ndarray], *,
            gain: float, v_max: float, q_kind: str, saturate, rtol: float, atol: float, what: str = "tracking") -> TrackingRun:
        """Integrate the tracking loop segment after segment, as run_tracking's ``while`` loop does.

        Parameters
        ----------
        z0 : ndarray (n_hat + n + 1,)
            [xi0, x0, W0].
        segments : sequence of (t0, t1, t_eval, i)
            One per dwell segment, in order: its span, its sample times (``sample_times(t0, t1, SAMPLE_DT)``,
            starting at t0 and ending at t1) and the index i into ``refs`` of its reference.
        refs : sequence of ndarray (n_hat,)
            The reference states xi_ref.
        gain, v_max : float
            The set-point controller.
        q_kind, saturate :
            ``interface.q`` and ``interface.saturate``.
        rtol, atol : float
            The tolerances (``TRACKING_TOL``).

        Raises
        ------
        NumericalError
            As ``simulate._integrate``: the step size fell below the spacing of floating-point numbers, or a
            sample is not finite.
        """
        q_ls, sat = self._flags(q_kind, saturate)
        evals = [np.asarray(te, dtype=float).reshape(-1) for _, _, te, _ in segments]
        if not evals or any(te.size == 0 for te in evals):
            raise ValueError("every segment needs its sample times")
        offsets = np.cumsum([0] + [te.size for te in evals]).astype(np.int64)
        t_eval = np.ascontiguousarray(np.concatenate(evals))
        t_bounds = np.ascontiguousarray(np.array([[float(a), float(b)] for a, b, _, _ in segments], dtype=float))
        index = np.array([i for *_, i in segments], dtype=np.int64)
        seg_refs = np.ascontiguousarray(np.stack([np.asarray(refs[i], dtype=float).reshape(self.nh) for i in index]))
        prm = self._prm(gain, v_max)
        z0 = np.ascontiguousarray(z0, dtype=float).reshape(-1)
        out = np.full((t_eval.size, z0.size), np.nan)
        A, B, E3, E5, D = self._tables
        fxi, fx = self.kernels.eval_xi, self.kernels.eval_x
        status, written, seg, nfev, steps = self.core.integrate(fxi, fx, self.dims, z0, t_bounds, t_eval, offsets, seg_refs, prm, self.L, self.K, self.U,
                                                                q_ls, sat, float(rtol), float(atol), A, B, E3, E5, D, out)
        if status != 0:
            t_bad = t_eval[written - 1] if written > 0 else t_bounds[min(seg, len(t_bounds) - 1), 0]
            message = "Required step size is less than spacing between numbers." if status == -1 else "a sample is not finite"
            raise NumericalError(f"simulate.{what}", f"integration failed at t = {t_bad:.6g} s ({message})", "a trajectory that stays finite")
        keep = np.ones(t_eval.size, dtype=bool)
        keep[offsets[1:-1]] = False            # each later segment's first sample repeats the previous end
        seg_of_row = np.repeat(np.arange(len(segments), dtype=np.int64), np.diff(offsets))
        V, Uo = np.empty((t_eval.size, self.mh)), np.empty((t_eval.size, self.m))
        PSI, Y = np.empty((t_eval.size, self.p)), np.empty((t_eval.size, self.p))
        self.core.samples(fxi, fx, self.dims, out, seg_of_row, seg_refs, prm, self.L, self.K, self.U, q_ls, sat, V, Uo, PSI, Y)
        Z = out[keep].T
        nh, n = self.nh, self.n
        return TrackingRun(t=t_eval[keep], xi=Z[:nh].copy(), x=Z[nh:nh + n].copy(), w=Z[-1].copy(), v=V[keep].T.copy(), u=Uo[keep].T.copy(),
                           psi=PSI[keep].T.copy(), y=Y[keep].T.copy(), reference_index=index[seg_of_row[keep]],
                           psi_end=PSI[offsets[1:] - 1].copy(), nfev=int(nfev), steps=int(steps))


def tracking_loop(model, up) -> TrackingLoop:
    """The compiled tracking loop of a design (``up``: the artefacts of stabilise .. bound by stage).

    Generates the kernels' source unless the cache directory holds it (keyed by :func:`kernel_key`), writes it
    (and the core's, once) there and imports both;
    numba compiles what its cache does not hold (the core once per machine, a few seconds; the kernels once per
    design, well under a second).

    Raises
    ------
    Unsupported
        numba is missing, ``$ASHC_COMPILED`` is ``0``, or an expression has no numba form: use the scipy path.
    """
    if not available():
        raise Unsupported("numba is not installed (or ASHC_COMPILED=0)")
    key = kernel_key(model, up)
    core = load_source(CORE_SOURCE, "ashc_core")
    try:
        kernels = load_source(lambda: kernel_source(model, up), "ashc_kernels", key)
    except Unsupported:
        raise
    except Exception as exc:   # numba could not type or compile an expression the printer let through
        raise Unsupported(f"numba could not compile the expressions of {model.spec.name!r}: {type(exc).__name__}: {str(exc)[:500]}") from exc
    return TrackingLoop(core, kernels, model, up)
