"""Tests of ashc_cli.design.contraction.objective (``objective: min_gain``): the M of the smallest bound."""

import numpy as np
import pytest

from ashc_cli.errors import SpecError
from ashc_cli.design.pipeline import DESIGN, design_model, run
from ashc_cli.problem.spec import parse_spec_text

TANK = """
name: quadruple_tank
parameters: {A1: 28.0, A2: 32.0, A3: 28.0, A4: 32.0, T1: 62.0, T2: 90.0, T3: 23.0, T4: 30.0, k1: 3.33, k2: 3.35, g1: 0.7, g2: 0.6, kc: 0.5}
concrete:
  states: [h1, h2, h3, h4]
  inputs: [u1, u2]
  f_bar: ["-h1/T1 + A3*h3/(A1*T3)", "-h2/T2 + A4*h4/(A2*T4)", "-h3/T3", "-h4/T4"]
  g: [["g1*k1/A1", "0"], ["0", "g2*k2/A2"], ["0", "(1 - g2)*k2/A3"], ["(1 - g1)*k1/A4", "0"]]
  h: ["kc*h1", "kc*h2"]
  input_bounds: [[-3, 3], [-3, 3]]
  output_set: [[-3, 3], [-3, 3]]
stabilisability: {method: polytopic_lmi, decay_rate: maximise, feedback: identity, objective: OBJECTIVE}
abstract:
  states: [xi1, xi2]
  inputs: [v1, v2]
  phi_bar: ["0", "0"]
  l: ["0.54247796*xi1 - 0.28472917*xi2", "-0.26961964*xi1 + 0.49530127*xi2"]
  domain: [[-3.2, 3.2], [-3.2, 3.2]]
interface: {q: least_squares, saturate: scale}
simulate:
  tracking: {t_final: 600.0, xi0: [0.0, 0.0], x0: on_manifold, reference_levels: [[2.0, 1.0], [-1.0, 2.0], [0.0, -2.0]], dwell: 200.0,
             abstract_controller: {kind: setpoint, gain: 0.05, v_max: 0.05}}
"""


@pytest.fixture(scope="module")
def tanks(tmp_path_factory):
    out = {}
    for objective in ("rate", "min_gain"):
        spec = parse_spec_text(TANK.replace("OBJECTIVE", objective))
        out[objective] = (spec, run(spec, tmp_path_factory.mktemp(objective), DESIGN))
    return out


def test_min_gain_divides_the_quadruple_tanks_gain_by_more_than_twenty(tanks):
    rate, small = tanks["rate"][1]["bound"].values["gain"], tanks["min_gain"][1]["bound"].values["gain"]
    assert rate > 3000 and small < rate / 20
    st = tanks["min_gain"][1]["stabilise"]
    assert st.meta["objective"].startswith("min_gain") and st.meta["rate_objective_gain_estimate"] > st.meta["gain_estimate"]
    frontier = np.array(st.meta["objective_frontier"])
    assert frontier.shape[1] == 2 and st.values["lambda"] in frontier[:, 0]
    assert st.meta["gain_estimate"] == pytest.approx(frontier[:, 1].min())
    assert all(tanks["min_gain"][1][s].checks[c].evidence == "proved" for s, c in (("stabilise", "lmi_margin"), ("bound", "alpha_h"), ("bound", "condition_B")))


def test_the_min_gain_bound_is_within_thirty_times_of_the_largest_error_found(tanks):
    from ashc_cli.products.falsify import falsify

    spec, arts = tanks["min_gain"]
    art = falsify(design_model(spec, arts), arts, 96, t_final=300.0)
    # on the manifold (W0 = 0) the bound is G ||v||_inf: the ratio is the largest error over the bound
    assert 1 / 30 <= art.values["max_ratio_w0_zero"] <= 1.0
    assert art.values["max_ratio"] <= 1.0


def test_min_gain_is_refused_where_it_does_not_apply(tmp_path):
    spec = parse_spec_text(TANK.replace("OBJECTIVE", "min_gain").replace("feedback: identity", "feedback: linear_gain"))
    with pytest.raises(SpecError, match=r"stabilisability\.objective: 'min_gain' with feedback linear_gain"):
        run(spec, tmp_path, DESIGN)
