"""The planner on the abstraction, design side (issue 42): the abstraction xi' = phi_bar(xi) + delta(xi) v of a
design on a uniform grid of V, with v held over each sampling period tau; its transitions by a growth bound
(:mod:`ashc_cli.numerics.growth`); the task's output sets mapped to cells through kappa; and the game
(:mod:`ashc_cli.numerics.grid_games`).

Soundness.  The bounds of f = phi_bar + delta v and of its Jacobian over V x [-v_max, v_max]^m_hat are proved
(interval arithmetic, :func:`ashc_cli.numerics.interval.enclose`), one set per cell over the states it can reach
within a period; kappa over a cell, and over the tube the state can sweep within a period (the cell grown by tau sup
|f| there), is enclosed per cell too.  The values of f at the centres the growth bound moves are double-precision
evaluations (padded: :data:`ashc_cli.numerics.growth.FLOAT_PAD`).  A reach set becomes the
cells whose every output lies in the set shrunk by ``eps`` (what |psi - y| may be, eq. (38)); an avoid set the cells
whose tube's outputs may meet the set grown by ``eps``; the always set the cells whose tube's outputs lie in it
shrunk by ``eps``: between samples as well as at them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sympy as sp

from ashc_cli.closedloop.batch import BatchPlant
from ashc_cli.closedloop.terms import design_matrices
from ashc_cli.errors import DesignError
from ashc_cli.numerics.grid_games import Grid, Phase, Transitions, Winning, chain
from ashc_cli.numerics.growth import GrowthBounds, growth_transitions
from ashc_cli.numerics.interval import compile_interval, enclose

__all__ = ["GridProblem", "GridGame", "abstraction_bounds", "kappa_boxes", "task_cells", "safe_cells", "solve", "why_not",
           "memory_bytes", "BLOCKS"]

#: Pieces of V along each abstract state over which the bounds are enclosed (their hull is kept): an interval
#: extension of a rational kappa or delta on the whole of V may hold a pole that no point of V has.
BLOCKS = {1: 64, 2: 16, 3: 6}
MAX_HALVINGS = 12


def _enclose_blocks(exprs: list, args: list, values: dict, box: np.ndarray, split: int) -> np.ndarray:
    """(lo, hi) per expression over ``box`` (rows per argument), as the hull of the enclosures over the pieces of
    the first ``split`` rows cut in :data:`BLOCKS` each; a piece without a finite enclosure is halved (along its
    widest split row, at most :data:`MAX_HALVINGS` times) before the hull is given up as nan."""
    fun = compile_interval(exprs, args, values)
    pieces = BLOCKS.get(split, 4)
    edges = [np.linspace(box[i, 0], box[i, 1], pieces + 1) for i in range(split)]
    lo = np.full(len(exprs), np.inf)
    hi = np.full(len(exprs), -np.inf)
    todo = []
    for idx in np.ndindex(*([pieces] * split)):
        sub = box.copy()
        for i, k in enumerate(idx):
            sub[i] = edges[i][k], edges[i][k + 1]
        todo.append((sub, 0))
    while todo:
        sub, depth = todo.pop()
        enc = np.array(enclose(fun, sub), dtype=float)
        if not np.all(np.isfinite(enc)) and depth < MAX_HALVINGS:
            i = int(np.argmax(sub[:split, 1] - sub[:split, 0]))
            mid = 0.5 * (sub[i, 0] + sub[i, 1])
            for a, b in ((sub[i, 0], mid), (mid, sub[i, 1])):
                half = sub.copy()
                half[i] = a, b
                todo.append((half, depth + 1))
            continue
        lo, hi = np.minimum(lo, enc[:, 0]), np.maximum(hi, enc[:, 1])       # a nan piece makes the hull nan
    return np.stack([lo, hi], axis=1)


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


def abstraction_bounds(model, arts: dict, grid: Grid, v_max: float, tau: float) -> GrowthBounds:
    """Proved bounds of f = phi_bar + delta v and of df/dxi, one set per cell, each over the states the cell can
    reach within a period (the cell grown by tau sup_V |f|, itself proved over V) and |v_a| <= v_max.

    Parameters
    ----------
    model : Model
    arts : dict of str to Artefact
        The design (its delta).
    grid : Grid
    v_max : float
    tau : float

    Returns
    -------
    GrowthBounds
        With a leading axis of grid.size; a cell whose region has no finite enclosure (a pole of the abstraction
        just outside V) gets infinite bounds: no input is admissible there.

    Raises
    ------
    DesignError
        If f has no finite bound on V (naming abstract.domain).
    """
    T = design_matrices(model, arts, ("phi", "delta"))
    v = sp.symbols(f"_v0:{model.m_hat}")
    f = T["phi"] + T["delta"] * sp.Matrix(v)
    xi, nh = list(model.xi), model.n_hat
    J = f.jacobian(xi)
    vbox = np.tile([-v_max, v_max], (model.m_hat, 1))
    V = np.asarray(model.V, dtype=float)
    glob = _enclose_blocks(list(f), xi + list(v), model.values, np.vstack([V, vbox]), nh)
    if not np.all(np.isfinite(glob)):
        raise DesignError("abstract.domain", "phi_bar + delta v has no finite bound on V", "a V where the abstraction is bounded")
    fun = compile_interval(list(f) + list(J), xi + list(v), model.values)
    c = grid.centres()
    half = grid.eta / 2
    reach = np.empty_like(c)
    enc = np.empty((grid.size, nh + nh * nh, 2))
    for n, x in enumerate(c):
        reach[n], enc[n] = _a_priori(fun, x, half, vbox, tau, nh)
    mag = np.where(np.isfinite(enc).all(axis=2), np.max(np.abs(enc), axis=2), np.inf)        # (size, nh + nh^2)
    Mf, Jabs = mag[:, :nh], mag[:, nh:].reshape(-1, nh, nh)
    top = np.where(np.isfinite(enc[:, nh:, 1]), enc[:, nh:, 1], np.inf).reshape(-1, nh, nh)
    L = np.where(np.eye(nh, dtype=bool)[None], top, Jabs)
    return GrowthBounds(Mf, Jabs, L, c - reach, c + reach)


#: Tries of the a priori enclosure of a cell's flow over a period (each widens the region by half again).
A_PRIORI_TRIES = 8


def _a_priori(fun, x: np.ndarray, half: np.ndarray, vbox: np.ndarray, tau: float, nh: int) -> tuple[np.ndarray, np.ndarray]:
    """A region D = x +- reach that the flow from the cell x +- half cannot leave within tau, and the enclosures of
    f and its Jacobian over it: D is accepted when half + tau sup_D |f| fits in reach (then |x(t) - x0| <= t sup_D |f|
    holds up to tau); (inf, nan) when no try fits."""
    reach = 2.0 * half
    for _ in range(A_PRIORI_TRIES):
        enc = np.array(enclose(fun, np.vstack([np.stack([x - reach, x + reach], axis=1), vbox])), dtype=float)
        if not np.all(np.isfinite(enc)):
            break
        need = half + tau * np.max(np.abs(enc[:nh]), axis=1)
        if np.all(need <= reach):
            return reach, enc
        reach = 1.5 * np.maximum(need, reach)
    return np.full_like(x, np.inf), np.full((nh + nh * nh, 2), np.nan)


def kappa_boxes(model, arts: dict, grid: Grid, grow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Proved bounds of psi = kappa(xi) over each cell grown by ``grow`` per side (interval arithmetic per cell).

    Parameters
    ----------
    model : Model
    arts : dict of str to Artefact
    grid : Grid
    grow : ndarray (d,) or (size, d)

    Returns
    -------
    lo, hi : ndarray (size, p)
        NaN-free: a cell without a finite enclosure gets (-inf, inf).
    """
    K = design_matrices(model, arts, ("kappa",))["kappa"]
    fun = compile_interval(list(K), list(model.xi), model.values)
    c = grid.centres()
    half = np.broadcast_to(grid.eta / 2 + np.asarray(grow, dtype=float), c.shape)
    enc = np.array([enclose(fun, np.stack([x - h, x + h], axis=1)) for x, h in zip(c, half)], dtype=float)     # (size, p, 2)
    bad = ~np.isfinite(enc).all(axis=2)
    return np.where(bad, -np.inf, enc[:, :, 0]), np.where(bad, np.inf, enc[:, :, 1])


