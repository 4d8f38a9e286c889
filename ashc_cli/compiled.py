"""The two closed loops of ``simulate`` as compiled (numba) code, with one DOP853 integrator.

``simulate.run_tracking`` and ``simulate.run_m_relation`` integrate their loops with scipy's ``solve_ivp`` and
a Python right-hand side (about 0.03-0.05 ms a call through :class:`~ashc_cli.stages.simulate._Plant`; 69 000
calls on the Cuk converter's 30 s tracking run, 40 000 on its 10 s m-relation run).  This module runs the same
loops in compiled code:

* **the design's expressions** (f_bar, g, h from the model; phi_bar, l; delta, p, dp/dxi delta and kappa
  from the artefacts) are printed from sympy, common subexpressions eliminated and the parameter values put in
  as :func:`ashc_cli.model.compile_flat` does, into two small numba functions (the *kernels*)
  ``eval_xi(xi, phi_bar, delta, l, dp/dxi delta, kappa, p)`` and ``eval_x(x, f_bar, g, h)``; the m-relation
  adds a *link module*, ``eval_link(x, b, c, m)`` (delta and inverse stages) and ``eval_u([t], u)`` (the spec's
  ``simulate.m_relation.u``, its time signals triangle, square and step as in :mod:`ashc_cli.expr`).  sympy
  stays the single source of truth;
* **the core** (the same for every design) holds the control laws and the integrator.  The tracking law is
  :func:`ashc_cli.stages.simulate.tracking_law` written out in loops (the set-point controller v = clip(delta^+
  (gain (xi_ref - xi) - phi_bar), -v_max, v_max); the interface u = SAT(l + K (x - p) + q v) with q the
  least-squares q of eq. egqLS or 0 and SAT as :func:`ashc_cli.model.apply_saturation`; the comparison system
  w' = -(lambda - eps) w + |L^T r|^2 / eps, r = dp/dxi delta v - g (u - l - K (x - p))); the m-relation's is
  u = u(t), v = b(x) + c(x) u (eq. mRelateLink), xi' = phi_bar + delta v, x' = f_bar + g u.  The integrator
  is scipy's DOP853 (scipy's coefficients, from ``scipy.integrate._ivp.dop853_coefficients``) with scipy's
  initial step, error norm, step-size control and 7th-order dense output at the sample times, and
  solve_ivp's terminal event (the m-relation run stops where h(x) leaves the certified set, the time found by
  scipy's brentq on the dense output).  One ``integrate`` runs both loops, which reach it as a first-class
  function of one signature (an indirect call costs the Cuk tracking run 15 ms of 75; inlining both loops at
  each call made the core take 2-3 s longer to compile).  The right-hand sides are scipy's to round-off
  (tests), and a run takes the steps ``solve_ivp`` takes (on the Cuk converter's tracking run the same
  right-hand-side calls per segment); the samples differ by the round-off of the stage sums (BLAS's order
  against a plain loop) as the loop amplifies it: 1e-9 of the scale on the Cuk tracking run (v, steeper, 3e-7
  of v_max).  Where the step sequence depends on the last bit, it does for scipy too: on a stiff loop
  (unstable_linear, K = [-1168, -484]), and at the kink of the Cuk m-relation's triangle input (t = 2 s), after
  which the runs differ by the integration's accuracy (4e-11 of the scale, as scipy does from x0 moved by one
  ulp).  The kernels reach the core as first-class functions (numba ``FunctionType``), so the core is compiled
  once per machine and a new design compiles only its kernels.

All are written to files in the cache directory (``$ASHC_CACHE/compiled``, else ``~/.cache/ashc/compiled``),
named by a SHA-256 (of the core's text; of the kernels' sympy input), and imported from there with numba's
``cache=True``: a later process loads the machine code instead of compiling.  ``ASHC_COMPILED=0`` turns the
compiled path off (:class:`Unsupported` is raised and the caller uses scipy).

Entry points: :func:`tracking_loop` (the compiled tracking loop of a design) and :meth:`TrackingLoop.run` (the
tracking scenario's segments, as ``run_tracking``'s loop integrates them); :func:`m_relation_loop` and
:meth:`MRelationLoop.run` (the m-relation scenario, as ``run_m_relation`` integrates it).
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
from .model import almost_everywhere

__all__ = ["Unsupported", "TrackingLoop", "TrackingRun", "tracking_loop", "MRelationLoop", "MRelationRun", "m_relation_loop", "cache_dir",
           "available", "kernel_source", "kernel_key", "link_source", "link_key", "load_source", "CORE_SOURCE", "SIGNAL_HELPERS"]


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
    """Python source for numba's nopython mode: ``math`` functions; min and max of floats, two at a time; the
    spec's time signals (triangle, square, step) as calls of SIGNAL_HELPERS."""

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

    # The time signals a spec's simulate.*.u may call (expr.SIGNAL_FUNCTIONS): calls of the numba functions of
    # SIGNAL_HELPERS, which a module printing them must hold (the m-relation's link module does).
    def _print_triangle(self, expr):
        return f"signal_triangle(float({self._print(expr.args[0])}))"

    def _print_square(self, expr):
        return f"signal_square(float({self._print(expr.args[0])}))"

    def _print_step(self, expr):
        return f"signal_step(float({self._print(expr.args[0])}))"


