"""The paper's figures, drawn from the artefacts of a design (``ashc plot``, ``ashc report``).

One function per figure of Section V, each taking the artefacts (plain data) and returning a matplotlib
Figure; :func:`write_all` saves them as PNG (default), PDF or SVG.  Every figure is exactly one or two paper
columns wide (IEEE: 3.5 in and 7.16 in; the saved file keeps that width, no tight bounding box), set in 8 pt
with mathtext symbols ($\\psi$, $\\xi$, $\\theta$) and labelled with the spec's ``units`` where it gives them.
Legends sit above their panel, outside the data.

=========================  ===============================================================
file                       the paper's figure
=========================  ===============================================================
``kappa_xi.png``           Fig. 5: kappa(xi) over V with the output region Y
``delta_compare.png``      Fig. 6: ||theta(xi, .)|| (q = 0) for delta = I and the design's delta
``tracking_inputs.png``    Fig. 7: v (with +-v_max) and u (with U) of the tracking run
``tracking_outputs.png``   Fig. 8: psi, y and the reference per output, and |psi - y| with the
                           uniform and a-posteriori bounds
``m_relation_inputs.png``  Fig. 9: v = b(x) + c(x) u and u (with U), panels in the order of
                           the tracking figure
``m_relation_outputs.png`` Fig. 10: psi and y
``falsify.png``            (ashc's own) largest error / bound of each falsification run, by strategy, log scale
=========================  ===============================================================
"""

from __future__ import annotations

import re
from collections import namedtuple
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, never a window
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker as mticker  # noqa: E402
import numpy as np  # noqa: E402

from ashc_cli.design.artefacts import Artefact  # noqa: E402
from ashc_cli.problem.spec import Spec  # noqa: E402

__all__ = ["write_all", "save", "FIGURES", "FORMATS", "COLUMN_WIDTH", "DOUBLE_WIDTH"]

COLUMN_WIDTH = 3.5  # inches: one IEEE column
DOUBLE_WIDTH = 7.16  # inches: two IEEE columns (text width)
#: File formats :func:`write_all` writes (the suffix of every file).
FORMATS = ("png", "pdf", "svg")
STYLE = {"font.size": 8, "axes.titlesize": 8, "axes.labelsize": 8, "legend.fontsize": 7, "xtick.labelsize": 7,
         "ytick.labelsize": 7, "lines.linewidth": 1.0, "axes.grid": True, "grid.alpha": 0.3, "savefig.dpi": 200,
         "mathtext.fontset": "dejavusans", "legend.frameon": False, "legend.handlelength": 2.2,
         "legend.columnspacing": 1.2, "legend.borderaxespad": 0.2,
         # fonts embedded as TrueType (not Type 3) in PDF, text kept as paths in SVG: what publishers ask for
         "pdf.fonttype": 42, "svg.fonttype": "path", "svg.hashsalt": "ashc"}

#: Colours and line styles of the output panels: psi and y differ in both, the reference is grey.
PSI_STYLE = {"color": "#1f4e9c", "linestyle": "-", "linewidth": 1.3}
Y_STYLE = {"color": "#e07b00", "linestyle": (0, (4, 2)), "linewidth": 1.0}
REF_STYLE = {"color": "0.45", "linestyle": ":", "linewidth": 0.9}
LIMIT_STYLE = {"color": "#b2182b", "linestyle": "-.", "linewidth": 0.8}

_GREEK = {"alpha", "beta", "gamma", "delta", "epsilon", "varepsilon", "zeta", "eta", "theta", "vartheta", "iota", "kappa",
          "lambda", "mu", "nu", "xi", "pi", "rho", "varrho", "sigma", "tau", "upsilon", "phi", "varphi", "chi", "psi",
          "omega", "Gamma", "Delta", "Theta", "Lambda", "Xi", "Pi", "Sigma", "Upsilon", "Phi", "Psi", "Omega"}


def _tex_part(text: str) -> str:
    """One part of a name in mathtext: a Greek letter's command, a single letter or digits as they are, else roman."""
    if text in _GREEK:
        return "\\" + text
    if len(text) == 1 or text.isdigit():
        return text
    return r"\mathrm{" + text + "}"


def math_name(name: str) -> str:
    """A spec name as mathtext: ``xi`` -> ``$\\xi$``, ``xi1`` -> ``$\\xi_{1}$``, ``G_L`` -> ``$G_{L}$``, ``v`` -> ``$v$``.

    Parameters
    ----------
    name : str
        A name of the spec (a state or an input), or ``t``.

    Returns
    -------
    str
        The mathtext; a name of another form (a letter and letters or digits, then optionally ``_`` and letters, digits
        or ``_``) as it is, ``$`` escaped.
    """
    base, sep, sub = name.partition("_")
    if not sep:
        m = re.fullmatch(r"([A-Za-z]+?)(\d+)", name)
        base, sub = (m.group(1), m.group(2)) if m else (name, "")
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9]*", base) or not re.fullmatch(r"[A-Za-z0-9_]*", sub):
        return name.replace("$", r"\$")
    tex = _tex_part(base) + (f"_{{{_tex_part(sub) if '_' not in sub else sub.replace('_', ',')}}}" if sub else "")
    return f"${tex}$"


