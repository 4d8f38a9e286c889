"""``ashc report``: one self-contained HTML page for a design review.

The page holds the spec as written, the Problem 1 verdict row by row, every stage's headline numbers and
checks, the error bounds (uniform, a-posteriori), the falsification result and the figures of
:mod:`ashc_cli.plots` embedded as base64 PNG.  No script and no external resource: it opens offline and can
be attached to a review as one file.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import numpy as np

from . import __version__
from .artefacts import Artefact
from .query import summary

__all__ = ["render"]

CSS = """
body { font-family: system-ui, sans-serif; max-width: 60rem; margin: 2rem auto; padding: 0 1rem; color: #222; }
h1 { font-size: 1.5rem; } h2 { font-size: 1.2rem; border-bottom: 1px solid #ccc; margin-top: 2rem; }
table { border-collapse: collapse; margin: 0.5rem 0; font-size: 0.9rem; }
td, th { border: 1px solid #ddd; padding: 0.2rem 0.5rem; text-align: left; vertical-align: top; }
th { background: #f4f4f4; } .pass { color: #176617; font-weight: bold; } .fail { color: #b00; font-weight: bold; }
.na { color: #888; } pre { background: #f8f8f8; padding: 0.5rem; overflow-x: auto; font-size: 0.8rem; }
figure { display: inline-block; margin: 0.5rem; } figcaption { font-size: 0.8rem; color: #555; max-width: 26rem; }
.verdict { font-size: 1.2rem; padding: 0.5rem; border: 2px solid; display: inline-block; }
"""

CAPTIONS = {
    "kappa_xi.png": "kappa(xi) over V, output region Y shaded (Fig. kappa_xi).",
    "delta_compare.png": "||theta(xi, .)|| with q = 0 for delta = I and the design's delta (Fig. delta_Compare).",
    "tracking_inputs.png": "Tracking run: abstract input v and concrete input u (Fig. Example_BoundedIn).",
    "tracking_outputs.png": "Tracking run: psi and y; |psi - y| against the a-posteriori and uniform bounds (Fig. Example_BoundedOut).",
    "m_relation_inputs.png": "m-relation run: u and v = b(x) + c(x) u (Fig. Example_mRelationIn).",
    "m_relation_outputs.png": "m-relation run: psi and y coincide (Fig. Example_mRelationOut).",
    "falsify.png": "Falsification: largest |psi - y| / guaranteed bound of each random run (must stay below 1).",
}


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, dict)):
        text = json.dumps(value)
        return text if len(text) <= 300 else text[:300] + " ..."
    return str(value)


def _status(passed: bool | None) -> str:
    if passed is None:
        return '<span class="na">not reached</span>'
    return '<span class="pass">pass</span>' if passed else '<span class="fail">fail</span>'


def _row(status: bool | None, *cells: str) -> str:
    """A table row: a pass/fail cell, then the text cells (escaped)."""
    return f"<tr><td>{_status(status)}</td>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>"


def _stage_section(name: str, entry: dict) -> str:
    rows = "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(_fmt(v))}</td></tr>"
                   for k, v in entry.items() if k not in ("checks", "provenance"))
    checks = "".join(_row(c["passed"], k, _fmt(c["value"]), c["description"]) for k, c in entry.get("checks", {}).items())
    prov = entry.get("provenance", {})
    return (f"<h3>{html.escape(name)}</h3><table>{rows}</table>"
            + (f"<table><tr><th></th><th>check</th><th>value</th><th>meaning</th></tr>{checks}</table>" if checks else "")
            + f"<p class=\"na\">artefact {html.escape(str(prov.get('sha256', ''))[:16])}..., made {html.escape(str(prov.get('created', '')))}</p>")


def render(spec_text: str, spec_name: str, arts: dict[str, Artefact], solved: bool, rows: list, figures: list[Path]) -> str:
    """The HTML page.

    Parameters
    ----------
    spec_text : str
        The spec file as written.
    spec_name : str
        Its name.
    arts : dict
        The artefacts (design stages, simulate and falsify where present).
    solved : bool
        The Problem 1 verdict.
    rows : list of verdict rows
        From :func:`ashc_cli.verdict.verdict`.
    figures : list of Path
        PNG files to embed.
    """
    summ = summary(arts)
    parts = [f"<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>ashc report: {html.escape(spec_name)}</title>",
             f"<style>{CSS}</style></head><body>",
             f"<h1>ASHC design report: {html.escape(spec_name)}</h1>",
             f"<p>ashc {html.escape(__version__)}. The method of \"Approximate Simulation-based Hierarchical Control of Nonlinear Systems\".</p>",
             f"<p class=\"verdict {'pass' if solved else 'fail'}\">Problem 1 solved: {'yes' if solved else 'no'}</p>"]

    parts.append("<h2>Verdict on Problem 1</h2><table><tr><th></th><th>condition</th><th>evidence</th><th>measured</th><th>reference</th><th>detail</th></tr>")
    for r in rows:
        value = "" if r.value is None else f"{r.value:.4g}"
        parts.append(_row({"pass": True, "fail": False}.get(r.status), r.condition, r.evidence, value, r.reference, r.detail or ""))
    parts.append("</table>")

    parts.append("<h2>Error bounds</h2><table>")
    if "bound" in summ:
        b = summ["bound"]
        region = ("global: every W(xi0, x0) and every v" if not np.isfinite(b.get("w0_max_certified", np.inf))
                  else f"W(xi0, x0) &lt;= {b['w0_max_certified']:.6g} and ||v||_inf &lt;= {b['v_max_certified']:.6g} ({html.escape(b.get('region_limits', ''))})")
        parts.append(f"<tr><th>uniform gain G (eq. egErrorBound, paper form)</th><td>|psi - y| &lt;= {b['gain']:.6g} ||v||_inf when W(xi0, x0) = 0</td></tr>"
                     f"<tr><th>certified region</th><td>{region}</td></tr>"
                     f"<tr><th>dbar entering G</th><td>{b.get('dbar', b['dbar_q0']):.6g}: {html.escape(str(b.get('dbar_how', '')))}</td></tr>"
                     f"<tr><th>comparison-lemma form</th><td>{b['gain_comparison']:.6g} ||v||_inf (ERRATA item 7)</td></tr>"
                     f"<tr><th>dbar (q = 0): design delta / delta = I</th><td>{b['dbar_q0']:.6g} / {b['dbar_q0_identity']:.6g}</td></tr>"
                     f"<tr><th>alpha_h, epsilon</th><td>{b['alpha_h']:.6g}, {b['epsilon']:.6g}</td></tr>")
    if "simulate" in summ and "tracking" in summ["simulate"]:
        t = summ["simulate"]["tracking"]
        parts.append(f"<tr><th>tracking run: measured max |psi - y|</th><td>{t['max_abs_error']:.6g}</td></tr>"
                     f"<tr><th>uniform bound G ||v||_inf</th><td>{t['uniform_bound']:.6g}</td></tr>")
        if "posterior_bound_max" in t:
            parts.append(f"<tr><th>a-posteriori bound (largest over the run)</th><td>{t['posterior_bound_max']:.6g}, "
                         f"{t['posterior_tightening']:.3g} times tighter than the uniform bound</td></tr>")
    parts.append("</table>")

    parts.append("<h2>Falsification</h2>")
    if "falsify" in summ:
        f = summ["falsify"]
        ok = f["max_ratio"] <= 1.0
        parts.append(f"<p>{f['runs']} searched closed-loop runs (seed {f['seed']}; random, adversarial, linearised worst case, "
                     f"boundary of the certified region, refined): largest measured error / guaranteed bound = "
                     f"<b>{f['max_ratio']:.6g}</b> (run {f['worst_run']}, {html.escape(str(f.get('strategy_of_worst', 'random')))}, "
                     f"t = {f['worst_time']:.4g} s); started on the manifold (W0 = 0, only G ||v||_inf counts): "
                     f"<b>{f.get('max_ratio_w0_zero', float('nan')):.4g}</b>; {_status(ok)}. "
                     f"{f['runs_leaving_V']} run(s) left V (not counted after that).</p>")
    else:
        parts.append("<p class=\"na\">not run</p>")

    if figures:
        parts.append("<h2>Figures</h2>")
        for path in figures:
            data = base64.b64encode(Path(path).read_bytes()).decode()
            cap = CAPTIONS.get(Path(path).name, Path(path).name)
            parts.append(f"<figure><img alt=\"{html.escape(cap)}\" src=\"data:image/png;base64,{data}\" width=\"420\">"
                         f"<figcaption>{html.escape(cap)}</figcaption></figure>")

    parts.append("<h2>Stages</h2>")
    for name, entry in summ.items():
        parts.append(_stage_section(name, entry))
    parts.append(f"<h2>Spec</h2><pre>{html.escape(spec_text)}</pre></body></html>")
    return "\n".join(parts)