_KERNEL_SIGNATURES = {"eval_xi": "types.void(F1, F1, F2, F1, F2, F1, F1)", "eval_x": "types.void(F1, F1, F2, F1)",
                      "eval_link": "types.void(F1, F1, F2, F1)", "eval_u": "types.void(F1, F1)"}


def _emit_kernel(name: str, state: str, symbols: Sequence[sp.Symbol], outputs: Sequence[tuple[str, sp.MatrixBase, bool]], values,
                 signature: str | None = None) -> str:
    """The numba function ``name(state, *outputs)`` filling its output arrays from the matrices.

    ``outputs``: (array name, matrix, as_vector); a column written to a 1-D array when ``as_vector``.
    ``signature``: the numba signature (text); by default the one :data:`_KERNEL_SIGNATURES` gives ``name``.
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
                exprs.append(almost_everywhere(sp.sympify(matrix[i, j]).xreplace(subs).xreplace(local)))
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
    head = f"@njit({signature or _KERNEL_SIGNATURES[name]}, cache=True, error_model='numpy')\ndef {name}({args}):\n"
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


# --- the m-relation's link and input signal, printed from sympy ----------------------------------------------

#: The numeric time signals of ashc_cli.expr (_np_triangle, _np_square, _np_step) for one float, in numba.
SIGNAL_HELPERS = '''@njit(types.float64(types.float64), cache=True, error_model='numpy')
def signal_triangle(t):
    """expr._np_triangle: (2/pi) int_0^t sign(sin s) ds - 1."""
    tau = np.mod(t, 2.0 * np.pi)
    return -1.0 + 2.0 * tau / np.pi if tau < np.pi else 3.0 - 2.0 * tau / np.pi


@njit(types.float64(types.float64), cache=True, error_model='numpy')
def signal_square(t):
    """expr._np_square: sign(sin t)."""
    return np.sign(np.sin(t))


@njit(types.float64(types.float64), cache=True, error_model='numpy')
def signal_step(t):
    """expr._np_step: 1 for t >= 0, else 0."""
    return 1.0 if t >= 0.0 else 0.0
'''


def _link_terms(model, up, u):
    """The m-relation's matrices: b, c (delta stage) and m (inverse stage) of x; u(t) of the spec."""
    x_terms = [("b", up["delta"].expr("b"), True), ("c", up["delta"].expr("c"), False), ("m", up["inverse"].expr("m"), True)]
    u_terms = [("u", sp.Matrix(u), True)]
    expected = {"b": (model.m_hat, 1), "c": (model.m_hat, model.m), "m": (model.n_hat, 1), "u": (model.m, 1)}
    for name, matrix, _ in x_terms + u_terms:
        if tuple(matrix.shape) != expected[name]:
            raise Unsupported(f"{name} has shape {tuple(matrix.shape)}, expected {expected[name]}")
    return x_terms, u_terms


