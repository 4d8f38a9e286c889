"""The falsifier's closed loop in numpy, on a batch of points at once: the design's maps fused into one compiled
function of xi and one of x (:class:`BatchPlant`) and the interface's terms that do not depend on v
(:func:`interface`), for the falsifier's linearisation.  The tests' numpy form of the whole loop
(tests/oracle.py ``batch_controls``, the compiled runs' oracle) is built on them.
"""

from __future__ import annotations

import numpy as np

from ashc_cli.closedloop.terms import design_matrices
from ashc_cli.numerics.linalg import least_squares_q
from ashc_cli.problem.model import Model, compile_flat


class BatchPlant:
    """The design's maps evaluated on a batch of points at once, fused into one compiled function of xi and
    one of x (each call returns every term, shape (N, rows, cols))."""

    def __init__(self, model: Model, arts: dict):
        xi_terms = design_matrices(model, arts, ("phi", "delta", "l", "dpd", "p", "kappa", "dp"))
        # A plant written as f(x, u): "f_bar" is f(x, u) and g = 0, compiled in x and u (at_x takes the inputs).
        x_terms = design_matrices(model, arts, ("f_bar", "g", "h", "dh"))
        self.m = model.m
        self._xi = self._named(xi_terms, list(model.xi), model)
        self._x = self._named(x_terms, list(model.x) + list(model.u), model)
        self.M = np.asarray(arts["stabilise"].value("M"), dtype=float)
        self.L = np.linalg.cholesky(self.M)
        self.K = np.asarray(arts["stabilise"].values.get("K", np.zeros((model.m, model.n))), dtype=float).reshape(model.m, model.n)

    @staticmethod
    def _named(terms: dict, args: list, model: Model):
        # One compiled function of every entry; the entries are written into one array (constants broadcast by
        # the assignment), several times cheaper per call than model.compile_terms on the small batches here.
        shapes = [t.shape for t in terms.values()]
        ends = np.cumsum([0] + [r * c for r, c in shapes]).tolist()
        fun = compile_flat([e for t in terms.values() for e in t], args, model.values)
        pieces = [(name, a, b, shape) for name, a, b, shape in zip(terms, ends[:-1], ends[1:], shapes)]

        def evaluate(points: np.ndarray) -> dict[str, np.ndarray]:
            N = points.shape[1]
            flat = np.empty((N, ends[-1]))
            for j, value in enumerate(fun(*points)):
                flat[:, j] = value
            return {name: flat[:, a:b].reshape((N,) + shape) for name, a, b, shape in pieces}

        return evaluate

    def at_xi(self, xi: np.ndarray) -> dict[str, np.ndarray]:
        """phi, delta, l, dpd (dp/dxi delta), p, kappa, dp (dp/dxi) at the columns of xi (n_hat, N)."""
        return self._xi(xi)

    def at_x(self, x: np.ndarray, u: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """f_bar, g, h, dh (dh/dx) at the columns of x (n, N); for a plant written as f(x, u), f_bar is f(x, u) at the
        columns of u (m, N; zero when not given: g, h and dh do not depend on it)."""
        u = np.zeros((self.m, x.shape[1])) if u is None else u
        return self._x(np.vstack([x, u]))


def interface(model: Model, plant: BatchPlant, xi: np.ndarray, x: np.ndarray) -> dict:
    """Everything of the closed loop at the columns xi (n_hat, N), x (n, N) that does not depend on v: the terms
    (``a`` of xi, ``b`` of x), K (x - p) and q (eq. (43), least squares, or 0).

    Parameters
    ----------
    model : Model
    plant : BatchPlant
    xi, x : ndarray (n_hat, N), (n, N)
    """
    a, b = plant.at_xi(xi), plant.at_x(x)
    kx = (x.T - a["p"][:, :, 0]) @ plant.K.T
    if model.spec.interface.q == "least_squares":
        q = least_squares_q(plant.L, b["g"], a["dpd"])                           # (N, m, m_hat), eq. (43)
    else:
        q = np.zeros((xi.shape[1], model.m, model.m_hat))
    return {"a": a, "b": b, "kx": kx, "q": q}
