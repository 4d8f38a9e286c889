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
from scipy import ndimage

__all__ = ["Grid", "Transitions", "contained", "admissible", "pre", "safety", "Phase", "Winning", "chain", "hold_sets",
           "geodesic", "layers", "Route", "route", "ROUTE_SLACK"]


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

    def cell_of(self, x: np.ndarray) -> int:
        """The flat index of the cell holding the point x (d,) (on a shared face, the upper cell; clipped to the grid)."""
        ilo, _, _ = self.index_range(np.asarray(x, dtype=float), np.asarray(x, dtype=float))
        return int(np.ravel_multi_index(tuple(ilo), self.cells))

    def cells_met(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """The flat indices of the cells the box [lo, hi] meets."""
        ilo, ihi, _ = self.index_range(np.asarray(lo, dtype=float), np.asarray(hi, dtype=float))
        axes = np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(ilo, ihi)], indexing="ij")
        return np.ravel_multi_index(tuple(a.reshape(-1) for a in axes), self.cells)

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


def contained(grid: Grid, mask: np.ndarray, trans: Transitions, cells: np.ndarray | None = None) -> np.ndarray:
    """Whether the successors of each (cell, input) all lie in the cell set ``mask`` (size, inputs) bool.

    Parameters
    ----------
    grid : Grid
    mask : bool ndarray (size,)
    trans : Transitions
    cells : int ndarray (K,), optional
        Only these cells' rows (K, inputs).

    Returns
    -------
    bool ndarray (size, inputs)
        False where the successor set leaves the grid.
    """
    S = _summed(grid, mask)
    d = len(grid.cells)
    lo, hi, inside = (trans.lo, trans.hi, trans.inside) if cells is None else (trans.lo[cells], trans.hi[cells], trans.inside[cells])
    count = np.zeros(inside.shape, dtype=np.int64)
    for corner in product((0, 1), repeat=d):      # inclusion-exclusion over the box's 2^d corners
        idx = tuple(np.where(c, hi[..., i] + 1, lo[..., i]) for i, c in enumerate(corner))
        sign = -1 if (d - sum(corner)) % 2 else 1
        count += sign * S[idx]
    size = np.prod(hi.astype(np.int64) - lo + 1, axis=-1)
    return inside & (count == size)