def _unit(spec: Spec, key: str) -> str | None:
    unit = spec.units.get(key)
    return unit.replace("$", r"\$") if unit else None


def _label(spec: Spec, name: str, key: str | None = None) -> str:
    """``$name$ (unit)`` if the spec gives a unit for ``key`` (default: name); ``name`` a spec name or mathtext."""
    unit = _unit(spec, key or name)
    text = name if "$" in name else math_name(name)
    return f"{text} ({unit})" if unit else text


def _output_label(spec: Spec, k: int, symbol: str) -> str:
    r"""The axis label of output ``k``: ``symbol`` (mathtext body, e.g. ``\psi``) with the output's index when
    there are several, and the unit of ``y<k+1>`` or ``y``."""
    unit = _unit(spec, f"y{k + 1}") or _unit(spec, "y")
    several = len(spec.concrete.h) > 1
    text = "$" + ", ".join(f"{s}_{{{k + 1}}}" if several else s for s in symbol.split(",")) + "$"
    return f"{text} ({unit})" if unit else text


def _figure(rows: int = 1, height: float | None = None, width: float = COLUMN_WIDTH, sharex: bool = True):
    """A figure exactly ``width`` inches wide, ``rows`` panels stacked, laid out by the constrained engine."""
    height = height if height is not None else {1: 2.4, 2: 3.9}.get(rows, 0.8 + 1.3 * rows)
    fig, axes = plt.subplots(rows, 1, figsize=(width, height), sharex=sharex and rows > 1, squeeze=False,
                             layout="constrained")
    return fig, axes[:, 0]


def legend_above(ax, ncol: int | None = None):
    """The axis' legend above the panel (outside the data), entries side by side in as many columns (at most
    ``ncol``) as fit in 80 % of the figure's width, so the layout never narrows the panel for it.

    Parameters
    ----------
    ax : matplotlib Axes
        The panel; its labelled artists are the entries.
    ncol : int, optional
        The most columns [default: one per entry].

    Returns
    -------
    matplotlib Legend or None
        None when the panel has no labelled artist.
    """
    handles, labels = ax.get_legend_handles_labels()
    if not handles:
        return None
    fig = ax.get_figure()
    renderer = fig.canvas.get_renderer()
    room = 0.8 * fig.get_figwidth() * fig.dpi
    for n in range(min(ncol or len(handles), len(handles)), 0, -1):
        leg = ax.legend(handles, labels, loc="lower left", bbox_to_anchor=(0.0, 1.0), ncol=n)
        if n == 1 or leg.get_window_extent(renderer).width <= room:
            return leg
        leg.remove()
    return None


def plain_log_ticks(ax):
    """A log axis spanning less than a decade labelled 1.5, 2, ... rather than 1.5 x 10^0.

    Parameters
    ----------
    ax : matplotlib Axes
        The panel; its y axis (log scale, limits already set) is relabelled, otherwise left as it is.
    """
    lo, hi = ax.get_ylim()
    if lo > 0 and hi / lo < 10:
        fmt = mticker.FuncFormatter(lambda value, _: f"{value:g}")
        ax.yaxis.set_major_formatter(fmt)
        ax.yaxis.set_minor_formatter(fmt)


def _delta_label(spec: Spec) -> str:
    """The design's delta for a legend: ``$\\delta = I$``, else its formula as mathtext when it is short, else
    ``design $\\delta$``; never the spec's Python text."""
    delta = spec.abstract.delta
    if delta == "identity":
        return r"design $\delta = I$"
    if not isinstance(delta, str) or delta == "flatten":
        return r"design $\delta$" + (" (flatten)" if delta == "flatten" else "")
    try:
        import sympy as sp
        from matplotlib.mathtext import MathTextParser

        names = [*spec.parameters, *spec.abstract.states, *spec.concrete.states]
        expr = sp.parse_expr(delta, local_dict={n: sp.Symbol(n) for n in names})
        tex = sp.latex(expr)
        arg = ", ".join(sp.latex(sp.Symbol(n)) for n in spec.abstract.states)
        text = rf"$\delta({arg}) = {tex}$"
        if len(tex) > 70:
            return r"design $\delta$"
        MathTextParser("path").parse(text)  # refuses what mathtext cannot draw
        return text
    except Exception:  # noqa: BLE001 - any failure: the plain name
        return r"design $\delta$"


