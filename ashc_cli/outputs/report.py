"""``ashc report``: one self-contained HTML page for a design review.

The page holds the spec as written, the Problem 1 verdict row by row, every stage's headline numbers and
checks, the error bounds (uniform, a-posteriori), the falsification result and the figures of
:mod:`ashc_cli.outputs.plots` embedded as base64 PNG.  No script and no external resource: it opens offline and can
be attached to a review as one file.  Numbers are shown to 5 significant digits (the artefacts and ``ashc summary
--json`` keep every digit); a formula, a matrix (M) or a long list sits in a scroll box, one formula or matrix
row per line, never cut short.  The layout fits a laptop screen (1366 px) without scrolling sideways: tables
wrap at spaces (a column is never narrower than its longest word), figures shrink to the page.
"""

from __future__ import annotations

import base64
import html
import struct
from pathlib import Path

import numpy as np

from ashc_cli import __version__
from ashc_cli.design.artefacts import Artefact
from ashc_cli.outputs.query import readable, summary

__all__ = ["render"]

CSS = """
body { font-family: system-ui, sans-serif; max-width: 72rem; margin: 2rem auto; padding: 0 1rem; color: #222; }
h1 { font-size: 1.5rem; } h2 { font-size: 1.2rem; border-bottom: 1px solid #ccc; margin-top: 2rem; }
table { border-collapse: collapse; margin: 0.5rem 0; font-size: 0.9rem; max-width: 100%; }
table.wide { width: 100%; table-layout: fixed; } table.wide th:first-child { width: 15rem; }
table.checks { width: 100%; table-layout: fixed; } table.checks th:first-child { width: 4rem; }
table.checks th:nth-child(2) { width: 19rem; } table.checks th:nth-child(3) { width: 8rem; }
table.rows { width: 100%; table-layout: fixed; }
table.rows th:nth-child(1) { width: 3rem; } table.rows th:nth-child(2) { width: 12rem; }
table.rows th:nth-child(3) { width: 6rem; } table.rows th:nth-child(4) { width: 6.5rem; }
table.rows th:nth-child(5) { width: 9rem; } td.num { text-align: right; white-space: nowrap; }
td, th { border: 1px solid #ddd; padding: 0.2rem 0.5rem; text-align: left; vertical-align: top; overflow-wrap: break-word; }
th { background: #f4f4f4; } .pass { color: #176617; font-weight: bold; } .fail { color: #b00; font-weight: bold; }
.na { color: #888; } pre { background: #f8f8f8; padding: 0.5rem; overflow: auto; font-size: 0.8rem; }
pre.spec { white-space: pre-wrap; overflow-wrap: break-word; }
pre.box { margin: 0; padding: 0.3rem; max-height: 14rem; overflow: auto; white-space: pre-wrap; overflow-wrap: anywhere; }
pre.box.matrix { white-space: pre; overflow-wrap: normal; }
code { overflow-wrap: anywhere; }
figure { display: inline-block; margin: 0.5rem; max-width: 100%; vertical-align: top; }
figure img { max-width: 100%; height: auto; } figcaption { font-size: 0.8rem; color: #555; max-width: 26rem; }
.verdict { font-size: 1.2rem; padding: 0.5rem; border: 2px solid; display: inline-block; }
.sampled { color: #8a5a00; font-weight: bold; } .note { color: #555; }
"""

#: The CSS class of each verdict's banner (proved green, on samples only amber, no red).
VERDICT_CLASS = {"proved": "pass", "sampled": "sampled", "fails": "fail"}

CAPTIONS = {
    "kappa_xi.png": "κ(ξ) over V, output region Y shaded (Fig. 5).",
    "delta_compare.png": "‖θ(ξ, ·)‖ with q = 0 for δ = I and the design's δ (Fig. 6).",
    "tracking_inputs.png": "Tracking run: abstract input v with ±v_max and concrete input u with the limits of U (Fig. 7).",
    "tracking_outputs.png": "Tracking run: ψ, y and the reference levels; |ψ − y| (upper envelope) against the a-posteriori "
                            "and uniform bounds, log scale (Fig. 8).",
    "m_relation_inputs.png": "m-relation run: v = b(x) + c(x) u and u with the limits of U (Fig. 9).",
    "m_relation_outputs.png": "m-relation run: ψ and y coincide; |ψ − y| below (Fig. 10).",
    "falsify.png": "Falsification: largest |ψ − y| / guaranteed bound of each run by search strategy, log scale; "
                   "runs started on the manifold (W0 = 0) filled, the worst of them starred; off it hollow (the W0 term is "
                   "tight at t = 0 by construction), the worst overall crossed. Every point must stay at or below 1.",
    "falsify_task.png": "Falsification of the task: the plant run of smallest robustness (its start in the certified start "
                        "region), drawn as the task figure.",
    "task.png": "The task: y of the plant and ψ under the synthesised plan; the always box, each reach set held from its reach "
                "time, its deepest hold hatched with the set deflated by ε (dashed) there, the deadlines, the avoid sets; below, ξ "
                "and the switches.",
}

