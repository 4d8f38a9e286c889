"""Tests of ashc_cli.products.attack: counter-examples to rows a design only sampled, found where the samples miss them.

The planted plant: x1' = -x1 + x2, x2' = -0.5 x1 - 2 x2 + 0.04 tanh(50000 (x1 + 0.0517)) + u on [-1.5, 1.5]^2,
U = [-3, 3].  df2/dx1 = -0.5 + 2000 sech^2(50000 (x1 + 0.0517)) reaches 1999.5 in a band about 1e-4 wide, and
for u in about (-0.169, -0.089) the frozen plant has two stable equilibria.  With the ranges of the Jacobian
entries taken from samples (as if ball arithmetic could not enclose them) the LMI "passes" at two vertices; the
attacks must find the band and the second equilibrium.
"""

import numpy as np
import pytest

from ashc_cli.products import attack
from ashc_cli.products.falsify import counterexample_text
from ashc_cli.design.pipeline import DESIGN, design_model, run
from ashc_cli.problem.spec import parse_spec_text
from ashc_cli.design.contraction import terms

STEEP = """
name: steep_band
concrete:
  states: [x1, x2]
  inputs: [u]
  f_bar: ["-x1 + x2", "-0.5*x1 - 2*x2 + 0.04*tanh(50000*(x1 + 0.0517))"]
  g: [["0"], ["1"]]
  h: ["x1"]
  input_bounds: [[-3, 3]]
  output_set: [[0.1, 0.5]]
  state_box: [[-1.5, 1.5], [-1.5, 1.5]]
stabilisability: {method: polytopic_lmi, decay_rate: 1.0, feedback: identity}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[0, 2]]
"""


@pytest.fixture(scope="module")
def sampled_design(tmp_path_factory):
    """The steep plant designed with sampled Jacobian ranges (the enclosure disabled): its LMI row passes, sampled."""
    mp = pytest.MonkeyPatch()
    mp.setattr(terms, "enclose_entry", lambda *a, **k: None)
    spec = parse_spec_text(STEEP)
    arts = run(spec, tmp_path_factory.mktemp("steep"), DESIGN)
    mp.undo()
    return design_model(spec, arts), arts


def test_the_planted_design_passes_its_lmi_on_samples_only(sampled_design):
    _, arts = sampled_design
    chk = arts["stabilise"].checks["lmi_margin"]
    assert chk.passed and chk.evidence == "sampled"
    assert np.asarray(arts["stabilise"].values["vertex_margins"]).size == 2     # df2/dx1 in [-0.5, -0.5 + tiny]


def test_lmi_counterexample_finds_the_band(sampled_design):
    model, arts = sampled_design
    hit = attack.lmi_counterexample(model, arts)
    assert hit is not None and hit["margin"] > 100
    assert abs(hit["x"][0] + 0.0517) < 1e-3                                    # inside the band
    # an independent re-check of the margin at the reported point
    M, lam = np.asarray(arts["stabilise"].values["M"]), float(arts["stabilise"].values["lambda"])
    x1 = hit["x"][0]
    J = np.array([[-1.0, 1.0], [-0.5 + 2000.0 / np.cosh(50000 * (x1 + 0.0517)) ** 2, -2.0]])
    assert np.linalg.eigvalsh(J.T @ M + M @ J + lam * M).max() == pytest.approx(hit["margin"], rel=1e-6)


def test_second_equilibrium_is_found_and_is_one(sampled_design):
    model, arts = sampled_design
    hit = attack.second_equilibrium(model, arts)
    assert hit is not None
    u = hit["u"][0]
    for x in (hit["x"], hit["x_other"]):
        x1, x2 = x
        assert abs(-x1 + x2) < 1e-9
        assert abs(-0.5 * x1 - 2 * x2 + 0.04 * np.tanh(50000 * (x1 + 0.0517)) + u) < 1e-9
    assert hit["distance"] > 1e-3
    assert "two equilibria" in counterexample_text(hit)


def test_falsify_reports_the_counterexamples_and_fails(sampled_design):
    from ashc_cli.products.falsify import falsify, summarise

    model, arts = sampled_design
    art = falsify(model, arts, runs=16, t_final=2.0)
    entry = summarise(art)
    assert entry["certificate_counterexamples"] >= 2
    assert not art.checks["certificate_attack"].passed
    assert any("eq. (28) fails at x = " in t for t in entry["counterexamples"])
    assert np.asarray(art.values["lmi_counterexample_x"]).shape == (2,)


def test_a_proved_design_is_not_attacked(tmp_path):
    # The same plant without the band: every row that the attacks cover is proved, so none runs.
    spec = parse_spec_text(STEEP.replace(" + 0.04*tanh(50000*(x1 + 0.0517))", " + 0.04*tanh(x1 + 0.0517)"))
    arts = run(spec, tmp_path, DESIGN)
    assert arts["stabilise"].checks["lmi_margin"].evidence == "proved"
    assert attack.attack(design_model(spec, arts), arts) == []


def test_lipschitz_counterexample_beats_a_sampled_L_h():
    # h = (x1 + 0.03 tanh(5000 (x2 + 0.0311)), x2): ||dh/dx||_2 reaches about 150 at x2 = -0.0311; a design that
    # had L_h = 1 from samples is refuted there.
    from types import SimpleNamespace

    spec = parse_spec_text("""
name: lh
concrete:
  states: [x1, x2]
  inputs: [u1, u2]
  f_bar: ["-x1", "-x2"]
  g: [["1", "0"], ["0", "1"]]
  h: ["x1 + 0.03*tanh(5000*(x2 + 0.0311))", "x2"]
  input_bounds: [[-3, 3], [-3, 3]]
  output_set: [[-0.5, 0.5], [-0.5, 0.5]]
  state_box: [[-1.5, 1.5], [-1.5, 1.5]]
stabilisability: {method: polytopic_lmi, decay_rate: 1.0}
abstract:
  states: [xi1, xi2]
  inputs: [v1, v2]
  phi_bar: ["0", "0"]
  l: ["xi1", "xi2"]
  domain: [[-1, 1], [-1, 1]]
""")
    from ashc_cli.problem.model import build_model

    model = build_model(spec)
    arts = {"bound": SimpleNamespace(values={"lipschitz_h": 1.0})}
    hit = attack.lipschitz_counterexample(model, arts)
    assert hit is not None and hit["norm"] > 149 and abs(hit["x"][1] + 0.0311) < 1e-3
