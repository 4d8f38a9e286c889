"""Tests of ashc_cli.design.grid_plan: the game of a task on the grid of a design's abstraction, on the one-state
plant of tests/test_synthesize.py (x' = -a x + u, y = x; the abstraction xi' = v, psi = xi), whose answer is known:
from xi = 0 the set [0.5, 1.3] deflated by EPS = 0.1 is entered no sooner than 0.6 / v_max = 1.2 s, v_max = 0.5."""

from __future__ import annotations

import numpy as np
import pytest

from ashc_cli.design.grid_plan import GridProblem, abstraction_bounds, enclose_cells, kappa_boxes, solve
from ashc_cli.design.pipeline import DESIGN, design_model, run
from ashc_cli.numerics.grid_games import Grid
from ashc_cli.problem.spec import parse_spec_text

from .test_synthesize import _task_spec


@pytest.fixture(scope="module")
def line(tmp_path_factory):
    spec = parse_spec_text(_task_spec(None, 0.5, 1.3))
    arts = run(spec, tmp_path_factory.mktemp("grid_plan"), DESIGN)
    return arts


def _model(arts, by: float):
    return design_model(parse_spec_text(_task_spec(None, 0.5, 1.3).replace("by: 8.0", f"by: {by}")), arts)


# from xi = 0 the deflated set [0.6, 1.2] is 1.2 s away at v_max = 0.5: nothing earlier can win; the grid (cells of
# 0.01, tau = 0.1, closed cells: a successor box on a cell boundary holds both cells) wins from 1.7 s on (measured)
@pytest.mark.parametrize("by, wins", [(8.0, True), (1.7, True), (1.1, False)])
def test_the_deadline_is_won_when_the_abstractions_speed_allows(line, by, wins):
    model = _model(line, by)
    game = solve(model, line, GridProblem((300,), np.linspace(-0.5, 0.5, 5)[:, None], 0.1, 0.1))
    grid, win = game.grid, game.win
    c = grid.centres()[:, 0]
    assert win.start()[np.argmin(np.abs(c))] == wins
    # every winning cell is in the always set shrunk by EPS, and the deflated target's cells win
    assert np.all(np.abs(c[win.start()]) <= 1.5 - 0.1)
    assert np.all(win.start()[(c - grid.eta[0] / 2 >= 0.6) & (c + grid.eta[0] / 2 <= 1.2)])


def test_the_bounds_hold_the_abstraction_and_kappa(line):
    model = _model(line, 8.0)
    V = np.asarray(model.V, dtype=float)
    grid = Grid(V[:, 0], V[:, 1], (30,))
    enc = enclose_cells(model, line, grid)
    b = abstraction_bounds(enc, 0.5, 0.1)
    # xi' = v: |f| <= 0.5 and a zero Jacobian on every cell's region
    assert np.all(b.Mf <= 0.5 + 1e-12) and np.all(b.Mf >= 0.5 - 1e-12) and np.all(b.Jabs == 0.0)
    assert np.all(b.D_lo[:, 0] <= grid.centres()[:, 0] - grid.eta[0] / 2 - 0.05 + 1e-12)    # the region holds a period's motion
    lo, hi = kappa_boxes(enc, np.zeros(1, dtype=int))
    c = grid.centres()[:, 0]
    np.testing.assert_allclose(lo[:, 0], c - grid.eta[0] / 2, atol=1e-12)              # psi = xi over each cell
    np.testing.assert_allclose(hi[:, 0], c + grid.eta[0] / 2, atol=1e-12)


def test_a_deadline_too_early_is_named_with_the_earliest_that_wins(line):
    # by = 1.1 s loses (the test above); the refusal names task.reach[0].by and the earliest deadline the grid wins
    # with, which must itself win, be no earlier than the answer known by hand (1.2 s) nor later than the 1.7 s the
    # test above wins with, and the period before it must lose
    import re

    from ashc_cli.design.grid_plan import why_not

    model = _model(line, 1.1)
    prob = GridProblem((300,), np.linspace(-0.5, 0.5, 5)[:, None], 0.1, 0.1)
    game = solve(model, line, prob)
    where, what = why_not(game, np.zeros(1), model.spec.task)
    assert where == "task.reach[0].by", what
    earliest = float(re.search(r"by = ([0-9.]+) s", what).group(1))
    assert 1.2 <= earliest <= 1.7 + 1e-9
    assert solve(_model(line, earliest), line, prob).wins(np.zeros(1))
    assert not solve(_model(line, round(earliest - 0.1, 6)), line, prob).wins(np.zeros(1))
