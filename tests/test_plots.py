"""Tests of ashc plot and ashc report: the paper's figures and the review page.

The figure tests draw from real designs: ``nonlinear_cascade`` (one input, one output) and
``bilinear_two_input`` (two inputs, two outputs, a two-column kappa map), each run once through ``ashc report``.
"""

import base64
import re
import xml.etree.ElementTree as ET

import matplotlib.image as mpimg
import matplotlib.pyplot as plt
import numpy as np
import pytest
from matplotlib.mathtext import MathTextParser

from ashc_cli.outputs import plots
from ashc_cli.design.pipeline import load_all
from ashc_cli.problem.spec import load_spec

from .conftest import CUK, SPECS, ashc

FIGURES = ["kappa_xi.png", "delta_compare.png", "tracking_inputs.png", "tracking_outputs.png",
           "m_relation_inputs.png", "m_relation_outputs.png", "falsify.png"]
DPI = plots.STYLE["savefig.dpi"]
WIDTHS_IN = (3.5, 7.16)  # IEEE one and two columns


@pytest.fixture(scope="module")
def reported(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    proc = ashc("report", str(SPECS / "nonlinear_cascade.yaml"), "--out", str(out), "--runs", "6", "--t-final", "2", check=True)
    return out, proc


@pytest.fixture(scope="module")
def two_input(tmp_path_factory):
    """The bilinear two-input, two-output design with simulate and falsify artefacts."""
    out = tmp_path_factory.mktemp("two_input")
    ashc("report", str(SPECS / "bilinear_two_input.yaml"), "--out", str(out), "--runs", "6", "--t-final", "2", check=True)
    return load_spec(SPECS / "bilinear_two_input.yaml"), load_all(out), out


@pytest.fixture(scope="module")
def one_input(reported):
    out, _ = reported
    return load_spec(SPECS / "nonlinear_cascade.yaml"), load_all(out)


def draw(fn, spec, arts):
    """A figure as write_all draws it (its style), laid out and drawn so text extents are final."""
    with plt.rc_context(plots.STYLE):
        fig = fn(spec, arts)
        fig.canvas.draw()
    return fig


def all_figures(spec, arts):
    """Every figure the artefacts allow (as write_all: the task figure only with a task scenario)."""
    return {name: draw(fn, spec, arts) for name, (fn, needs, key) in plots.FIGURES.items()
            if all(n in arts for n in needs) and (key is None or key in arts["simulate"].values)}


def texts(fig) -> list[str]:
    """Every label a reader sees: legend entries, axis labels and tick labels of every axes (colour bars too)."""
    out = []
    for ax in fig.axes:
        out += [ax.get_xlabel(), ax.get_ylabel(), ax.get_title()]
        out += [t.get_text() for t in ax.get_xticklabels() + ax.get_yticklabels()]
        if ax.get_legend() is not None:
            out += [t.get_text() for t in ax.get_legend().get_texts()]
    return [t for t in out if t]


def by_label(ax, pattern):
    return [line for line in ax.get_lines() if re.search(pattern, line.get_label())]


def level_lines(ax) -> set[float]:
    """The y values of the horizontal lines of an axes (axhline: two points at one level)."""
    return {round(float(line.get_ydata()[0]), 9) for line in ax.get_lines()
            if len(line.get_ydata()) == 2 and line.get_ydata()[0] == line.get_ydata()[1]}


# --- files -------------------------------------------------------------------------------------------------


def test_every_figure_is_written_and_not_blank(reported):
    out, _ = reported
    for name in FIGURES:
        path = out / "plots" / name
        assert path.stat().st_size > 10_000, name
        img = mpimg.imread(path)
        assert img.shape[1] in [round(w * DPI) for w in WIDTHS_IN], (name, img.shape)  # exactly one or two columns
        assert np.std(img[..., :3]) > 0.05, name         # curves, not an empty canvas


@pytest.mark.parametrize("fmt", ["pdf", "svg"])
def test_vector_formats_are_written_valid_and_exactly_column_wide(two_input, tmp_path, fmt):
    spec, arts, _ = two_input
    paths = plots.write_all(spec, arts, tmp_path, fmt=fmt)
    assert sorted(p.name for p in paths) == sorted(n.replace(".png", f".{fmt}") for n in FIGURES)
    assert not list(tmp_path.glob("*.png")) and not list(tmp_path.glob("*tmp*"))
    widths = {}
    for p in paths:
        data = p.read_bytes()
        if fmt == "pdf":
            assert data.startswith(b"%PDF-") and data.rstrip().endswith(b"%%EOF"), p.name
            box = re.search(rb"/MediaBox \[\s*0 0 ([\d.]+) ([\d.]+)\s*\]", data)
            widths[p.stem] = float(box.group(1)) / 72
            assert b"/FontType 3" not in data and b"/Subtype /Type3" not in data  # fonts embedded as TrueType
        else:
            root = ET.fromstring(data)
            assert root.tag.endswith("svg")
            widths[p.stem] = float(root.get("width").removesuffix("pt")) / 72
    assert all(any(abs(w - c) < 1e-6 for c in WIDTHS_IN) for w in widths.values()), widths
    assert abs(widths["kappa_xi"] - 7.16) < 1e-6       # two outputs: two maps side by side, two columns
    assert abs(widths["tracking_outputs"] - 3.5) < 1e-6


def test_vector_files_are_the_same_for_the_same_design(two_input, tmp_path):
    spec, arts, _ = two_input
    first = plots.write_all(spec, arts, tmp_path / "a", fmt="pdf")
    second = plots.write_all(spec, arts, tmp_path / "b", fmt="pdf")
    assert [p.read_bytes() for p in first] == [p.read_bytes() for p in second]   # no creation date inside


def test_an_unknown_format_is_refused(two_input, tmp_path):
    spec, arts, _ = two_input
    with pytest.raises(ValueError, match="png, pdf, svg"):
        plots.write_all(spec, arts, tmp_path, fmt="jpg")
    assert not list(tmp_path.iterdir())


def test_plot_labels_axes_with_the_spec_units(tmp_path):
    proc = ashc("plot", str(SPECS / "boost_converter.yaml"), "--out", str(tmp_path), "--json", check=True)
    assert '"figures"' in proc.stdout
    assert (tmp_path / "plots" / "tracking_outputs.png").exists()
    spec = load_spec(SPECS / "boost_converter.yaml")
    assert plots._output_label(spec, 0, r"\psi") == r"$\psi$ (V)"
    assert plots._label(spec, "t") == "$t$ (s)"


# --- what the figures say ----------------------------------------------------------------------------------


@pytest.mark.parametrize("name, expected", [("xi", r"$\xi$"), ("xi1", r"$\xi_{1}$"), ("G_L", "$G_{L}$"), ("u", "$u$"),
                                            ("v10", "$v_{10}$"), ("theta_2", r"$\theta_{2}$"), ("speed", r"$\mathrm{speed}$")])
def test_spec_names_become_mathtext_symbols(name, expected):
    assert plots.math_name(name) == expected
    MathTextParser("path").parse(expected)


@pytest.mark.parametrize("design", ["one_input", "two_input"])
def test_no_python_syntax_or_spelled_out_symbol_in_any_label(design, request):
    spec, arts = request.getfixturevalue(design)[:2]
    parser = MathTextParser("path")
    for name, fig in all_figures(spec, arts).items():
        for text in texts(fig):
            for math in re.findall(r"\$[^$]*\$", text):
                parser.parse(math)                           # every mathtext part draws
            plain = re.sub(r"\$[^$]*\$", "", text)
            assert not re.search(r"\*|\|\||_|\b(psi|xi|theta|kappa|delta|lambda|phi)\b", plain), (name, text)
        plt.close(fig)


def test_the_design_delta_is_mathtext_in_the_legend(one_input):
    spec, arts = one_input
    cuk = load_spec(CUK)
    label = plots._delta_label(cuk)
    assert label.startswith(r"$\delta(\xi) = ") and "**" not in label and "G_{L}" in label
    MathTextParser("path").parse(label)
    # the cascade's arts drawn with a delta given as a formula: the legend shows it typeset, not as Python
    formula = spec.model_copy(update={"abstract": spec.abstract.model_copy(update={"delta": "((xi - 1)**2 + 0.5*xi**2)**2"})})
    fig = draw(plots.delta_figure, formula, arts)
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert len(labels) == 2 and labels[0].startswith(r"$\delta = I$")
    assert labels[1].startswith(r"$\delta(\xi) = ") and "**" not in labels[1]
    plt.close(fig)
    assert plots._delta_label(spec) == r"design $\delta = I$"


def test_axis_labels_use_symbols(one_input, two_input):
    spec, arts = one_input
    fig = draw(plots.kappa_figure, spec, arts)
    assert fig.axes[0].get_xlabel() == r"$\xi$" and fig.axes[0].get_ylabel().startswith(r"$\psi$")
    fig = draw(plots.delta_figure, spec, arts)
    assert r"\theta(\xi, \cdot)" in fig.axes[0].get_ylabel()
    spec2, arts2, _ = two_input
    fig = draw(plots.kappa_figure, spec2, arts2)
    assert [ax.get_xlabel() for ax in fig.axes[:2]] == [r"$\xi_{1}$"] * 2
    plt.close("all")


def test_psi_and_y_differ_in_colour_and_style_and_the_reference_is_drawn(two_input):
    spec, arts, _ = two_input
    fig = draw(plots.tracking_outputs_figure, spec, arts)
    s = arts["simulate"].values
    levels = np.asarray(s["tracking/reference_levels"], dtype=float)
    idx = np.asarray(s["tracking/reference_index"], dtype=int)
    for j, ax in enumerate(fig.axes[:2]):
        (psi,), (y,), (ref,) = by_label(ax, rf"^\$\\psi_\{{{j + 1}\}}\$$"), by_label(ax, rf"^\$y_\{{{j + 1}\}}\$$"), by_label(ax, "reference")
        assert psi.get_color() != y.get_color()
        assert psi.get_linestyle() != y.get_linestyle()
        np.testing.assert_array_equal(ref.get_ydata(), levels[idx, j])
        assert set(np.unique(ref.get_ydata())) == set(levels[:, j])
    plt.close(fig)


@pytest.mark.parametrize("design", ["one_input", "two_input"])
def test_input_limits_are_drawn(design, request):
    spec, arts = request.getfixturevalue(design)[:2]
    vmax = spec.simulate.tracking.abstract_controller.v_max
    U = {float(b) for pair in spec.concrete.input_bounds for b in pair}
    tracking = draw(plots.tracking_inputs_figure, spec, arts)
    ax_v, ax_u = tracking.axes
    assert {-vmax, vmax} <= level_lines(ax_v)
    assert U <= level_lines(ax_u)
    m_rel = draw(plots.m_relation_inputs_figure, spec, arts)
    assert U <= level_lines(m_rel.axes[1])
    plt.close("all")


@pytest.mark.parametrize("design", ["one_input", "two_input"])
def test_legends_sit_outside_the_data_and_leave_the_panels_wide(design, request):
    spec, arts = request.getfixturevalue(design)[:2]
    seen = 0
    for name, fig in all_figures(spec, arts).items():
        fig_px = fig.get_figwidth() * fig.dpi
        for ax in fig.axes:
            leg = ax.get_legend()
            if leg is None:
                continue
            seen += 1
            lb, ab = leg.get_window_extent(), ax.get_window_extent()
            overlap_w = min(lb.x1, ab.x1) - max(lb.x0, ab.x0)
            overlap_h = min(lb.y1, ab.y1) - max(lb.y0, ab.y0)
            assert overlap_w <= 1 or overlap_h <= 1, (name, lb, ab)     # never over the data
            assert lb.x0 >= -1 and lb.x1 <= fig_px + 1, (name, lb)       # and inside the page
            if fig.get_figwidth() == 3.5:
                assert ab.width >= 0.6 * fig_px, (name, ab.width)        # the legend did not squeeze the panel
        plt.close(fig)
    assert seen >= 6


def test_tracking_and_m_relation_panels_are_in_the_same_order(two_input):
    spec, arts, _ = two_input
    order = {}
    for name in ("tracking_inputs", "m_relation_inputs", "tracking_outputs", "m_relation_outputs"):
        fig = draw(getattr(plots, f"{name}_figure"), spec, arts)
        order[name] = [ax.get_ylabel() for ax in fig.axes]
        plt.close(fig)
    assert order["tracking_inputs"] == order["m_relation_inputs"]
    assert order["tracking_inputs"][0].startswith("$v_{1}$") and order["tracking_inputs"][1].startswith("$u_{1}$")
    # the same panels; the m-relation error panel may carry a power of ten in its unit ("(10^-9 V)")
    assert [lab.split(" (")[0] for lab in order["tracking_outputs"]] == [lab.split(" (")[0] for lab in order["m_relation_outputs"]]


def test_the_error_trace_is_a_thin_envelope(two_input):
    spec, arts, _ = two_input
    s = arts["simulate"].values
    err = np.linalg.norm(np.atleast_2d(s["tracking/e_y"]), axis=0)
    fig = draw(plots.tracking_outputs_figure, spec, arts)
    ax_e = fig.axes[-1]
    (line,) = by_label(ax_e, r"psi - y")
    assert line.get_linewidth() <= 0.8
    assert len(line.get_ydata()) < err.size / 10           # binned: one point per time bin, not per sample
    assert np.isclose(np.max(line.get_ydata()), err.max())  # the envelope keeps the largest error
    assert ax_e.get_yscale() == "log"
    assert by_label(ax_e, "a-posteriori") and by_label(ax_e, "uniform bound")
    plt.close(fig)


def test_falsify_figure_is_log_scale_by_strategy_and_leads_with_the_runs_on_the_manifold(two_input):
    spec, arts, _ = two_input
    v = arts["falsify"].values
    fig = draw(plots.falsify_figure, spec, arts)
    (ax,) = fig.axes
    assert ax.get_yscale() == "log"
    strategies = list(dict.fromkeys(np.asarray(v["strategy"]).astype(str)))
    ticks = [t.get_text() for t in ax.get_xticklabels()]
    assert ticks == [plots.STRATEGY_NAMES.get(n, n) for n in strategies]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    # the star: the worst run started on the manifold (W0 = 0), to 4 digits (not 10)
    lead = int(v["worst_w0_zero_run"])
    assert float(v["W0"][lead]) == 0
    assert f"worst, $W_0 = 0$: run {lead}, {float(v['run_ratio'][lead]):.4g}" in labels
    star = [c for c in ax.collections if c.get_label().startswith("worst, $W_0 = 0$")]
    x, y = star[0].get_offsets()[0]
    assert ticks[int(round(x))] == plots.STRATEGY_NAMES.get(str(v["strategy"][lead]), str(v["strategy"][lead]))
    assert np.isclose(y, max(float(v["run_ratio"][lead]), 1e-300))
    # the worst of all runs, crossed when it started off the manifold (the W0 term tight at t = 0)
    worst = int(v["worst_run"])
    if float(v["W0"][worst]) > 0:
        assert f"worst of all: run {worst}, {float(v['run_ratio'][worst]):.4g}" in labels
    filled = [c for c in ax.collections if c.get_label() == "run with $W_0 = 0$"]
    assert len(filled[0].get_offsets()) == int(np.sum(np.asarray(v["W0"]) == 0))
    assert 1.0 in level_lines(ax)
    plt.close(fig)


# --- the page ----------------------------------------------------------------------------------------------


def test_report_is_one_self_contained_page(reported):
    out, proc = reported
    page = (out / "report.html").read_text()
    assert "Problem 1 solved: proved" in page and "Problem 1 solved: proved" in proc.stdout
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(images) == len(FIGURES)
    assert all(base64.b64decode(i)[:8] == b"\x89PNG\r\n\x1a\n" for i in images)
    assert "http://" not in page and "https://" not in page and "<script" not in page
    for text in ("invariance PDE residual", "a-posteriori bound", "searched closed-loop runs", "name: nonlinear_cascade"):
        assert text in page


def test_report_of_a_failing_design_says_why(tmp_path):
    spec = tmp_path / "bad.yaml"
    spec.write_text((SPECS / "boost_converter.yaml").read_text().replace("output_set: [[12, 40]]", "output_set: [[12, 400]]"))
    proc = ashc("report", str(spec), "--out", str(tmp_path / "o"))
    assert proc.returncode == 0
    page = (tmp_path / "o" / "report.html").read_text()
    assert "Problem 1 solved: no" in page and "V covers Y" in page
