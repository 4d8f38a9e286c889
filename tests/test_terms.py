"""Tests of ashc_cli.design.contraction.terms: the Jacobian over the plant's nonlinear terms, and its polytopes."""

import numpy as np
import pytest
import sympy as sp

from ashc_cli.design.contraction import terms, vertex
from ashc_cli.problem.model import build_model, sparse_jacobian
from ashc_cli.problem.spec import parse_spec_text
from ashc_cli.design.stages import stabilise

CSTR = """
name: cstr_test
parameters: {q: 1.0, k0: 20.0, E: 8.0, hr: 3.0, ua: 2.0, cf: 1.0, tf: 1.0}
concrete:
  states: [c, T]
  inputs: [u]
  f_bar: ["q*(cf - c) - k0*exp(-E/T)*c", "q*(tf - T) + hr*k0*exp(-E/T)*c - ua*T"]
  g: [["0"], ["ua"]]
  h: ["T"]
  input_bounds: [[1.0, 2.0]]
  output_set: [[1.2, 1.5]]
  state_box: [[0.2, 1.0], [1.0, 2.0]]
stabilisability: {method: polytopic_lmi, decay_rate: maximise}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[1.0, 2.0]]
"""


def _sampled_supremum(model, per: int) -> float:
    """An upper estimate of the supremum rate: the LMI imposed at Jacobians sampled on a grid of state_box x U only
    (fewer constraints than the whole box, so a larger rate), computed independently of the stage's polytopes."""
    J = sparse_jacobian(model.f, model.x)
    Jf = model.numeric(J, list(model.x) + list(model.u))
    box = np.r_[model.state_box, model.U]
    axes = [np.linspace(lo, hi, per) if hi > lo else np.array([lo]) for lo, hi in box]
    pts = np.array(np.meshgrid(*axes, indexing="ij")).reshape(len(box), -1)
    vals = np.broadcast_to(Jf(*pts), (model.n, model.n, pts.shape[1]))
    samples = [np.array(vals[:, :, k]) for k in range(pts.shape[1])]
    s = vertex.lmi_scale(samples)
    lam, _ = vertex.largest_decay_rate([A / s for A in samples])
    return lam * s


def test_the_arrhenius_term_is_two_terms_with_the_hand_derived_coefficients():
    model = build_model(parse_spec_text(CSTR))
    T = terms.decompose(model, sparse_jacobian(model.f, model.x))
    c, temp = model.x
    assert [sp.simplify(t) for t in T.thetas] == [sp.exp(-8.0 / temp), c * sp.exp(-8.0 / temp) / temp**2]
    # J = [[-q - k0 e, -k0 E c e / T^2], [hr k0 e, -q - ua + hr k0 E c e / T^2]]
    np.testing.assert_allclose(T.A0, [[-1.0, 0.0], [0.0, -3.0]])
    np.testing.assert_allclose(T.dense()[0], [[-20.0, 0.0], [60.0, 0.0]])
    np.testing.assert_allclose(T.dense()[1], [[0.0, -160.0], [0.0, 480.0]])
    assert T.proved
    # every Jacobian of the box is A0 + sum theta_k A_k with theta_k in its enclosed range
    rng = np.random.default_rng(0)
    Jf = model.numeric(sparse_jacobian(model.f, model.x), list(model.x) + list(model.u))
    for _ in range(50):
        x = rng.uniform(model.state_box[:, 0], model.state_box[:, 1])
        th = [float(t.subs({c: x[0], temp: x[1]})) for t in T.thetas]
        assert all(lo <= v <= hi for v, (lo, hi) in zip(th, T.ranges))
        np.testing.assert_allclose(T.A0 + sum(v * A for v, A in zip(th, T.dense())), np.asarray(Jf(*x, 1.5), dtype=float).reshape(2, 2), rtol=1e-12)


@pytest.mark.slow
def test_a_reactor_certifies_near_the_supremum_where_the_entry_box_loses_half():
    # The box of four independent entries: 0.93; the box of the two terms: 1.28; terms over sub-boxes refined where
    # the LMI binds: within 5% of the sampled supremum estimate (1.958).
    model = build_model(parse_spec_text(CSTR))
    J = sparse_jacobian(model.f, model.x)
    entry = terms.entry_polytope(model, J)
    term = terms.term_polytope(model, terms.decompose(model, J))

    def rate(poly):
        s = vertex.lmi_scale(poly.matrices)
        return vertex.largest_decay_rate([A / s for A in poly.matrices])[0] * s

    assert rate(entry) < 0.95 < 1.2 < rate(term) < 1.35
    sup = _sampled_supremum(model, 15)
    art = stabilise.run(model, {})
    assert art.meta["polytope"] == "Jacobian terms" and "sub-boxes" in art.meta["subdivision"]
    assert sup * 0.95 <= art.values["lambda"] <= sup
    assert art.checks["lmi_margin"].evidence == "proved"


