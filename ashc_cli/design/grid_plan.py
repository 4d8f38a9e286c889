"""The planner on the abstraction, design side (issue 42): the abstraction xi' = phi_bar(xi) + delta(xi) v of a
design on a uniform grid of V, with v held over each sampling period tau; its transitions by a growth bound
(:mod:`ashc_cli.numerics.growth`); the task's output sets mapped to cells through kappa; and the game
(:mod:`ashc_cli.numerics.grid_games`).

Soundness.  phi_bar, delta, their Jacobians and kappa are enclosed over every cell of the grid padded by
:data:`PAD` cells (interval arithmetic, :func:`ashc_cli.numerics.interval.enclose`, once per grid:
:func:`enclose_cells`).  The bounds of f = phi_bar + delta v and of its Jacobian over |v_a| <= v_max follow by
interval sums; a period's flow from a cell stays within ``r`` cells of it (r = ceil(tau sup |f| / eta), sup over the
padded grid), so the hull of the enclosures over that window bounds f and its Jacobian over every state the cell's
flow visits (the growth bound's region), and the hull of kappa's bounds psi between samples.  The values of f at the centres the growth bound moves are double-precision
evaluations (padded: :data:`ashc_cli.numerics.growth.FLOAT_PAD`).  A reach set becomes the
cells whose every output lies in the set shrunk by ``eps`` (what |psi - y| may be, eq. (38)); an avoid set the cells
whose tube's outputs may meet the set grown by ``eps``; the always set the cells whose tube's outputs lie in it
shrunk by ``eps``: between samples as well as at them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sympy as sp

from scipy import ndimage

from ashc_cli.closedloop.batch import BatchPlant
from ashc_cli.closedloop.terms import design_matrices
from ashc_cli.errors import DesignError
from ashc_cli.numerics.grid_games import Grid, Phase, Transitions, Winning, chain
from ashc_cli.numerics.growth import GrowthBounds, growth_transitions
from ashc_cli.numerics.interval import compile_interval, enclose

__all__ = ["Grid", "GridProblem", "GridGame", "CellEnclosures", "enclose_cells", "motion_cells", "abstraction_bounds", "kappa_boxes",
           "task_cells", "safe_cells", "solve", "why_not", "memory_bytes", "PAD"]


@dataclass(frozen=True)
class GridProblem:
    """The planner's choices for one task.

    Attributes
    ----------
    cells : tuple of int
        Cells of V per abstract state.
    inputs : ndarray (U, m_hat)
        The abstract inputs the table chooses from (|v_a| <= v_max).
    tau : float
        The sampling period (s): the table's input is held over it.
    eps : float
        The tolerance the sets are deflated by (|psi - y| <= eps on the plant).
    substeps : int
        Substeps of the growth bound per period.
    """

    cells: tuple
    inputs: np.ndarray
    tau: float
    eps: float
    substeps: int = 4


#: Cells around the grid whose enclosures are kept too (the states a period's flow from an edge cell may reach), by
#: the number of abstract states (fewer in 3-D, where the padding is most of the cells: 24^3 padded by 8 is 4.7 x).
PAD = {1: 8, 2: 8, 3: 4}


@dataclass(frozen=True)
class CellEnclosures:
    """Proved enclosures of the abstraction's terms over each cell of a grid padded by ``pad`` cells per side
    (interval arithmetic once per cell; every EPS, v_max and tau of a search reuses them).

    Attributes
    ----------
    grid : Grid
        The task's grid (unpadded).
    pad : int
    fields : ndarray (padded..., k, 2)
        phi_bar (n_hat), delta (n_hat m_hat, row-major), d phi_bar / d xi (n_hat^2) and d delta / d xi
        (n_hat m_hat n_hat), as (lo, hi); nan where not finite.
    kappa : ndarray (padded..., p, 2)
    """

    grid: Grid
    pad: int
    fields: np.ndarray
    kappa: np.ndarray


def enclose_cells(model, arts: dict, grid: Grid, pad: int | None = None) -> CellEnclosures:
    """:class:`CellEnclosures` of a design's abstraction on ``grid``.

    Parameters
    ----------
    model : Model
    arts : dict of str to Artefact
        The design (its kappa and delta).
    grid : Grid
    pad : int, optional
        Cells of padding per side [default: :data:`PAD` of the grid's dimension].

    Returns
    -------
    CellEnclosures

    Raises
    ------
    DesignError
        If no cell of V has finite enclosures (naming abstract.domain).
    """
    pad = PAD[len(grid.cells)] if pad is None else int(pad)
    T = design_matrices(model, arts, ("phi", "delta", "kappa"))
    xi = list(model.xi)
    phi, delta = T["phi"], T["delta"]
    exprs = list(phi) + list(delta) + list(phi.jacobian(xi)) + [sp.diff(e, z) for e in delta for z in xi]
    shape = tuple(n + 2 * pad for n in grid.cells)
    big = Grid(np.asarray(grid.lo, dtype=float) - pad * grid.eta, np.asarray(grid.hi, dtype=float) + pad * grid.eta, shape)
    c, half = big.centres(), big.eta / 2
    out = []
    for exprs_ in (exprs, list(T["kappa"])):
        fun = compile_interval(exprs_, xi, model.values)
        out.append(np.array([enclose(fun, np.stack([x - half, x + half], axis=1)) for x in c], dtype=float).reshape(shape + (len(exprs_), 2)))
    fields, kappa = out
    inner = fields[tuple(slice(pad, pad + n) for n in grid.cells)]
    if not np.isfinite(inner).all(axis=(-2, -1)).any():
        raise DesignError("abstract.domain", "phi_bar + delta v has no finite bound on any cell of V", "a V where the abstraction is bounded")
    return CellEnclosures(grid, pad, fields, kappa)


def _mag(enc: np.ndarray) -> np.ndarray:
    """sup |.| of (lo, hi) pairs (inf where not finite)."""
    return np.where(np.isfinite(enc).all(axis=-1), np.max(np.abs(enc), axis=-1), np.inf)


def _window(values: np.ndarray, r: np.ndarray, pad: int, cells: tuple, upper: bool) -> np.ndarray:
    """The max (``upper``) or min over the cells within r[i] cells along each axis, of the grid's cells (cropped
    from the padded array; a window leaving the padded grid takes inf / -inf)."""
    size = tuple(2 * int(k) + 1 for k in r) + (1,) * (values.ndim - len(r))
    fill = np.inf if upper else -np.inf
    vals = np.nan_to_num(values, nan=fill)
    res = (ndimage.maximum_filter if upper else ndimage.minimum_filter)(vals, size=size, mode="constant", cval=fill)
    return res[tuple(slice(pad, pad + n) for n in cells)].reshape((int(np.prod(cells)),) + values.shape[len(r):])


def motion_cells(enc: CellEnclosures, v_max: float, tau: float) -> np.ndarray:
    """Cells per axis within which a period's flow from any cell stays: ceil(tau sup |f_i| / eta_i), sup over the
    padded grid's finite cells and |v_a| <= v_max.

    Parameters
    ----------
    enc : CellEnclosures
    v_max : float
    tau : float

    Returns
    -------
    int ndarray (n_hat,)
    """
    return _motion(_field_parts(enc, v_max)[0], enc.grid.eta, tau)


def _motion(f_mag: np.ndarray, eta: np.ndarray, tau: float) -> np.ndarray:
    """:func:`motion_cells` from the padded cells' sup |f_i| (``f_mag``, as :func:`_field_parts` gives it)."""
    finite = np.where(np.isfinite(f_mag), f_mag, 0.0).reshape(-1, f_mag.shape[-1]).max(axis=0)
    return np.ceil(tau * finite / eta * (1 + 1e-12)).astype(np.int64)


