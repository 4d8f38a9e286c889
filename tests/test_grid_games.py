"""Tests of ashc_cli.numerics.grid_games: the summed-area containment against brute force, and the games on grids
whose answers are known (a 1-D integrator's deadlines and holds, a 2-D route around a wall, a wall that closes it)."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from ashc_cli.numerics.grid_games import Grid, Phase, Transitions, admissible, chain, contained, hold_sets, pre, route, safety


@pytest.mark.parametrize("cells", [(13,), (7, 9), (4, 5, 6)])
def test_containment_is_brute_force_containment(cells):
    rng = np.random.default_rng(len(cells))
    d = len(cells)
    grid = Grid(np.zeros(d), np.ones(d), cells)
    mask = rng.random(grid.size) < 0.7
    N, U = grid.size, 5
    a = rng.integers(0, np.array(cells), size=(N, U, d))
    b = rng.integers(0, np.array(cells), size=(N, U, d))
    trans = Transitions(np.minimum(a, b), np.maximum(a, b), rng.random((N, U)) < 0.9)
    got = contained(grid, mask, trans)
    box = mask.reshape(cells)
    for c in range(N):
        for u in range(U):
            sl = tuple(slice(trans.lo[c, u, i], trans.hi[c, u, i] + 1) for i in range(d))
            assert got[c, u] == (trans.inside[c, u] and bool(box[sl].all()))
    cells_, choice = pre(grid, mask, trans)
    assert np.array_equal(cells_, got.any(axis=1))
    assert np.all(got[np.flatnonzero(cells_), choice[cells_]]) and np.all(choice[~cells_] == -1)


def _shift(grid: Grid, moves: np.ndarray) -> Transitions:
    """Exact moves: cell index + move (no growth), outside the grid not admissible."""
    idx = np.stack(np.unravel_index(np.arange(grid.size), grid.cells), axis=1)        # (N, d)
    to = idx[:, None, :] + moves[None, :, :]
    inside = np.all((to >= 0) & (to < np.array(grid.cells)), axis=2)
    to = np.clip(to, 0, np.array(grid.cells) - 1)
    return Transitions(to, to, inside)


def test_a_deadline_on_a_line_is_met_exactly_when_the_distance_allows():
    grid = Grid(np.array([0.0]), np.array([10.0]), (100,))
    trans = _shift(grid, np.array([[-1], [0], [1]]))
    steps = 120
    safe = np.ones((steps + 1, grid.size), dtype=bool)
    target = grid.inner([7.0], [8.0])                   # cells 70 .. 79
    assert np.flatnonzero(target).tolist() == list(range(70, 80))
    for by, hold in ((65, 0), (64, 0), (65, 10), (100, 30)):
        win = chain(grid, safe, [Phase(target, by, hold)], trans, steps).start()
        assert win[5] == (70 - 5 <= by)                  # from cell 5 the target is 65 steps away
        assert np.array_equal(win, np.abs(np.arange(100) - np.clip(np.arange(100), 70, 79)) <= by)
    # a hold longer than the horizon allows after the deadline is lost
    assert not chain(grid, safe, [Phase(target, 65, 60)], trans, steps).start()[5]


def _bfs(free: np.ndarray, start: tuple, goal: np.ndarray) -> int:
    """Fewest 4-neighbour moves from start into goal through free cells (-1: none)."""
    seen = {start: 0}
    todo = deque([start])
    while todo:
        c = todo.popleft()
        if goal[c]:
            return seen[c]
        for d in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            n = (c[0] + d[0], c[1] + d[1])
            if 0 <= n[0] < free.shape[0] and 0 <= n[1] < free.shape[1] and free[n] and n not in seen:
                seen[n] = seen[c] + 1
                todo.append(n)
    return -1


@pytest.mark.parametrize("gap", [True, False])
def test_a_route_around_a_wall_is_found_and_a_closed_wall_is_refused(gap):
    grid = Grid(np.zeros(2), np.full(2, 20.0), (20, 20))
    trans = _shift(grid, np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]]))
    free = np.ones((20, 20), dtype=bool)
    free[10, : 17 if gap else 20] = False                 # a wall across the first axis at row 10
    target = np.zeros((20, 20), dtype=bool)
    target[17:19, 2:4] = True
    steps = 80
    safe = np.repeat(free.reshape(1, -1), steps + 1, axis=0)
    need = _bfs(free, (2, 2), target)
    assert (need > 0) == gap
    for by in ([need - 1, need] if gap else [steps - 2]):
        win = chain(grid, safe, [Phase(target.reshape(-1), by, 2)], trans, steps)
        assert win.start().reshape(20, 20)[2, 2] == (gap and by >= need)
    # the winning set never holds a wall cell, and a safety game alone keeps every free cell (the stay input)
    assert not np.any(win.start() & ~free.reshape(-1))
    assert np.array_equal(safety(grid, safe, trans, steps)[0], free.reshape(-1))


def test_two_phases_in_order_with_an_avoid_window():
    # reach cells 70..79 by step 70 and hold 3, then cells 10..19; cells 40..49 are forbidden during steps 85..95:
    # the way back (cell 49 at step 89 at the earliest) waits at cell 50 until the window has passed
    grid = Grid(np.array([0.0]), np.array([10.0]), (100,))
    trans = _shift(grid, np.array([[-1], [0], [1]]))
    steps = 150
    open_ = np.ones((steps + 1, grid.size), dtype=bool)
    safe = open_.copy()
    safe[85:96, 40:50] = False
    first, second = grid.inner([7.0], [8.0]), grid.inner([1.0], [2.0])

    def met(safe, by):
        return chain(grid, safe, [Phase(first, 70, 3), Phase(second, by, 0)], trans, steps).start()[5]

    assert met(open_, 119) and not met(open_, 118)      # 65 steps there, 3 held, 51 back
    assert met(safe, 126) and not met(safe, 125)        # 49 entered at step 96 at the earliest, 30 more to cell 19


def test_the_route_is_the_tables_law_and_goes_around_the_wall_in_the_fewest_moves():
    # exact moves on a 20 x 20 grid with a wall that leaves a gap: the table's route from (2, 2) holds the target from
    # the fewest moves a breadth-first search needs (the layers aim at where the hold can begin), every input it
    # holds is admissible towards the next winning set, it never enters the wall, and the hold is kept
    grid = Grid(np.zeros(2), np.full(2, 20.0), (20, 20))
    moves = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]])
    trans = _shift(grid, moves)
    free = np.ones((20, 20), dtype=bool)
    free[10, :17] = False
    target = np.zeros((20, 20), dtype=bool)
    target[17:19, 2:4] = True
    steps, hold = 80, 3
    safe = np.repeat(free.reshape(1, -1), steps + 1, axis=0)
    need = _bfs(free, (2, 2), target)
    phases = [Phase(target.reshape(-1), need + 5, hold)]
    win = chain(grid, safe, phases, trans, steps)
    centre = grid.centres()
    start = centre[np.ravel_multi_index((2, 2), grid.cells)]
    r = route(grid, safe, phases, trans, win, start, lambda x, u: x + moves[u] * grid.eta, np.abs(moves).sum(axis=1).astype(float))
    assert r.holds == [need] and r.widened == 0
    assert not np.any(~free.reshape(-1)[r.cells])
    assert np.all(target.reshape(-1)[r.cells[need:need + hold + 1]])
    held = hold_sets(grid, phases[0], safe, win.after(0), trans, need)
    for k, (c, u) in enumerate(zip(r.cells[:-1], r.choice)):
        mask = held[k + 1 - need] if need <= k < need + hold else (win.reach[0][k + 1] if k < need else win.done[k + 1])
        assert admissible(grid, mask, trans, np.array([c]))[u], k