@pytest.mark.slow
def test_a_three_node_diode_ladder_certifies_within_ten_percent_of_its_supremum():
    from ashc_cli.problem.examples import rc_ladder

    model = build_model(parse_spec_text(rc_ladder(3)))
    art = stabilise.run(model, {})
    sup = _sampled_supremum(model, 7)
    assert sup * 0.9 <= art.values["lambda"] <= sup
    assert art.checks["lmi_margin"].evidence == "proved"


def test_sub_boxes_cover_the_box_and_split_where_the_lmi_binds():
    model = build_model(parse_spec_text(CSTR))
    grid = terms.SubBoxes(model, terms.decompose(model, sparse_jacobian(model.f, model.x)))
    poly = grid.polytope()
    s = vertex.lmi_scale(poly.matrices)
    lam, M = vertex.largest_decay_rate([A / s for A in poly.matrices])
    assert grid.split(poly, M, lam, share=0.25)
    boxes = np.array(grid.boxes)
    volume = np.prod(np.ptp(boxes, axis=2)[:, :2], axis=1).sum()
    assert volume == pytest.approx(np.prod(np.ptp(model.state_box, axis=1)), rel=1e-12)   # a partition of the box
    assert len(grid.boxes) == 2


# A term that is numerically tiny on the whole box (exp(40 x) in [4.2e-18, 2.3e-16]) times a huge coefficient: df/dx
# = -1 + 40 a exp(40 x) spans [-0.5, 26.3], so the plant is not contracting on the box.  Rounding the corners of the
# sub-boxes' term ranges to 15 decimals merged the two ends and kept only the stable one (audit, finding 1).
TINY_TERM = """
name: tiny_term
parameters: {a: 2.94e15}
concrete:
  states: [x1]
  inputs: [u]
  f_bar: ["-x1 + a*exp(40*x1)"]
  g: [["1"]]
  h: ["x1"]
  input_bounds: [[-0.01, 0.01]]
  output_set: [[-1.0, -0.9]]
  state_box: [[-1.0, -0.9]]
stabilisability: {method: polytopic_lmi, decay_rate: maximise}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[-1.0, -0.9]]
"""


def test_a_tiny_term_with_a_huge_coefficient_keeps_both_corners_on_every_sub_box():
    model = build_model(parse_spec_text(TINY_TERM))
    grid = terms.SubBoxes(model, terms.decompose(model, sparse_jacobian(model.f, model.x)))
    for _ in range(3):
        poly = grid.polytope()
        # every sub-box contributes both ends of its range of df/dx (no rounding merges them), and of all those corners
        # the hull's two ends are kept (one term: the LMI at them implies it between): the largest is the true sup (26.3)
        ends = [end for sub in grid.boxes for end in grid.ranges(sub)[0]]
        assert len(set(ends)) == 2 * len(grid.boxes)
        assert len(poly.matrices) == 2 and poly.meta["subdivision"].endswith(f"{2 * len(grid.boxes) - 2} corners inside it left out)")
        assert max(A[0, 0] for A in poly.matrices) == pytest.approx(-1 + 40 * 2.94e15 * np.exp(-36.0), rel=1e-6)
        theta = sorted(float(label.split(" = ")[1]) for label in poly.labels)
        assert theta == pytest.approx([min(ends), max(ends)], rel=1e-5)     # the labels print 6 digits
        grid.split(poly, np.eye(1), 0.0, share=1.0)


def test_a_plant_that_is_not_contracting_on_its_box_is_refused_not_proved():
    from ashc_cli.errors import DesignError

    model = build_model(parse_spec_text(TINY_TERM))
    with pytest.raises(DesignError):
        stabilise.run(model, {})


# Audit finding 5: a diode Is exp((x1 - 0.7) / Vt) with Vt = 1 mV.  With the parameters put in as doubles sympy splits
# it into 1e-313 exp(1000 x1), whose exp(1000 x1) overflows on the box (NaN vertex matrices, a LinAlgError); the
# term is enclosed as written.
DIODE = """
name: diode
parameters: {Is: 1e-12, Vt: 0.001}
concrete:
  states: [x1, x2]
  inputs: [u]
  f_bar: ["-x1 + x2 - Is*exp((x1 - 0.7)/Vt)", "-x2 - x1"]
  g: [["1"], ["0"]]
  h: ["x1"]
  input_bounds: [[-0.5, 0.5]]
  output_set: [[-0.1, 0.1]]
  state_box: [[-1, 0.72], [-1, 1]]
stabilisability: {method: polytopic_lmi, decay_rate: maximise}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[-0.3, 0.3]]
"""