def kappa_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. 5: psi = kappa(xi) over V, the output region Y shaded.

    Parameters
    ----------
    spec : Spec
        The design's spec (state names, ``units``, ``concrete.output_set``).
    arts : dict of str to Artefact
        Artefacts by stage; ``kappa`` is read (``xi_grid``, ``kappa_grid``).

    Returns
    -------
    matplotlib Figure
    """
    kap = arts["kappa"].values
    xi, k = np.asarray(kap["xi_grid"]), np.asarray(kap["kappa_grid"])
    Y = np.asarray(spec.concrete.output_set, dtype=float)
    a = spec.abstract.states
    if xi.shape[0] == 1:
        fig, (ax,) = _figure()
        for j in range(k.shape[0]):
            sub = f"_{{{j + 1}}}" if k.shape[0] > 1 else ""
            ax.plot(xi[0], k[j], color=f"C{j}", label=rf"$\kappa{sub}({math_name(a[0]).strip('$')})$")
            ax.axhspan(Y[j, 0], Y[j, 1], color=f"C{j}", alpha=0.12, linewidth=0, label=f"output set $Y{sub}$")
        ax.set_xlabel(_label(spec, a[0]))
        ax.set_ylabel(_output_label(spec, 0, r"\psi") if k.shape[0] == 1 else r"$\psi$")
        legend_above(ax)
        return fig
    # Several abstract states: one map per output over the first two, Y's edges as contours.
    per = int(round(xi.shape[1] ** (1 / xi.shape[0])))
    cols = min(k.shape[0], 2)
    rows = -(-k.shape[0] // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(COLUMN_WIDTH if cols == 1 else DOUBLE_WIDTH, 2.6 * rows), squeeze=False,
                             layout="constrained")
    for j, ax in enumerate(axes.flat):
        if j >= k.shape[0]:
            ax.set_visible(False)
            continue
        grid = k[j].reshape((per,) * xi.shape[0])
        while grid.ndim > 2:
            grid = grid[..., grid.shape[-1] // 2]
        x0, x1 = xi[0].reshape((per,) * xi.shape[0]), xi[1].reshape((per,) * xi.shape[0])
        while x0.ndim > 2:
            x0, x1 = x0[..., 0], x1[..., 0]
        mesh = ax.pcolormesh(x0, x1, grid, shading="auto", cmap="viridis", rasterized=True)
        ax.contour(x0, x1, grid, levels=sorted(set(Y[j])), colors="w", linewidths=0.8)
        ax.plot([], [], color="w", linewidth=0.8, label=f"edges of $Y_{{{j + 1}}}$")
        fig.colorbar(mesh, ax=ax, label=_output_label(spec, j, r"\psi"))
        ax.set_xlabel(_label(spec, a[0]))
        ax.set_ylabel(_label(spec, a[1]))
        ax.grid(False)
        leg = legend_above(ax)
        if leg is not None:
            leg.legend_handles[0].set_color("0.3")
    return fig


def delta_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. 6: ||theta(xi, .)|| with q = 0, for delta = I and the design's delta (log scale).

    With several abstract states the values over the grid of V are drawn sorted (a quantile curve), not in the
    grid's order.

    Parameters
    ----------
    spec : Spec
        The design's spec (state names, ``units``, ``abstract.delta``).
    arts : dict of str to Artefact
        Artefacts by stage; ``bound`` is read (``xi_grid``, ``theta_norm_q0``, ``theta_norm_q0_identity``, ``dbar_q0``,
        ``dbar_q0_identity``).

    Returns
    -------
    matplotlib Figure
    """
    bd = arts["bound"].values
    xi = np.asarray(bd["xi_grid"])
    ident, design = np.asarray(bd["theta_norm_q0_identity"]), np.asarray(bd["theta_norm_q0"])
    fig, (ax,) = _figure()
    if xi.shape[0] == 1:
        x, ident_y, design_y = xi[0], ident, design
        ax.set_xlabel(_label(spec, spec.abstract.states[0]))
    else:
        x, ident_y, design_y = np.linspace(0.0, 1.0, ident.size), np.sort(ident), np.sort(design)
        ax.set_xlabel(f"share of the {ident.size} grid points of $V$, sorted")
    dbar_i, dbar_d = float(bd["dbar_q0_identity"]), float(bd["dbar_q0"])
    if spec.abstract.delta == "identity":
        ax.plot(x, design_y, color="C0", label=rf"$\delta = I$, the design's ($\bar d = {dbar_d:.4g}$)")
    else:
        ax.plot(x, ident_y, color="C0", linestyle=(0, (4, 2)), label=rf"$\delta = I$ ($\bar d = {dbar_i:.4g}$)")
        ax.plot(x, design_y, color="C1", label=rf"{_delta_label(spec)} ($\bar d = {dbar_d:.4g}$)")
    drawn = np.concatenate([design_y, [] if spec.abstract.delta == "identity" else ident_y])
    drawn = drawn[np.isfinite(drawn)]
    if drawn.size and drawn.min() > 0 and drawn.max() / drawn.min() >= 10:   # a log axis only where it spans a decade
        ax.set_yscale("log")
        plain_log_ticks(ax)
    else:
        ax.set_ylim(bottom=0)
    ax.set_ylabel(r"$\|\theta(\xi, \cdot)\|$, $q = 0$")
    legend_above(ax, ncol=1)
    return fig