def link_source(model, up, u) -> str:
    """The numba module of the m-relation's link and input: ``eval_link(x, b, c, m)`` and ``eval_u([t], u)``.

    Parameters
    ----------
    model : Model
    up : dict of str to Artefact
        The design's artefacts (b and c from the delta stage, m from the inverse stage).
    u : sympy Matrix (m, 1)
        The spec's ``simulate.m_relation.u`` as parsed (``t`` is :data:`ashc_cli.model.TIME`).
    """
    from .model import TIME

    x_terms, u_terms = _link_terms(model, up, u)
    parts = [f'"""Generated by ashc_cli.compiled (first for design {model.spec.name!r}): the m-relation link and input; do not edit."""',
             "import math", "import numpy as np", "from numba import njit, types", "", "F1 = types.float64[::1]", "F2 = types.float64[:, ::1]",
             "", "", SIGNAL_HELPERS, "", _emit_kernel("eval_link", "x", list(model.x), x_terms, model.values), "",
             _emit_kernel("eval_u", "t", [TIME], u_terms, model.values)]
    return "\n".join(parts)


def link_key(model, up, u) -> str:
    """What the m-relation's kernels are made from, hashed (as :func:`kernel_key`): b, c, m, u, the states,
    the parameter values, the signal helpers' text, the generator's version and sympy's."""
    from .model import TIME

    x_terms, u_terms = _link_terms(model, up, u)
    digest = hashlib.sha256(f"ashc link {KERNEL_VERSION} sympy {sp.__version__}|{SIGNAL_HELPERS}".encode())
    for arr, matrix, as_vector in x_terms + u_terms:
        digest.update(f"|{arr}|{as_vector}|{sp.srepr(matrix)}".encode())
    digest.update(f"|{sp.srepr(list(model.x))}|{sp.srepr(TIME)}".encode())
    digest.update("|".join(f"{sp.srepr(k)}={float(v)!r}" for k, v in sorted(model.values.items(), key=lambda kv: str(kv[0]))).encode())
    return digest.hexdigest()[:24]


# --- the core: closed loop, integrator, sampling (the same text for every design) ---------------------------

