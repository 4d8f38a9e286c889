"""``ashc falsify`` on a task: the synthesised plan (:mod:`ashc_cli.design.task_plan`) run on the plant from starts
across its certified start region, the minimum of the task's robustness over all runs.

The plan is deterministic (the set-point law of the abstraction from the task's xi0: one admissible input at each
state), so the only choice left to an attacker is the plant's start x0: drawn with W(xi0, x0) = (p(xi0) - x0)^T M
(p(xi0) - x0) <= W0* (:func:`ashc_cli.design.task_plan.start_region`): the plan's own start, the boundary along
each eigen-direction of M (both signs), then random directions, half on the boundary and half inside; then a
search around the worst starts so far (a (1 + lambda) evolution strategy over x0 within the region, a quarter of the
runs, :func:`attack_task`).  Every start follows from the seed and the robustness of the runs before it, so a
campaign spread over a Dask cluster (``--scheduler``) runs the same runs as one on this machine.  Each run is the compiled tracking loop of ``simulate``'s task scenario; the runs share the
cores through threads (the compiled loop releases the GIL).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ashc_cli.closedloop import runner
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design import task_plan
from ashc_cli.design.artefacts import Artefact, Check
from ashc_cli.errors import SpecError
from ashc_cli.numerics.proofs import SIMULATED

__all__ = ["draw_starts", "attack_task", "robustness_of_runs", "record"]

#: Runs per task handed to a Dask worker.
CHUNK = 64
#: The search after the drawn starts: its share of the runs (from SEARCH_MIN_RUNS runs on), generations, the worst
#: starts it searches around, and its first step (a fraction of the start region's radius in M's metric).
SEARCH_SHARE = 0.25
SEARCH_MIN_RUNS = 12
SEARCH_GENERATIONS = 2
SEARCH_SEEDS = 3
SEARCH_STEP = 0.25


def draw_starts(M: np.ndarray, p0: np.ndarray, W0_max: float, runs: int, seed: int) -> np.ndarray:
    """Plant starts x0 with (p0 - x0)^T M (p0 - x0) <= W0_max: p0, the boundary along M's eigen-directions, random.

    Parameters
    ----------
    M : ndarray (n, n)
        The stabilise stage's metric (positive definite).
    p0 : ndarray (n,)
        p(xi0), the start on the manifold.
    W0_max : float
        The certified start region (0: only p0).
    runs : int
        How many starts.
    seed : int

    Returns
    -------
    ndarray (runs, n)
    """
    n = p0.size
    if not W0_max > 0 or runs <= 1:
        return np.repeat(p0[None], max(runs, 1), axis=0)[:runs]
    lam, vec = np.linalg.eigh(M)
    radius = np.sqrt(W0_max * (1 - 1e-9))
    edges = [vec[:, j] * radius / np.sqrt(lam[j]) * s for j in range(n) for s in (1.0, -1.0)]
    rng = np.random.default_rng(seed)
    rest = max(runs - 1 - len(edges), 0)
    u = rng.standard_normal((rest, n))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    scale = np.where(np.arange(rest) % 2 == 0, 1.0, rng.random(rest) ** (1.0 / n))
    # e = L^-T u r with M = L L^T: e^T M e = r^2 |u|^2
    L = np.linalg.cholesky(M)
    random = np.linalg.solve(L.T, (u * (radius * scale)[:, None]).T).T
    e = np.vstack([np.zeros((1, n)), np.array(edges), random])[:runs]
    return p0[None] - e


def robustness_of_runs(model, up: dict[str, Artefact], plan: task_plan.TaskPlan, x0s: np.ndarray, threads: int | None = None) -> np.ndarray:
    """The task's robustness on the plant run of ``plan`` from each start.

    Parameters
    ----------
    model, up : Model, dict of str to Artefact
    plan : TaskPlan
    x0s : ndarray (runs, n)
    threads : int, optional
        Threads sharing the runs (default: every core).

    Returns
    -------
    ndarray (runs,)
    """
    plant = DesignTerms(model, up)
    loop = runner.tracking_loop_for(model, up, plan.law())

    def one(x0):
        res = task_plan.task_run(model, plant, up, plan, x0=x0, loop=loop)
        return task_plan.on_the_plant(model, plant, plan, res)[1]["robustness"]

    with ThreadPoolExecutor(max_workers=threads or os.cpu_count() or 1) as pool:
        return np.array(list(pool.map(one, list(x0s))), dtype=float)


def _chunk(spec_json: dict, folder: str, x0s: np.ndarray) -> np.ndarray:
    """A Dask task: the stored design of ``folder`` (never recomputed), the plan, the runs of ``x0s``."""
    from pathlib import Path

    from ashc_cli.design.pipeline import DESIGN, Folder, design_model, run
    from ashc_cli.problem.spec import Spec

    spec = Spec.model_validate(spec_json)
    arts = run(spec, Folder(Path(folder)), DESIGN, frozen=DESIGN)
    model = design_model(spec, arts)
    plan = task_plan.plan_task(model, arts)
    return robustness_of_runs(model, arts, plan, x0s, threads=1)


def _robustness(model, up: dict[str, Artefact], plan: task_plan.TaskPlan, x0s: np.ndarray, scheduler: str | None, folder) -> np.ndarray:
    """The robustness of the plan's plant run from each start: threads here, or chunks of :data:`CHUNK` on a Dask
    cluster (the same runs either way: each run depends only on its start)."""
    if scheduler is None:
        return robustness_of_runs(model, up, plan, x0s)
    try:
        from dask.distributed import Client
    except ImportError:
        raise SpecError("--scheduler", "needs dask.distributed, which is not installed", "pip install 'ashc[sweep]'") from None
    try:
        client = Client(scheduler, timeout=5)
    except (OSError, TimeoutError) as exc:
        raise SpecError("--scheduler", f"no dask scheduler answers at {scheduler} ({exc})", "the address of a running dask.distributed scheduler") from None
    try:
        spec_json = model.spec.model_dump(mode="json")
        chunks = [x0s[i:i + CHUNK] for i in range(0, len(x0s), CHUNK)]
        futures = client.map(_chunk, [spec_json] * len(chunks), [str(folder)] * len(chunks), chunks, pure=False)
        return np.concatenate(client.gather(futures))
    finally:
        client.close()


def _children(seeds: np.ndarray, p0: np.ndarray, L: np.ndarray, W0_max: float, count: int, step: float, rng) -> np.ndarray:
    """``count`` starts around the seed starts (in turn): e = p0 - x0 moved in M's coordinates u = L^T e (|u|^2 = W0)
    by ``step`` times the region's radius, a normal direction, and pulled back inside W0 <= W0_max."""
    radius = np.sqrt(W0_max * (1 - 1e-9))
    u = (p0[None] - seeds) @ L                                        # rows: L^T e
    u = u[np.arange(count) % len(seeds)] + step * radius * rng.standard_normal((count, p0.size))
    norm = np.linalg.norm(u, axis=1, keepdims=True)
    u = np.where(norm > radius, u * (radius / np.maximum(norm, 1e-300)), u)
    return p0[None] - np.linalg.solve(L.T, u.T).T


