"""The design's terms bundled once from the artefacts: the maps every closed loop evaluates (plant, abstraction,
interface), compiled into fused numpy functions on first use."""

from __future__ import annotations

import numpy as np
import sympy as sp

from ashc_cli.problem.model import Model, compile_terms


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
        m_of_x = up["inverse"].expr("m")
        self._terms = {
            "xi": ([model.phi_bar, up["delta"].expr("delta"), model.l, up["bound"].expr("dp_delta"), up["kappa"].expr("kappa"),
                    up["manifold"].expr("p")], model.xi),
            # a plant written as f(x, u): f_bar is f(x, u), g = 0 and b is b(x, u) (at_x takes the input)
            "x": ([model.f_bar if model.affine else model.f, model.g if model.affine else sp.zeros(model.n, model.m), model.h,
                   up["delta"].expr("b"), up["delta"].expr("c"), m_of_x], list(model.x) + list(model.u)),
            "h_m": ([model.h, m_of_x], model.x),
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

    def at_x(self, x: np.ndarray, u: np.ndarray | None = None) -> list[np.ndarray]:
        """[f_bar (n,1), g (n,m), h (p,1), b (m_hat,1), c (m_hat,m), m (n_hat,1)] at x (for a plant written as f(x, u):
        f(x, u) and b(x, u) at the input u, zero when not given)."""
        x = np.asarray(x, dtype=float)
        u = np.zeros((self.m,) + x.shape[1:]) if u is None else np.asarray(u, dtype=float)
        return self._fused("x")(np.concatenate([x, u]))

    def h_m(self, x: np.ndarray) -> list[np.ndarray]:
        """[h (p,1), m (n_hat,1)] at x: the m-relation's start and where it stops."""
        return self._fused("h_m")(x)
