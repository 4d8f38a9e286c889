"""Bounded-time games on a uniform grid of the abstraction's state space: the fixed points a grid tool (SCOTS,
Dionysos) computes, here over the one to three states of xi (issue 42, the planner on the abstraction).

Transitions are boxes of cells.  The successors of cell c under input u over one sampling period lie in the box of
cells ``lo[c, u] .. hi[c, u]`` (index ranges per dimension, inclusive), made by the caller from a sound
over-approximation of the successor set; ``inside[c, u]`` is False where that set leaves the grid (the input is not
admissible there).  A box of cells lies in a set of cells when the set's count over the box, read from a summed-area
table in 2^d lookups, equals the box's size: one vectorised test per (cell, input) and no list of successors (the
memory is cells x inputs x 2 d indices).

The games are those of a task on the output mapped to cells (:func:`chain`): stay in ``safe[k]`` at every step k,
and reach the targets in order, each by its deadline, holding each for its hold.  Everything is a backward
recursion of :func:`pre`, the cells with an admissible input whose successors all lie in a set.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import product

import numpy as np
from numba import njit

__all__ = ["Grid", "Transitions", "contained", "pre", "safety", "Phase", "Winning", "chain"]


@dataclass(frozen=True)
class Grid:
    """A uniform grid of the box [lo, hi] with ``cells[i]`` cells along dimension i (cells are numbered in C order).

    Attributes
    ----------
    lo, hi : ndarray (d,)
    cells : tuple of int
    """

    lo: np.ndarray
    hi: np.ndarray
    cells: tuple

    @property
    def eta(self) -> np.ndarray:
        """The cell widths (d,)."""
        return (np.asarray(self.hi, dtype=float) - np.asarray(self.lo, dtype=float)) / np.asarray(self.cells, dtype=float)

    @property
    def size(self) -> int:
        """The number of cells."""
        return int(np.prod(self.cells))

    def centres(self) -> np.ndarray:
        """The cell centres, (size, d), in C order."""
        axes = [np.asarray(self.lo, dtype=float)[i] + (np.arange(n) + 0.5) * self.eta[i] for i, n in enumerate(self.cells)]
        return np.stack([g.reshape(-1) for g in np.meshgrid(*axes, indexing="ij")], axis=1)

    def index_range(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The cells a box [lo, hi] meets (..., d) -> (ilo, ihi, inside): index ranges (inclusive, clipped to the grid)
        and whether the box lies in the grid.  A box edge on a cell boundary meets the cells on both sides (closed
        cells: the range is never too small)."""
        g0, eta = np.asarray(self.lo, dtype=float), self.eta
        top = np.asarray(self.cells) - 1
        inside = np.all((lo >= g0) & (hi <= np.asarray(self.hi, dtype=float)), axis=-1)       # False for NaN too
        with np.errstate(invalid="ignore"):
            ilo = np.floor(np.clip(np.nan_to_num((lo - g0) / eta, nan=0.0), 0, top)).astype(np.int64)
            ihi = np.floor(np.clip(np.nan_to_num((hi - g0) / eta, nan=0.0), 0, top)).astype(np.int64)
        return ilo, ihi, inside

    def inner(self, lo, hi) -> np.ndarray:
        """Cells lying in the closed box [lo, hi] (size,) bool: an inner approximation of a set to reach."""
        c, half = self.centres(), self.eta / 2
        return np.all((c - half >= np.asarray(lo, dtype=float)) & (c + half <= np.asarray(hi, dtype=float)), axis=1)


@dataclass(frozen=True)
class Transitions:
    """Where each (cell, input) may go in one sampling period.

    Attributes
    ----------
    lo, hi : int ndarray (size, inputs, d)
        The box of cells holding every successor (inclusive index ranges).
    inside : bool ndarray (size, inputs)
        Whether the successor set lies in the grid (else the input is not admissible at the cell).
    """

    lo: np.ndarray
    hi: np.ndarray
    inside: np.ndarray

    @property
    def inputs(self) -> int:
        """The number of inputs."""
        return int(self.inside.shape[1])


def _summed(grid: Grid, mask: np.ndarray) -> np.ndarray:
    """The summed-area table of a cell set, one leading zero per axis: S[i + 1, j + 1] = count over [0..i, 0..j]."""
    table = np.asarray(mask, dtype=np.int64).reshape(grid.cells)
    for axis in range(table.ndim):
        table = np.cumsum(table, axis=axis)
    return np.pad(table, [(1, 0)] * table.ndim)


def contained(grid: Grid, mask: np.ndarray, trans: Transitions) -> np.ndarray:
    """Whether the successors of each (cell, input) all lie in the cell set ``mask`` (size, inputs) bool.

    Parameters
    ----------
    grid : Grid
    mask : bool ndarray (size,)
    trans : Transitions

    Returns
    -------
    bool ndarray (size, inputs)
        False where the successor set leaves the grid.
    """
    S = _summed(grid, mask)
    d = len(grid.cells)
    count = np.zeros(trans.inside.shape, dtype=np.int64)
    for corner in product((0, 1), repeat=d):      # inclusion-exclusion over the box's 2^d corners
        idx = tuple(np.where(c, trans.hi[..., i] + 1, trans.lo[..., i]) for i, c in enumerate(corner))
        sign = -1 if (d - sum(corner)) % 2 else 1
        count += sign * S[idx]
    size = np.prod(trans.hi - trans.lo + 1, axis=-1)
    return trans.inside & (count == size)


