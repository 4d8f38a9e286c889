"""A falsification campaign on a stored design: bring the design up to date, run
:func:`ashc_cli.products.falsify.falsify`, store ``falsify.h5``; and whether a stored one answers a request."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ashc_cli.design.artefacts import Artefact, write_artefact
from ashc_cli.design.pipeline import DESIGN, Folder, OnStart, StageReport, artefact_path, as_folder, declared_names, design_model, run
from ashc_cli.problem.spec import Spec
from ashc_cli.products import falsify as falsify_mod


#: The design stages a falsify artefact records as its upstream.
FALSIFY_UPSTREAM = ("stabilise", "manifold", "kappa", "delta", "bound")


#: Length of a falsification run when neither ``--t-final`` nor the spec's tracking scenario gives one
#: (the same default as :func:`ashc_cli.products.falsify.falsify`).
FALSIFY_T_FINAL = falsify_mod.DEFAULT_T_FINAL


def falsify_t_final(spec: Spec, t_final: float | None) -> float:
    """The length of run :func:`ashc_cli.products.falsify.falsify` uses: ``t_final``, else the spec's tracking t_final, else 10 s.

    Parameters
    ----------
    spec : Spec
        The spec (``simulate.tracking.t_final`` is read).
    t_final : float, optional
        The length asked for (``--t-final``); None for the default.

    Returns
    -------
    float
        In seconds.
    """
    if t_final is not None:
        return float(t_final)
    tracking = spec.simulate.tracking
    return float(tracking.t_final) if tracking is not None else FALSIFY_T_FINAL


def falsify_differs(spec: Spec, arts: dict[str, Artefact], stored: Artefact, runs: int | None = None, seed: int | None = None,
                    t_final: float | None = None, *, t_final_given: bool = False) -> str | None:
    """Why a stored falsify artefact does not answer a request, or None if it does.

    Parameters
    ----------
    spec : Spec
        The current spec.
    arts : dict of str to Artefact
        The current design's artefacts (at least :data:`FALSIFY_UPSTREAM`).
    stored : Artefact
        The falsify artefact in the folder.
    runs, seed : int, optional
        The settings asked for; None accepts any.
    t_final : float, optional
        The length of run asked for (None: the default, :func:`falsify_t_final`).
    t_final_given : bool
        Whether a length of run is asked for at all (False accepts any).

    Returns
    -------
    str or None
        What is different, to follow "falsify.h5 was": ``made with --runs 64, not 32``; or None.
    """
    if stored.provenance.get("spec_sha256") != spec.sha256:
        return "made from another spec"
    recorded = stored.provenance.get("upstream", {})
    for up in FALSIFY_UPSTREAM:
        if up in arts and recorded.get(up) != arts[up].provenance.get("sha256"):
            return f"made for an earlier design ({up}.h5 changed since)"
    differs = []
    if runs is not None and int(stored.meta.get("runs", -1)) != runs:
        differs.append(f"--runs {stored.meta.get('runs')}, not {runs}")
    if seed is not None and int(stored.meta.get("seed", -1)) != seed:
        differs.append(f"--seed {stored.meta.get('seed')}, not {seed}")
    if t_final_given:
        want = falsify_t_final(spec, t_final)
        have = float(stored.values.get("t_final", float("nan")))
        if not np.isclose(have, want, rtol=1e-12, atol=0.0):
            differs.append(f"--t-final {have:g}, not {want:g}")
    return f"made with {', '.join(differs)}" if differs else None


def run_falsify(spec: Spec, out: str | Path | Folder, runs: int, seed: int = 0, t_final: float | None = None, *,
                on_stage: Callable[[StageReport], None] | None = None, progress=None, on_runs=None,
                frozen: bool = False, on_start: OnStart | None = None, scheduler: str | None = None) -> tuple[dict[str, Artefact], Artefact]:
    """Bring the design up to date, run :func:`ashc_cli.products.falsify.falsify` (and, when the spec has a task,
    :func:`ashc_cli.products.task_attack.attack_task` with as many runs) and store ``falsify.h5``.

    The artefact is written whatever the verdict (a violation must be kept to be studied).

    Parameters
    ----------
    spec : Spec
        The validated spec.
    out : str, Path or Folder
        The artefact folder.
    runs, seed, t_final
        Passed to :func:`ashc_cli.products.falsify.falsify`.
    on_stage : callable, optional
        Called with a :class:`StageReport` after each design stage and after the falsification.
    progress, on_runs : callable, optional
        Passed to :func:`ashc_cli.products.falsify.falsify` (steps done of ``SEGMENTS``; runs done and runs per second).
    frozen : bool
        Never recompute a design stage: refuse (naming it) if one is not up to date.
    on_start : callable, optional
        Called with (stage, reason) before a design stage is computed and before the falsification starts.
    scheduler : str, optional
        A dask.distributed scheduler for the task attack's runs.

    Returns
    -------
    arts : dict
        The design's artefacts.
    art : Artefact
        The falsify artefact just written.
    """
    folder = as_folder(out)
    arts = run(spec, folder, DESIGN, frozen=DESIGN if frozen else False, on_stage=on_stage, on_start=on_start)
    if on_start is not None:
        on_start(falsify_mod.NAME, f"{runs} runs")
    start = time.perf_counter()
    model = design_model(spec, arts)
    art = falsify_mod.falsify(model, arts, runs, seed, t_final, progress, on_runs)
    if spec.task is not None:
        from ashc_cli.products.task_attack import attack_task, record

        if on_start is not None:
            on_start(falsify_mod.NAME, f"the task: {runs} plant runs of the synthesised plan across its certified start region")
        from ashc_cli.closedloop.terms import DesignTerms
        from ashc_cli.design import task_plan
        from ashc_cli.design.task_plan import task_run

        plant = DesignTerms(model, arts)
        plan = task_plan.plan_task(model, arts, plant=plant)
        plan, _ = task_plan.on_the_plant(model, plant, plan, task_run(model, plant, arts, plan))
        found = attack_task(model, arts, runs, seed, scheduler=scheduler, folder=folder.path, plan=plan)
        record(art, found)
        if model.e is not None:
            # the same plan with w held at each vertex of disturbance_bounds (numpy runs), from the plan's start and the
            # boundary of its start region along M's eigen-directions
            from ashc_cli.products.disturbance_attack import attack_task_disturbances, record_task

            record_task(art, attack_task_disturbances(model, arts, plan, np.asarray(found["task_starts"])[: 1 + 2 * model.n]))
    write_artefact(artefact_path(folder.path, falsify_mod.NAME), art, spec_sha256=spec.sha256, spec_name=spec.name,
                   parameters=dict(spec.parameters), upstream={up: arts[up].provenance["sha256"] for up in FALSIFY_UPSTREAM},
                   names=declared_names(spec))
    if on_stage is not None:
        on_stage(StageReport(falsify_mod.NAME, "ran", time.perf_counter() - start, falsify_mod.headline(art)))
    return arts, art
