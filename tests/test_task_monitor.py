"""Tests of ashc_cli.closedloop.task_monitor: the task robustness against rtamt, the maintained STL monitor, on random
runs (one and two outputs, every part of the task), and by hand on runs whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest
import rtamt

from ashc_cli.closedloop.task_monitor import box_margin, robustness
from ashc_cli.problem.spec import Task


def _box(names, box) -> str:
    return "(" + " and ".join(f"({n} >= {lo!r}) and ({n} <= {hi!r})" for n, (lo, hi) in zip(names, box)) + ")"


def _rtamt(task: Task, t: np.ndarray, y: np.ndarray, part: str | None = None) -> float:
    """The same task written as an STL formula for rtamt's discrete-time monitor, at t = 0 (unit sampling)."""
    names = [f"y{j + 1}" for j in range(y.shape[0])]
    parts = {}
    if task.always is not None:
        parts["always"] = f"always[0:{task.horizon:g}]{_box(names, task.always)}"
    for k, r in enumerate(task.reach):
        parts[f"reach[{k}]"] = f"eventually[0:{r.by:g}](always[0:{r.hold:g}]{_box(names, r.set)})"
    for k, a in enumerate(task.avoid):
        parts[f"avoid[{k}]"] = f"always[{a.during[0]:g}:{a.during[1]:g}](not {_box(names, a.set)})"
    spec = rtamt.StlDiscreteTimeSpecification()
    for n in names:
        spec.declare_var(n, "float")
    spec.spec = parts[part] if part else " and ".join(parts.values())
    spec.parse()
    return float(spec.evaluate({"time": t.tolist(), **{n: y[j].tolist() for j, n in enumerate(names)}})[0][1])


def _random_task(rng, p: int, horizon: int) -> Task:
    def box(width):
        centre = rng.uniform(-3, 3, p)
        half = rng.uniform(0.5, width, p)
        return [[float(c - h), float(c + h)] for c, h in zip(centre, half)]
    deadlines = np.sort(rng.integers(0, horizon // 2, 2))
    reach = [{"set": box(3), "by": float(d), "hold": float(rng.integers(0, horizon // 4))} for d in deadlines]
    a = int(rng.integers(0, horizon // 2))
    avoid = [{"set": box(2), "during": [float(a), float(a + rng.integers(0, horizon // 2))]}]
    return Task(horizon=horizon, always=box(9), reach=reach, avoid=avoid)


@pytest.mark.parametrize("p", [1, 2])
def test_robustness_is_rtamts_on_random_runs(p):
    rng = np.random.default_rng(10 + p)
    for _ in range(12):
        horizon = 40
        t = np.arange(horizon + 5, dtype=float)
        y = np.cumsum(rng.normal(size=(p, t.size)), axis=1) * 0.6
        task = _random_task(rng, p, horizon)
        got = robustness(task, t, y)
        assert got.robustness == pytest.approx(_rtamt(task, t, y), abs=1e-12)
        for part, value in got.parts.items():
            assert value == pytest.approx(_rtamt(task, t, y, part), abs=1e-12), part


def test_a_run_that_meets_the_task_by_a_known_margin():
    # y ramps from 0 to -100 over 10 s and stays there: it reaches [-101, -99] at t = 10 s (margin 1, held to the end),
    # stays in [-110, 5] (margin 5 at t = 0), and avoids [-60, -50] during [0, 4] (y is above -40 until then: 10).
    t = np.linspace(0.0, 20.0, 2001)
    y = np.where(t < 10, -10.0 * t, -100.0)[None, :]
    task = Task(horizon=20, always=[[-110, 5]], reach=[{"set": [[-101, -99]], "by": 12, "hold": 5}],
                avoid=[{"set": [[-60, -50]], "during": [0, 4]}])
    got = robustness(task, t, y)
    assert got.parts == pytest.approx({"always": 5.0, "reach[0]": 1.0, "avoid[0]": 10.0})
    assert got.robustness == pytest.approx(1.0) and got.satisfied
    assert got.reach_times == [pytest.approx(9.9)]          # inside [-101, -99] from y = -99, at t = 9.9 s
    # the same run with a deadline before it gets there: missed by 19 (at the deadline, 8 s, y = -80 is 19 above -99)
    late = Task(horizon=20, reach=[{"set": [[-101, -99]], "by": 8, "hold": 5}])
    missed = robustness(late, t, y)
    assert missed.robustness == pytest.approx(-19.0) and not missed.satisfied and np.isnan(missed.reach_times[0])


def test_box_margin_is_the_distance_to_the_nearest_face():
    y = np.array([[0.0, 1.0, 3.0], [0.0, -2.0, 0.5]])
    assert box_margin(y, [[-1, 2], [-1, 1]]).tolist() == pytest.approx([1.0, -1.0, -1.0])
