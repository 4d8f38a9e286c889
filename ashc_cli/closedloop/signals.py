"""The time signals of :mod:`ashc_cli.problem.expr` (triangle, square, step) for one float, in numba: the
generated link modules of the m-relation import them (the spec's ``simulate.m_relation.u`` may call them)."""

import numpy as np
from numba import njit, types


@njit(types.float64(types.float64), cache=True, error_model='numpy')
def signal_triangle(t):
    """expr.triangle: (2/pi) int_0^t sign(sin s) ds - 1.

    Parameters
    ----------
    t : float
        The time.

    Returns
    -------
    float
        The triangle wave of period 2 pi at t, in [-1, 1] (-1 at t = 0).
    """
    tau = np.mod(t, 2.0 * np.pi)
    return -1.0 + 2.0 * tau / np.pi if tau < np.pi else 3.0 - 2.0 * tau / np.pi


@njit(types.float64(types.float64), cache=True, error_model='numpy')
def signal_square(t):
    """expr.square: sign(sin t).

    Parameters
    ----------
    t : float
        The time.

    Returns
    -------
    float
        1, -1, or 0 where sin t = 0.
    """
    return np.sign(np.sin(t))


@njit(types.float64(types.float64), cache=True, error_model='numpy')
def signal_step(t):
    """expr.step: 1 for t >= 0, else 0.

    Parameters
    ----------
    t : float
        The time.

    Returns
    -------
    float
        1.0 or 0.0 (0.0 for a NaN t).
    """
    return 1.0 if t >= 0.0 else 0.0