def _series(ax, t, rows, names):
    for j, row in enumerate(np.atleast_2d(rows)):
        ax.plot(t, row, color=f"C{j}", label=math_name(names[j]) if j < len(names) else None)


def _limit_lines(ax, bounds, label: str, names: list[str]):
    """Horizontal lines at each channel's [lo, hi]: one style and one legend entry ``label`` when the channels
    agree, else one colour and entry per channel (``label`` of ``names[j]``)."""
    bounds = np.atleast_2d(np.asarray(bounds, dtype=float))
    same = bool(np.allclose(bounds, bounds[0]))
    for j, (lo, hi) in enumerate(bounds[:1] if same else bounds):
        style = dict(LIMIT_STYLE) if same else {**LIMIT_STYLE, "color": f"C{j}"}
        text = label if same else f"{label} of {math_name(names[j])}"
        for level in (lo, hi):
            if np.isfinite(level):
                ax.axhline(level, label=text, **style)
                text = None


def _inputs_figure(spec: Spec, arts: dict[str, Artefact], scenario: str):
    """Two panels: the abstract input v (top) and the concrete input u (bottom), with their limits: the
    set-point controller's +-v_max (tracking) and the input set U."""
    s = arts["simulate"].values
    t = np.asarray(s[f"{scenario}/t"])
    fig, (ax_v, ax_u) = _figure(2)
    _series(ax_v, t, s[f"{scenario}/v"], spec.abstract.inputs)
    tr = spec.simulate.tracking
    if scenario == "tracking" and tr is not None:
        vm = getattr(tr.abstract_controller, "v_max", None)
        if vm is None and s.get("tracking/guaranteed_mode") == "budget":
            vm = s["tracking/budget_v_max"]
        if vm is not None and np.isfinite(vm):
            _limit_lines(ax_v, [[-float(vm), float(vm)]], r"$\pm v_{\max}$", spec.abstract.inputs)
    _series(ax_u, t, s[f"{scenario}/u"], spec.concrete.inputs)
    _limit_lines(ax_u, spec.concrete.input_bounds, "limits of $U$", spec.concrete.inputs)
    for ax, names in ((ax_v, spec.abstract.inputs), (ax_u, spec.concrete.inputs)):
        label = ", ".join(math_name(n) for n in names)
        ax.set_ylabel(_label(spec, label, names[0]))
        if ax.get_legend_handles_labels()[0]:   # every panel names what it draws, as its neighbours do
            legend_above(ax, ncol=4)
    ax_u.set_xlabel(_label(spec, "t"))
    return fig


def _envelope(ax, t, err, *, log: bool, bins: int = 350, color: str = "k", label: str = ""):
    """|psi - y| readable when it oscillates fast: per time bin its maximum as a thin line (the upper envelope,
    what the bounds are compared with) and, on a linear axis, its min..max band shaded.  A trace with few
    samples is drawn as it is, thin."""
    if t.size <= 2 * bins:
        ax.plot(t, err, color=color, linewidth=0.7, label=label)
        return
    edges = np.linspace(0, t.size, bins + 1).astype(int)
    lo = np.minimum.reduceat(err, edges[:-1])
    hi = np.maximum.reduceat(err, edges[:-1])
    mid = 0.5 * (t[edges[:-1]] + t[edges[1:] - 1])
    if not log:
        ax.fill_between(mid, lo, hi, color=color, alpha=0.2, linewidth=0, label="min to max per time bin")
    ax.plot(mid, hi, color=color, linewidth=0.7, label=label + (" (envelope)" if log else ""))


