"""The runs of ``ashc falsify`` as compiled (numba) code: one adaptive integration per run, runs over every core.

Each run is integrated on its own with the Dormand-Prince 5(4) pair of :mod:`ashc_cli.closedloop.falsify_core`
(its own step-size control), its right-hand side the design's kernels (printed from sympy by
:func:`ashc_cli.closedloop.compiled.emit_kernel`) and the core's laws; a pool of Python threads runs the
batch's runs over every core, the core releasing the GIL.  ``ASHC_COMPILED=0``, or a design whose expressions
numba cannot run, raises :class:`ashc_cli.errors.Unsupported` (falsify then exits with a one-line error); the tests'
oracle is solve_ivp on the numpy form of the loop.  The rationale and the
measurements are in docs/guide.md ("Compiled closed loops").
"""

from __future__ import annotations

import hashlib
import os
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Callable

import numpy as np
import sympy as sp

from ashc_cli.closedloop.compiled import Unsupported, emit_kernel, available, interface_codes, load_source
from ashc_cli.closedloop.laws import no_law
from ashc_cli.numerics.linalg import lower_bandwidth
from ashc_cli.closedloop.terms import design_matrices

__all__ = ["FalsifyLoop", "falsify_loop", "threads"]

#: Bump when the kernels' printing changes (part of their cache key; the core is keyed by its text).
KERNEL_VERSION = 3

#: Both kernels: (z = [xi, x], the flat output buffer).
KERNEL_SIGNATURE = "types.void(F1, F1)"




def _matrices(model, arts):
    """The kernels' matrices, in the order of the flat buffers: (name, matrix) for xi and for x."""
    try:
        T = design_matrices(model, arts, ("phi", "delta", "l", "dpd", "kappa", "p", "dp", "f_bar", "g", "h", "dh"), {"f_bar": _drift(model)})
    except ValueError as exc:
        raise Unsupported(str(exc)) from None
    xi_terms = [(k, T[name]) for k, name in (("phi", "phi"), ("delta", "delta"), ("l", "l"), ("dpd", "dpd"), ("kap", "kappa"),
                                              ("pm", "p"), ("dp", "dp"))]
    return xi_terms, [(k, T[name]) for k, name in (("fb", "f_bar"), ("g", "g"), ("h", "h"), ("dh", "dh"))]


def _drift(model) -> sp.Matrix:
    """f_bar(x); for a plant written as f(x, u), f(x, u_w) with the input the interface applies, u_w = SAT(l(xi))
    (identity feedback and q = 0: no K (x - p), no q v), so the core's x' = fb + g u with g = 0 is f(x, u_w) exactly."""
    if model.affine:
        return model.f_bar
    if model.spec.stabilisability.feedback != "identity" or model.spec.interface.q != "zero":
        raise Unsupported("a plant written as f(x, u) is falsified with identity feedback and q = 0 only")
    u = model.l
    if model.spec.interface.saturate is True:
        u = sp.Matrix([sp.Min(sp.Max(e, float(lo)), float(hi)) for e, (lo, hi) in zip(model.l, model.U)])
    return model.f_on(model.x, u)


def _flat(terms) -> sp.Matrix:
    """The matrices' entries row after row, as one column (what the core reads with the offsets of :func:`layout`)."""
    return sp.Matrix([e for _, matrix in terms for e in matrix])


def layout(nh: int, n: int, m: int, mh: int, p: int) -> np.ndarray:
    """Offsets of the terms in the flat buffers (the core's O_* indices), then the sizes of A, B and wk.

    Parameters
    ----------
    nh, n, m, mh, p : int
        n_hat, n, m, m_hat and p of the model.

    Returns
    -------
    ndarray (22,) of int64
        The offsets of phi, delta, l, dpd, kappa, p, dp/dxi in A (7), of f_bar, g, h, dh/dx in B (4), of the
        work terms in wk (8), then the lengths of A, B and wk.
    """
    sizes_a = [nh, nh * mh, m, n * mh, p, n, n * nh]                 # phi, delta, l, dpd, kappa, p, dp/dxi
    sizes_b = [n, n * m, p, p * n]                                   # f_bar, g, h, dh/dx
    sizes_w = [m, m * mh, n * m, n * mh, m * n, mh * nh, m, mh]      # kx, q, L^T g, L^T dpd, pinv(L^T g), delta^+, corr, v_in
    off = []
    for sizes in (sizes_a, sizes_b, sizes_w):
        off.extend(np.cumsum([0] + sizes[:-1]).tolist())
    totals = [sum(sizes_a), sum(sizes_b), sum(sizes_w)]
    return np.array(off + totals, dtype=np.int64)


