"""``ashc tradeoff``: how fast a guaranteed controller reaches the reference levels, against its tolerance.

For each tolerance EPS, both modes of the guaranteed controller (docs/guaranteed.md) track the spec's
reference levels from the spec's start, each level held until it is reached within EPS
(:func:`ashc_cli.design.stages.simulate.reach_times`): the **budget** (the set-point law with the largest uniform
v_max that eq. (9) allows, v_max = (EPS - sqrt(W0 / alpha_h)) / G, eq. (38)) and the
**governor** (v = s v_sp keeping the comparison system's w below EPS^2 alpha_h along the run).  The result is
the time to reach every level, per tolerance and mode: the speed/accuracy frontier of the design.

:func:`tradeoff` is a pure function of the model and the design's artefacts; :func:`run_tradeoff` brings the
design up to date, stores ``tradeoff.h5`` (:mod:`ashc_cli.design.artefacts`) and draws ``plots/tradeoff.png``
(:func:`plot`); :func:`table` formats the rows ``ashc tradeoff`` prints.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ashc_cli.design.artefacts import Artefact, write_artefact
from ashc_cli.errors import DesignError, SpecError
from ashc_cli.problem.spec import Spec
from ashc_cli.closedloop import plan as guaranteed
from ashc_cli.closedloop.falsify_loop import threads
from ashc_cli.closedloop import runner
from ashc_cli.closedloop.terms import DesignTerms
from ashc_cli.design.upstream import tracking_start

__all__ = ["NAME", "UPSTREAM", "MODES", "parse_tolerances", "tradeoff", "table", "plot", "summarise", "headline", "run_tradeoff"]

NAME = "tradeoff"
#: The design stages a tradeoff artefact records as its upstream.
UPSTREAM = ("stabilise", "manifold", "kappa", "delta", "bound")
#: The modes compared, in the order of the rows.
MODES = ("budget", "governor")


def parse_tolerances(text: str) -> list[float]:
    """``"1,2,5"`` -> [1.0, 2.0, 5.0]: positive, finite, each once, in the order given.

    Parameters
    ----------
    text : str
        The ``--tolerances`` value, comma-separated.

    Returns
    -------
    list of float

    Raises
    ------
    SpecError
        Naming ``--tolerances``, for an empty list, a word that is not a number, a value <= 0 or not finite, or a
        value given twice.
    """
    items = [item.strip() for item in str(text).split(",")]
    if not any(items):
        raise SpecError("--tolerances", "is empty", "comma-separated tolerances > 0, e.g. 1,2,5,10,20")
    values = []
    for item in items:
        try:
            value = float(item)
        except ValueError:
            raise SpecError("--tolerances", f"'{item}' is not a number", "comma-separated tolerances > 0, e.g. 1,2,5,10,20") from None
        if not (np.isfinite(value) and value > 0):
            raise SpecError("--tolerances", f"{item} is not a positive, finite tolerance", "comma-separated tolerances > 0, e.g. 1,2,5,10,20")
        if value in values:
            raise SpecError("--tolerances", f"{item} is given twice", "each tolerance once")
        values.append(value)
    return values


def tradeoff(model, arts: dict[str, Artefact], tolerances: list[float], horizon_dwells: int = runner.REACH_HORIZON_DWELLS) -> Artefact:
    """Time to reach every reference level, per tolerance, for the budget and the governor.

    Parameters
    ----------
    model : Model
        The spec's model with V fixed (:func:`ashc_cli.design.pipeline.design_model`).
    arts : dict
        The design's artefacts (stabilise .. bound).
    tolerances : list of float
        The tolerances EPS, > 0.
    horizon_dwells : int
        Each level is held at most this many dwells (the spec's) before it counts as not reached (NaN).

    Returns
    -------
    Artefact
        Values ``tolerances`` (K,), ``levels`` (L, p), ``reach_time/budget`` and ``reach_time/governor`` (K, L;
        seconds from the switch to each level until |y - level| <= EPS for good, NaN if not reached or the
        mode cannot certify EPS), ``total_time/<mode>`` (K,: the sum over the levels), ``speedup`` (K, L:
        budget / governor), ``budget_v_max``, ``proved_tolerance/<mode>`` (K,), ``refusal/<mode>`` (K strings,
        "" where the mode runs) and ``gain``.

    Raises
    ------
    DesignError
        If the spec has no tracking scenario, or its reference is a signal.
    """
    tr = model.spec.simulate.tracking
    if tr is None:
        raise DesignError("simulate.tracking", "the spec has no tracking scenario", "simulate.tracking with reference_levels and a controller")
    if tr.reference is not None:
        raise DesignError("simulate.tracking.reference", "a reference signal has no levels to reach (the trade-off times reaching each level)",
                          "simulate.tracking with reference_levels and dwell")
    ctl = tr.abstract_controller
    if ctl.kind == "signal":
        raise DesignError("simulate.tracking.abstract_controller.kind", "signal: an abstract input v(t) reaches no levels (the trade-off times reaching each level)",
                          "kind setpoint or guaranteed, with reference_levels and dwell")
    plant = DesignTerms(model, arts)
    xi0, x0, W0, levels, refs = tracking_start(model, plant, arts)
    z0 = np.r_[xi0, x0, W0]
    lam, eps = float(arts["bound"].value("lambda")), float(arts["bound"].value("epsilon"))
    v_cert = float(arts["bound"].values.get("v_max_certified", np.inf))
    K, L = len(tolerances), len(levels)
    times = {mode: np.full((K, L), np.nan) for mode in MODES}
    proved = {mode: np.full(K, np.nan) for mode in MODES}
    refusal = {mode: [""] * K for mode in MODES}
    budget_v = np.full(K, np.nan)
    loops, tasks = {}, []
    for k, tol in enumerate(tolerances):
        try:
            plan = guaranteed.guaranteed_plan(float(tol), "auto", W0, arts)
        except DesignError as exc:            # neither mode certifies this tolerance from the start
            for mode in MODES:
                refusal[mode][k] = exc.what
            continue
        budget_v[k] = plan.budget_v_max
        for mode in MODES:
            why = plan.budget_refusal if mode == "budget" else plan.governor_refusal
            if why is not None:
                refusal[mode][k] = why
                continue
            law = plan.law(mode, ctl.gain, model.m_hat, v_cert, lam, eps)
            if law.kind not in loops:
                loops[law.kind] = runner.tracking_loop_for(model, arts, law)
            tasks.append((k, mode, law, float(tol)))
            proved[mode][k] = plan.budget_tolerance if mode == "budget" else plan.governor_tolerance

    def reach(task):
        k, mode, law, tol = task
        return runner.reach_times(model, plant, arts, law, z0, levels, refs, tol, tr.dwell, horizon_dwells=horizon_dwells, loop=loops[law.kind])

    # The runs are independent and the compiled loop runs without the GIL: one thread per core, the same numbers.
    with ThreadPoolExecutor(max_workers=max(1, min(threads(), len(tasks)))) as pool:
        for (k, mode, _, _), reached in zip(tasks, pool.map(reach, tasks)):
            times[mode][k] = reached
    with np.errstate(divide="ignore", invalid="ignore"):
        speedup = np.where(times["governor"] > 0, times["budget"] / times["governor"], np.nan)
    values = {
        "tolerances": np.asarray(tolerances, dtype=float), "levels": np.stack(levels), "budget_v_max": budget_v,
        "speedup": speedup, "gain": float(ctl.gain), "W0": float(W0),
    }
    for mode in MODES:
        values[f"reach_time/{mode}"] = times[mode]
        # NaN (not reached, or refused) propagates: a total is given only when every level was reached.
        values[f"total_time/{mode}"] = times[mode].sum(axis=1)
        values[f"proved_tolerance/{mode}"] = proved[mode]
        values[f"refusal/{mode}"] = refusal[mode]
    meta = {"dwell": float(tr.dwell), "horizon_dwells": int(horizon_dwells), "sample_dt": max(runner.SAMPLE_DT, runner.REACH_SAMPLE_DWELLS * tr.dwell),
            "integrator": runner.TRACKING_TOL, "governor_rate": guaranteed.GOVERNOR_RATE, "governor_margin": guaranteed.GOVERNOR_MARGIN,
            "implementation": {kind: "ashc_cli.closedloop.compiled (numba)" if getattr(loop, "compiled", True) else "scipy.integrate.solve_ivp"
                               for kind, loop in loops.items()}}
    return Artefact(stage=NAME, values=values, meta=meta)


def _seconds(value: float) -> str:
    return "-" if not np.isfinite(value) else f"{value:.4g}"


def output_unit(spec: Spec) -> str | None:
    """The unit of the output the tolerance is on (``units.y1`` or ``units.y``), None if the spec gives none.

    Parameters
    ----------
    spec : Spec

    Returns
    -------
    str or None
    """
    return spec.units.get("y1") or spec.units.get("y")


def table(art: Artefact, unit: str | None = None) -> list[str]:
    """The rows ``ashc tradeoff`` prints: one per tolerance and mode, the seconds to reach each level.

    A ``-`` is a level not reached within the horizon; a refused mode shows its reason instead of times.

    Parameters
    ----------
    art : Artefact
        The tradeoff artefact (of :func:`tradeoff`).
    unit : str, optional
        The output's unit, shown in the EPS column's head.

    Returns
    -------
    list of str
        A header, a line naming the units (seconds; the output's unit), then per tolerance a budget and a
        governor row: EPS, mode, the seconds per level, their total and (governor rows) the speed-up of the
        totals, budget / governor.
    """
    v = art.values
    levels = np.asarray(v["levels"], dtype=float)
    names = [f"{lv[0]:g}" if lv.size == 1 else "(" + ", ".join(f"{x:g}" for x in lv) + ")" for lv in levels]
    width = max(9, *(len(n) for n in names))
    head = f"{'EPS':>8}  {'mode':<8}  " + "  ".join(f"{n:>{width}}" for n in names) + f"  {'total':>9}  {'speed-up':>8}"
    rows = [head, f"seconds to reach each level within EPS and their total; levels and EPS in {unit or 'the output units'}"]
    tot_b, tot_g = np.asarray(v["total_time/budget"]), np.asarray(v["total_time/governor"])
    for k, tol in enumerate(np.asarray(v["tolerances"], dtype=float)):
        for mode in MODES:
            why = v[f"refusal/{mode}"][k]
            if why:
                rows.append(f"{tol:>8g}  {mode:<8}  refused: {why}")
                continue
            times = np.asarray(v[f"reach_time/{mode}"])[k]
            ratio = tot_b[k] / tot_g[k] if mode == "governor" and np.isfinite(tot_b[k]) and tot_g[k] > 0 else np.nan
            rows.append(f"{tol:>8g}  {mode:<8}  " + "  ".join(f"{_seconds(x):>{width}}" for x in times)
                        + f"  {_seconds(float(np.sum(times))):>9}  {'' if not np.isfinite(ratio) else f'{ratio:.3g}x':>8}")
    return rows


def plot(art: Artefact, path: str | Path, unit: str | None = None) -> Path:
    """The speed/accuracy frontier: time to reach every level (the sum of the reach times) against EPS, for the
    budget and the governor (top, log-log), and the governor's speed-up over the budget (bottom).  One IEEE
    column wide (3.5 in), mathtext labels, in the style of :mod:`ashc_cli.outputs.plots`.

    Parameters
    ----------
    art : Artefact
        The tradeoff artefact (``tolerances``, ``total_time/budget``, ``total_time/governor`` are read).
    path : str or Path
        The file; its suffix gives the format (:func:`ashc_cli.outputs.plots.save`).
    unit : str, optional
        The output's unit, on the tolerance axis.

    Returns
    -------
    Path
        ``path``.
    """
    from ashc_cli.outputs.plots import COLUMN_WIDTH, STYLE, legend_above, plain_log_ticks, mticker, plt, save

    v = art.values
    eps_values = np.asarray(v["tolerances"], dtype=float)
    order = np.argsort(eps_values)
    with plt.rc_context(STYLE):
        fig, (ax_t, ax_s) = plt.subplots(2, 1, figsize=(COLUMN_WIDTH, 3.9), sharex=True, layout="constrained")
        styles = {"budget": {"color": "#b2182b", "marker": "s", "linestyle": (0, (4, 2))},
                  "governor": {"color": "#1f4e9c", "marker": "o", "linestyle": "-"}}
        labels = {"budget": r"budget: $|v| \leq (\varepsilon - \sqrt{W_0/\alpha_h})/G$",
                  "governor": r"governor: $w \leq \varepsilon^2 \alpha_h$"}
        drawn = False
        for mode in MODES:
            total = np.asarray(v[f"total_time/{mode}"], dtype=float)[order]
            ok = np.isfinite(total) & (total > 0)
            drawn |= bool(ok.any())
            ax_t.plot(eps_values[order][ok], total[ok], markersize=3.5, label=labels[mode], **styles[mode])
        ax_t.set_xscale("log")
        if drawn:
            ax_t.set_yscale("log")
        else:
            ax_t.text(0.5, 0.5, "no tolerance reached every level", transform=ax_t.transAxes, ha="center", va="center")
        ax_t.set_ylabel("time to all levels (s)")
        legend_above(ax_t, ncol=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = (np.asarray(v["total_time/budget"], dtype=float) / np.asarray(v["total_time/governor"], dtype=float))[order]
        ok = np.isfinite(ratio) & (ratio > 0)
        ax_s.plot(eps_values[order][ok], ratio[ok], color="0.2", marker="o", markersize=3.5)
        ax_s.axhline(1.0, color="0.45", linestyle=":", linewidth=0.9)
        ax_s.set_yscale("log")
        if not ok.any():
            ax_s.text(0.5, 0.5, "no speed-up: a mode missed a level", transform=ax_s.transAxes, ha="center", va="center")
        shown_unit = "" if not unit else " (" + unit.replace("$", "\\$") + ")"   # a literal $ in mathtext
        ax_s.set_xlabel(r"guaranteed tolerance $\varepsilon$ on $|\psi - y|$" + shown_unit)
        ax_s.set_ylabel("speed-up")
        # Plain factors on the log axis (7x, not 7 x 10^0).
        ax_s.yaxis.set_major_formatter(mticker.FuncFormatter(lambda value, _: f"{value:g}x"))
        ax_s.yaxis.set_minor_formatter(mticker.FuncFormatter(lambda value, _: f"{value:g}x" if f"{value:g}"[0] in "25" else ""))
        # The tolerances asked for as the ticks, written plainly (5, not 5 x 10^0).
        ax_s.xaxis.set_major_locator(mticker.FixedLocator(eps_values[order]))
        ax_s.xaxis.set_major_formatter(mticker.FuncFormatter(lambda value, _: f"{value:g}"))
        ax_s.xaxis.set_minor_locator(mticker.NullLocator())
        for ax in (ax_t, ax_s):
            if ax.get_yscale() == "log":
                plain_log_ticks(ax)
        return save(fig, Path(path))


def summarise(art: Artefact) -> dict:
    """Headline numbers for ``ashc summary``.

    Parameters
    ----------
    art : Artefact
        The tradeoff artefact (of :func:`tradeoff`).

    Returns
    -------
    dict
        Lists: ``tolerances``, ``levels``, ``total_time_<mode>``, ``reach_time_<mode>`` (NaN: not reached or
        refused) and ``speedup``.
    """
    v = art.values
    out = {"tolerances": np.asarray(v["tolerances"]).tolist(), "levels": np.asarray(v["levels"]).tolist()}
    for mode in MODES:
        out[f"total_time_{mode}"] = np.asarray(v[f"total_time/{mode}"]).tolist()
        out[f"reach_time_{mode}"] = np.asarray(v[f"reach_time/{mode}"]).tolist()
    out["speedup"] = np.asarray(v["speedup"]).tolist()
    return out


def headline(art: Artefact) -> str:
    """One line: the total time to reach every level at each tolerance, both modes.

    Parameters
    ----------
    art : Artefact
        The tradeoff artefact (of :func:`tradeoff`).

    Returns
    -------
    str
        ``-`` for a total that is NaN (a level not reached, or the mode refused).
    """
    v = art.values
    parts = [f"EPS {tol:g}: budget {_seconds(b)} s, governor {_seconds(g)} s"
             for tol, b, g in zip(np.asarray(v["tolerances"]), np.asarray(v["total_time/budget"]), np.asarray(v["total_time/governor"]))]
    return "time to reach every level: " + "; ".join(parts)


def run_tradeoff(spec: Spec, out, tolerances: list[float], *, on_stage: Callable | None = None, on_start: Callable | None = None,
                 frozen: bool = False) -> tuple[dict[str, Artefact], Artefact, Path]:
    """Bring the design up to date, run :func:`tradeoff`, store ``tradeoff.h5`` and draw ``plots/tradeoff.png``.

    Parameters
    ----------
    spec : Spec
        The validated spec (with a tracking scenario).
    out : str, Path or Folder
        The artefact folder.
    tolerances : list of float
        The tolerances (:func:`parse_tolerances`).
    on_stage, on_start : callable, optional
        As :func:`ashc_cli.design.pipeline.run` (a :class:`~ashc_cli.design.pipeline.StageReport` for the design stages and
        for the tradeoff).
    frozen : bool
        Never recompute a design stage: refuse (naming it) if one is stale.

    Returns
    -------
    arts : dict
        The design's artefacts.
    art : Artefact
        The tradeoff artefact just written.
    figure : Path
        The frontier figure.
    """
    from ashc_cli.design.pipeline import DESIGN, StageReport, artefact_path, as_folder, declared_names, design_model, run

    folder = as_folder(out)
    arts = run(spec, folder, DESIGN, frozen=DESIGN if frozen else False, on_stage=on_stage, on_start=on_start)
    if on_start is not None:
        on_start(NAME, f"{len(tolerances)} tolerance(s), budget and governor")
    start = time.perf_counter()
    art = tradeoff(design_model(spec, arts), arts, tolerances)
    write_artefact(artefact_path(folder.path, NAME), art, spec_sha256=spec.sha256, spec_name=spec.name,
                   parameters=dict(spec.parameters), upstream={up: arts[up].provenance["sha256"] for up in UPSTREAM},
                   names=declared_names(spec))
    figure = plot(art, folder.path / "plots" / f"{NAME}.png", unit=output_unit(spec))
    if on_stage is not None:
        on_stage(StageReport(NAME, "ran", time.perf_counter() - start, headline(art)))
    return arts, art, figure