#: CSS pixels per PNG pixel of a figure: a one-column figure (3.5 in at 200 dpi) is shown 420 px wide.
FIGURE_SCALE = 0.6


def _text(value) -> str:
    """A stored value as text, in full: one formula, matrix row or key per line for a list or a mapping."""
    if isinstance(value, dict):
        return "\n".join(f"{k}: {readable(v)}" for k, v in value.items())
    if isinstance(value, (list, tuple)):
        if value and all(isinstance(v, (list, tuple)) for v in value):  # a matrix: one row per line
            return "\n".join(readable(row) for row in value)
        if value and all(isinstance(v, str) for v in value) and max(map(len, value)) > 20:  # formulas
            return "\n".join(value)
    return readable(value)


#: A value longer than this, or of several lines, goes into a scroll box.
INLINE_CHARS = 80


def _is_matrix(value) -> bool:
    return isinstance(value, (list, tuple)) and bool(value) and all(isinstance(v, (list, tuple)) for v in value)


def _fmt(value) -> str:
    """A stored value as HTML (escaped), never shortened: long or many-line values in a scroll box (a matrix
    one row per line, scrolled sideways inside the box rather than wrapped)."""
    text = _text(value)
    if len(text) > INLINE_CHARS or "\n" in text:
        return f'<pre class="box{" matrix" if _is_matrix(value) else ""}">{html.escape(text)}</pre>'
    return html.escape(text)


def _status(passed: bool | None) -> str:
    if passed is None:
        return '<span class="na">not reached</span>'
    return '<span class="pass">pass</span>' if passed else '<span class="fail">fail</span>'


def _row(status: bool | None, *cells: str, num: int | None = None) -> str:
    """A table row: a pass/fail cell, then the text cells (escaped); cell ``num`` (0-based) right-aligned, unbroken."""
    opening = ["<td class=\"num\">" if k == num else "<td>" for k in range(len(cells))]
    return f"<tr><td>{_status(status)}</td>" + "".join(f"{o}{html.escape(c)}</td>" for o, c in zip(opening, cells)) + "</tr>"


def _stage_section(name: str, entry: dict) -> str:
    rows = "".join(f"<tr><th>{html.escape(k)}</th><td>{_fmt(v)}</td></tr>"
                   for k, v in entry.items() if k not in ("checks", "provenance"))
    checks = "".join(f"<tr><td>{_status(c['passed'])}</td><td>{html.escape(k)}</td><td>{_fmt(c['value'])}</td>"
                     f"<td>{html.escape(str(c['description']))}</td></tr>" for k, c in entry.get("checks", {}).items())
    prov = entry.get("provenance", {})
    return (f"<h3>{html.escape(name)}</h3><table class=\"wide\">{rows}</table>"
            + (f"<table class=\"checks\"><tr><th></th><th>check</th><th>value</th><th>meaning</th></tr>{checks}</table>" if checks else "")
            + f"<p class=\"na\">artefact sha256 <code>{html.escape(str(prov.get('sha256', '')))}</code>, made {html.escape(str(prov.get('created', '')))}</p>")


def _png_width(data: bytes) -> int | None:
    """The width in pixels of a PNG (from its IHDR chunk), None for anything else."""
    if data[:8] != b"\x89PNG\r\n\x1a\n" or len(data) < 24:
        return None
    return struct.unpack(">I", data[16:20])[0]


def _figure_html(path: Path) -> str:
    """One embedded figure, shown at a fixed share of its pixel width (a two-column figure twice as wide as a
    one-column one) and never wider than the page."""
    raw = Path(path).read_bytes()
    cap = CAPTIONS.get(Path(path).stem + ".png", Path(path).name)
    px = _png_width(raw)
    width = f' width="{round(px * FIGURE_SCALE)}"' if px else ""
    mime = "image/png" if px else "image/svg+xml"
    return (f"<figure><img alt=\"{html.escape(cap)}\" src=\"data:{mime};base64,{base64.b64encode(raw).decode()}\"{width}>"
            f"<figcaption>{html.escape(cap)}</figcaption></figure>")