def kernel_source(model, arts) -> str:
    """The numba module of a design's expressions for the falsifier: ``falsify_xi(z, A)`` and ``falsify_x(z, B)``.

    Parameters
    ----------
    model : Model
        The spec's systems (phi_bar, l, f_bar, g, h and the parameter values are read).
    arts : dict
        Artefacts by stage (``delta``, ``bound``, ``kappa`` and ``manifold`` are read).

    Returns
    -------
    str
        The module's source.

    Raises
    ------
    Unsupported
        A term does not have the shape the core expects.
    """
    xi_terms, x_terms = _matrices(model, arts)
    # Both kernels read z = [xi, x]; the x kernel skips the first n_hat entries (placeholders) unless f(x, u_w(xi)) reads them.
    skip = [sp.Dummy(f"skip{i}") for i in range(model.n_hat)]
    parts = [f'"""Generated by ashc_cli.closedloop.falsify_loop (first for design {model.spec.name!r}): the expressions of a design; do not edit."""',
             "import math", "from numba import njit, types", "", "F1 = types.float64[::1]", "F2 = types.float64[:, ::1]", "", "",
             emit_kernel("falsify_xi", "z", list(model.xi), [("out", _flat(xi_terms), True)], model.values, KERNEL_SIGNATURE), "",
             emit_kernel("falsify_x", "z", (skip if model.affine else list(model.xi)) + list(model.x), [("out", _flat(x_terms), True)], model.values,
                         KERNEL_SIGNATURE)]
    return "\n".join(parts)


def kernel_key(model, arts) -> str:
    """What the kernels are made from, hashed (every digit of the matrices, the symbols, the parameter values).

    Parameters
    ----------
    model, arts : Model, dict
        As for :func:`kernel_source`.

    Returns
    -------
    str
        The first 24 hex digits of a SHA-256 (also of :data:`KERNEL_VERSION` and the sympy version).
    """
    xi_terms, x_terms = _matrices(model, arts)
    digest = hashlib.sha256(f"ashc falsify kernels {KERNEL_VERSION} sympy {sp.__version__}".encode())
    for arr, matrix in xi_terms + x_terms:
        digest.update(f"|{arr}|{sp.srepr(matrix)}".encode())
    digest.update(f"|{sp.srepr(list(model.xi))}|{sp.srepr(list(model.x))}".encode())
    digest.update("|".join(f"{sp.srepr(k)}={float(v)!r}" for k, v in sorted(model.values.items(), key=lambda kv: str(kv[0]))).encode())
    return digest.hexdigest()[:24]


def threads() -> int:
    """Threads the runs are spread over: ``$ASHC_THREADS`` if set, else the cores this process may use."""
    env = os.environ.get("ASHC_THREADS", "").strip()
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            pass
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


