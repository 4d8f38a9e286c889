"""The output's cone of influence (issue 43): which states reach y, and the spec restricted to them."""

from __future__ import annotations

import numpy as np
import pytest

from ashc_cli.design.artefacts import read_artefact
from ashc_cli.problem.influence import cone_model, on_the_cone, output_cone
from ashc_cli.problem.model import build_model
from ashc_cli.problem.spec import parse_spec_text

from .conftest import SPECS, ashc

# a 4-state plant whose output reads x2: x1 drives x2 (kept); px integrates x2 and yaw integrates u2 (left out; yaw
# reads px, which leaves it outside too: a path must lead *to* y)
SPEC = """
name: cone
concrete:
  states: [x1, px, x2, yaw]
  inputs: [u1, u2]
  f_bar: ["-x1", "x2", "x1 - 2*x2", "px"]
  g: [["1", "0"], ["0", "0"], ["0", "0"], ["0", "1"]]
  h: ["x2"]
  input_bounds: [[-1, 1], [-1, 1]]
  output_set: [[-1, 1]]
  state_box: [[-1, 1], [-5, 5], [-2, 2], [0, 4]]
stabilisability:
  method: given
  decay_rate: 0.5
  M: [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 3, 0], [0, 0, 0, 4]]
  K: [[1, 2, 3, 4], [5, 6, 7, 8]]
  feedback: linear_gain
  linearise_at: {x: [0.1, 0.2, 0.3, 0.4], u: [0, 0]}
abstract: {states: [xi], inputs: [v], phi_bar: ["0"], l: ["xi", "0"], domain: [[-0.5, 0.5]]}
simulate:
  tracking: {t_final: 2.0, xi0: [0.0], x0: [0.1, 1.5, 0.2, 3.0], reference_levels: [0.2], dwell: 2.0,
             abstract_controller: {kind: setpoint, gain: 1.0, v_max: 0.5}}
  m_relation: {t_final: 1.0, x0: [0.1, 1.5, 0.2, 3.0], u: ["0.1", "0"]}
"""


def test_the_cone_follows_paths_to_y_and_the_spec_keeps_only_its_states():
    spec = parse_spec_text(SPEC)
    full = build_model(spec)
    assert output_cone(full) == ([0, 2], [1, 3])
    reduced, beside = on_the_cone(spec, full)
    c, s = reduced.concrete, reduced.stabilisability
    assert c.states == ["x1", "x2"] and [str(e) for e in build_model(reduced).f] == ["u1 - x1", "x1 - 2*x2"]
    assert np.asarray(c.state_box).tolist() == [[-1, 1], [-2, 2]]
    assert np.asarray(s.M).tolist() == [[1, 0], [0, 3]] and np.asarray(s.K).tolist() == [[1, 3], [5, 7]]
    assert s.linearise_at.x == [0.1, 0.3] and s.linearise_at.u == [0, 0]
    assert reduced.simulate.tracking.x0 == [0.1, 0.2] and reduced.simulate.m_relation.x0 == [0.1, 0.2]
    # what the spec left to defaults stays a default (model_fields_set), and nothing else changed
    assert reduced.interface.model_fields_set == spec.interface.model_fields_set
    assert reduced.abstract == spec.abstract and reduced.name == spec.name
    # the left-out states: named, their f in the full plant's symbols, their start from the tracking x0
    assert beside.names == ("px", "yaw") and beside.index == (1, 3) and beside.kept == (0, 2)
    assert [str(e) for e in beside.f] == ["x2", "px + u2"] and beside.x0.tolist() == [1.5, 3.0]
    assert "left out px, yaw" in beside.line()
    model = cone_model(spec)
    assert model.n == 2 and model.beside.names == ("px", "yaw")


def test_an_abstraction_with_more_states_than_outputs_keeps_every_state():
    # two abstract states, one output: the abstraction's second direction may be a state y cannot see (the bilinear
    # plant of test_inverse's augmented outputs), so nothing is left out
    text = SPEC.replace("abstract: {states: [xi], inputs: [v], phi_bar: [\"0\"], l: [\"xi\", \"0\"], domain: [[-0.5, 0.5]]}",
                        "abstract: {states: [xi, eta], inputs: [v, w], phi_bar: [\"0\", \"0\"], l: [\"xi\", \"eta\"], domain: [[-0.5, 0.5], [-0.5, 0.5]]}")
    text = text.replace("xi0: [0.0]", "xi0: [0.0, 0.0]")
    spec = parse_spec_text(text)
    assert output_cone(build_model(spec))[1] == [1, 3]
    reduced, beside = on_the_cone(spec, build_model(spec))
    assert reduced is spec and beside is None
    # likewise one abstract state whose given m reads a state outside the cone (the user's m means it)
    spec = parse_spec_text(SPEC.replace('domain: [[-0.5, 0.5]]}', 'domain: [[-0.5, 0.5]], m: ["x2 + px/100"]}'))
    assert on_the_cone(spec, build_model(spec)) == (spec, None)
    spec = parse_spec_text(SPEC.replace('domain: [[-0.5, 0.5]]}', 'domain: [[-0.5, 0.5]], m: ["x2"]}'))
    assert on_the_cone(spec, build_model(spec))[1].names == ("px", "yaw")