@njit(cache=True, nogil=True)
def _pre_kernel(S, strides, lo, hi, inside, choice):
    """choice[c] = the first input u whose box lo[c, u] .. hi[c, u] the summed-area table S (flat, strides per
    padded axis) counts full, -1 if none: the 2^d corners of each box, the inputs of a cell tried until one fits."""
    N, U, d = lo.shape
    for c in range(N):
        choice[c] = -1
        for u in range(U):
            if not inside[c, u]:
                continue
            count = 0
            size = 1
            for i in range(d):
                size *= hi[c, u, i] - lo[c, u, i] + 1
            for corner in range(1 << d):
                idx = 0
                ones = 0
                for i in range(d):
                    if (corner >> i) & 1:
                        idx += (hi[c, u, i] + 1) * strides[i]
                        ones += 1
                    else:
                        idx += lo[c, u, i] * strides[i]
                count += S[idx] if (d - ones) % 2 == 0 else -S[idx]
            if count == size:
                choice[c] = u
                break


def pre(grid: Grid, mask: np.ndarray, trans: Transitions) -> tuple[np.ndarray, np.ndarray]:
    """The controllable predecessor of a cell set: cells with an input whose successors all lie in it (compiled:
    each cell's inputs are tried in order until one fits).

    Parameters
    ----------
    grid : Grid
    mask : bool ndarray (size,)
    trans : Transitions

    Returns
    -------
    cells : bool ndarray (size,)
    choice : int ndarray (size,)
        The first such input of each cell (-1 where none).
    """
    S = _summed(grid, mask)
    strides = np.array(S.strides, dtype=np.int64) // S.itemsize
    choice = np.empty(grid.size, dtype=np.int64)
    _pre_kernel(S.reshape(-1), strides, trans.lo, trans.hi, trans.inside, choice)
    return choice >= 0, choice


def safety(grid: Grid, safe: np.ndarray, trans: Transitions, steps: int) -> np.ndarray:
    """The cells from which the run can stay in ``safe[k]`` at steps k .. steps, per start step.

    Parameters
    ----------
    grid : Grid
    safe : bool ndarray (steps + 1, size)
        The safe cells at each step.
    trans : Transitions
    steps : int

    Returns
    -------
    bool ndarray (steps + 1, size)
        ``win[k]``: safe from step k to the end.
    """
    win = np.zeros((steps + 1, grid.size), dtype=bool)
    win[steps] = safe[steps]
    for k in range(steps - 1, -1, -1):
        win[k] = safe[k] & pre(grid, win[k + 1], trans)[0]
    return win


@dataclass(frozen=True)
class Phase:
    """One reach of a task on the grid: enter ``target`` by step ``by`` and stay in it for ``hold`` steps.

    Attributes
    ----------
    target : bool ndarray (size,)
        The cells of the set (an inner approximation, deflated as the caller's guarantee needs).
    by, hold : int
        The deadline and the hold, in sampling steps.
    """

    target: np.ndarray
    by: int
    hold: int


@dataclass(frozen=True)
class Winning:
    """The winning sets of :func:`chain`.

    Attributes
    ----------
    reach : list of bool ndarray (steps + 1, size)
        Per phase p, ``reach[p][k]``: from cell c at step k, with phase p still to start, the task can be met.
    done : bool ndarray (steps + 1, size)
        After the last phase: staying safe to the end.
    """

    reach: list
    done: np.ndarray

    def start(self) -> np.ndarray:
        """The cells from which the whole task can be met from step 0 (size,) bool."""
        return self.reach[0][0] if self.reach else self.done[0]


def _hold_starts(grid: Grid, phase: Phase, safe: np.ndarray, after: np.ndarray, trans: Transitions, steps: int) -> np.ndarray:
    """start[s]: cells from which a hold of ``phase`` begun at step s <= by (in the target and safe at steps s .. s +
    hold, then in ``after[s + hold]``) can be kept; steps past the horizon are not allowed."""
    start = np.zeros((steps + 1, grid.size), dtype=bool)
    for s in range(min(phase.by, steps - phase.hold) + 1):
        end = s + phase.hold
        held = phase.target & safe[end] & after[end]
        for k in range(end - 1, s - 1, -1):
            held = phase.target & safe[k] & pre(grid, held, trans)[0]
        start[s] = held
    return start


def chain(grid: Grid, safe: np.ndarray, phases: list[Phase], trans: Transitions, steps: int) -> Winning:
    """The task as a game: stay in ``safe[k]`` at every step k <= steps, and meet the phases in order (each target
    entered by its deadline and held for its hold; the next phase starts where the last hold ends).

    Parameters
    ----------
    grid : Grid
    safe : bool ndarray (steps + 1, size)
        The safe cells at each step (the always set, less the avoid sets in their windows).
    phases : list of Phase
    trans : Transitions
    steps : int
        The horizon in sampling steps.

    Returns
    -------
    Winning
    """
    done = safety(grid, safe, trans, steps)
    after, reach = done, []
    for phase in reversed(phases):
        starts = _hold_starts(grid, phase, safe, after, trans, steps)
        win = np.zeros((steps + 1, grid.size), dtype=bool)
        last = min(phase.by, steps)
        win[last] = starts[last]
        for k in range(last - 1, -1, -1):
            win[k] = starts[k] | (safe[k] & pre(grid, win[k + 1], trans)[0])
        reach.insert(0, win)
        after = win
    return Winning(reach, done)