def _falsify_paragraph(f: dict) -> str:
    """The falsification result, led by the runs started on the manifold: off it, the W0 term of the bound is tight
    at t = 0 by construction (ratio 1 at t = 0 says nothing about G)."""
    ok = f["max_ratio"] <= 1.0
    lead = f.get("max_ratio_w0_zero")
    head = ""
    if lead is not None and np.isfinite(lead):
        head = (f"Started on the manifold (W0 = 0, where only G ||v||_inf counts): largest measured error / guaranteed "
                f"bound = <b>{readable(lead, 4)}</b> (run {f.get('worst_w0_zero_run', '?')}; strongest strategy: "
                f"{html.escape(str(f.get('strategy_of_worst_w0_zero', '?')))}). ")
    names = ", ".join(str(k).replace("_", "-") for k in f.get("ratio_by_strategy", {})) or "random"
    return (f"<p>{head}{f['runs']} searched closed-loop runs in all (seed {f['seed']}; strategies {html.escape(names)}), "
            f"with starts off the manifold: largest ratio "
            f"{readable(f['max_ratio'], 4)} (run {f['worst_run']}, {html.escape(str(f.get('strategy_of_worst', 'random')))}, "
            f"t = {readable(f['worst_time'], 4)} s; at t = 0 the W0 term is tight by construction); {_status(ok)} "
            f"(every ratio must stay at or below 1). Runs that left V: {f['runs_leaving_V']} (not counted after that).</p>")


def _box_text(box, grow: float = 0.0) -> str:
    """A box as [lo, hi] per output, each side moved out by ``grow`` (in by -grow); empty: 'empty'."""
    sides = [(float(lo) - grow, float(hi) + grow) for lo, hi in box]
    if any(lo > hi for lo, hi in sides):
        return "empty"
    return " x ".join(f"[{readable(lo, 5)}, {readable(hi, 5)}]" for lo, hi in sides)


def _task_rows(task, eps: float) -> list[str]:
    """One table row per part of the task: as stated, and as deflated by EPS (what psi was held to)."""
    rows = []
    if task.always is not None:
        rows.append(("always", f"y in {_box_text(task.always)} on [0, {readable(task.horizon, 5)}] s", _box_text(task.always, -eps)))
    for k, r in enumerate(task.reach):
        rows.append((f"reach[{k}]", f"y in {_box_text(r.set)} for {readable(r.hold, 5)} s, starting by {readable(r.by, 5)} s",
                     _box_text(r.set, -eps)))
    for k, a in enumerate(task.avoid):
        rows.append((f"avoid[{k}]", f"y outside {_box_text(a.set)} during [{readable(a.during[0], 5)}, {readable(a.during[1], 5)}] s",
                     _box_text(a.set, eps)))
    return [f"<tr><th>{name}</th><td>{html.escape(stated)}</td><td>{html.escape(deflated)}</td></tr>" for name, stated, deflated in rows]


def _margin_row(v: dict) -> str:
    """The report's row on the plan's certified margin: proved on the grid, or sampled in time (the set-point plan)."""
    margin = float(v["task/certified_margin"])
    if float(v.get("task/proved", 0.0)):
        how = ("the grid planner: the start's cell wins the task's game on a grid of V with every transition over-approximated "
               "and every set deflated by EPS over each period; proved")
    elif str(v.get("task/planner", "")) == "error_aware":
        how = ("error-aware planning: psi's robustness against the sets deflated by sqrt(w(t) / alpha_h), w the comparison bound the plan "
               "carries (at most alpha_h EPS^2), less the sampling margin and the plan's deviation; sampled in time")
    else:
        how = "psi's robustness less EPS, the sampling margin and the plan's deviation; sampled in time"
    return f"<tr><th>certified margin of the plan</th><td>{readable(margin, 5)} ({how}) {_status(margin >= 0)}</td></tr>"


