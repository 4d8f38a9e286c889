"""The falsifier's closed loop in numpy, on a batch of points at once: the design's maps fused into one compiled
function of xi and one of x (:class:`BatchPlant`), the interface with its saturation, and the two systems.  The
compiled runs (:mod:`ashc_cli.closedloop.falsify_core`) are checked against it (tests/test_falsify_loop.py); the
falsifier's linearisation uses it.
"""

from __future__ import annotations

import numpy as np

from ashc_cli.numerics.linalg import pinv
from ashc_cli.problem.model import Model, apply_saturation, compile_flat, sparse_jacobian


class BatchPlant:
    """The design's maps evaluated on a batch of points at once, fused into one compiled function of xi and
    one of x (each call returns every term, shape (N, rows, cols))."""

    def __init__(self, model: Model, arts: dict):
        xi_terms = {"phi": model.phi_bar, "delta": arts["delta"].expr("delta"), "l": model.l,
                    "dpd": arts["bound"].expr("dp_delta"), "p": arts["manifold"].expr("p"), "kappa": arts["kappa"].expr("kappa"),
                    "dp": arts["manifold"].expr("dp_dxi")}
        x_terms = {"f_bar": model.f_bar, "g": model.g, "h": model.h, "dh": sparse_jacobian(model.h, model.x)}
        self._xi = self._named(xi_terms, list(model.xi), model)
        self._x = self._named(x_terms, list(model.x), model)
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

    def at_x(self, x: np.ndarray) -> dict[str, np.ndarray]:
        """f_bar, g, h, dh (dh/dx) at the columns of x (n, N)."""
        return self._x(x)


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
        A = plant.L.T @ a["dpd"]
        B = plant.L.T @ b["g"]
        q = pinv(B) @ A                                                          # (N, m, m_hat)
    else:
        q = np.zeros((xi.shape[1], model.m, model.m_hat))
    return {"a": a, "b": b, "kx": kx, "q": q}


def _mv(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A stack of matrices (N, r, c) times a stack of vectors (N, c)."""
    return (A @ v[:, :, None])[:, :, 0]


def apply(model: Model, pre: dict, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """u, xi', x' for the batch with input v (N, m_hat): u = sat(l + K (x - p) + q v).

    Parameters
    ----------
    model : Model
    pre : dict
        From :func:`interface`.
    v : ndarray (N, m_hat)
    """
    a, b = pre["a"], pre["b"]
    u = apply_saturation(a["l"][:, :, 0], pre["kx"] + _mv(pre["q"], v), model.U, model.spec.interface.saturate)
    dxi = a["phi"][:, :, 0] + _mv(a["delta"], v)
    dx = b["f_bar"][:, :, 0] + _mv(b["g"], u)
    return u, dxi, dx


def controls(model: Model, plant: BatchPlant, xi: np.ndarray, x: np.ndarray, v: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """v, u, xi' and x' for the batch (shapes (N, m_hat), (N, m), (N, n_hat), (N, n)) with the interface
    u = sat(l(xi) + K (x - p(xi)) + q(xi, x) v) (model.apply_saturation) and the two systems.

    Parameters
    ----------
    model : Model
    plant : BatchPlant
    xi, x : ndarray (n_hat, N), (n, N)
    v : ndarray (N, m_hat)
    """
    u, dxi, dx = apply(model, interface(model, plant, xi, x), v)
    return v, u, dxi, dx