def _outputs_figure(spec: Spec, arts: dict[str, Artefact], scenario: str, log_error: bool):
    """One panel per output with psi, y (and the reference levels for tracking), and below |psi - y|."""
    s = arts["simulate"].values
    t = np.asarray(s[f"{scenario}/t"])
    psi, y = np.atleast_2d(s[f"{scenario}/psi"]), np.atleast_2d(s[f"{scenario}/y"])
    p = psi.shape[0]
    fig, axes = _figure(p + 1)
    ref = None
    if f"{scenario}/reference_levels" in s and f"{scenario}/reference_index" in s:
        levels = np.asarray(s[f"{scenario}/reference_levels"], dtype=float).reshape(-1, p)
        ref = levels[np.asarray(s[f"{scenario}/reference_index"], dtype=int)].T
    several = p > 1
    for j, ax in enumerate(axes[:p]):
        sub = f"_{{{j + 1}}}" if several else ""
        if ref is not None:
            ax.plot(t, ref[j], label=f"reference $r{sub}$", drawstyle="steps-post", **REF_STYLE)
        ax.plot(t, psi[j], label=rf"$\psi{sub}$", **PSI_STYLE)
        ax.plot(t, y[j], label=f"$y{sub}$", **Y_STYLE)
        ax.set_ylabel(_output_label(spec, j, r"\psi, y"))
        legend_above(ax)
    ax_e = axes[-1]
    err = np.linalg.norm(np.atleast_2d(s[f"{scenario}/e_y"]), axis=0)
    body = r"\|\psi - y\|" if several else r"|\psi - y|"
    unit = None if several else (_unit(spec, "y1") or _unit(spec, "y"))
    scale = 1.0
    if not log_error:   # a power of ten in the axis label, not matplotlib's offset text above the axis
        top = float(np.nanmax(err)) if err.size and np.isfinite(err).any() else 0.0
        exponent = int(np.floor(np.log10(top))) if top > 0 else 0
        scale = 10.0 ** exponent if abs(exponent) >= 3 else 1.0
        unit = (f"$10^{{{exponent}}}$" + (f" {unit}" if unit else "")) if scale != 1.0 else unit
    _envelope(ax_e, t, err / scale, log=log_error, label=f"${body}$")
    ax_e.set_ylabel(f"${body}$" + (f" ({unit})" if unit else ""))
    if not log_error:
        legend_above(ax_e)
    ax_e.set_xlabel(_label(spec, "t"))
    if log_error:
        ax_e.set_yscale("log", nonpositive="clip")
    return fig, ax_e, t, err, s


def tracking_inputs_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. 7: the abstract input v (with +-v_max) and the concrete input u (with U).

    Parameters
    ----------
    spec : Spec
        The design's spec (input names, ``units``, ``concrete.input_bounds``, ``simulate.tracking.abstract_controller.v_max``).
    arts : dict of str to Artefact
        Artefacts by stage; ``simulate`` is read (``tracking/t``, ``tracking/v``, ``tracking/u``, and
        ``tracking/budget_v_max`` in budget mode).

    Returns
    -------
    matplotlib Figure
    """
    return _inputs_figure(spec, arts, "tracking")


def tracking_outputs_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. 8: psi, y and the reference levels; |psi - y| with the uniform and a-posteriori
    bounds (log scale).

    Parameters
    ----------
    spec : Spec
        The design's spec (``units``, the number of outputs).
    arts : dict of str to Artefact
        Artefacts by stage; ``simulate`` is read (``tracking/t``, ``/psi``, ``/y``, ``/e_y``, ``/uniform_bound``, and if
        present ``/reference_levels``, ``/reference_index``, ``/posterior_bound``).

    Returns
    -------
    matplotlib Figure
    """
    fig, ax_e, t, err, s = _outputs_figure(spec, arts, "tracking", log_error=True)
    tops = [float(err.max())]
    if "tracking/posterior_bound" in s:
        post = np.asarray(s["tracking/posterior_bound"], dtype=float)
        ax_e.plot(t, post, color="C2", linewidth=1.0, label="a-posteriori bound")
        tops.append(float(np.nanmax(post)))
    uniform = float(s["tracking/uniform_bound"])
    certified = bool(s.get("tracking/inside_certified_region", True))
    ax_e.axhline(uniform, color="C3" if certified else "0.5", linestyle=":", linewidth=1.0,
                 label=r"uniform bound $G\,\|v\|_\infty$" + ("" if certified else " (not certified for this run)"))
    tops.append(uniform)
    positive = err[err > 0]
    top = max(v for v in tops if np.isfinite(v)) if any(np.isfinite(v) for v in tops) else 1.0
    # The floor a decade below the envelope's smallest values (its lowest 1 %, so that a lone zero-crossing does
    # not stretch the axis), never more than 12 decades below the top; a decade of room above the top line.
    low = float(np.percentile(positive, 1)) if positive.size else top * 1e-6
    floor = 10.0 ** np.floor(np.log10(max(low, top * 1e-12)))
    ax_e.set_ylim(floor, top * 10)
    legend_above(ax_e)
    return fig