def attack_task(model, up: dict[str, Artefact], runs: int, seed: int = 0, scheduler: str | None = None, folder=None,
                plan: task_plan.TaskPlan | None = None, W0_max: float | None = None) -> dict:
    """Run the plan from ``runs`` starts across its certified start region, then search around the worst; the minimum
    robustness and the worst run.

    The first starts are drawn (:func:`draw_starts`); :data:`SEARCH_SHARE` of the runs (from :data:`SEARCH_MIN_RUNS`
    runs on, when the region is not a point) then search: :data:`SEARCH_GENERATIONS` generations around the
    :data:`SEARCH_SEEDS` worst starts so far, each step half the last (a (1 + lambda) evolution strategy over x0,
    seeded from ``seed``).

    Parameters
    ----------
    model, up : Model, dict of str to Artefact
    runs, seed : int
    scheduler : str, optional
        Address of a running dask.distributed scheduler: the runs go there in chunks of :data:`CHUNK` (its workers
        read the design from ``folder``, which they must see).
    folder : Path, optional
        The design's folder (with ``scheduler``).
    plan : TaskPlan, optional
        The plan to attack (default: the synthesised one; the tests hand it a planted wrong one).
    W0_max : float, optional
        The start region attacked (default: the plan's own, :func:`ashc_cli.design.task_plan.start_region`; the
        tests attack a planted plan over the region the synthesised one certifies).

    Returns
    -------
    dict
        ``task_min_robustness``, ``task_worst_start`` (x0), ``task_worst_W0``, ``task_start_region_W0``,
        ``task_runs``, ``task_searched`` (runs of the search), ``task_robustness`` (per run), ``task_tolerance``,
        ``task_starts`` (the x0 of each run), ``task_switch_times``, and the worst run (``task_worst/t``, ``/y``,
        ``/psi``, ``/xi``, ``/reach_times``, ``/best_hold_starts``).
    """
    plant = DesignTerms(model, up)
    if plan is None:
        plan = task_plan.plan_task(model, up, plant=plant)
        plan, _ = task_plan.on_the_plant(model, plant, plan, task_plan.task_run(model, plant, up, plan))
    W0_max = task_plan.start_region(plan, up) if W0_max is None else float(W0_max)
    M = np.asarray(up["stabilise"].value("M"))
    p0 = plant.p_map(*plan.xi0)[:, 0]
    searched = int(round(SEARCH_SHARE * runs)) if runs >= SEARCH_MIN_RUNS and W0_max > 0 else 0
    x0s = draw_starts(M, p0, W0_max, runs - searched, seed)
    rob = _robustness(model, up, plan, x0s, scheduler, folder)
    rng, L, step = np.random.default_rng([seed, 41]), np.linalg.cholesky(M), SEARCH_STEP
    for g in range(SEARCH_GENERATIONS):
        count = searched // SEARCH_GENERATIONS + (searched % SEARCH_GENERATIONS if g == SEARCH_GENERATIONS - 1 else 0)
        if count == 0:
            continue
        seeds = x0s[np.argsort(rob, kind="stable")[:SEARCH_SEEDS]]
        children = _children(seeds, p0, L, W0_max, count, step, rng)
        x0s, rob = np.vstack([x0s, children]), np.concatenate([rob, _robustness(model, up, plan, children, scheduler, folder)])
        step /= 2
    e = p0[None] - x0s
    W0s = np.einsum("ri,ij,rj->r", e, M, e)
    k = int(np.argmin(rob))
    worst = task_plan.on_the_plant(model, plant, plan, task_plan.task_run(model, plant, up, plan, x0=x0s[k]))[1]
    return {"task_min_robustness": float(rob[k]), "task_worst_start": x0s[k], "task_worst_W0": float(W0s[k]),
            "task_start_region_W0": W0_max, "task_runs": int(len(rob)), "task_searched": searched, "task_robustness": rob,
            "task_tolerance": plan.eps, "task_starts": x0s, "task_switch_times": np.asarray(plan.switches, dtype=float),
            **{f"task_worst/{key}": worst[key] for key in ("t", "y", "psi", "xi", "reach_times", "best_hold_starts")}}


def record(art: Artefact, found: dict) -> None:
    """Store the task attack in the falsify artefact: its values under ``task/`` and the check
    ``task_met_on_every_run`` (minimum robustness >= 0; simulated).

    Parameters
    ----------
    art : Artefact
        The falsify artefact.
    found : dict
        Of :func:`attack_task`.
    """
    for key, value in found.items():
        art.values[f"task/{key.removeprefix('task_')}"] = value
    art.checks["task_met_on_every_run"] = Check(
        found["task_min_robustness"], found["task_min_robustness"] >= 0,
        f"the task's smallest robustness over {found['task_runs']} plant runs of the plan from starts with W0 <= "
        f"{found['task_start_region_W0']:.4g} (the certified start region; >= 0: met on every run)", SIMULATED)