def test_a_plant_whose_states_all_reach_y_is_its_own_cone():
    text = SPEC.replace('h: ["x2"]', 'h: ["yaw"]')       # yaw reads px reads x2 reads x1: every state reaches y
    spec = parse_spec_text(text)
    assert output_cone(build_model(spec)) == ([0, 1, 2, 3], [])
    reduced, beside = on_the_cone(spec, build_model(spec))
    assert reduced is spec and beside is None and cone_model(spec).beside is None


@pytest.mark.slow
def test_the_aerial_vehicle_designs_on_its_cone_and_simulates_the_whole_plant(tmp_path):
    # specs/aerial_vehicle.yaml: 13 states, 16 distinct nonlinear terms on the cone; proved with the 5 states that
    # cannot reach the altitude left out and named, and the tracking run carries them beside the loop
    spec = SPECS / "aerial_vehicle.yaml"
    proc = ashc("design", str(spec), "--out", str(tmp_path), check=True)
    line = proc.stdout.strip().splitlines()[-1]
    assert "proved (15/15" in line and "left out px, py, vx, vy, psi" in line, line
    ashc("simulate", str(spec), "--out", str(tmp_path), check=True)
    st, sim = read_artefact(tmp_path / "stabilise.h5"), read_artefact(tmp_path / "simulate.h5")
    assert st.meta["left_out"]["states"] == ["px", "py", "vx", "vy", "psi"]
    assert "norm-bound" in st.meta["route"]
    v = sim.values
    t, x, out = (np.asarray(v[k]) for k in ("tracking/t", "tracking/x", "tracking/x_beside"))
    assert x.shape == (8, t.size) and out.shape == (5, t.size) and np.all(np.isfinite(out))
    assert all(c.passed for c in sim.checks.values()), {k: c.value for k, c in sim.checks.items() if not c.passed}
    # no lateral thrust without tilt: the horizontal states stay near their start (tilts of at most 0.03 rad)
    assert np.abs(out).max() < 1.0


def test_a_state_read_through_e_is_in_the_cone_and_a_constant_output_keeps_every_state():
    # a disturbance's e(x) acts on x' as f does: px read by e's row of x1 reaches y (found by an independent attack,
    # which had px left out and the spec refused); an output that reads no state leaves nothing to design on: the
    # spec stays whole (the stages refuse it in their own words), never an empty one
    text = SPEC.replace('  state_box:', '  disturbances: [w]\n  e: [["px/10"], ["0"], ["0"], ["0"]]\n  disturbance_bounds: [[-0.1, 0.1]]\n  state_box:')
    spec = parse_spec_text(text)
    assert output_cone(build_model(spec)) == ([0, 1, 2], [3])
    assert cone_model(spec).beside.names == ("yaw",)
    spec = parse_spec_text(SPEC.replace('h: ["x2"]', 'h: ["0.1"]'))
    assert output_cone(build_model(spec)) == ([], [0, 1, 2, 3])
    assert on_the_cone(spec, build_model(spec)) == (spec, None)


def test_the_states_beside_carry_the_runs_constant_disturbance():
    # x_out' = f_out + e_out w0 on the run's samples: with f_out = 0 and e_out = 2, x_out(t) = x_out(0) + 2 w0 t
    from ashc_cli.closedloop.beside import integrate_beside

    text = SPEC.replace('  state_box:', '  disturbances: [w]\n  e: [["0"], ["1"], ["0.5"], ["2"]]\n  disturbance_bounds: [[-0.1, 0.1]]\n  state_box:')
    text = text.replace('f_bar: ["-x1", "x2", "x1 - 2*x2", "px"]', 'f_bar: ["-x1", "0", "x1 - 2*x2", "0"]')
    model = cone_model(parse_spec_text(text))
    assert model.beside.names == ("px", "yaw")
    t = np.linspace(0.0, 4.0, 401)
    X = integrate_beside(model.beside, t, np.zeros((2, t.size)), np.zeros((2, t.size)), w0=[0.1])
    assert np.allclose(X[:, -1] - X[:, 0], [0.1 * 4.0, 0.2 * 4.0], rtol=1e-12, atol=1e-12)
    assert np.allclose(integrate_beside(model.beside, t, np.zeros((2, t.size)), np.zeros((2, t.size)))[:, -1], X[:, 0])
