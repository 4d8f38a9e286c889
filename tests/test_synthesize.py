"""Tests of ashc_cli.products.synthesize (`ashc synthesize`): the Cuk task is certified on the abstraction and met on
the plant, rtamt agrees with the stored run's robustness, a deadline no admissible v can meet is refused with the
part named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ashc_cli.closedloop.task_monitor import robustness
from ashc_cli.design.artefacts import read_artefact
from ashc_cli.problem.spec import Task, load_spec

from .conftest import CUK, ashc, edited
from .test_task_monitor import _rtamt

TASK_SPEC = Path(__file__).resolve().parent / "specs" / "cuk_task.yaml"


@pytest.fixture(scope="module")
def synthesized(tmp_path_factory):
    out = tmp_path_factory.mktemp("cuk_task")
    proc = ashc("synthesize", str(TASK_SPEC), "--out", str(out), "--json", check=True)
    return out, json.loads(proc.stdout), read_artefact(out / "synthesize.h5")


def test_the_cuk_task_is_certified_and_met_on_the_plant(synthesized):
    _, entry, art = synthesized
    v = art.values
    eps = entry["tolerance"]
    assert entry["certified_margin"] >= 0 and art.checks["task_certified"].passed
    assert entry["task"]["satisfied"] and entry["task"]["robustness"] >= 0
    # Theorem 2 in the budget mode: the plant's output stays within EPS of psi, so its robustness is at least psi's less EPS
    assert v["run/max_abs_error"] <= eps
    assert entry["task"]["robustness"] >= entry["plan_robustness"] - eps - float(v["plan_deviation"]) - float(v["sampling_margin"])
    assert entry["v_max"] == pytest.approx(eps / float(read_artefact(synthesized[0] / "bound.h5").value("gain")), rel=1e-9)
    # each reach's deepest hold window lies within its deadline, and the figure is drawn
    assert all(s <= r.by for s, r in zip(v["task/best_hold_starts"], load_spec(TASK_SPEC).task.reach))
    assert (synthesized[0] / "plots" / "synthesize.png").stat().st_size > 10_000


def test_rtamt_agrees_with_the_stored_runs_robustness(synthesized):
    _, entry, art = synthesized
    task = load_spec(TASK_SPEC).task
    t, keep = np.unique(np.asarray(art.values["run/t"]), return_index=True)
    y = np.asarray(art.values["run/y"])[:, keep]
    tenth = np.isclose(t * 10, np.round(t * 10), atol=1e-6)          # the samples on a 0.1 s grid, as rtamt's unit steps
    ts, ys = np.round(t[tenth] * 10), y[:, tenth]
    assert np.all(np.diff(ts) == 1)
    scaled = Task(horizon=task.horizon * 10, always=task.always,
                  reach=[{"set": r.set, "by": r.by * 10, "hold": r.hold * 10} for r in task.reach],
                  avoid=[{"set": a.set, "during": [a.during[0] * 10, a.during[1] * 10]} for a in task.avoid])
    assert _rtamt(scaled, ts, ys) == pytest.approx(robustness(task, t[tenth], ys).robustness, abs=1e-9)
    # and the stored number (every sample) is within the output's motion over 0.1 s of it
    assert entry["task"]["robustness"] == pytest.approx(_rtamt(scaled, ts, ys), abs=0.05)


def test_a_deadline_no_admissible_v_meets_is_refused_with_the_part(tmp_path):
    late = edited(TASK_SPEC, tmp_path, ("by: 250.0", "by: 60.0"))
    proc = ashc("synthesize", str(late), "--out", str(tmp_path / "o"))
    assert proc.returncode == 3
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith("error: task.reach[0]: no tolerance makes the plan meet the task: at the best, EPS = "), line
    assert "reach[0] misses by" in line and not (tmp_path / "o" / "synthesize.h5").exists()


def test_a_spec_without_a_task_is_told_what_synthesize_needs(tmp_path):
    proc = ashc("synthesize", str(CUK), "--out", str(tmp_path / "o"))
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1] == ("error: task: missing; expected a task on the output "
                                                     "(docs/spec-format.md, 'task') for `ashc synthesize`")