def _task_section(task, arts: dict[str, Artefact]) -> str:
    """The task (``spec.task``): as stated and as deflated by EPS, EPS and the certified margin of the plan, the plant's
    robustness and reach times (simulate's task scenario), falsify's smallest robustness; not part of Problem 1."""
    if "simulate" not in arts or "task/robustness" not in arts["simulate"].values:
        return ("<p class='na'>The spec has a task, but simulate.h5 holds no task scenario: run `ashc simulate` "
                "(it synthesises the plan and runs it on the plant).</p>")
    v = arts["simulate"].values
    eps = float(v["task/tolerance"])
    parts = {k.split("/", 2)[2]: float(x) for k, x in v.items() if k.startswith("task/parts/")}
    reach = ", ".join(f"reach[{k}] {'never' if not np.isfinite(x) else readable(float(x), 5) + ' s'}"
                      for k, x in enumerate(np.atleast_1d(v["task/reach_times"])))
    out = ["<p>Not part of Problem 1's verdict: the task is solved on the abstraction by the synthesised plan (error-aware planning, "
           "the set-point law in the budget mode of the guaranteed controller, eq. (38), or the grid planner's table), which keeps |psi - y| &lt;= EPS "
           "(error-aware: &lt;= sqrt(w(t) / alpha_h) &lt;= EPS, w the comparison bound it carries), so a psi that meets "
           "the task deflated so is a plant that meets it as stated.</p>",
           "<table class='wide'><tr><th>part</th><th>as stated</th><th>as deflated by EPS (psi's task)</th></tr>",
           *_task_rows(task, eps), "</table><table class='wide'>",
           f"<tr><th>EPS (tolerance), v_max</th><td>{readable(eps, 5)}, {readable(float(v['task/v_max']), 5)}</td></tr>",
           _margin_row(v),
           f"<tr><th>plant run: robustness</th><td>{readable(float(v['task/robustness']), 5)} {_status(bool(v['task/satisfied']))} "
           f"(max |psi - y| = {readable(float(v['task/max_abs_error']), 4)}; per part: "
           f"{html.escape(', '.join(f'{k} {readable(x, 5)}' for k, x in parts.items()))})</td></tr>",
           f"<tr><th>reach times (first met)</th><td>{html.escape(reach)}</td></tr>"]
    f = arts["falsify"].values if "falsify" in arts else {}
    if "task/min_robustness" in f:
        out.append(f"<tr><th>falsify: smallest robustness</th><td>{readable(float(f['task/min_robustness']), 5)} "
                   f"{_status(float(f['task/min_robustness']) >= 0)} over {int(f['task/runs'])} plant runs from starts with "
                   f"W0 &lt;= {readable(float(f['task/start_region_W0']), 5)} (the certified start region; worst W0 "
                   f"{readable(float(f['task/worst_W0']), 4)})</td></tr>")
    if "task_disturbed/min_robustness" in f:
        out.append(f"<tr><th>falsify: with disturbances</th><td>{readable(float(f['task_disturbed/min_robustness']), 5)} "
                   f"{_status(float(f['task_disturbed/min_robustness']) >= 0)} (w held at each vertex of its box)</td></tr>")
    out.append("</table>")
    return "\n".join(out)


