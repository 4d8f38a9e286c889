"""The per-design half of the compiled closed loops: the design's expressions printed from sympy into small
numba *kernels* (``eval_xi``, ``eval_x``; for the m-relation ``eval_link`` and ``eval_u``), common
subexpressions eliminated and the parameter values put in as :func:`ashc_cli.problem.model.compile_flat` does,
cached on disk under a SHA-256 of their sympy input (``$ASHC_CACHE/compiled``, else ``~/.cache/ashc/compiled``);
and the loops that run them through the design-independent core (:mod:`ashc_cli.closedloop.tracking_core`,
:mod:`ashc_cli.closedloop.governor`): :func:`tracking_loop` / :meth:`TrackingLoop.run` and
:func:`m_relation_loop` / :meth:`MRelationLoop.run`, in ``simulate``'s shapes.  ``ASHC_COMPILED=0`` turns the
compiled path off (:class:`Unsupported`, which simulate reports as a one-line error).  How the core agrees with scipy, and what it
costs, is in docs/guide.md ("Compiled closed loops").
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
import tempfile
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import sympy as sp
from sympy.printing.pycode import PythonCodePrinter

from ashc_cli.closedloop.terms import design_matrices
from ashc_cli.errors import NumericalError, Unsupported
from ashc_cli.closedloop.interface import SATURATE_CODES, interface_codes
from ashc_cli.closedloop.laws import setpoint_law
from ashc_cli.numerics.linalg import lower_bandwidth
from ashc_cli.problem.model import almost_everywhere

__all__ = ["Unsupported", "SATURATE_CODES", "interface_codes", "TrackingLoop", "TrackingRun", "tracking_loop", "abstract_signal", "MRelationLoop", "MRelationRun", "m_relation_loop", "cache_dir",
           "available", "kernel_source", "kernel_key", "link_source", "link_key", "load_source", "SIGNAL_IMPORT"]


#: Bump when the kernels' printing or the modules they import change (it is part of their cache key; numba keys the
#: cached machine code of a generated module by its own file only).
KERNEL_VERSION = 6


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
    spec's time signals (triangle, square, step) as calls of :mod:`ashc_cli.closedloop.signals`."""

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
    # ashc_cli.closedloop.signals, which a module printing them must import (the m-relation's link module does).
    def _print_triangle(self, expr):
        return f"signal_triangle(float({self._print(expr.args[0])}))"

    def _print_square(self, expr):
        return f"signal_square(float({self._print(expr.args[0])}))"

    def _print_step(self, expr):
        return f"signal_step(float({self._print(expr.args[0])}))"


_KERNEL_SIGNATURES = {"eval_xi": "types.void(F1, F1, F2, F1, F2, F1, F1)", "eval_x": "types.void(F1, F1, F2, F1)",
                      "eval_link": "types.void(F1, F1, F2, F1)", "eval_u": "types.void(F1, F1)"}