@pytest.mark.slow
def test_a_steep_diode_is_enclosed_as_written_not_after_a_split_that_overflows():
    model = build_model(parse_spec_text(DIODE))
    T = terms.decompose(model, sparse_jacobian(model.f, model.x))
    assert len(T) == 1 and np.all(np.isfinite(T.ranges)) and T.proved
    # df1/dx1 = -1 - (Is / Vt) exp((x1 - 0.7) / Vt) in [-1 - 1e-9 e^20, -1]
    np.testing.assert_allclose(np.sort(T.ranges[0] * T.dense()[0][0, 0]), [-1e-9 * np.exp(20.0), 0.0], rtol=1e-9, atol=1e-300)
    art = stabilise.run(model, {})
    # J = [[-1 - d, 1], [-1, -1]], d >= 0: M = I certifies rate 2 at every d, and no M does better at d = 0
    assert art.values["lambda"] == pytest.approx(2.0, rel=1e-4) and art.checks["lmi_margin"].evidence == "proved"


def test_the_corners_left_out_of_a_subdivided_polytope_lie_inside_the_hull_of_those_kept():
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(3)
    for K in (1, 2, 3):
        points = rng.random((200, K)) ** 3          # crowded near a corner, as sub-boxes' term ranges are
        keep = terms.hull_points(points)
        assert 0 < len(keep) < len(points)
        dropped = np.setdiff1d(np.arange(len(points)), keep)
        if K == 1:
            assert points[keep].min() == points.min() and points[keep].max() == points.max()
        else:
            assert np.all(Delaunay(points[keep]).find_simplex(points[dropped]) >= 0)
    # a flat set (one term constant) is kept whole: no hull of full dimension to decide on
    flat = np.c_[rng.random(20), np.ones(20)]
    assert len(terms.hull_points(flat)) == 20


def test_an_infeasible_feedback_lmi_costs_one_solve_not_one_per_condition_cap(monkeypatch):
    from ashc_cli.design.contraction import feedback

    calls = []
    original = feedback._min_gain
    monkeypatch.setattr(feedback, "_min_gain", lambda *a: calls.append(a[-1]) or original(*a))
    A = np.array([[1.0, 0.0], [0.0, 1.0]])                 # the second state is unreachable from B: no K helps
    B = np.array([[1.0], [0.0]])
    assert feedback.solve_lmi_feedback([A], B, 0.5)[0] is None and calls == [feedback.FEEDBACK_CONDITION[-1]]
    calls.clear()
    M, K, _, status = feedback.solve_lmi_feedback([np.array([[0.0, 1.0], [0.0, 0.0]])], np.array([[0.0], [1.0]]), 0.5)
    assert M is not None and calls[0] == feedback.FEEDBACK_CONDITION[-1] and f"<= {feedback.FEEDBACK_CONDITION[len(calls) - 2]:g} I" in status


def test_a_term_whose_range_ends_at_zero_is_enclosed_without_spending_the_box_budget():
    # x2^2 and tanh(x1)^2 on boxes around 0: their inf is 0, which no relative tolerance reaches; the search spent
    # the budget (20000 boxes) on a gap of 5e-324 in 23 searches of the saturating spring's stabilise stage (30 s).
    from ashc_cli.numerics import boxsearch

    from ashc_cli.numerics import proofs

    from .conftest import SPECS

    model = build_model(parse_spec_text((SPECS / "saturating_spring.yaml").read_text()))
    x1, x2 = list(model.x)
    for term, var, box in ((x2**2, x2, [-1.0, 1.0]), (sp.tanh(x1) ** 2, x1, [-0.5, 2.0])):
        fun = proofs.compile_claims(model, [term], [var])
        with boxsearch.work_budget() as work:
            lo, hi, ok = terms.enclose_term(fun, np.array([box]))
        assert ok and -1e-6 * hi <= lo <= 0.0 and hi >= max(float(term.subs(var, v)) for v in box)
        assert work.spent == 0, work.as_meta()
    with boxsearch.work_budget() as work:
        stabilise.run(model, {})
    assert work.spent == 0 and work.searches > 0, work.as_meta()