def m_relation_inputs_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. 9: v = b(x) + c(x) u and u (with U), in the panel order of the tracking figure.

    Parameters
    ----------
    spec : Spec
        The design's spec (input names, ``units``, ``concrete.input_bounds``).
    arts : dict of str to Artefact
        Artefacts by stage; ``simulate`` is read (``m_relation/t``, ``m_relation/v``, ``m_relation/u``).

    Returns
    -------
    matplotlib Figure
    """
    return _inputs_figure(spec, arts, "m_relation")


def m_relation_outputs_figure(spec: Spec, arts: dict[str, Artefact]):
    """Fig. 10: psi and y coincide (Theorem 3); their difference below.

    Parameters
    ----------
    spec : Spec
        The design's spec (output names, ``units``).
    arts : dict of str to Artefact
        Artefacts by stage; ``simulate`` is read (its ``m_relation/*`` entries).

    Returns
    -------
    matplotlib Figure
    """
    fig, *_ = _outputs_figure(spec, arts, "m_relation", log_error=False)
    return fig


STRATEGY_NAMES = {"off_manifold": "off-manifold"}


def falsify_figure(spec: Spec, arts: dict[str, Artefact]):
    """Largest measured error / guaranteed bound of each falsification run (all must be <= 1), one column of
    points per search strategy on a log scale; each strategy's largest ratio marked.  Runs started on the
    manifold (W0 = 0, where only G ||v||_inf counts) are filled, runs started off it hollow (there the W0 term of
    the bound is tight at t = 0 by construction); the worst run on the manifold is starred and named, the worst
    overall crossed.  A ratio of exactly 0 is drawn at the bottom edge.

    Parameters
    ----------
    spec : Spec
        The design's spec (not read; the signature of every figure).
    arts : dict of str to Artefact
        Artefacts by stage; ``falsify`` is read (``run_ratio``, and if present ``W0``, ``strategy``, ``worst_run``
        and ``worst_w0_zero_run``).

    Returns
    -------
    matplotlib Figure
    """
    v = arts["falsify"].values
    ratios = np.asarray(v["run_ratio"], dtype=float)
    strategies = np.asarray(v["strategy"]).astype(str) if "strategy" in v else np.full(ratios.size, "random")
    on_manifold = np.asarray(v["W0"], dtype=float) == 0 if "W0" in v else np.ones(ratios.size, dtype=bool)
    names = list(dict.fromkeys(strategies))          # the order falsify ran them in
    fig, (ax,) = _figure(height=3.4)     # room for the legend above the panel
    positive = ratios[ratios > 0]
    floor = float(positive.min()) / 2 if positive.size else 1e-12
    shown = np.maximum(ratios, floor)
    rng = np.random.default_rng(0)  # the same jitter every time
    x = np.zeros(ratios.size)
    for i, name in enumerate(names):
        sel = strategies == name
        x[sel] = i + rng.uniform(-0.25, 0.25, sel.sum())
        ax.hlines(shown[sel].max(), i - 0.35, i + 0.35, color="k", linewidth=1.0,
                  label="strategy's largest" if i == 0 else None, zorder=3)
    ax.scatter(x[on_manifold], shown[on_manifold], s=7, color="C0", alpha=0.7, linewidths=0, zorder=2,
               label=r"run with $W_0 = 0$")
    if (~on_manifold).any():
        ax.scatter(x[~on_manifold], shown[~on_manifold], s=9, facecolors="none", edgecolors="0.45", linewidths=0.6,
                   zorder=2, label=r"run with $W_0 > 0$")
    if on_manifold.any():
        lead = int(v["worst_w0_zero_run"]) if "worst_w0_zero_run" in v else int(np.flatnonzero(on_manifold)[np.argmax(ratios[on_manifold])])
        ax.scatter([x[lead]], [shown[lead]], marker="*", s=70, color="C3", edgecolors="k", linewidths=0.4, zorder=4,
                   label=rf"worst, $W_0 = 0$: run {lead}, {ratios[lead]:.4g}")
    worst = int(v["worst_run"]) if "worst_run" in v else int(np.argmax(ratios))
    if not on_manifold[worst]:
        ax.scatter([x[worst]], [shown[worst]], marker="x", s=30, color="k", linewidths=1.0, zorder=4,
                   label=f"worst of all: run {worst}, {ratios[worst]:.4g}")
    ax.axhline(1.0, color="C3", linestyle=":", linewidth=1.0, label="bound")
    ax.set_yscale("log")
    ax.set_xticks(range(len(names)), [STRATEGY_NAMES.get(n, n).replace("_", " ") for n in names], rotation=25,
                  ha="right")
    ax.set_xlim(-0.6, len(names) - 0.4)
    ax.set_ylim(floor / 2, max(2.0, float(ratios.max()) * 2))
    ax.set_ylabel(r"largest $|\psi - y|$ / bound")
    ax.grid(False, axis="x")
    legend_above(ax, ncol=2)
    return fig


#: file name (PNG; the stem is kept for the other formats) -> (figure function, artefacts it needs, what it
#: needs inside the simulate artefact)
#: One task run to draw (:func:`draw_task`): the plant's output y at t; the abstraction's psi and xi at t_plan; the
#: switching times, EPS, and per reach its reach time (first met, NaN: never) and the start of its deepest hold.
#: ``bound`` (optional): an error-aware plan's sqrt(w(t) / alpha_h) on t_plan, drawn as a band around psi.
TaskRun = namedtuple("TaskRun", "t y t_plan psi xi switches eps reach_times best_starts bound", defaults=(None,))


#: draw_task marks at most this many switches below.
MAX_SWITCH_LINES = 60


def draw_task(task, run: TaskRun, unit: str | None = None, note: str | None = None):
    """The task on the output: y of the plant's run and psi, the always box, each reach set over its hold from its
    reach time (the number ``simulate`` and ``synthesize`` print; the deepest hold, hatched, where it is met later or
    never), each set deflated by EPS (what psi was held to) over its deepest hold, each deadline, each avoid set over
    its window; below,
    xi with the switching times.  One IEEE column wide.

    Parameters
    ----------
    task : Task
        ``spec.task``.
    run : TaskRun
    unit : str, optional
        The output's unit, on the y axis.
    note : str, optional
        A line above the lower panel (which run this is).

    Returns
    -------
    matplotlib Figure
    """
    from matplotlib.patches import Rectangle

    t, y = np.asarray(run.t), np.atleast_2d(np.asarray(run.y))
    tp, psi, xi = np.asarray(run.t_plan), np.atleast_2d(np.asarray(run.psi)), np.atleast_2d(np.asarray(run.xi))
    eps, width = float(run.eps), tp[-1] * 0.005
    fig, (ax, ax_xi) = plt.subplots(2, 1, figsize=(COLUMN_WIDTH, 4.2), sharex=True, layout="constrained",
                                    gridspec_kw={"height_ratios": [2.2, 1]})
    if task.always is not None:
        lo, hi = task.always[0]
        ax.axhline(lo, color="0.35", linewidth=0.8, label="always")
        ax.axhline(hi, color="0.35", linewidth=0.8)
    for k, r in enumerate(task.reach):
        lo, hi = r.set[0]
        met, best = float(run.reach_times[k]), float(run.best_starts[k])
        start = met if np.isfinite(met) else best
        ax.add_patch(Rectangle((start, lo), max(r.hold, width), hi - lo, facecolor="#2ca02c" if np.isfinite(met) else "#d62728",
                               alpha=0.25, linewidth=0, label="reach set, held" if k == 0 else None))
        if np.isfinite(met) and abs(best - met) > r.hold:
            ax.add_patch(Rectangle((best, lo), max(r.hold, width), hi - lo, fill=False, hatch="////", edgecolor="#2ca02c",
                                   linewidth=0, alpha=0.5, label="deepest hold" if k == 0 else None))
        ax.add_patch(Rectangle((best, lo + eps), max(r.hold, width), hi - lo - 2 * eps, fill=False, edgecolor="#2ca02c",
                               linestyle="--", linewidth=0.8, label=r"deflated by $\varepsilon$" if k == 0 else None))
        ax.plot([r.by, r.by], [lo, hi], color="#2ca02c", linewidth=1.2, label="deadline" if k == 0 else None)
    for k, a in enumerate(task.avoid):
        lo, hi = a.set[0]
        ax.add_patch(Rectangle((a.during[0], lo), a.during[1] - a.during[0], hi - lo, facecolor="#d62728", alpha=0.2,
                               linewidth=0, label="avoid" if k == 0 else None))
    if run.bound is not None:
        band = np.asarray(run.bound, dtype=float)
        ax.fill_between(tp, psi[0] - band, psi[0] + band, color=PSI_STYLE.get("color", "C0"), alpha=0.18, linewidth=0,
                        label=r"$\psi \pm \sqrt{w/\alpha_h}$")
    ax.plot(tp, psi[0], label=r"$\psi$", **PSI_STYLE)
    ax.plot(t, y[0], label="$y$ (plant)", **Y_STYLE)
    ax.set_ylabel("$y$" + (f" ({unit})" if unit else ""))
    legend_above(ax, ncol=3)
    ax_xi.plot(tp, xi[0], color="0.2", linewidth=1.0)
    marks = np.asarray(run.switches)[1:]
    for sw in marks if marks.size <= MAX_SWITCH_LINES else []:     # a held table switches every period: too many to mark
        ax_xi.axvline(float(sw), color="0.5", linestyle=":", linewidth=0.8)
    ax_xi.set_ylabel(r"$\xi$")
    ax_xi.set_xlabel("$t$ (s)")
    if note:
        ax_xi.set_title(note, fontsize="small", loc="left", color="0.25")
    return fig


def task_figure(spec: Spec, arts: dict[str, Artefact]):
    """The task scenario of ``simulate`` (its ``task/`` group: the synthesised plan run on the plant), drawn by
    :func:`draw_task`.

    Parameters
    ----------
    spec : Spec
        The design's spec (``task``, ``units``).
    arts : dict of str to Artefact
        ``simulate`` is read (``task/t``, ``/y``, ``/psi``, ``/xi``, ``/switch_times``, ``/tolerance``,
        ``/reach_times``, ``/best_hold_starts``).

    Returns
    -------
    matplotlib Figure
    """
    return _stored_task_run(spec, arts["simulate"].values, "task/")


def falsify_task_figure(spec: Spec, arts: dict[str, Artefact]):
    """The worst plant run of falsify's task attack (``task/worst/*``: the start of smallest robustness), drawn by
    :func:`draw_task`.

    Parameters
    ----------
    spec : Spec
        The design's spec (``task``, ``units``).
    arts : dict of str to Artefact
        ``falsify`` is read (``task/worst/t``, ``/y``, ``/psi``, ``/xi``, ``/reach_times``, ``/best_hold_starts``,
        ``task/switch_times``, ``task/tolerance``).

    Returns
    -------
    matplotlib Figure
    """
    v = arts["falsify"].values
    return _stored_task_run(spec, v, "task/worst/", note=f"falsify's worst run: robustness {float(v['task/min_robustness']):.4g}, "
                                                        f"W0 = {float(v['task/worst_W0']):.3g}")


def _stored_task_run(spec: Spec, v, run: str, note: str | None = None):
    """:func:`draw_task` of a stored run (``<run>t``, ``y``, ``psi``, ``xi``, ``reach_times``, ``best_hold_starts``) with
    the plan's ``task/switch_times`` and ``task/tolerance``."""
    band = None
    if f"{run}w_plan" in v and "task/w_level" in v:         # an error-aware plan: its bound sqrt(w / alpha_h) around psi
        band = float(v["task/tolerance"]) * np.sqrt(np.maximum(np.asarray(v[f"{run}w_plan"], dtype=float), 0.0) / float(v["task/w_level"]))
    stored = TaskRun(v[f"{run}t"], v[f"{run}y"], v[f"{run}t"], v[f"{run}psi"], v[f"{run}xi"], v["task/switch_times"], v["task/tolerance"],
                     v[f"{run}reach_times"], v[f"{run}best_hold_starts"], band)
    return draw_task(spec.task, stored, unit=spec.units.get("y1") or spec.units.get("y"), note=note)


FIGURES = {
    "kappa_xi.png": (kappa_figure, ("kappa",), None),
    "delta_compare.png": (delta_figure, ("bound",), None),
    "tracking_inputs.png": (tracking_inputs_figure, ("simulate",), "tracking/t"),
    "tracking_outputs.png": (tracking_outputs_figure, ("simulate",), "tracking/t"),
    "m_relation_inputs.png": (m_relation_inputs_figure, ("simulate",), "m_relation/t"),
    "m_relation_outputs.png": (m_relation_outputs_figure, ("simulate",), "m_relation/t"),
    "falsify.png": (falsify_figure, ("falsify",), None),
    "task.png": (task_figure, ("simulate",), "task/xi"),
    "falsify_task.png": (falsify_task_figure, ("falsify",), "task/worst/xi"),
}

#: Metadata that would change every run (creation date): left out, so the same design gives the same file.
_METADATA = {"png": {"Software": None}, "pdf": {"CreationDate": None, "Creator": None, "Producer": None},
             "svg": {"Date": None, "Creator": None}}


def _format(path: Path, fmt: str | None) -> str:
    fmt = (fmt or path.suffix.lstrip(".") or "png").lower()
    if fmt not in FORMATS:
        raise ValueError(f"figure format '{fmt}' is not one of {', '.join(FORMATS)}")
    return fmt


def save(fig, path: Path, fmt: str | None = None) -> Path:
    """Save a figure atomically (a reader never sees half a file) and close it; ``fmt`` png, pdf or svg
    (default: the path's suffix).  The page keeps the figure's size, so a column-wide figure stays exactly
    one column wide.

    Parameters
    ----------
    fig : matplotlib Figure
        Closed once saved (also when saving fails).
    path : Path or str
        The file; its folder is created.
    fmt : str, optional
        ``png``, ``pdf`` or ``svg`` [default: the path's suffix, else ``png``].

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        For a format not in :data:`FORMATS`.
    """
    path = Path(path)
    fmt = _format(path, fmt)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        fig.savefig(tmp, format=fmt, dpi=STYLE["savefig.dpi"], metadata=_METADATA[fmt])
    finally:
        plt.close(fig)
    tmp.replace(path)
    return path


def write_all(spec: Spec, arts: dict[str, Artefact], folder: str | Path, fmt: str = "png") -> list[Path]:
    """Draw every figure the artefacts allow and save it under ``folder`` as ``<name>.<fmt>``.

    Parameters
    ----------
    fmt : str
        ``png`` (default; what the report embeds), ``pdf`` or ``svg`` (vector, for a paper).

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    ValueError
        For a format not in :data:`FORMATS`.
    """
    fmt = _format(Path(f"x.{fmt}"), fmt)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    with plt.rc_context(STYLE):
        for name, (draw, needs, key) in FIGURES.items():
            if not all(n in arts for n in needs) or (key is not None and key not in arts[needs[0]].values):
                continue
            written.append(save(draw(spec, arts), folder / f"{Path(name).stem}.{fmt}", fmt))
    return written