def task_cells(model, arts: dict, grid: Grid, prob: GridProblem, bounds: GrowthBounds, steps: int) -> tuple[np.ndarray, list[Phase], tuple]:
    """The task on the cells: the safe cells at each step (always and avoid, over the tube of a period) and one
    phase per reach (its cells at the samples, and those whose tube over a period stays in it, for a hold).

    Parameters
    ----------
    model : Model
    arts : dict of str to Artefact
    grid : Grid
    prob : GridProblem
    bounds : GrowthBounds
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
    task, eps = model.spec.task, prob.eps
    at_lo, at_hi = kappa_boxes(model, arts, grid, np.zeros(len(grid.cells)))
    tube_lo, tube_hi = kappa_boxes(model, arts, grid, np.where(np.isfinite(bounds.Mf), prob.tau * bounds.Mf, 1e300))
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
    trans : Transitions
    safe : bool ndarray (steps + 1, size)
    phases : list of Phase
    win : Winning
    steps : int
    """

    grid: Grid
    inputs: np.ndarray
    trans: Transitions
    safe: np.ndarray
    phases: list
    win: Winning
    steps: int
    parts: tuple = ((), [])

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


def solve(model, arts: dict, prob: GridProblem, memory_limit: float = np.inf) -> GridGame:
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
    bounds = abstraction_bounds(model, arts, grid, v_max, prob.tau)
    plant = BatchPlant(model, arts)

    def field(v):
        def f(x):
            a = plant.at_xi(x.T)
            return a["phi"][:, :, 0] + a["delta"] @ v
        return f

    trans = growth_transitions(grid, [field(v) for v in inputs], [bounds] * len(inputs), prob.tau, prob.substeps)
    safe, phases, parts = task_cells(model, arts, grid, prob, bounds, steps)
    return GridGame(grid, inputs, trans, safe, phases, chain(grid, safe, phases, trans, steps), steps, parts)


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
        late = [Phase(q.target, steps - q.hold if i >= k else q.by, q.hold, q.tube) for i, q in enumerate(game.phases)]
        if chain(g, game.safe, late, trans, steps).start()[c]:
            return f"task.reach[{k}].by", "is too early for the abstraction at this v_max: with every deadline from it on at the horizon the start wins"
    won = int(game.win.start().sum())
    return "task", f"the start's cell is not winning ({won} of {g.size} cells win)"