CORE_SOURCE = '''"""Generated by ashc_cli.compiled (core): the tracking and m-relation loops and scipy's DOP853 in numba; do not edit."""
import math
import numpy as np
from numba import njit, types

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


@njit(**OPTIONS)
def _design_at(eval_xi, eval_x, dims, z):
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
    phi, delta, l, dpd, kap, pm, fb, g, h = _design_at(eval_xi, eval_x, dims, z)
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


@njit(types.void(XI_KERNEL, X_KERNEL, LINK_KERNEL, U_KERNEL, I1, types.float64, F1, F1, F1, F1), **OPTIONS)
def link_loop(eval_xi, eval_x, eval_link, eval_u, dims, t, z, v, u, dz):
    """simulate.run_m_relation's right-hand side at (t, z = [xi, x]); fills u = u(t), v and dz = [dxi, dx].

    v = b(x) + c(x) u (eq. mRelateLink); dxi = phi_bar(xi) + delta(xi) v; dx = f_bar(x) + g(x) u.
    """
    NH, N, M, MH, P = dims[0], dims[1], dims[2], dims[3], dims[4]
    tt = np.empty(1)
    tt[0] = t
    eval_u(tt, u)
    x = z[NH:NH + N].copy()
    phi, delta, l, dpd, kap, pm, fb, g, h = _design_at(eval_xi, eval_x, dims, z)
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
    NH, N, M, MH, P = dims[0], dims[1], dims[2], dims[3], dims[4]
    dz = np.empty(NH + N + 1)
    v = np.empty(MH)
    u = np.empty(M)
    for k in range(Z.shape[0]):
        z = Z[k]
        closed_loop(eval_xi, eval_x, dims, z, refs[seg_of_row[k]], prm, L, K, U, q_ls, sat, v, u, dz)
        phi, delta, l, dpd, kap, pm, fb, g, h = _design_at(eval_xi, eval_x, dims, z)
        # element by element, as in integrate
        for a in range(MH):
            V[k, a] = v[a]
        for j in range(M):
            Uo[k, j] = u[j]
        for i in range(P):
            PSI[k, i] = kap[i]
            Y[k, i] = h[i]


@njit(types.void(XI_KERNEL, X_KERNEL, LINK_KERNEL, U_KERNEL, I1, F1, F2, F2, F2, F2, F2, F2), **OPTIONS)
def link_samples(eval_xi, eval_x, eval_link, eval_u, dims, t, Z, V, Uo, PSI, Y, MX):
    """At every row of Z = [xi, x] (time t[k]): v and u (link_loop), psi = kappa(xi), y = h(x) and m(x)."""
    NH, N, M, MH, P = dims[0], dims[1], dims[2], dims[3], dims[4]
    dz = np.empty(NH + N)
    v = np.empty(MH)
    u = np.empty(M)
    b = np.empty(MH)
    c = np.empty((MH, M))
    mx = np.empty(NH)
    for k in range(Z.shape[0]):
        z = Z[k]
        link_loop(eval_xi, eval_x, eval_link, eval_u, dims, t[k], z, v, u, dz)
        phi, delta, l, dpd, kap, pm, fb, g, h = _design_at(eval_xi, eval_x, dims, z)
        x = z[NH:NH + N].copy()
        eval_link(x, b, c, mx)
        for a in range(MH):
            V[k, a] = v[a]
        for j in range(M):
            Uo[k, j] = u[j]
        for i in range(P):
            PSI[k, i] = kap[i]
            Y[k, i] = h[i]
        for i in range(NH):
            MX[k, i] = mx[i]
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


def _dop853_nodes() -> np.ndarray:
    """scipy's DOP853 stage nodes C (16, the extra stages included): stage s is evaluated at t + C[s] h."""
    from scipy.integrate._ivp import dop853_coefficients as c

    return np.ascontiguousarray(c.C, dtype=float)


def _integrate(core, rhs, kernels, link, dims, z0, t_bounds, t_eval, offsets, refs, prm, L, K, U, q_ls, sat, edges, rtol, atol, what):
    """One call of the core's DOP853 ``integrate``; the samples (rows of t_eval) and the event.

    ``link`` holds eval_link and eval_u (the core's no_link and no_signal for the tracking loop); ``edges``
    is empty or [lo, lo_margin, hi, hi_margin] (the m-relation's event).

    Returns
    -------
    status : int
        0 (every sample written) or 1 (the run left the edges: see ``hit``).
    out : ndarray (len(t_eval), len(z0))
        The samples.
    hit : ndarray (1 + len(z0),)
        [t, z] where the event stopped the run (NaN when it did not).
    nfev, steps : int

    Raises
    ------
    NumericalError
        As ``simulate._integrate``: the step size fell below the spacing of floating-point numbers, or a
        sample is not finite.
    """
    z0 = np.ascontiguousarray(z0, dtype=float).reshape(-1)
    out = np.full((t_eval.size, z0.size), np.nan)
    hit = np.full(z0.size + 1, np.nan)
    A, B, E3, E5, D = _dop853_tables()
    status, written, seg, nfev, steps = core.integrate(rhs, kernels.eval_xi, kernels.eval_x, link[0], link[1], dims, z0, t_bounds, t_eval, offsets, refs,
                                                       prm, L, K, U, q_ls, sat, np.ascontiguousarray(edges, dtype=float), float(rtol), float(atol),
                                                       A, B, _dop853_nodes(), E3, E5, D, out, hit)
    if status < 0:
        t_bad = t_eval[written - 1] if written > 0 else t_bounds[min(seg, len(t_bounds) - 1), 0]
        message = "Required step size is less than spacing between numbers." if status == -1 else "a sample is not finite"
        raise NumericalError(f"simulate.{what}", f"integration failed at t = {t_bad:.6g} s ({message})", "a trajectory that stays finite")
    return status, out, hit, int(nfev), int(steps)


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
        _, out, _, nfev, steps = _integrate(self.core, self.core.tracking_rhs, self.kernels, (self.core.no_link, self.core.no_signal), self.dims,
                                            z0, t_bounds, t_eval, offsets, seg_refs, prm, self.L, self.K, self.U, q_ls, sat, np.empty(0),
                                            rtol, atol, what)
        keep = np.ones(t_eval.size, dtype=bool)
        keep[offsets[1:-1]] = False            # each later segment's first sample repeats the previous end
        seg_of_row = np.repeat(np.arange(len(segments), dtype=np.int64), np.diff(offsets))
        V, Uo = np.empty((t_eval.size, self.mh)), np.empty((t_eval.size, self.m))
        PSI, Y = np.empty((t_eval.size, self.p)), np.empty((t_eval.size, self.p))
        fxi, fx = self.kernels.eval_xi, self.kernels.eval_x
        self.core.samples(fxi, fx, self.dims, out, seg_of_row, seg_refs, prm, self.L, self.K, self.U, q_ls, sat, V, Uo, PSI, Y)
        Z = out[keep].T
        nh, n = self.nh, self.n
        return TrackingRun(t=t_eval[keep], xi=Z[:nh].copy(), x=Z[nh:nh + n].copy(), w=Z[-1].copy(), v=V[keep].T.copy(), u=Uo[keep].T.copy(),
                           psi=PSI[keep].T.copy(), y=Y[keep].T.copy(), reference_index=index[seg_of_row[keep]],
                           psi_end=PSI[offsets[1:] - 1].copy(), nfev=nfev, steps=steps)


def _design_kernels(model, up):
    """The core and the design's kernels (eval_xi, eval_x), imported (generated and compiled when the cache
    directory does not hold them)."""
    if not available():
        raise Unsupported("numba is not installed (or ASHC_COMPILED=0)")
    key = kernel_key(model, up)
    core = load_source(CORE_SOURCE, "ashc_core")
    return core, _load_kernels(lambda: kernel_source(model, up), "ashc_kernels", key, model)


def _load_kernels(source, prefix: str, key: str, model):
    """load_source for generated kernels: a failure of numba on a printed expression is :class:`Unsupported`."""
    try:
        return load_source(source, prefix, key)
    except Unsupported:
        raise
    except Exception as exc:   # numba could not type or compile an expression the printer let through
        raise Unsupported(f"numba could not compile the expressions of {model.spec.name!r}: {type(exc).__name__}: {str(exc)[:500]}") from exc


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
    core, kernels = _design_kernels(model, up)
    return TrackingLoop(core, kernels, model, up)


@dataclass
class MRelationRun:
    """A compiled m-relation run in run_m_relation's shapes (N samples), or where it left the certified set.

    Attributes
    ----------
    t : ndarray (N,)
        Sample times.
    xi, x : ndarray (n_hat, N), (n, N)
        Abstract and concrete state.
    u, v : ndarray (m, N), (m_hat, N)
        u(t) and v = b(x) + c(x) u.
    psi, y : ndarray (p, N)
        kappa(xi) and h(x).
    m : ndarray (n_hat, N)
        m(x), whose distance to xi is the invariance residual.
    left : (float, ndarray) or None
        (t, [xi, x]) where y = h(x) left the certified interval (the run stopped there, the samples are
        empty), as solve_ivp's terminal event finds it; None when the run went to the end.
    nfev, steps : int
        Right-hand-side calls and accepted steps.
    """

    t: np.ndarray
    xi: np.ndarray
    x: np.ndarray
    u: np.ndarray
    v: np.ndarray
    psi: np.ndarray
    y: np.ndarray
    m: np.ndarray
    left: tuple[float, np.ndarray] | None
    nfev: int
    steps: int


class MRelationLoop:
    """The compiled m-relation closed loop of one design and input signal (build it with :func:`m_relation_loop`).

    The concrete system runs open loop under u(t); the abstract one receives v = b(x) + c(x) u (eq.
    mRelateLink): the right-hand side run_m_relation integrates, with the same DOP853 as the tracking loop.
    """

    def __init__(self, core, kernels, link, model):
        self.core, self.kernels, self.link = core, kernels, link
        self.nh, self.n, self.m, self.mh, self.p = model.n_hat, model.n, model.m, model.m_hat, model.p
        self.dims = np.array([self.nh, self.n, self.m, self.mh, self.p], dtype=np.int64)

    def run(self, z0: np.ndarray, t_span: tuple[float, float], t_eval: np.ndarray, *, edges: Sequence[float] | None, rtol: float,
            atol: float, what: str = "m_relation") -> MRelationRun:
        """Integrate over t_span and evaluate the run at the sample times, as solve_ivp(fun, t_span, z0, t_eval=t_eval).

        Parameters
        ----------
        z0 : ndarray (n_hat + n,)
            [xi0, x0], xi0 = m(x0).
        t_span : (float, float)
            Start and end of the run, t0 < t1.
        t_eval : ndarray (N,)
            Increasing sample times in t_span, at least one.
        edges : [lo, lo_margin, hi, hi_margin] or None
            Stop where y = h(x) falls to lo + lo_margin or rises to hi - hi_margin (one output; run_m_relation's
            leaves_certified_set); None: no event.
        rtol, atol : float
            The tolerances (``M_RELATION_TOL``).

        Raises
        ------
        NumericalError
            As ``simulate._integrate``.
        """
        t0, t1 = float(t_span[0]), float(t_span[1])
        t_eval = np.ascontiguousarray(t_eval, dtype=float).reshape(-1)
        if not (t0 < t1 and t_eval.size and np.all(np.diff(t_eval) > 0) and t0 <= t_eval[0] and t_eval[-1] <= t1):
            raise ValueError("t_span must increase and hold t_eval, increasing and not empty")
        n, m, nh = self.n, self.m, self.nh
        status, out, hit, nfev, steps = _integrate(self.core, self.core.link_rhs, self.kernels, (self.link.eval_link, self.link.eval_u), self.dims,
                                                   z0, np.array([[t0, t1]]), t_eval, np.array([0, t_eval.size], dtype=np.int64),
                                                   np.zeros((1, nh)), np.zeros(4), np.zeros((n, n)), np.zeros((m, n)), np.zeros((m, 2)), 0, 0,
                                                   np.empty(0) if edges is None else np.asarray(edges, dtype=float), rtol, atol, what)
        if status == 1:
            empty = np.empty((0, 0))
            return MRelationRun(t=np.empty(0), xi=empty, x=empty, u=empty, v=empty, psi=empty, y=empty, m=empty,
                                left=(float(hit[0]), hit[1:].copy()), nfev=nfev, steps=steps)
        N = t_eval.size
        V, Uo, PSI, Y, MX = np.empty((N, self.mh)), np.empty((N, m)), np.empty((N, self.p)), np.empty((N, self.p)), np.empty((N, nh))
        self.core.link_samples(self.kernels.eval_xi, self.kernels.eval_x, self.link.eval_link, self.link.eval_u, self.dims, t_eval, out,
                               V, Uo, PSI, Y, MX)
        Z = out.T
        return MRelationRun(t=t_eval, xi=Z[:nh].copy(), x=Z[nh:].copy(), u=Uo.T.copy(), v=V.T.copy(), psi=PSI.T.copy(), y=Y.T.copy(),
                            m=MX.T.copy(), left=None, nfev=nfev, steps=steps)


def m_relation_loop(model, up, u) -> MRelationLoop:
    """The compiled m-relation loop of a design under the input u(t) (``up``: the design's artefacts by stage).

    Imports the core and the design's kernels as :func:`tracking_loop` does (shared with it), and the link
    module (b, c and m of x, u of t; keyed by :func:`link_key`), generated and compiled on its first use.

    Parameters
    ----------
    model : Model
    up : dict of str to Artefact
    u : sympy Matrix (m, 1)
        The spec's ``simulate.m_relation.u``, parsed.

    Raises
    ------
    Unsupported
        numba is missing, ``$ASHC_COMPILED`` is ``0``, or an expression has no numba form: use the scipy path.
    """
    core, kernels = _design_kernels(model, up)
    link = _load_kernels(lambda: link_source(model, up, u), "ashc_link", link_key(model, up, u), model)
    return MRelationLoop(core, kernels, link, model)
