"""Tests of ashc_cli.numerics.growth: the successor boxes hold the exact flow of a linear system from every point of
a cell (sampled across the cell, its corners included), and are not much wider than the flow's own spread."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.linalg as sla

from ashc_cli.numerics.grid_games import Grid
from ashc_cli.numerics.growth import GrowthBounds, growth_transitions, successor_boxes

A = np.array([[-1.0, 2.0], [-2.0, -1.0]])
B = np.array([1.0, 0.5])


def _bounds(u: float) -> GrowthBounds:
    D = 5.0
    Mf = np.abs(A) @ np.full(2, D) + np.abs(B * u)
    L = np.where(np.eye(2, dtype=bool), A, np.abs(A))
    return GrowthBounds(Mf, np.abs(A), L, np.full(2, -D), np.full(2, D))


def _flow(x0: np.ndarray, u: float, tau: float) -> np.ndarray:
    big = np.zeros((3, 3))
    big[:2, :2], big[:2, 2] = A, B * u
    E = sla.expm(big * tau)
    return x0 @ E[:2, :2].T + E[:2, 2]


# the widest box over the flow's own spread, measured: 1.41, 2.38, 5.56; the componentwise growth bound of a
# rotating, decaying flow grows like e^((-1 + 2) t) where the flow decays like e^(-t) (SCOTS's bound has the same)
@pytest.mark.parametrize("tau, substeps, widest", [(0.05, 1, 1.5), (0.2, 4, 2.5), (0.5, 10, 6.0)])
def test_the_successor_box_holds_the_flow_of_every_point_of_the_cell(tau, substeps, widest):
    rng = np.random.default_rng(4)
    half = np.array([0.1, 0.05])
    worst = 0.0
    for u in (-1.0, 0.0, 1.0):
        centres = rng.uniform(-2, 2, (200, 2))
        c, r, stays = successor_boxes(lambda x, u=u: x @ A.T + B * u, centres, half, _bounds(u), tau, substeps)
        assert stays.all()
        corners = np.array(list(itertools.product((-1, 1), repeat=2)), dtype=float)
        pts = np.concatenate([corners, rng.uniform(-1, 1, (30, 2))]) * half            # offsets within the cell
        for k in range(len(centres)):
            end = _flow(centres[k] + pts, u, tau)
            assert np.all(np.abs(end - c[k]) <= r[k]), (tau, u, k)
            spread = np.ptp(end, axis=0) / 2
            worst = max(worst, float(np.max(r[k] / spread)))
    assert worst <= widest


def test_a_box_whose_tube_leaves_D_is_not_admissible():
    c, r, stays = successor_boxes(lambda x: x @ A.T, np.array([[4.95, 0.0], [0.0, 0.0]]), np.array([0.1, 0.1]), _bounds(0.0), 0.1, 2)
    assert not stays[0] and stays[1]


def test_transitions_of_a_grid_hold_the_cells_the_flow_reaches():
    grid = Grid(np.array([-3.0, -3.0]), np.array([3.0, 3.0]), (30, 30))
    us = [-1.0, 1.0]
    trans = growth_transitions(grid, [lambda x, u=u: x @ A.T + B * u for u in us], [_bounds(u) for u in us], 0.1, 2)
    rng = np.random.default_rng(5)
    cells = rng.integers(0, grid.size, 100)
    for k in cells:
        for j, u in enumerate(us):
            if not trans.inside[k, j]:
                continue
            x0 = grid.centres()[k] + rng.uniform(-0.5, 0.5, (20, 2)) * grid.eta
            idx = np.floor((_flow(x0, u, 0.1) - grid.lo) / grid.eta).astype(int)
            assert np.all((idx >= trans.lo[k, j]) & (idx <= trans.hi[k, j]))


def test_an_admissible_input_keeps_the_flow_in_the_grid_within_the_period():
    # a rotation xi' = (-xi2, xi1) on V = [-1, 1]^2 with bounds valid on a larger region: a cell at V's edge whose
    # flow leaves V within the period and comes back by its end was admissible when only the period's end was
    # checked (a review found xi1 = 1.0003 from cell (79, 39) at tau = 0.145); now every admissible cell's exact
    # flow, from its corners at 60 times in the period, stays in V
    grid = Grid(np.array([-1.0, -1.0]), np.array([1.0, 1.0]), (80, 80))
    J = np.array([[0.0, 1.0], [1.0, 0.0]])
    bounds = GrowthBounds(np.array([2.0, 2.0]), J, J, np.array([-2.0, -2.0]), np.array([2.0, 2.0]))
    tau = 0.145
    trans = growth_transitions(grid, [lambda x: np.stack([-x[:, 1], x[:, 0]], axis=1)], [bounds], tau, 8)
    ok = np.flatnonzero(trans.inside[:, 0])
    assert 0 < ok.size < grid.size
    c, half = grid.centres()[ok], grid.eta / 2
    corners = np.concatenate([c + np.array(s) * half for s in ((-1, -1), (-1, 1), (1, -1), (1, 1))])
    for t in np.linspace(0.0, tau, 60):
        R = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
        assert np.abs(corners @ R.T).max() <= 1.0 + 1e-12, t
