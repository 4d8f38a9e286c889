"""The states left out of the design (outside the output's cone, :class:`ashc_cli.problem.influence.Beside`),
integrated beside a stored run of the closed loop: they read the designed states and the input and act on nothing the
loop reads, so a run of the loop drives them one way, and they are integrated afterwards on its samples.
"""

from __future__ import annotations

import numpy as np
import sympy as sp

from ashc_cli.closedloop.rk import fixed_step
from ashc_cli.problem.model import lambdify

__all__ = ["integrate_beside"]


def integrate_beside(beside, t: np.ndarray, x: np.ndarray, u: np.ndarray, w0=None) -> np.ndarray:
    """The left-out states along a run: x_out' = f_out(x, u) from ``beside.x0``, by the classical Runge-Kutta step
    between the run's samples, the designed states and the input interpolated linearly within each step.

    Parameters
    ----------
    beside : Beside
        The states left out (their f, the full plant's symbols, their start and the parameters).
    t : ndarray (N,)
        The run's sample times (increasing).
    x, u : ndarray (n_kept, N), (m, N)
        The designed states and the input at the samples.
    w0 : array_like (d,), optional
        The run's constant disturbance: e_out(x) w0 is added to their right-hand sides (as the loop adds e(x) w0).

    Returns
    -------
    ndarray (k, N)
        The left-out states at the samples (not checked: a left-out state faster than the sampling interval
        diverges, to inf or NaN, without a word; docs/guide.md).
    """
    n = len(beside.kept) + len(beside.index)
    drive = beside.f
    if w0 is not None and beside.e is not None:
        drive = beside.f + beside.e * sp.Matrix(np.asarray(w0, dtype=float).reshape(-1))
    f = lambdify(drive, [*beside.x, *beside.u], beside.values)
    kept, out = np.asarray(beside.kept), np.asarray(beside.index)
    k = out.size
    X = np.empty((k, t.size))
    X[:, 0] = beside.x0
    full = np.empty(n)

    def field(z: np.ndarray) -> np.ndarray:
        # z = [x_out, s]: s in [0, 1] the position within the step, for the interpolated x and u
        s = z[-1]
        full[kept] = (1 - s) * xa + s * xb
        full[out] = z[:-1]
        return np.r_[np.asarray(f(*full, *((1 - s) * ua + s * ub)), dtype=float).reshape(k), 1.0 / h]

    for i in range(t.size - 1):
        h = float(t[i + 1] - t[i])
        xa, xb, ua, ub = x[:, i], x[:, i + 1], u[:, i], u[:, i + 1]
        if h <= 0:
            X[:, i + 1] = X[:, i]
            continue
        z = np.r_[X[:, i], 0.0]
        X[:, i + 1] = fixed_step(field, z, h, field(z))[:-1]
    return X