def admissible(grid: Grid, mask: np.ndarray, trans: Transitions, cells: np.ndarray) -> np.ndarray:
    """The inputs admissible at every one of ``cells`` towards ``mask`` (inputs,) bool: those whose successors from
    each of the cells all lie in the set (the inputs a feedback law may choose when the state may be in any of them).

    Parameters
    ----------
    grid : Grid
    mask : bool ndarray (size,)
    trans : Transitions
    cells : int ndarray (K,)

    Returns
    -------
    bool ndarray (inputs,)
    """
    return np.all(contained(grid, mask, trans, np.asarray(cells, dtype=np.int64)), axis=0)


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
    tube : bool ndarray (size,), optional
        The cells whose whole period stays in the set (what a hold needs between its samples, before its last);
        None: ``target`` (the set is only asked of the samples).
    """

    target: np.ndarray
    by: int
    hold: int
    tube: np.ndarray | None = None

    @property
    def during(self) -> np.ndarray:
        """The cells a hold may be in at a sample before its last (``tube``, else ``target``)."""
        return self.target if self.tube is None else self.tube


@dataclass(frozen=True)
class Winning:
    """The winning sets of :func:`chain`.

    Attributes
    ----------
    reach : list of bool ndarray (steps + 1, size)
        Per phase p, ``reach[p][k]``: from cell c at step k, with phase p still to start, the task can be met.
    done : bool ndarray (steps + 1, size)
        After the last phase: staying safe to the end.
    starts : list of bool ndarray (steps + 1, size)
        Per phase p, ``starts[p][s]``: cells from which p's hold begun at step s can be kept and the rest met.
    """

    reach: list
    done: np.ndarray
    starts: list = None

    def start(self) -> np.ndarray:
        """The cells from which the whole task can be met from step 0 (size,) bool."""
        return self.reach[0][0] if self.reach else self.done[0]

    def after(self, p: int) -> np.ndarray:
        """What must follow phase p's hold: the next phase's winning sets, or staying safe after the last."""
        return self.reach[p + 1] if p + 1 < len(self.reach) else self.done


def hold_sets(grid: Grid, phase: Phase, safe: np.ndarray, after: np.ndarray, trans: Transitions, s: int) -> list[np.ndarray]:
    """The sets a hold of ``phase`` begun at step s must keep to: ``sets[j]`` at step s + j, j = 0 .. hold (in the
    target, in its tube before the last sample, safe, and at the end in ``after[s + hold]``).

    Parameters
    ----------
    grid : Grid
    phase : Phase
    safe : bool ndarray (steps + 1, size)
    after : bool ndarray (steps + 1, size)
        What must follow the hold (the next phase's winning sets, or staying safe).
    trans : Transitions
    s : int
        The step the hold begins at (s + hold <= steps).

    Returns
    -------
    list of bool ndarray (size,)
    """
    end = s + phase.hold
    sets = [phase.target & safe[end] & after[end]]
    for k in range(end - 1, s - 1, -1):
        sets.insert(0, phase.during & phase.target & safe[k] & pre(grid, sets[0], trans)[0])
    return sets


def _hold_starts(grid: Grid, phase: Phase, safe: np.ndarray, after: np.ndarray, trans: Transitions, steps: int) -> np.ndarray:
    """start[s]: cells from which a hold of ``phase`` begun at step s <= by can be kept (:func:`hold_sets`); steps
    past the horizon are not allowed."""
    start = np.zeros((steps + 1, grid.size), dtype=bool)
    for s in range(min(phase.by, steps - phase.hold) + 1):
        start[s] = hold_sets(grid, phase, safe, after, trans, s)[0]
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
    after, reach, begun = done, [], []
    for phase in reversed(phases):
        starts = _hold_starts(grid, phase, safe, after, trans, steps)
        begun.insert(0, starts)
        win = np.zeros((steps + 1, grid.size), dtype=bool)
        last = min(phase.by, steps)
        win[last] = starts[last]
        for k in range(last - 1, -1, -1):
            win[k] = starts[k] | (safe[k] & pre(grid, win[k + 1], trans)[0])
        reach.insert(0, win)
        after = win
    return Winning(reach, done, begun)


def geodesic(grid: Grid, target: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """Steps from each cell to ``target`` through ``allowed`` cells (a move to any of the 3^d - 1 neighbours is one
    step), inf where no such path: how far a route still has to go, around what it may not cross.

    Parameters
    ----------
    grid : Grid
    target, allowed : bool ndarray (size,)

    Returns
    -------
    float ndarray (size,)
    """
    shape, d = grid.cells, len(grid.cells)
    ok = np.asarray(allowed, dtype=bool).reshape(shape)
    front = np.asarray(target, dtype=bool).reshape(shape) & ok
    dist = np.where(front, 0.0, np.inf)
    seen, k = front.copy(), 0
    box = ndimage.generate_binary_structure(d, d)
    while front.any():
        k += 1
        grown = ndimage.binary_dilation(seen, structure=box, mask=ok)
        front = grown & ~seen
        dist[front] = k
        seen = grown
    return dist.reshape(-1)


def layers(grid: Grid, target: np.ndarray, allowed: np.ndarray, trans: Transitions, most: int) -> np.ndarray:
    """How many periods each cell needs, at the fewest, to be driven into ``target`` through ``allowed`` cells (the
    attractor's layers of a time-invariant reach game: layer j is pre of layer j - 1 within ``allowed``), inf where
    ``most`` layers do not reach it.

    Parameters
    ----------
    grid : Grid
    target, allowed : bool ndarray (size,)
    trans : Transitions
    most : int

    Returns
    -------
    float ndarray (size,)
    """
    reached = np.asarray(target, dtype=bool).copy()
    depth = np.where(reached, 0.0, np.inf)
    for j in range(1, most + 1):
        grown = reached | (allowed & pre(grid, reached, trans)[0])
        if np.array_equal(grown, reached):
            break
        depth[grown & ~reached] = j
        reached = grown
    return depth


#: The route's state is taken as possibly in any cell within this share of a cell of it: the input it holds must be
#: admissible from each (the state is integrated, not exact, and may sit on a face).
ROUTE_SLACK = 1e-6


@dataclass(frozen=True)
class Route:
    """One run of the table from a start: the feedback law (the cell's admissible inputs, one chosen) applied to the
    state the caller's ``advance`` moves.

    Attributes
    ----------
    choice : int ndarray (steps,)
        The input held over each period.
    cells : int ndarray (steps + 1,)
        The cell at each sample.
    phase : int ndarray (steps + 1,)
        The phase worked on at each sample (len(phases): all met, staying safe).
    states : float ndarray (steps + 1, d)
        The state at each sample.
    holds : list of int
        The step each phase's hold began at.
    widened : int
        Samples after the first at which no input was admissible from every cell near the state, and the state's own
        cell decided (at the first the state is xi0 exactly, which lies in each closed cell it touches).
    """

    choice: np.ndarray
    cells: np.ndarray
    phase: np.ndarray
    states: np.ndarray
    holds: list
    widened: int


def _next_phase(grid: Grid, phases: list[Phase], safe: np.ndarray, trans: Transitions, win: Winning, state: list, k: int,
                c: np.ndarray) -> int:
    """Begin and end holds at step k with the state in one of the cells ``c``: ``state`` = [phase, its hold sets or
    None, the hold's first step], updated in place (a hold begins only when every one of the cells may begin it);
    returns how many holds began."""
    begun = 0
    while True:
        p, held, s = state
        if held is not None and k == s + phases[p].hold:
            state[:] = [p + 1, None, -1]
        elif held is None and p < len(phases) and k <= phases[p].by and bool(np.all(win.starts[p][k][c])):
            state[:] = [p, hold_sets(grid, phases[p], safe, win.after(p), trans, k), k]
            begun += 1
        else:
            return begun


def route(grid: Grid, safe: np.ndarray, phases: list[Phase], trans: Transitions, win: Winning, x0: np.ndarray,
          advance, effort: np.ndarray) -> Route:
    """Run the table of :func:`chain` from the state x0: at each sample, the inputs whose successors from the state's
    cell (and the cells within :data:`ROUTE_SLACK` of it) all lie in the next winning set; of those, the one whose
    successor box's centre needs the fewest periods to where the phase's hold can begin (:func:`layers`, through the
    cells safe at some step), then the fewest cells around the cells that never win (:func:`geodesic`); the one
    deepest in the target during a hold; and then the least ``effort``.

    Parameters
    ----------
    grid : Grid
    safe : bool ndarray (steps + 1, size)
    phases : list of Phase
    trans : Transitions
    win : Winning
        Of :func:`chain` on these (``x0``'s cell must be in ``win.start()``).
    x0 : ndarray (d,)
    advance : callable
        (x, u) -> the state one period later under input index u held.
    effort : ndarray (inputs,)
        The tie-break (for example |v|).

    Returns
    -------
    Route
    """
    steps = safe.shape[0] - 1
    slack = ROUTE_SLACK * grid.eta
    centre = np.ravel_multi_index(tuple(((trans.lo + trans.hi) // 2).transpose(2, 0, 1)), grid.cells)       # (size, inputs)
    anywhere = np.ones(grid.size, dtype=bool)
    to_go = [geodesic(grid, ph.target, win.reach[p].any(axis=0) | ph.target) for p, ph in enumerate(phases)]
    near = [layers(grid, win.starts[p].any(axis=0), safe.any(axis=0), trans, steps) for p in range(len(phases))]
    depth = [geodesic(grid, ~ph.target, anywhere) for ph in phases]
    choice, cells, phase, states, holds = [], [], [], [np.asarray(x0, dtype=float)], []
    state, widened = [0, None, -1], 0
    x = states[0]
    for k in range(steps + 1):
        c = grid.cell_of(x)
        around = grid.cells_met(x - slack, x + slack)
        holds += [k] * _next_phase(grid, phases, safe, trans, win, state, k, around)
        cells.append(c)
        phase.append(state[0])
        if k == steps:
            break
        p, held, s = state
        mask = held[k + 1 - s] if held is not None else (win.reach[p][k + 1] if p < len(phases) else win.done[k + 1])
        ok = admissible(grid, mask, trans, around)
        if not ok.any():
            ok = admissible(grid, mask, trans, np.array([c]))
            widened += k > 0        # at the start the state is xi0 itself, in each closed cell it touches
        if not ok.any():
            raise ValueError(f"no admissible input at step {k} from cell {c}: the start was not winning")
        zero = np.zeros(trans.inputs)
        first, second = ((zero, zero) if p >= len(phases) else (-depth[p][centre[c]], zero) if held is not None else
                         (near[p][centre[c]], to_go[p][centre[c]]))
        order = np.lexsort((np.arange(trans.inputs), effort, second, first, ~ok))
        u = int(order[0])
        choice.append(u)
        x = np.asarray(advance(x, u), dtype=float)
        states.append(x)
    return Route(np.array(choice, dtype=np.int64), np.array(cells, dtype=np.int64), np.array(phase, dtype=np.int64),
                 np.array(states), holds, widened)
