"""Tests of ashc plot and ashc report: the paper's figures and the review page."""

import base64
import re

import matplotlib.image as mpimg
import numpy as np
import pytest

from .conftest import SPECS, ashc

FIGURES = ["kappa_xi.png", "delta_compare.png", "tracking_inputs.png", "tracking_outputs.png",
           "m_relation_inputs.png", "m_relation_outputs.png", "falsify.png"]


@pytest.fixture(scope="module")
def reported(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    proc = ashc("report", str(SPECS / "nonlinear_cascade.yaml"), "--out", str(out), "--runs", "6", "--t-final", "2", check=True)
    return out, proc


def test_every_figure_is_written_and_not_blank(reported):
    out, _ = reported
    for name in FIGURES:
        path = out / "plots" / name
        assert path.stat().st_size > 10_000, name
        img = mpimg.imread(path)
        assert img.shape[1] >= 600                      # 3.5 in at 200 dpi: readable at column width
        assert np.std(img[..., :3]) > 0.05, name         # curves, not an empty canvas


def test_report_is_one_self_contained_page(reported):
    out, proc = reported
    page = (out / "report.html").read_text()
    assert "Problem 1 solved: yes" in page and "Problem 1 solved: yes" in proc.stdout
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(images) == len(FIGURES)
    assert all(base64.b64decode(i)[:8] == b"\x89PNG\r\n\x1a\n" for i in images)
    assert "http://" not in page and "https://" not in page and "<script" not in page
    for text in ("invariance PDE residual", "a-posteriori bound", "searched closed-loop runs", "name: nonlinear_cascade"):
        assert text in page


def test_plot_labels_axes_with_the_spec_units(tmp_path):
    proc = ashc("plot", str(SPECS / "boost_converter.yaml"), "--out", str(tmp_path), "--json", check=True)
    assert '"figures"' in proc.stdout
    assert (tmp_path / "plots" / "tracking_outputs.png").exists()
    from ashc_cli import plots
    from ashc_cli.spec import load_spec
    spec = load_spec(SPECS / "boost_converter.yaml")
    assert plots._output_label(spec, 0, "psi") == "psi (V)"
    assert plots._label(spec, "t") == "t (s)"


def test_report_of_a_failing_design_says_why(tmp_path):
    spec = tmp_path / "bad.yaml"
    spec.write_text((SPECS / "boost_converter.yaml").read_text().replace("output_set: [[12, 40]]", "output_set: [[12, 400]]"))
    proc = ashc("report", str(spec), "--out", str(tmp_path / "o"))
    assert proc.returncode == 0
    page = (tmp_path / "o" / "report.html").read_text()
    assert "Problem 1 solved: no" in page and "V covers Y" in page
