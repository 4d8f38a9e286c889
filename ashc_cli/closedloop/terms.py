"""The design's terms bundled once from the artefacts: the maps every closed loop evaluates (plant, abstraction,
interface), compiled into fused numpy functions on first use.

:func:`design_matrices` is the one place that says where each term comes from and what shape it has; every loop
(these fused functions, the batch of :mod:`~ashc_cli.closedloop.batch`, the tracking kernels of
:mod:`~ashc_cli.closedloop.compiled` and falsify's of :mod:`~ashc_cli.closedloop.falsify_loop`) takes the terms it
reads from it by name."""

from __future__ import annotations

import numpy as np
import sympy as sp

from ashc_cli.problem.model import Model, compile_terms, sparse_jacobian

#: Each term's shape, in the sizes n_hat, n, m, m_hat, p of the model.
SHAPES = {"phi": ("n_hat", 1), "delta": ("n_hat", "m_hat"), "l": ("m", 1), "dpd": ("n", "m_hat"), "p": ("n", 1),
          "kappa": ("p", 1), "dp": ("n", "n_hat"), "f_bar": ("n", 1), "g": ("n", "m"), "h": ("p", 1), "dh": ("p", "n"),
          "b": ("m_hat", 1), "c": ("m_hat", "m"), "m": ("n_hat", 1)}


def design_matrices(model: Model, up: dict, names, replace: dict | None = None) -> dict[str, sp.Matrix]:
    """The design's terms ``names`` as sympy matrices, each checked against its shape.

    phi = phi_bar(xi), delta(xi), l(xi), dpd = dp/dxi delta(xi), p(xi), kappa(xi), dp = dp/dxi(xi) of the
    abstraction and the manifold; f_bar(x), g(x), h(x), dh = dh/dx(x), b(x), c(x) and m(x) of the plant, the link and
    the left inverse.  For a plant written as f(x, u), f_bar is f(x, u) and g = 0 (a loop then evaluates f at the
    input it applies).

    Parameters
    ----------
    model : Model
    up : dict of str to Artefact
        The design's artefacts by stage (those the names need).
    names : iterable of str
        Keys of :data:`SHAPES`.
    replace : dict, optional
        Terms a loop builds its own way (falsify's f_bar at the saturated input, the tracking run's disturbance),
        by name; they are checked against the shape too.

    Returns
    -------
    dict of str to sympy Matrix

    Raises
    ------
    ValueError
        A term's shape is not the one :data:`SHAPES` gives.
    """
    sources = {"phi": lambda: model.phi_bar, "delta": lambda: up["delta"].expr("delta"), "l": lambda: model.l,
               "dpd": lambda: up["bound"].expr("dp_delta"), "p": lambda: up["manifold"].expr("p"),
               "kappa": lambda: up["kappa"].expr("kappa"), "dp": lambda: up["manifold"].expr("dp_dxi"),
               "f_bar": lambda: model.f_bar if model.affine else model.f,
               "g": lambda: model.g if model.affine else sp.zeros(model.n, model.m), "h": lambda: model.h,
               "dh": lambda: sparse_jacobian(model.h, model.x), "b": lambda: up["delta"].expr("b"),
               "c": lambda: up["delta"].expr("c"), "m": lambda: up["inverse"].expr("m")}
    sizes = {"n_hat": model.n_hat, "n": model.n, "m": model.m, "m_hat": model.m_hat, "p": model.p, 1: 1}
    out = {}
    for name in names:
        matrix = (replace or {}).get(name)
        matrix = sources[name]() if matrix is None else matrix
        expected = tuple(sizes[s] for s in SHAPES[name])
        if tuple(matrix.shape) != expected:
            raise ValueError(f"{name} has shape {tuple(matrix.shape)}, expected {expected}")
        out[name] = matrix
    return out


class DesignTerms:
    """The numeric terms of a design, compiled into fused functions, each on its first use.

    ``at_xi(xi)`` gives phi_bar, delta, l, dp/dxi delta and kappa at one abstract state; ``at_x(x)`` gives
    f_bar, g, h, b and c at one concrete state.  One call each per right-hand side keeps the ODE fast.
    ``h_m(x)`` gives h and m alone, for the m-relation's start and stop.  The compiled loops
    (ashc_cli.closedloop.compiled) call neither at_xi nor at_x, so they are compiled only when something evaluates them (the tests' oracle; on the
    Cuk converter the two take 0.05-0.1 s to lambdify, b(x) the largest).
    """

    def __init__(self, model: Model, up: dict):
        self.n, self.m, self.nh, self.mh, self.p = model.n, model.m, model.n_hat, model.m_hat, model.p
        T = design_matrices(model, up, ("phi", "delta", "l", "dpd", "kappa", "p", "f_bar", "g", "h", "b", "c", "m"))
        self._terms = {
            "xi": ([T[k] for k in ("phi", "delta", "l", "dpd", "kappa", "p")], model.xi),
            # a plant written as f(x, u): f_bar is f(x, u), g = 0 and b is b(x, u) (at_x takes the input)
            "x": ([T[k] for k in ("f_bar", "g", "h", "b", "c", "m")], list(model.x) + list(model.u)),
            "h_m": ([T["h"], T["m"]], model.x),
            "abstraction": ([T[k] for k in ("phi", "delta", "kappa")], model.xi),
        }
        self._values = model.values
        self._compiled = {}
        self.p_map = model.numeric(up["manifold"].expr("p"), list(model.xi))
        self.kappa = model.numeric(up["kappa"].expr("kappa"), list(model.xi))
        self.L = np.asarray(up["bound"].value("L"))
        self.K = np.asarray(up["stabilise"].values.get("K", np.zeros((model.m, model.n))), dtype=float).reshape(model.m, model.n)
        self.U = model.U

    def _fused(self, which: str):
        if which not in self._compiled:
            terms, args = self._terms[which]
            self._compiled[which] = compile_terms(terms, list(args), self._values)
        return self._compiled[which]

    def at_xi(self, xi: np.ndarray) -> list[np.ndarray]:
        """[phi_bar (n_hat,1), delta (n_hat,m_hat), l (m,1), dp/dxi delta (n,m_hat), kappa (p,1), p (n,1)] at xi."""
        return self._fused("xi")(xi)

    def abstraction(self, xi: np.ndarray) -> list[np.ndarray]:
        """[phi_bar (n_hat,1), delta (n_hat,m_hat), kappa (p,1)] at xi: the abstraction alone (a plan on it reads
        nothing else; half the work of :meth:`at_xi` on the Cuk converter)."""
        return self._fused("abstraction")(xi)

    def at_x(self, x: np.ndarray, u: np.ndarray | None = None) -> list[np.ndarray]:
        """[f_bar (n,1), g (n,m), h (p,1), b (m_hat,1), c (m_hat,m), m (n_hat,1)] at x (for a plant written as f(x, u):
        f(x, u) and b(x, u) at the input u, zero when not given)."""
        x = np.asarray(x, dtype=float)
        u = np.zeros((self.m,) + x.shape[1:]) if u is None else np.asarray(u, dtype=float)
        return self._fused("x")(np.concatenate([x, u]))

    def h_m(self, x: np.ndarray) -> list[np.ndarray]:
        """[h (p,1), m (n_hat,1)] at x: the m-relation's start and where it stops."""
        return self._fused("h_m")(x)