def emit_kernel(name: str, state: str, symbols: Sequence[sp.Symbol], outputs: Sequence[tuple[str, sp.MatrixBase, bool]], values,
                 signature: str | None = None) -> str:
    """The numba function ``name(state, *outputs)`` filling its output arrays from the matrices.

    ``outputs``: (array name, matrix, as_vector); a column written to a 1-D array when ``as_vector``.
    ``signature``: the numba signature (text); by default the one :data:`_KERNEL_SIGNATURES` gives ``name``.

    Parameters
    ----------
    name : str
        The function's name (``eval_xi``, ``eval_x``, ``eval_link`` or ``eval_u`` when ``signature`` is not given).
    state : str
        The name of its first argument, a 1-D array: ``symbols[i]`` is read from ``state[i]``.
    symbols : sequence of sympy Symbol
        The state's entries, in order (placeholders for entries the matrices do not use).
    outputs : sequence of (str, sympy Matrix, bool)
        As above; the array names follow ``state`` as the function's arguments.
    values : mapping of Symbol to float, or None
        The parameter values, put in as numbers.
    signature : str, optional
        As above.

    Returns
    -------
    str
        The decorated function's source; the module holding it imports ``math``, ``njit`` and ``types``, defines
        ``F1`` and ``F2`` (and imports the signals, :data:`SIGNAL_IMPORT`, when the matrices call them).

    Raises
    ------
    Unsupported
        An expression depends on a symbol that is not in ``symbols``, or has no numba form.
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
    """The kernels' outputs (array name, matrix, as a vector), from :func:`~ashc_cli.closedloop.terms.design_matrices`:
    phi, delta, l, dpd, kap, pm of xi; fb, g, h of [x, u] (a plant written as f(x, u): fb = f(x, u) and g = 0; the
    kernel's state is [x, u], an input-affine one ignores u)."""
    replace = {}
    w0 = _run_disturbance(model)
    if w0 is not None:      # the tracking run's constant disturbance, switched by the kernel's last state entry
        f = model.f_bar if model.affine else model.f
        replace["f_bar"] = f + DISTURBANCE_ON * model.e * sp.Matrix(w0)
    try:
        T = design_matrices(model, up, ("phi", "delta", "l", "dpd", "kappa", "p", "f_bar", "g", "h"), replace)
    except ValueError as exc:
        raise Unsupported(str(exc)) from None
    xi_terms = [("phi", T["phi"], True), ("delta", T["delta"], False), ("l", T["l"], True), ("dpd", T["dpd"], False),
                ("kap", T["kappa"], True), ("pm", T["p"], True)]
    return xi_terms, [("fb", T["f_bar"], True), ("g", T["g"], False), ("h", T["h"], True)]


#: The x kernel's last state entry: 1 switches the tracking run's constant disturbance e(x) w0 on, 0 off.
DISTURBANCE_ON = sp.Symbol("_disturbance_on", real=True)


def _run_disturbance(model) -> list[float] | None:
    """The tracking run's constant disturbance w0 (``simulate.tracking.disturbance``), or None."""
    tr = model.spec.simulate.tracking
    return None if model.e is None or tr is None or tr.disturbance is None else [float(w) for w in tr.disturbance]


def kernel_source(model, up) -> str:
    """The numba module of a design's expressions: ``eval_xi`` and ``eval_x`` (Python source).

    The matrices are those ``DesignTerms`` compiles: phi_bar, l and f_bar, g, h from the model; delta
    (delta stage), p (manifold), dp/dxi delta (bound) and kappa (kappa stage).

    Parameters
    ----------
    model : Model
        The spec's systems (phi_bar, l, f_bar, g, h, the states and the parameter values are read).
    up : dict of str to Artefact
        The design's artefacts by stage (``delta``, ``manifold``, ``bound`` and ``kappa`` are read).

    Returns
    -------
    str
        The module's source.

    Raises
    ------
    Unsupported
        A matrix does not have the shape the core expects, or an expression has no numba form.
    """
    xi_terms, x_terms = _design_terms(model, up)
    parts = [f'"""Generated by ashc_cli.closedloop.compiled (first for design {model.spec.name!r}): the expressions of a design; do not edit."""',
             "import math", "from numba import njit, types", "", "F1 = types.float64[::1]", "F2 = types.float64[:, ::1]", "", "",
             emit_kernel("eval_xi", "xi", list(model.xi), xi_terms, model.values), "",
             emit_kernel("eval_x", "x", list(model.x) + list(model.u) + [DISTURBANCE_ON], x_terms, model.values)]
    return "\n".join(parts)


# --- the m-relation's link and input signal, printed from sympy ----------------------------------------------

#: The line a generated module holds to call the spec's time signals (:mod:`ashc_cli.closedloop.signals`).
SIGNAL_IMPORT = "from ashc_cli.closedloop.signals import signal_square, signal_step, signal_triangle"


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
    """The numba module of the m-relation's link and input: ``eval_link([x, u], b, c, m)`` and ``eval_u([t], u)``.

    Parameters
    ----------
    model : Model
    up : dict of str to Artefact
        The design's artefacts (b and c from the delta stage, m from the inverse stage).
    u : sympy Matrix (m, 1)
        The spec's ``simulate.m_relation.u`` as parsed (``t`` is :data:`ashc_cli.problem.model.TIME`).
    """
    from ashc_cli.problem.model import TIME

    x_terms, u_terms = _link_terms(model, up, u)
    parts = [f'"""Generated by ashc_cli.closedloop.compiled (first for design {model.spec.name!r}): the m-relation link and input; do not edit."""',
             "import math", "import numpy as np", "from numba import njit, types", "", "F1 = types.float64[::1]", "F2 = types.float64[:, ::1]",
             SIGNAL_IMPORT, "", "", emit_kernel("eval_link", "x", list(model.x) + list(model.u), x_terms, model.values), "",
             emit_kernel("eval_u", "t", [TIME], u_terms, model.values)]
    return "\n".join(parts)


def link_key(model, up, u) -> str:
    """What the m-relation's kernels are made from, hashed (as :func:`kernel_key`): b, c, m, u, the states,
    the parameter values, the signals' import, the generator's version and sympy's.

    Parameters
    ----------
    model, up, u
        As :func:`link_source`.

    Returns
    -------
    str
        The first 24 hex digits of a SHA-256.
    """
    from ashc_cli.problem.model import TIME

    x_terms, u_terms = _link_terms(model, up, u)
    digest = hashlib.sha256(f"ashc link {KERNEL_VERSION} sympy {sp.__version__}|{SIGNAL_IMPORT}".encode())
    for arr, matrix, as_vector in x_terms + u_terms:
        digest.update(f"|{arr}|{as_vector}|{sp.srepr(matrix)}".encode())
    digest.update(f"|{sp.srepr(list(model.x))}|{sp.srepr(list(model.u))}|{sp.srepr(TIME)}".encode())
    digest.update("|".join(f"{sp.srepr(k)}={float(v)!r}" for k, v in sorted(model.values.items(), key=lambda kv: str(kv[0]))).encode())
    return digest.hexdigest()[:24]


def abstract_signal(model, v):
    """The numba module of the spec's abstract input v(t) (``abstract_controller.kind: signal``): ``eval_u([t], v)``
    and ``law``, the same behind the abstract controllers' signature (:data:`~ashc_cli.closedloop.laws.LAW_SIGNATURE`).

    Parameters
    ----------
    model : Model
    v : sympy Matrix (m_hat, 1)
        The expressions in t (:data:`ashc_cli.problem.model.TIME`) and the parameters.

    Returns
    -------
    module
        With ``eval_u`` and ``law``, compiled (or loaded from the cache directory).

    Raises
    ------
    Unsupported
        v has the wrong shape, or an expression has no numba form.
    """
    from ashc_cli.problem.model import TIME

    v = sp.Matrix(v)
    if tuple(v.shape) != (model.m_hat, 1):
        raise Unsupported(f"v has shape {tuple(v.shape)}, expected {(model.m_hat, 1)}")
    digest = hashlib.sha256(f"ashc signal {KERNEL_VERSION} sympy {sp.__version__}|{SIGNAL_IMPORT}|{sp.srepr(v)}|{sp.srepr(TIME)}".encode())
    digest.update("|".join(f"{sp.srepr(k)}={float(val)!r}" for k, val in sorted(model.values.items(), key=lambda kv: str(kv[0]))).encode())

    def source() -> str:
        return "\n".join([f'"""Generated by ashc_cli.closedloop.compiled (first for design {model.spec.name!r}): the abstract input v(t); do not edit."""',
                          "import math", "import numpy as np", "from numba import njit, types", "", "F1 = types.float64[::1]", "F2 = types.float64[:, ::1]",
                          SIGNAL_IMPORT, "", "", emit_kernel("eval_u", "t", [TIME], [("u", v, True)], model.values), "", "",
                          "@njit(types.void(types.float64, F1, F1, F1, F2, F1, F1), cache=True, error_model='numpy')",
                          "def law(t, z, ref, phi, delta, prm, v):", '    """v = v(t), the abstract controller of kind signal."""',
                          "    tt = np.empty(1)", "    tt[0] = t", "    eval_u(tt, v)", ""])

    return _load_kernels(source, "ashc_signal", digest.hexdigest()[:24], model)


# --- the core: closed loop, integrator, sampling (the same text for every design) ---------------------------



_MODULES: dict[str, object] = {}


def load_source(source, prefix: str, key: str | None = None):
    """Import generated source from the cache directory, once per process.

    The file is ``<prefix>_<key>.py``, ``key`` defaulting to the SHA-256 of the text; ``source`` may be a
    function returning the text, called only when the file is missing (the kernels are keyed by their sympy
    input, so a second run skips common-subexpression elimination too).  A file is written atomically and never
    rewritten, since numba's cache is keyed on its time stamp.

    Parameters
    ----------
    source : str or callable returning str
        The module's text (a callable needs ``key``: the default hashes the text).
    prefix : str
        The start of the file's and the module's name.
    key : str, optional
        The rest of the name.

    Returns
    -------
    module
        The imported module (the same object for the same name later in the process).

    Raises
    ------
    Unsupported
        numba is missing, ``$ASHC_COMPILED`` is ``0``, or no cache directory can be written (:func:`cache_dir`).
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
    symbols, the parameter values, the generator's version and sympy's.

    Parameters
    ----------
    model, up
        As :func:`kernel_source`.

    Returns
    -------
    str
        The first 24 hex digits of a SHA-256.
    """
    xi_terms, x_terms = _design_terms(model, up)
    digest = hashlib.sha256(f"ashc kernels {KERNEL_VERSION} sympy {sp.__version__}".encode())
    for arr, matrix, as_vector in xi_terms + x_terms:
        digest.update(f"|{arr}|{as_vector}|{sp.srepr(matrix)}".encode())
    digest.update(f"|{sp.srepr(list(model.xi))}|{sp.srepr(list(model.x))}|{sp.srepr(list(model.u))}".encode())
    digest.update("|".join(f"{sp.srepr(k)}={float(v)!r}" for k, v in sorted(model.values.items(), key=lambda kv: str(kv[0]))).encode())
    return digest.hexdigest()[:24]


def _integrate(core, rhs, kernels, link, loop, run, what: str):
    """One call of the core's DOP853 ``integrate``; the samples (rows of run.t_eval) and the event.

    ``link`` holds eval_link, eval_u and the law (the core's no_link and no_signal and the controller's law for the
    tracking loop, the m-relation's kernels and no_law for it); ``loop`` is the
    core's Loop, ``run`` its Segments (run.edges is empty or [lo, lo_margin, hi, hi_margin], the m-relation's
    event); ``what`` names the scenario in an error.

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
    from ashc_cli.closedloop import rk

    run = run._replace(z0=np.ascontiguousarray(run.z0, dtype=float).reshape(-1), edges=np.ascontiguousarray(run.edges, dtype=float),
                       rtol=float(run.rtol), atol=float(run.atol))
    out = np.full((run.t_eval.size, run.z0.size), np.nan)
    hit = np.full(run.z0.size + 1, np.nan)
    status, written, seg, nfev, steps = core.integrate(rhs, kernels.eval_xi, kernels.eval_x, link[0], link[1], link[2], loop, run, rk.DOP853, out, hit)
    if status < 0:
        t_bad = run.t_eval[written - 1] if written > 0 else run.t_bounds[min(seg, len(run.t_bounds) - 1), 0]
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
    scale, slack : ndarray (N,) or None
        The governor's s and the margin of its invariance condition at the samples (None for the set-point law).
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
    scale: np.ndarray | None = None
    slack: np.ndarray | None = None


class TrackingLoop:
    """The compiled tracking closed loop of one design (build it with :func:`tracking_loop`)."""

    def __init__(self, core, kernels, model, up):
        self.core, self.kernels = core, kernels
        self.nh, self.n, self.m, self.mh, self.p = model.n_hat, model.n, model.m, model.m_hat, model.p
        self.L = np.ascontiguousarray(np.asarray(up["bound"].value("L"), dtype=float).reshape(self.n, self.n))
        self.dims = np.array([self.nh, self.n, self.m, self.mh, self.p, int(model.affine), int(_run_disturbance(model) is not None),
                              lower_bandwidth(self.L)], dtype=np.int64)
        K = up["stabilise"].values.get("K", np.zeros((model.m, model.n)))
        self.K = np.ascontiguousarray(np.asarray(K, dtype=float).reshape(self.m, self.n))
        self.U = np.ascontiguousarray(np.asarray(model.U, dtype=float).reshape(self.m, 2))
        self.lam = float(up["bound"].value("lambda"))
        self.eps = float(up["bound"].value("epsilon"))
        # a fitted p's PDE residual, |L^T rho| <= rho_bar (bound.rho_bar): the comparison system and the governor count it
        self.rho = float(up["bound"].values.get("rho_bar", 0.0))

    @staticmethod
    def _flags(q_kind: str, saturate) -> tuple[int, int]:
        try:
            return interface_codes(q_kind, saturate)
        except ValueError as exc:
            raise Unsupported(str(exc)) from None

    def _prm(self, gain: float, v_max: float) -> np.ndarray:
        return np.array([gain, v_max, self.lam, self.eps, self.rho], dtype=float)

    def _loop(self, prm: np.ndarray, q_kind: str, saturate, lprm=None):
        """The core's Loop of this design with the loop's prm, the interface's codes and the law's parameters."""
        q_ls, sat = self._flags(q_kind, saturate)
        lprm = np.zeros(0) if lprm is None else np.ascontiguousarray(lprm, dtype=float).reshape(-1)
        return self.core.Loop(self.dims, np.ascontiguousarray(prm, dtype=float), self.L, self.K, self.U, q_ls, sat, lprm)

    def law(self, xi, x, xi_ref, gain: float, v_max: float, q_kind: str, saturate, w: float = 0.0):
        """(v, u, dz) at one point under the set-point law: the compiled tracking_law, dz = [dxi, dx, dw]."""
        loop = self._loop(self._prm(gain, v_max), q_kind, saturate, [gain, v_max])
        z = np.ascontiguousarray(np.r_[np.ravel(xi), np.ravel(x), w], dtype=float)
        v, u, dz = np.empty(self.mh), np.empty(self.m), np.empty(z.size)
        self.core.closed_loop(self.kernels.eval_xi, self.kernels.eval_x, setpoint_law, loop, 0.0, z,
                              np.ascontiguousarray(xi_ref, dtype=float).reshape(self.nh), v, u, dz)
        return v, u, dz

    def run(self, z0: np.ndarray, segments: Sequence[tuple[float, float, np.ndarray, int]], refs: Sequence[np.ndarray], *,
            gain: float, v_max: float, q_kind: str, saturate, rtol: float, atol: float, what: str = "tracking",
            governor: tuple | None = None, law: tuple | None = None) -> TrackingRun:
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
            The set-point controller (the governor's v_sp; the law's parameters when ``law`` is None).
        q_kind, saturate :
            ``interface.q`` and ``interface.saturate``.
        rtol, atol : float
            The tolerances (``TRACKING_TOL``).
        governor : tuple, optional
            (W_max, c, grid, bisections, backoffs): run the guaranteed governor (:mod:`ashc_cli.closedloop.governor`)
            instead of the set-point law; the run then records s and the slack.
        law : (law, prm), optional
            The abstract controller (:mod:`~ashc_cli.closedloop.controllers`): its compiled law and parameters;
            default the set-point law with [gain, v_max].

        Raises
        ------
        NumericalError
            As ``simulate._integrate``: the step size fell below the spacing of floating-point numbers, or a
            sample is not finite.
        """
        evals = [np.asarray(te, dtype=float).reshape(-1) for _, _, te, _ in segments]
        if not evals or any(te.size == 0 for te in evals):
            raise ValueError("every segment needs its sample times")
        offsets = np.cumsum([0] + [te.size for te in evals]).astype(np.int64)
        t_eval = np.ascontiguousarray(np.concatenate(evals))
        t_bounds = np.ascontiguousarray(np.array([[float(a), float(b)] for a, b, _, _ in segments], dtype=float))
        index = np.array([i for *_, i in segments], dtype=np.int64)
        seg_refs = np.ascontiguousarray(np.stack([np.asarray(refs[i], dtype=float).reshape(self.nh) for i in index]))
        prm = self._prm(gain, v_max)
        rhs = self.core.tracking_rhs
        law_kernel, lprm = (setpoint_law, [gain, v_max]) if law is None else law
        if governor is not None:
            from ashc_cli.closedloop import governor as gov

            w_level, rate, grid, bisections, backoff = governor
            prm = np.r_[prm[:4], w_level, rate, self.rho, grid, bisections, np.asarray(backoff, dtype=float)]
            rhs = gov.governor_rhs
        loop = self._loop(prm, q_kind, saturate, lprm)
        run = self.core.Segments(z0, t_bounds, t_eval, offsets, seg_refs, np.empty(0), rtol, atol)
        _, out, _, nfev, steps = _integrate(self.core, rhs, self.kernels, (self.core.no_link, self.core.no_signal, law_kernel), loop, run, what)
        keep = np.ones(t_eval.size, dtype=bool)
        keep[offsets[1:-1]] = False            # each later segment's first sample repeats the previous end
        seg_of_row = np.repeat(np.arange(len(segments), dtype=np.int64), np.diff(offsets))
        sampled = self.core.Samples(np.empty((t_eval.size, self.mh)), np.empty((t_eval.size, self.m)),
                                    np.empty((t_eval.size, self.p)), np.empty((t_eval.size, self.p)))
        V, Uo, PSI, Y = sampled
        fxi, fx = self.kernels.eval_xi, self.kernels.eval_x
        scale = slack = None
        if governor is None:
            self.core.samples(fxi, fx, law_kernel, loop, t_eval, out, seg_of_row, seg_refs, sampled)
        else:
            S, SL = np.empty(t_eval.size), np.empty(t_eval.size)
            gov.governor_samples(fxi, fx, loop, out, seg_of_row, seg_refs, sampled, S, SL)
            scale, slack = S[keep].copy(), SL[keep].copy()
        Z = out[keep].T
        nh, n = self.nh, self.n
        return TrackingRun(t=t_eval[keep], xi=Z[:nh].copy(), x=Z[nh:nh + n].copy(), w=Z[-1].copy(), v=V[keep].T.copy(), u=Uo[keep].T.copy(),
                           psi=PSI[keep].T.copy(), y=Y[keep].T.copy(), reference_index=index[seg_of_row[keep]],
                           psi_end=PSI[offsets[1:] - 1].copy(), nfev=nfev, steps=steps, scale=scale, slack=slack)


def _design_kernels(model, up):
    """The core and the design's kernels (eval_xi, eval_x), imported (generated and compiled when the cache
    directory does not hold them)."""
    if not available():
        raise Unsupported("numba is not installed (or ASHC_COMPILED=0)")
    key = kernel_key(model, up)
    from numba.core.errors import NumbaExperimentalFeatureWarning

    with warnings.catch_warnings():
        # The kernels reach the core as first-class functions, which numba calls experimental (tested here).
        warnings.simplefilter("ignore", NumbaExperimentalFeatureWarning)
        from ashc_cli.closedloop import tracking_core as core   # numba compiles (or loads from its cache) on import
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

    Parameters
    ----------
    model : Model
        The spec's systems (the kernels' expressions, the dimensions and U are read).
    up : dict of str to Artefact
        The design's artefacts by stage (``stabilise`` (K), ``manifold``, ``kappa``, ``delta`` and ``bound`` (L,
        lambda, epsilon, dp/dxi delta) are read).

    Returns
    -------
    TrackingLoop

    Raises
    ------
    Unsupported
        numba is missing, ``$ASHC_COMPILED`` is ``0``, or an expression has no numba form (simulate then stops with a one-line error).
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

    The concrete system runs open loop under u(t); the abstract one receives v = b(x) + c(x) u (eq. (22)): the right-hand side run_m_relation integrates, with the same DOP853 as the tracking loop.
    """

    def __init__(self, core, kernels, link, model):
        self.core, self.kernels, self.link = core, kernels, link
        self.nh, self.n, self.m, self.mh, self.p = model.n_hat, model.n, model.m, model.m_hat, model.p
        self.dims = np.array([self.nh, self.n, self.m, self.mh, self.p, int(model.affine), 0, 0], dtype=np.int64)   # no disturbance, no L

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
        loop = self.core.Loop(self.dims, np.zeros(4), np.zeros((n, n)), np.zeros((m, n)), np.zeros((m, 2)), 0, 0, np.zeros(0))   # dims only are read
        run = self.core.Segments(z0, np.array([[t0, t1]]), t_eval, np.array([0, t_eval.size], dtype=np.int64), np.zeros((1, nh)),
                                 np.empty(0) if edges is None else np.asarray(edges, dtype=float), rtol, atol)
        status, out, hit, nfev, steps = _integrate(self.core, self.core.link_rhs, self.kernels, (self.link.eval_link, self.link.eval_u, self.core.no_law),
                                                   loop, run, what)
        if status == 1:
            empty = np.empty((0, 0))
            return MRelationRun(t=np.empty(0), xi=empty, x=empty, u=empty, v=empty, psi=empty, y=empty, m=empty,
                                left=(float(hit[0]), hit[1:].copy()), nfev=nfev, steps=steps)
        N = t_eval.size
        sampled = self.core.Samples(np.empty((N, self.mh)), np.empty((N, m)), np.empty((N, self.p)), np.empty((N, self.p)))
        V, Uo, PSI, Y = sampled
        MX = np.empty((N, nh))
        self.core.link_samples(self.kernels.eval_xi, self.kernels.eval_x, self.link.eval_link, self.link.eval_u, self.dims, t_eval, out, sampled, MX)
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
        numba is missing, ``$ASHC_COMPILED`` is ``0``, or an expression has no numba form (simulate then stops with a one-line error).
    """
    core, kernels = _design_kernels(model, up)
    link = _load_kernels(lambda: link_source(model, up, u), "ashc_link", link_key(model, up, u), model)
    return MRelationLoop(core, kernels, link, model)