class FalsifyLoop:
    """The compiled runs of one design (build it with :func:`falsify_loop`)."""

    def __init__(self, core, kernels, model, M: np.ndarray, L: np.ndarray, K: np.ndarray):
        self.core, self.kernels, self.model = core, kernels, model
        self.M = np.ascontiguousarray(M, dtype=float)
        self.L = np.ascontiguousarray(L, dtype=float)
        self.K = np.ascontiguousarray(np.asarray(K, dtype=float).reshape(model.m, model.n))
        self.U = np.ascontiguousarray(np.asarray(model.U, dtype=float).reshape(model.m, 2))
        q = model.spec.interface.q
        sat = model.spec.interface.saturate
        try:
            self.iprm = np.array([*interface_codes(q, sat), lower_bandwidth(self.L)], dtype=np.int64)
        except ValueError as exc:
            raise Unsupported(str(exc)) from None
        self.threads = threads()

    def run(self, st, b, tol: dict, cand: np.ndarray, W0: np.ndarray, divergence: float, lookahead: float,
            record: bool = False, progress: Callable[[int, int, float], None] | None = None, chunk: int | None = None,
            keep_inputs: bool = True, objective=None) -> dict:
        """Integrate the runs of batch ``b`` (strategies.Batch) with the setting ``st`` (strategies.Setup).

        Parameters
        ----------
        st, b :
            The search's setting and the runs (their laws, starts, references); ``st.controller``: the registered
            controller the CONTROLLER runs close the loop with and its parameters (needed when ``b`` has such runs).
        tol : dict
            ``rtol`` and ``atol`` (the latter times ``st.scale`` per state).
        cand : ndarray (C, m_hat)
            The unit inputs the greedy adversary chooses from.
        W0 : ndarray (N,)
            W(xi0, x0) per run.
        divergence, lookahead : float
            strategies.DIVERGED and strategies.GUARD_LOOKAHEAD.
        record : bool
            Also return the series at the hold boundaries (``Z``, ``err``, ``bound``, ``v``).
        progress : callable, optional
            Called after each chunk with (runs done, runs in all, seconds since the start).
        chunk : int, optional
            Runs per piece handed to a thread [default: an eighth of the runs per thread, 1 to 64].
        keep_inputs : bool
            Return the held inputs (``vused``, N x holds x m_hat).  Without them the memory does not grow with
            runs x holds; a run's inputs are the same when it is integrated again alone (its integration does
            not depend on the other runs).
        objective : numba function, optional
            A run's score at each hold boundary, of the signature ``falsify_core.OBJECTIVE_SIGNATURE`` (t, z, err,
            bound, floor); ``ratio`` is its largest [default ``falsify_core.bound_ratio``].

        Returns
        -------
        dict
            Per run (``ratio``, ``ratio_late``, ``k_at``, ``max_error``, ``left_V``,
            ``diverged``, ``vused`` (with ``keep_inputs``), ``W0``, ``forced``, ``vsup``, ``at_limit``,
            ``largest_bound``, ``steps``).
        """
        model = self.model
        nh, n, m, mh, p = model.n_hat, model.n, model.m, model.m_hat, model.p
        N, H, S = len(b), st.holds, b.refs.shape[0]
        c = np.ascontiguousarray
        dims = np.array([nh, n, m, mh, p, H, S, int(record), int(keep_inputs)], dtype=np.int64)
        off = layout(nh, n, m, mh, p)
        fprm = np.array([st.hold, st.v_limit, st.lam, st.eps, st.alpha_h, st.G, st.floor, tol["rtol"], divergence, lookahead], dtype=float)
        atol = c(tol["atol"] * st.scale, dtype=float)
        scale = c(st.scale, dtype=float)
        lo, hi = c(model.V[:, 0], dtype=float), c(model.V[:, 1], dtype=float)
        centre = c(model.V.mean(axis=1), dtype=float)
        core = self.core
        starts = core.Starts(xi0=c(b.xi0, dtype=float).reshape(N, nh), x0=c(b.x0, dtype=float).reshape(N, n),
                             mode=c(b.mode, dtype=np.int64), vtab=c(b.vtab, dtype=float).reshape(N, H, mh),
                             rho=c(b.rho, dtype=float), dwell=c(b.dwell, dtype=np.int64), amp=c(b.amp, dtype=float),
                             guard=c(b.guard, dtype=np.int64), refs=c(np.swapaxes(b.refs, 0, 1), dtype=float).reshape(N, S, nh),
                             gains=c(b.gains, dtype=float), noise=c(np.swapaxes(b.noise, 0, 1), dtype=float).reshape(N, S, mh),
                             W0=c(W0, dtype=float))
        R = N if record else 0
        outputs = core.Outputs(fout=np.zeros((N, 6)), iout=np.zeros((N, 6), dtype=np.int64),
                               vused=np.zeros((N if keep_inputs else 0, H, mh)), recZ=np.zeros((R, H + 1, nh + n)),
                               recE=np.zeros((R, H + 1)), recB=np.zeros((R, H + 1)), recV=np.zeros((R, H + 1, mh)))
        fout, iout, vused = outputs.fout, outputs.iout, outputs.vused
        recZ, recE, recB, recV = outputs.recZ, outputs.recE, outputs.recB, outputs.recV
        # Small pieces handed to a pool of threads (the compiled batch runs without the GIL): each thread takes
        # the next piece when it is done, so a stiff run holds up one thread only.
        step = int(chunk) if chunk else int(np.clip(N // (8 * self.threads), 1, 64))
        pieces = [np.arange(a, min(N, a + step), dtype=np.int64) for a in range(0, N, step)]
        if st.controller is None and np.any(b.mode == core.CONTROLLER):
            raise ValueError("runs of mode CONTROLLER need the controller's law (st.controller)")
        kernel, lprm = st.controller or (no_law, np.zeros(0))
        design = core.Design(dims=dims, off=off, fprm=fprm, iprm=self.iprm, M=self.M, L=self.L, K=self.K, U=self.U, atol=atol,
                             scale=scale, lo=lo, hi=hi, centre=centre, cand=c(cand, dtype=float), tgrid=c(st.t, dtype=float),
                             lprm=c(lprm, dtype=float).reshape(-1))
        exi, ex = self.kernels.falsify_xi, self.kernels.falsify_x
        score = core.bound_ratio if objective is None else objective

        def work(rows):
            core.run_batch(exi, ex, score, kernel, design, starts, rows, outputs)
            return rows.size

        self._dispatch(work, pieces, N, progress)
        out = {"ratio": fout[:, 0].copy(), "ratio_late": fout[:, 1].copy(), "k_at": iout[:, 0].copy(), "max_error": fout[:, 2].copy(),
               "left_V": iout[:, 1].astype(bool), "diverged": iout[:, 2].astype(bool), "W0": np.asarray(W0, dtype=float),
               "forced": iout[:, 3].copy(), "vsup": fout[:, 3].copy(), "at_limit": fout[:, 4].copy(),
               "largest_bound": float(fout[:, 5].max()) if N else 0.0, "steps": iout[:, 4:6].sum(axis=0)}
        if keep_inputs:
            out["vused"] = vused
        if record:
            out.update({"Z": recZ, "err": recE, "bound": recB, "v": recV})
        return out

    def _dispatch(self, work: Callable, pieces: list, N: int, progress: Callable[[int, int, float], None] | None) -> None:
        """``work`` on every piece, over the pool of threads (in order on one), ``progress`` after each."""
        start = time.perf_counter()
        done = 0
        if self.threads == 1 or len(pieces) == 1:
            finished = map(work, pieces)
            for count in finished:
                done += count
                if progress is not None:
                    progress(done, N, time.perf_counter() - start)
            return
        with ThreadPoolExecutor(max_workers=self.threads) as pool:
            for count in pool.map(work, pieces):
                done += count
                if progress is not None:
                    progress(done, N, time.perf_counter() - start)


def falsify_loop(model, arts, M: np.ndarray, L: np.ndarray, K: np.ndarray) -> FalsifyLoop:
    """The compiled runs of a design (``arts``: the artefacts of stabilise .. bound by stage).

    Parameters
    ----------
    model : Model
        The spec's systems (its expressions, U, and the interface's ``q`` and ``saturate``).
    arts : dict
        Artefacts by stage (``delta``, ``bound``, ``kappa`` and ``manifold`` are read).
    M, L, K : ndarray (n, n), (n, n), (m, n)
        Stabilise's M, its Cholesky factor (M = L L^T) and the feedback gain (``BatchPlant.M``, ``.L``, ``.K``).

    Returns
    -------
    FalsifyLoop

    Raises
    ------
    Unsupported
        numba is missing, ``$ASHC_COMPILED`` is ``0``, an expression has no numba form, or the interface's ``q`` or
        ``saturate`` is not one the core runs.
    """
    if not available():
        raise Unsupported("numba is not installed (or ASHC_COMPILED=0)")
    from numba.core.errors import NumbaExperimentalFeatureWarning

    with warnings.catch_warnings():
        # The kernels reach the core as first-class functions, which numba calls experimental (tested here).
        warnings.simplefilter("ignore", NumbaExperimentalFeatureWarning)
        from ashc_cli.closedloop import falsify_core as core

        try:
            kernels = load_source(lambda: kernel_source(model, arts), "ashc_falsify_kernels", kernel_key(model, arts))
        except Unsupported:
            raise
        except Exception as exc:   # numba could not type or compile an expression the printer let through
            raise Unsupported(f"numba could not compile the expressions of {model.spec.name!r}: {type(exc).__name__}: {str(exc)[:500]}") from exc
    return FalsifyLoop(core, kernels, model, M, L, K)
