"""Issue 45's table (`make bench`, `python bench/bench.py --only-tasks`): for each task, when the plant's y is in each
reach set with the budget's set-point law, with the governor and with error-aware planning, and the abstraction's
lower bound under the guarantee, all at the error-aware plan's tolerance EPS.

* error-aware: the plan of `ashc synthesize` (task.planner: error_aware) run on the plant; the time from which y stays
  in reach[k] for its hold (the task monitor's reach time);
* budget and governor: the guaranteed controller of the tracking scenario at the same EPS (budget: v_max =
  (EPS - sqrt(W0 / alpha_h)) / G with G fitted to the task as synthesize fits it; governor: w <= alpha_h EPS^2), aimed at each set's reference and held until y is
  within the set's half-width of its centre (``runner.reach_times``); a leg starts on the manifold at the previous
  set's reference (settled), the hold added between legs;
* lower bound: :func:`ashc_cli.design.error_plan.reach_lower_bounds` (no input certified at EPS by the comparison
  bound has psi in the set earlier; the sets in order).

    python bench/task_times.py FOLDER SPEC [SPEC ...]      (prints one JSON line per spec)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import yaml

from ashc_cli.closedloop import plan as guaranteed
from ashc_cli.closedloop import runner
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design import error_plan, task_plan
from ashc_cli.design.pipeline import DESIGN, design_model, run
from ashc_cli.errors import DesignError
from ashc_cli.problem.spec import parse_spec_text

#: The chunk a level is held in while the budget or the governor is on its way (s), at most REACH_HORIZON_DWELLS.
CHUNK = 5.0


def times(spec_path: Path, folder: Path) -> dict:
    """The row of one task (see the module's docstring)."""
    data = yaml.safe_load(spec_path.read_text())
    data["task"]["planner"] = {"kind": "error_aware"}
    spec = parse_spec_text(yaml.safe_dump(data, sort_keys=False))
    arts = run(spec, folder, DESIGN)
    model = design_model(spec, arts)
    plant = DesignTerms(model, arts)
    task = spec.task
    row = {"task": spec.name, "deadlines": [r.by for r in task.reach]}
    plan = task_plan.plan_task(model, arts, plant=plant)
    _, on_plant = task_plan.on_the_plant(model, plant, plan, task_plan.task_run(model, plant, arts, plan))
    row.update(eps=plan.eps, error_aware=in_order(task, on_plant["t"], on_plant["y"]))
    comp = error_plan.comparison(arts)
    row["lower_bound"] = error_plan.reach_lower_bounds(model, arts, error_plan.theta_table(model, arts), comp, comp.alpha_h * plan.eps ** 2,
                                                       plan.xi0).tolist()
    refs = task_plan.reach_references(model, plant)
    bd, lam = arts["bound"].values, float(arts["stabilise"].value("lambda"))
    gain = task_plan.plan_gain(model)
    fit = error_plan.fitted_gain(model, arts, plan.xi0, refs)       # the budget's G on the part of V the task keeps to, as synthesize's
    for mode in ("budget", "governor"):
        try:
            g = guaranteed.guaranteed_plan(plan.eps, mode, plan.W0, arts, gain=fit[0] if fit is not None and mode == "budget" else None)
        except DesignError as exc:
            row[mode] = f"refused: {exc.what}"
            continue
        law = g.law(mode, gain, model.m_hat, float(bd.get("v_max_certified", np.inf)), lam, float(bd["epsilon"]))
        loop = runner.tracking_loop_for(model, arts, law)
        z = np.r_[plan.xi0, plan.x0, plan.W0]
        now, out = 0.0, []
        for r, ref in zip(task.reach, refs):
            box = np.asarray(r.set, dtype=float)
            centre, half = box.mean(axis=1), float(np.min(np.diff(box, axis=1)) / 2)
            reached = runner.reach_times(model, plant, arts, law, z, [centre], [ref], half, CHUNK, loop=loop)[0]
            now += float(reached)
            out.append(now)
            now += r.hold
            z = np.r_[ref, plant.p_map(*ref)[:, 0], 0.0]
        row[mode] = out
    return row


def in_order(task, t: np.ndarray, y: np.ndarray) -> list[float]:
    """When y is in each reach set for its hold, the sets in order (each searched from the end of the last hold; the
    task monitor takes them as independent clauses, and a set passed on the way to another counts there)."""
    y = np.atleast_2d(y)
    start, out = 0.0, []
    for r in task.reach:
        box = np.asarray(r.set, dtype=float)
        inside = np.all((y >= box[:, :1]) & (y <= box[:, 1:]), axis=0)
        found = float("nan")
        for i in np.flatnonzero(inside & (t >= start)):
            window = (t >= t[i]) & (t <= t[i] + r.hold)
            if t[i] + r.hold <= t[-1] and inside[window].all():
                found = float(t[i])
                break
        out.append(found)
        start = found + r.hold if np.isfinite(found) else float("inf")
    return out


def main() -> int:
    folder = Path(sys.argv[1])
    for spec in sys.argv[2:]:
        print(json.dumps(times(Path(spec), folder / Path(spec).stem)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
