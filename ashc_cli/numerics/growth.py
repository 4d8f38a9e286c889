"""Sound successor boxes of a grid's cells over one sampling period, for x' = f(x, u) with u held (the transitions of
:mod:`ashc_cli.numerics.grid_games`), by a growth bound as SCOTS computes it, with the centre's flow enclosed too.

Over a box D of states and the input box, the caller gives (proved, :func:`ashc_cli.numerics.interval.enclose`):
``Mf`` >= sup |f_i|, ``Jabs`` >= sup |df_i/dx_j| and the growth matrix ``L`` (L_ii >= sup df_i/dx_i, L_ij = Jabs_ij
off the diagonal).  One substep of length h from the box c +- r (every point of it and of its flow in D):

- the flow stays within c +- (r + h Mf) (checked inside D, else the input is not admissible from the cell);
- the centre: x_c(h) = c + h f(c) + e; with |x_c(s) - c| <= rho(s) = s |f(c)| + Jabs Mf s^2 / 2 (since |f(x_c(s))|
  <= |f(c)| + Jabs Mf s), |e| <= int_0^h Jabs rho(s) ds = Jabs |f(c)| h^2 / 2 + Jabs Jabs Mf h^3 / 6;
- a point c + d of the box: |x(h) - x_c(h)| <= expm(L h) |d| (the growth bound: L is a Metzler bound of the
  Jacobian, so the deviation is dominated by the linear system with matrix L);

so the box after h is (c + h f(c)) +- (expm(L h) r + |e| + pad), and ``substeps`` such steps make the
period.  ``pad`` covers the floating-point evaluation of f at the centres (``FLOAT_PAD`` of sup |f| times h): f(c)
is evaluated in double precision, not in interval arithmetic, which the caller's evidence must say.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ashc_cli.numerics.grid_games import Grid, Transitions

__all__ = ["GrowthBounds", "FLOAT_PAD", "successor_boxes", "growth_transitions"]

#: Relative padding of f's double-precision value at a centre (times sup |f| and the substep).
FLOAT_PAD = 1e-12


@dataclass(frozen=True)
class GrowthBounds:
    """Bounds of f over the states D and the inputs, per input of the grid or shared; shared by every box, or one
    per box (a leading axis of N: local bounds, each on its own D).

    Attributes
    ----------
    Mf : ndarray (d,) or (N, d)
        sup |f_i|.
    Jabs : ndarray (d, d) or (N, d, d)
        sup |df_i / dx_j|.
    L : ndarray (d, d) or (N, d, d)
        The growth matrix: sup df_i/dx_i on the diagonal, Jabs off it.
    D_lo, D_hi : ndarray (d,) or (N, d)
        The states the bounds hold on (the flow must stay there).
    """

    Mf: np.ndarray
    Jabs: np.ndarray
    L: np.ndarray
    D_lo: np.ndarray
    D_hi: np.ndarray


def successor_boxes(f: Callable[[np.ndarray], np.ndarray], centre: np.ndarray, radius: np.ndarray, bounds: GrowthBounds,
                    tau: float, substeps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The boxes holding the flow of f from the boxes centre +- radius after tau.

    Parameters
    ----------
    f : callable
        (N, d) states -> (N, d) f at those states (the input fixed).
    centre, radius : ndarray (N, d), (d,) or (N, d)
    bounds : GrowthBounds
    tau : float
    substeps : int

    Returns
    -------
    centre, radius : ndarray (N, d)
        The box at tau.
    stays : bool ndarray (N,)
        Whether every substep's tube lies in D (else the bound does not hold: the input is not admissible).
    """
    h = tau / substeps
    c = np.array(centre, dtype=float)
    N, d = c.shape
    Mf = np.broadcast_to(np.asarray(bounds.Mf, dtype=float), (N, d))
    Jabs = np.broadcast_to(np.asarray(bounds.Jabs, dtype=float), (N, d, d))
    grow = sla.expm(np.broadcast_to(np.asarray(bounds.L, dtype=float), (N, d, d)) * h)
    grow = np.maximum(grow, 0.0) * (1 + 1e-12) + 1e-300          # expm of a Metzler matrix is nonnegative; round up
    second = np.einsum("nij,njk,nk->ni", Jabs, Jabs, Mf) * h ** 3 / 6 + FLOAT_PAD * Mf.max(axis=1, keepdims=True) * h
    r = np.broadcast_to(np.asarray(radius, dtype=float), c.shape).copy()
    stays = np.ones(N, dtype=bool)
    for _ in range(substeps):
        tube = r + h * Mf
        stays &= np.all((c - tube >= bounds.D_lo) & (c + tube <= bounds.D_hi), axis=1)
        fc = f(c)
        step = h * fc
        # the rounding of c + h f(c) (a few units in the last place of the larger of the two), beyond FLOAT_PAD's
        rounding = 4 * np.spacing(np.abs(c) + np.abs(step))
        r = np.einsum("nij,nj->ni", grow, r) + np.einsum("nij,nj->ni", Jabs, np.abs(fc)) * (h * h / 2) + second + rounding
        c = c + step
    return c, r, stays


def growth_transitions(grid: Grid, fields: list[Callable[[np.ndarray], np.ndarray]], bounds: list[GrowthBounds], tau: float,
                       substeps: int = 4) -> Transitions:
    """The transitions of every (cell, input) of ``grid`` over tau (:func:`successor_boxes` from each cell).

    Parameters
    ----------
    grid : Grid
    fields : list of callable
        Per input, f(., u) on (N, d) states.
    bounds : list of GrowthBounds
        Per input (or one shared, repeated); shared by every cell or one per cell (a leading axis of grid.size).
    tau : float
        The sampling period.
    substeps : int

    Returns
    -------
    Transitions
        An input is admissible from a cell only when every substep's tube lies in the grid (the abstraction's
        guarantee, Theorem 2, needs xi in V at every time) and in the bounds' region.
    """
    centres = grid.centres()
    half = grid.eta / 2
    N, U, d = grid.size, len(fields), len(grid.cells)
    lo = np.empty((N, U, d), dtype=np.int32)          # int32: the transitions are the memory of the games
    hi = np.empty((N, U, d), dtype=np.int32)
    inside = np.empty((N, U), dtype=bool)
    lo_v, hi_v = np.asarray(grid.lo, dtype=float), np.asarray(grid.hi, dtype=float)
    for u, (f, b) in enumerate(zip(fields, bounds)):
        # the flow must stay in the grid (V) within the period too, not only at its end: the bounds' region is cut to it
        inner = GrowthBounds(b.Mf, b.Jabs, b.L, np.maximum(b.D_lo, lo_v), np.minimum(b.D_hi, hi_v))
        c, r, stays = successor_boxes(f, centres, half, inner, tau, substeps)
        stays &= np.all(np.isfinite(c) & np.isfinite(r), axis=1)
        lo[:, u], hi[:, u], fits = grid.index_range(c - r, c + r)
        inside[:, u] = stays & fits
    return Transitions(lo, hi, inside)