def _field_parts(enc: CellEnclosures, v_max: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per padded cell: sup |f_i|, sup |df_i/dxi_j| and the upper bound of df_i/dxi_i, f = phi_bar + delta v over
    |v_a| <= v_max (the terms' enclosures combined: sup |phi_i| + sum_a sup |delta_ia| v_max, and alike)."""
    nh = enc.grid.eta.size
    F = enc.fields
    mh = (F.shape[-2] - nh - nh * nh) // (nh + nh * nh)
    k = np.cumsum([0, nh, nh * mh, nh * nh, nh * mh * nh])
    phi, delta, dphi, ddelta = (F[..., k[i]:k[i + 1], :] for i in range(4))
    lead = F.shape[:-2]
    f_mag = _mag(phi) + _mag(delta).reshape(lead + (nh, mh)).sum(axis=-1) * v_max
    dd = _mag(ddelta).reshape(lead + (nh, mh, nh)).sum(axis=-2) * v_max            # (.., nh, nh): sum_a sup |d delta_ia / dxi_j|
    j_mag = _mag(dphi).reshape(lead + (nh, nh)) + dd
    top = np.where(np.isfinite(dphi[..., 1]), dphi[..., 1], np.inf).reshape(lead + (nh, nh)) + dd
    return f_mag, j_mag, top


def abstraction_bounds(enc: CellEnclosures, v_max: float, tau: float) -> GrowthBounds:
    """Proved bounds of f = phi_bar + delta v and of df/dxi, one set per cell, each over the states the cell's flow
    can reach within a period (the cell grown by :func:`motion_cells` plus one cell per side) and |v_a| <= v_max:
    the hull of the cells' enclosures over that window.

    Parameters
    ----------
    enc : CellEnclosures
    v_max : float
    tau : float

    Returns
    -------
    GrowthBounds
        With a leading axis of grid.size; a cell whose window meets a cell without finite enclosures (a pole of the
        abstraction just outside V, or the padded grid's edge) gets infinite bounds: no input is admissible there.
    """
    grid, pad = enc.grid, enc.pad
    nh = grid.eta.size
    f_mag, j_mag, top = _field_parts(enc, v_max)
    r = _motion(f_mag, grid.eta, tau) + 1
    Mf = _window(f_mag, r, pad, grid.cells, True)
    Jabs = _window(j_mag, r, pad, grid.cells, True)
    L = np.where(np.eye(nh, dtype=bool)[None], _window(top, r, pad, grid.cells, True), Jabs)
    c = grid.centres()
    reach = grid.eta / 2 + r * grid.eta
    return GrowthBounds(Mf, Jabs, L, c - reach, c + reach)


def kappa_boxes(enc: CellEnclosures, grow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Proved bounds of psi = kappa(xi) over each cell grown by ``grow`` cells per axis: the hull of the cells'
    enclosures over the window.

    Parameters
    ----------
    enc : CellEnclosures
    grow : int ndarray (n_hat,)

    Returns
    -------
    lo, hi : ndarray (size, p)
        (-inf, inf) where the window meets a cell without a finite enclosure.
    """
    grow = np.asarray(grow, dtype=np.int64)
    lo = _window(enc.kappa[..., 0], grow, enc.pad, enc.grid.cells, False)
    hi = _window(enc.kappa[..., 1], grow, enc.pad, enc.grid.cells, True)
    return lo, hi


def task_cells(model, enc: CellEnclosures, prob: GridProblem, steps: int) -> tuple[np.ndarray, list[Phase], tuple]:
    """The task on the cells: the safe cells at each step (always and avoid, over the tube of a period) and one
    phase per reach (its cells at the samples, and those whose tube over a period stays in it, for a hold).

    Parameters
    ----------
    model : Model
    enc : CellEnclosures
    prob : GridProblem
    steps : int
        The horizon in periods.

    Returns
    -------
    safe : bool ndarray (steps + 1, size)
    phases : list of Phase
    parts : (bool ndarray (size,), list of (bool ndarray (size,), int, int))
        The always set's cells and, per avoid set, the cells whose tube may meet it with the steps its window covers
        (:func:`safe_cells` composes them).
    """
    task, eps, grid = model.spec.task, prob.eps, enc.grid
    v_max = float(np.max(np.abs(prob.inputs))) if np.size(prob.inputs) else 0.0
    at_lo, at_hi = kappa_boxes(enc, np.zeros(len(grid.cells), dtype=np.int64))
    tube_lo, tube_hi = kappa_boxes(enc, motion_cells(enc, v_max, prob.tau))       # psi between samples
    always = np.ones(grid.size, dtype=bool)
    if task.always is not None:
        box = np.asarray(task.always, dtype=float)
        always = np.all((tube_lo >= box[:, 0] + eps) & (tube_hi <= box[:, 1] - eps), axis=1)
    avoids = []
    for avoid in task.avoid:
        box = np.asarray(avoid.set, dtype=float)
        meets = np.all((tube_hi >= box[:, 0] - eps) & (tube_lo <= box[:, 1] + eps), axis=1)
        first, last = int(np.floor(avoid.during[0] / prob.tau)), int(np.ceil(avoid.during[1] / prob.tau * (1 - 1e-12)))
        avoids.append((meets, max(first - 1, 0), min(last, steps)))       # the periods that overlap the window
    phases = []
    for r in task.reach:
        box = np.asarray(r.set, dtype=float)
        target = np.all((at_lo >= box[:, 0] + eps) & (at_hi <= box[:, 1] - eps), axis=1)
        tube = np.all((tube_lo >= box[:, 0] + eps) & (tube_hi <= box[:, 1] - eps), axis=1)
        phases.append(Phase(target, int(np.floor(r.by / prob.tau * (1 + 1e-12))), int(np.ceil(r.hold / prob.tau * (1 - 1e-12))), tube))
    return safe_cells(steps, always, avoids), phases, (always, avoids)


def safe_cells(steps: int, always: np.ndarray, avoids: list) -> np.ndarray:
    """The safe cells at each step: the always set's, less each avoid set's over the steps of its window.

    Parameters
    ----------
    steps : int
    always : bool ndarray (size,)
    avoids : list of (bool ndarray (size,), int, int)
        The cells that may meet the set, and the first and last step its window covers.

    Returns
    -------
    bool ndarray (steps + 1, size)
    """
    safe = np.repeat(always[None, :], steps + 1, axis=0)
    for meets, first, last in avoids:
        safe[first:last + 1] &= ~meets[None, :]
    return safe


@dataclass(frozen=True)
class GridGame:
    """A task's game on the abstraction's grid, solved.

    Attributes
    ----------
    grid : Grid
    inputs : ndarray (U, m_hat)
    trans : Transitions or None
        None when the game was lost before it was built (:func:`solve`'s xi0).
    safe : bool ndarray (steps + 1, size)
    phases : list of Phase
    win : Winning
    steps : int
    parts : tuple
        The always set's cells and each avoid set's (:func:`task_cells`).
    tau : float
        The period (s).
    """

    grid: Grid
    inputs: np.ndarray
    trans: Transitions | None
    safe: np.ndarray
    phases: list
    win: Winning
    steps: int
    parts: tuple = ((), [])
    tau: float = 0.0

    def wins(self, xi: np.ndarray) -> bool:
        """Whether the state xi's cell is winning from step 0."""
        return bool(self.win.start()[self.grid.cell_of(xi)])


def memory_bytes(cells: int, inputs: int, d: int, steps: int, phases: int) -> int:
    """What a game holds at its peak: the transitions (two int32 index boxes and a flag per cell and input, and the
    successor boxes' float work arrays of one input) and the winning sets (bool per cell and step: safe, done, and
    two per phase).

    Parameters
    ----------
    cells, inputs, d, steps, phases : int

    Returns
    -------
    int
    """
    return cells * inputs * (8 * d + 1) + cells * 8 * d * 8 + (steps + 1) * cells * (2 + 2 * phases)


def solve(model, arts: dict, prob: GridProblem, memory_limit: float = np.inf, enc: CellEnclosures | None = None,
          xi0: np.ndarray | None = None) -> GridGame:
    """The task's game on the abstraction's grid.

    Parameters
    ----------
    model : Model
        With a task.
    arts : dict of str to Artefact
        The design (stabilise .. bound).
    prob : GridProblem
    memory_limit : float
        Bytes: a game estimated (:func:`memory_bytes`) past it is refused before it is built.
    enc : CellEnclosures, optional
        Of this grid (:func:`enclose_cells`; computed if not given).
    xi0 : ndarray (n_hat,), optional
        The start: when its cell is not safe at step 0 or a reach set has no cell, the game is lost before any
        transition is built (the transitions are then None and no cell wins).

    Returns
    -------
    GridGame

    Raises
    ------
    DesignError
        Naming task.planner.cells when the game would not fit in ``memory_limit``.
    """
    V = np.asarray(model.V, dtype=float)
    grid = Grid(V[:, 0], V[:, 1], tuple(int(n) for n in prob.cells))
    inputs = np.atleast_2d(np.asarray(prob.inputs, dtype=float))
    steps = int(np.ceil(model.spec.task.horizon / prob.tau * (1 - 1e-12)))
    need = memory_bytes(grid.size, len(inputs), len(grid.cells), steps, len(model.spec.task.reach))
    if need > memory_limit:
        raise DesignError("task.planner.cells", f"{list(grid.cells)} with {len(inputs)} inputs and {steps} periods needs about "
                          f"{need / 2**30:.3g} GiB, past the {memory_limit / 2**30:.3g} GiB this machine has free",
                          "fewer cells, fewer inputs or a longer task.planner.tau")
    v_max = float(np.max(np.abs(inputs))) if inputs.size else 0.0
    enc = enclose_cells(model, arts, grid) if enc is None else enc
    safe, phases, parts = task_cells(model, enc, prob, steps)
    if xi0 is not None and (not safe[0, grid.cell_of(xi0)] or not all(ph.target.any() for ph in phases)):
        lost = np.zeros((steps + 1, grid.size), dtype=bool)
        return GridGame(grid, inputs, None, safe, phases, Winning([lost] * len(phases), lost, [lost] * len(phases)), steps, parts, prob.tau)
    bounds = abstraction_bounds(enc, v_max, prob.tau)
    plant = BatchPlant(model, arts)

    def field(v):
        def f(x):
            a = plant.at_xi(x.T)
            return a["phi"][:, :, 0] + a["delta"] @ v
        return f

    trans = growth_transitions(grid, [field(v) for v in inputs], [bounds] * len(inputs), prob.tau, prob.substeps)
    return GridGame(grid, inputs, trans, safe, phases, chain(grid, safe, phases, trans, steps), steps, parts, prob.tau)


def why_not(game: GridGame, xi0: np.ndarray, task) -> tuple[str, str]:
    """(field, what) of a game the start does not win: the start's cell unsafe, a reach set with no cell, the avoid
    set whose removal would let the start win, a deadline that only the horizon would meet, or the task as a whole.

    Parameters
    ----------
    game : GridGame
    xi0 : ndarray (n_hat,)
    task : Task

    Returns
    -------
    field, what : str
    """
    g = game.grid
    c = g.cell_of(xi0)
    if not game.safe[0, c]:
        return "task", f"the start xi0 = {np.round(xi0, 6).tolist()} is already outside task.always or in an avoid set (deflated by EPS, over a period)"
    for k, ph in enumerate(game.phases):
        if not ph.target.any():
            return f"task.reach[{k}].set", "has no cell of V whose psi lies in it deflated by EPS (psi = kappa(xi) bounded over each cell)"
    steps, trans = game.steps, game.trans
    always, avoids = game.parts
    for j, _ in enumerate(task.avoid):
        safe = safe_cells(steps, always, [a for i, a in enumerate(avoids) if i != j])
        if chain(g, safe, game.phases, trans, steps).start()[c]:
            return f"task.avoid[{j}]", "closes every route from the start: without it the start's cell wins"
    for k in range(len(game.phases)):
        def wins(by: int, k=k) -> bool:
            late = [Phase(q.target, by if i == k else steps - q.hold if i > k else q.by, q.hold, q.tube) for i, q in enumerate(game.phases)]
            return bool(chain(g, game.safe, late, trans, steps).start()[c])

        lo, hi = game.phases[k].by, steps - game.phases[k].hold
        if hi > lo and wins(hi):
            while hi - lo > 1:          # the earliest deadline (in periods) that wins, by bisection
                mid = (lo + hi) // 2
                lo, hi = (lo, mid) if wins(mid) else (mid, hi)
            late = f"{hi * game.tau:.4g} s" if game.tau > 0 else f"period {hi}"
            return f"task.reach[{k}].by", (f"{task.reach[k].by:g} s is too early for the abstraction at this v_max: the start wins with "
                                           f"by = {late} (the later deadlines at the horizon)")
    won = int(game.win.start().sum())
    return "task", f"the start's cell is not winning ({won} of {g.size} cells win)"