def render(spec_text: str, spec_name: str, arts: dict[str, Artefact], result, figures: list[Path], task=None) -> str:
    """The HTML page.

    Parameters
    ----------
    spec_text : str
        The spec file as written.
    spec_name : str
        Its name.
    arts : dict
        The artefacts (design stages, simulate and falsify where present).
    result : Verdict
        The Problem 1 verdict and its rows (:func:`ashc_cli.design.verdict.verdict`).
    figures : list of Path
        PNG (or SVG) files to embed; other files are left out.
    task : Task, optional
        ``spec.task``: a section of its own (:func:`_task_section`).
    """
    summ = summary(arts)
    parts = [f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>ashc report: {html.escape(spec_name)}</title>",
             f"<style>{CSS}</style></head><body>",
             f"<h1>ASHC design report: {html.escape(spec_name)}</h1>",
             f"<p>ashc {html.escape(__version__)}. The method of \"Approximate Simulation-based Hierarchical Control of Nonlinear Systems\".</p>",
             f"<p class=\"verdict {VERDICT_CLASS[result.kind]}\">{html.escape(result.line())}</p>"]
    if result.kind == "sampled":
        parts.append("<p class=\"note\">Every condition passes, but the rows marked <i>sampled</i> were checked on a grid or on "
                     "random points only: the design is not certified until they are proved (or falsified).</p>")

    parts.append("<h2>Verdict on Problem 1</h2><table class=\"rows\"><tr><th></th><th>condition</th><th>evidence</th><th>measured</th><th>reference</th><th>detail</th></tr>")
    for r in result.rows:
        value = "" if r.value is None else f"{r.value:.4g}"
        parts.append(_row({"pass": True, "fail": False}.get(r.status), r.condition, r.evidence, value, r.reference, r.detail or "", num=2))
    parts.append("</table>")

    parts.append("<h2>Error bounds</h2><table class=\"wide\">")
    if "bound" in summ:
        b = summ["bound"]
        region = ("global: every W(xi0, x0) and every v" if not np.isfinite(b.get("w0_max_certified", np.inf))
                  else f"W(xi0, x0) &lt;= {b['w0_max_certified']:.5g} and ||v||_inf &lt;= {b['v_max_certified']:.5g} ({html.escape(b.get('region_limits', ''))})")
        ev = b.get("evidence", {})
        sampled = "" if b.get("bound_evidence") == "proved" else f" <span class=\"sampled\">(sampled: {html.escape(str(b.get('bound_sampled', '')))})</span>"
        dist = f" + {b['gain_w']:.5g} ||w||_inf (disturbance, ebar = {b['ebar']:.5g})" if "gain_w" in b else ""
        dist += f" + {b['residual_term']:.3g} (p's PDE residual, rho_bar = {b['rho_bar']:.3g})" if b.get("residual_term", 0.0) > 0 else ""
        parts.append(f"<tr><th>uniform gain G (eq. (38), paper form)</th><td>|psi - y| &lt;= {b['gain']:.5g}{sampled} ||v||_inf{dist} when W(xi0, x0) = 0</td></tr>"
                     f"<tr><th>how each number was established</th><td>{html.escape(', '.join(f'{k}: {v}' for k, v in ev.items()))}</td></tr>"
                     f"<tr><th>certified region</th><td>{region}</td></tr>"
                     f"<tr><th>dbar entering G</th><td>{b.get('dbar', b['dbar_q0']):.5g}: {html.escape(str(b.get('dbar_how', '')))}</td></tr>"
                     f"<tr><th>comparison-lemma form</th><td>{b['gain_comparison']:.5g} ||v||_inf (ERRATA item 7)</td></tr>"
                     f"<tr><th>dbar (q = 0): design delta / delta = I</th><td>{b['dbar_q0']:.5g} / {b['dbar_q0_identity']:.5g}</td></tr>"
                     f"<tr><th>alpha_h, epsilon</th><td>{b['alpha_h']:.5g}, {b['epsilon']:.5g}</td></tr>")
    if "simulate" in summ and "tracking" in summ["simulate"]:
        t = summ["simulate"]["tracking"]
        parts.append(f"<tr><th>tracking run: measured max |psi - y|</th><td>{t['max_abs_error']:.5g}</td></tr>"
                     f"<tr><th>uniform bound G ||v||_inf</th><td>{t['uniform_bound']:.5g}"
                     + ("" if t.get("inside_certified_region", True) else
                        " <span class=\"fail\">not certified for this run</span> (it leaves the certified region: "
                        "W0 or ||v||_inf above what the bound stage certifies; the number is only compared)")
                     + "</td></tr>")
        if "posterior_bound_max" in t:
            parts.append(f"<tr><th>a-posteriori bound (largest over the run)</th><td>{t['posterior_bound_max']:.5g}, "
                         f"{t['posterior_tightening']:.3g} times tighter than the uniform bound</td></tr>")
    parts.append("</table>")

    parts.append("<h2>Falsification</h2>")
    if "falsify" in summ:
        parts.append(_falsify_paragraph(summ["falsify"]))
    else:
        parts.append("<p class=\"na\">not run</p>")

    if task is not None:
        parts.append("<h2>Task on the output</h2>")
        parts.append(_task_section(task, arts))

    if figures:
        parts.append("<h2>Figures</h2>")
        for path in figures:
            if Path(path).suffix.lower() in (".png", ".svg"):  # what a browser shows inline (not PDF)
                parts.append(_figure_html(path))

    parts.append("<h2>Stages</h2>")
    for name, entry in summ.items():
        parts.append(_stage_section(name, entry))
    parts.append(f"<h2>Spec</h2><pre class=\"spec\">{html.escape(spec_text)}</pre></body></html>")
    return "\n".join(parts)

