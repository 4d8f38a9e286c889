"""Tests of error-aware planning (ashc_cli.design.error_plan, issue 45): the comparison equation's closed form and its
room, theta's table against theta on a fine grid (an attack on each cell's bound), the task monitor's margin, and the
Cuk converter's task with deadlines the budget cannot meet: certified, met on the plant, the plant's own comparison w
below the plan's at every sample."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ashc_cli.closedloop.task_monitor import robustness
from ashc_cli.design import error_plan
from ashc_cli.design.artefacts import read_artefact
from ashc_cli.problem.spec import Task

from .conftest import ashc, edited

SPEC = Path(__file__).resolve().parents[1] / "specs" / "cuk_deadlines.yaml"


def test_the_closed_form_is_the_comparison_equations_solution_and_room_is_its_largest_input():
    comp = error_plan.Comparison(a=0.7, eps=1.3, alpha_h=0.9, a0=0.05, w_cap=np.inf, v_cap=np.inf)
    for w0, theta, v, tau in [(0.0, 2.0, 0.3, 0.2), (1.5, 0.4, 2.0, 0.05), (3.0, 1.0, 0.0, 1.0)]:
        b = (theta * abs(v) + comp.a0) ** 2 / comp.eps
        sol = solve_ivp(lambda t, w: [-comp.a * w[0] + b], (0.0, tau), [w0], rtol=1e-12, atol=1e-14)
        end = comp.step(w0, theta, v, tau)
        assert end >= sol.y[0, -1] and end == pytest.approx(sol.y[0, -1], rel=1e-9)
    level = 2.0
    for w0 in (0.0, 1.0, 1.99):
        v = comp.room(w0, 0.8, 0.1, level)
        assert comp.step(w0, 0.8, v, 0.1) <= level < comp.step(w0, 0.8, v * 1.001, 0.1)
    # v = 0 must fit: a0 alone past the level leaves no room
    assert error_plan.Comparison(0.7, 1.3, 0.9, 10.0, np.inf, np.inf).room(0.0, 1.0, 0.1, 2.0) == 0.0
    thetas = np.array([0.0, 0.1, 1.0, 3.0])
    assert np.array_equal(comp.room_many(0.5, thetas, 0.1, level), [comp.room(0.5, th, 0.1, level) for th in thetas])


def test_the_sparse_table_of_maxima_is_the_plain_one():
    rng = np.random.default_rng(3)
    table = error_plan.ThetaTable(0.0, 0.01, rng.random(300), 9.0, "", "")
    a = rng.uniform(-0.2, 3.2, 2000)
    b = a + rng.exponential(0.1, a.size) * rng.choice([-1, 1], a.size)
    a[::50] = np.inf
    def plain(x, y):          # the cells meeting [x, y] widened by a cell each side, by a plain max; dbar off V
        if not np.isfinite(x + y):
            return 9.0
        i, k = int(np.floor((min(x, y) - 0.0) / 0.01)) - 1, int(np.floor((max(x, y) - 0.0) / 0.01)) + 1
        return 9.0 if i < -1 or k > 300 else float(table.theta[max(i, 0):min(k, 299) + 1].max())

    assert np.array_equal(table.over_many(a, b), [plain(x, y) for x, y in zip(a, b)])
    assert table.over(-1.0, 0.5) == 9.0 and table.over(0.0, 2.99) == table.theta.max()


def test_a_margin_signal_deflates_every_part_of_the_task():
    task = Task(horizon=10.0, always=[[-2, 2]], reach=[{"set": [[0.5, 1.5]], "by": 6.0, "hold": 2.0}],
                avoid=[{"set": [[-2, -1.5]], "during": [0.0, 10.0]}])
    t = np.linspace(0, 10, 1001)
    y = np.sin(t / 3)[None, :]
    plain = robustness(task, t, y)
    shifted = robustness(task, t, y, margin=0.125)
    assert {k: plain.parts[k] - 0.125 for k in plain.parts} == pytest.approx(shifted.parts, abs=1e-12)
    # a margin only where y is near the always box's edge lowers only what it touches
    bump = np.where(t > 9.0, 0.3, 0.0)
    assert robustness(task, t, y, margin=bump).parts["reach[0]"] == pytest.approx(plain.parts["reach[0]"], abs=1e-12)


@pytest.fixture(scope="module")
def synthesized(tmp_path_factory):
    out = tmp_path_factory.mktemp("cuk_deadlines")
    proc = ashc("synthesize", str(SPEC), "--out", str(out), "--json", check=True)
    return out, json.loads(proc.stdout), read_artefact(out / "synthesize.h5")


def test_thetas_table_bounds_theta_on_a_fine_grid_of_each_cell(synthesized):
    # an attack on the proved bounds: theta(xi) = ||L^T dp/dxi delta|| at 40 points of every cell (the bound stage's grid)
    from ashc_cli.design.pipeline import DESIGN, design_model, run
    from ashc_cli.problem.spec import load_spec

    spec = load_spec(SPEC)
    arts = run(spec, synthesized[0], DESIGN, frozen=DESIGN)
    model = design_model(spec, arts)
    table = error_plan.theta_table(model, arts)
    assert table.evidence == "proved" and np.all(table.theta <= table.dbar)
    bd = arts["bound"]
    dpd = model.numeric(bd.expr("dp_delta"), list(model.xi))
    L = np.asarray(bd.value("L"), dtype=float)
    xs = table.lo + table.eta * (np.arange(table.theta.size * 40) + 0.5) / 40
    theta = np.linalg.norm(L.T @ dpd(xs)[:, 0, :], axis=0)
    per_cell = theta.reshape(-1, 40).max(axis=1)
    assert np.all(per_cell <= table.theta)
    # and tight: within 1 % of the cell's sampled sup plus the variation over a cell
    assert np.all(table.theta <= per_cell * 1.01 + np.abs(np.diff(np.r_[per_cell, per_cell[-1]])) + 1e-9)


def test_the_deadlines_the_budget_refuses_are_certified_and_met(synthesized, tmp_path):
    out, entry, art = synthesized
    v = art.values
    assert art.meta["planner"] == "error_aware" and entry["planner"] == "error_aware"
    assert entry["certified_margin"] > 0 and art.checks["task_certified"].passed
    assert entry["task"]["satisfied"] and entry["task"]["robustness"] > 0
    assert v["task/reach_times"][0] <= 60.0 and v["task/reach_times"][1] <= 140.0
    # the plan's w stays below its level, and its deflation bounds the plant's |psi - y| at every sample
    w_plan = np.asarray(v["run/w_plan"])
    assert float(np.max(v["plan/w"])) <= float(v["w_level"])
    # (plus the plant loop's integration floor: rtol = atol = 1e-9 on states of tens of volts, while w decays to 1e-16 on the holds)
    bound = float(v["tolerance"]) * np.sqrt(w_plan / float(v["w_level"]))
    assert np.all(np.abs(np.asarray(v["run/psi"]) - np.asarray(v["run/y"]))[0] <= bound + 1e-6)
    # the plant's own comparison system (its |L^T r|) never above the plan's bound, the run's xi within a cell of the plan's
    assert art.checks["w_within_plan"].passed and float(v["w_over_plan"]) <= 0.0
    # the budget's plan alone refuses the same task, naming reach[0]
    budget = edited(SPEC, tmp_path, ("  horizon: 160.0", "  horizon: 160.0\n  planner: {kind: setpoint}"))
    proc = ashc("synthesize", str(budget), "--out", str(tmp_path / "budget"))
    assert proc.returncode == 3 and re.search(r"task\.reach\[\d\]: no tolerance makes the plan meet the task", proc.stderr)


def test_falsify_attacks_the_error_aware_plan_across_its_start_region(synthesized):
    out, entry, _ = synthesized
    proc = ashc("falsify", str(SPEC), "--out", str(out), "--runs", "24", "--json", check=True)
    found = json.loads(proc.stdout)
    assert found["task_min_robustness"] >= 0 and found["task_start_region_W0"] > 0


def test_the_lower_bound_lies_below_the_plans_entry_times(synthesized):
    # psi of the plan enters each set (in order) no earlier than the abstraction's lower bound under the guarantee
    _, entry, art = synthesized
    v = art.values
    lower = np.asarray(v["lower_bound_reach_times"], dtype=float)
    assert entry["lower_bound_reach_times"] == pytest.approx(lower.tolist())
    t, psi = np.asarray(v["plan/t"]), np.asarray(v["plan/psi"])[0]
    start = 0.0
    for k, r in enumerate(load_task().reach):
        lo, hi = r.set[0]
        entered = t[np.flatnonzero((psi >= lo) & (psi <= hi) & (t >= start))[0]]
        assert 0 < lower[k] <= entered
        start = entered + r.hold
    # a longer leg or a tighter level takes longer
    comp = error_plan.Comparison(a=1.0, eps=1.0, alpha_h=1.0, a0=0.0, w_cap=np.inf, v_cap=np.inf)
    assert error_plan._time_for(2.0, comp, 1.0) > error_plan._time_for(1.0, comp, 1.0) > error_plan._time_for(1.0, comp, 4.0) > 0


def load_task():
    from ashc_cli.problem.spec import load_spec

    return load_spec(SPEC).task


HOVER = SPEC.with_name("hover_vehicle.yaml")


def test_the_hover_vehicle_reaches_its_band_within_ten_seconds_certified(tmp_path):
    proc = ashc("synthesize", str(HOVER), "--out", str(tmp_path / "o"), "--json", check=True)
    entry = json.loads(proc.stdout)
    assert entry["planner"] == "error_aware" and entry["certified_margin"] > 0 and entry["task"]["satisfied"]
    assert entry["task"]["reach_times"][0] <= 10.0 and entry["lower_bound_reach_times"][0] <= entry["task"]["reach_times"][0]
    budget = edited(HOVER, tmp_path, ("  xi0: [1.0]\n  always", "  xi0: [1.0]\n  planner: {kind: setpoint}\n  always"))
    proc = ashc("synthesize", str(budget), "--out", str(tmp_path / "b"))
    assert proc.returncode == 3 and "task.reach[0]: no tolerance makes the plan meet the task" in proc.stderr


@pytest.mark.slow
def test_an_error_aware_plan_counts_the_disturbance_and_holds_with_w_at_the_vertices(tmp_path):
    # a0 = ebar w_max enters the comparison bound the plan carries: certified with w in [-0.05, 0.05], and the plant with w
    # held at each vertex meets the task; a plan that left a0 out would not know the disturbance is there
    from .test_synthesize import _plan_on_the_disturbed_plant, _synthesized, _task_spec

    text = _task_spec(0.05, 0.5, 1.3).replace("planner: {kind: setpoint}", "planner: {kind: error_aware}")
    spec, arts, art = _synthesized(text, tmp_path)
    assert art.meta["planner"] == "error_aware" and art.checks["task_certified"].passed
    comp = error_plan.comparison(arts)
    assert comp.a0 == pytest.approx(float(arts["bound"].values["ebar"]) * 0.05) and comp.a0 > 0
    assert min(_plan_on_the_disturbed_plant(spec, art, w) for w in (-0.05, 0.0, 0.05)) >= 0


PATTERN = """
name: two_inputs_clipped
concrete:
  states: [x1, x2]
  inputs: [u1, u2]
  f_bar: ["-3*x1 - 3*x2", "-x1 - 2*x2"]
  g: [["1", "0"], ["0", "1"]]
  h: ["x2"]
  input_bounds: [[0, 0.8], [-5, 5]]
  output_set: [[0, 1]]
stabilisability:
  method: given
  decay_rate: 0.55
  feedback: identity
  M: [[1.0, 0.9], [0.9, 1.0]]
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["0.75*xi**8", "xi + 0.25*xi**8"]
  p: ["-xi + 0.25*xi**8", "xi"]
  domain: [[0, 1]]
  delta: identity
interface: {q: least_squares, saturate: true}
task:
  horizon: 300.0
  xi0: [0.02]
  always: [[-0.5, 1.5]]
  reach:
    - {set: [[0.45, 0.95]], by: 250.0, hold: 1.0}
"""


def test_two_inputs_clipped_channel_by_channel_keep_dbar_on_every_cell(tmp_path):
    # An attack found this: l1 sits on U1's lower edge, so q1 v is clipped for the whole climb, and with one channel
    # clipped |L^T r| / |v| is 1.0 where the q = 0 value is 0.447 (while the patterns' sup equals dbar_q0, so the bound
    # stage's dbar is dbar_q0).  theta's table is dbar on every cell there, and the plant run's own w stays below the plan's.
    from .test_synthesize import _synthesized

    spec, arts, art = _synthesized(PATTERN, tmp_path)
    from ashc_cli.design.pipeline import design_model

    table = error_plan.build_theta_table(design_model(spec, arts), arts)
    assert np.all(table.theta == float(arts["bound"].values["dbar"])) and "clipping patterns" in table.how
    assert art.meta["planner"] == "error_aware" and art.checks["task_certified"].passed
    assert art.checks["w_within_plan"].passed and float(art.values["w_over_plan"]) <= 0.0
