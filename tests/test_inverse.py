"""Tests of stage 4, the left inverse m and conditions (i), (ii), SimuLocalRequire."""

import math

import numpy as np
import pytest
import sympy as sp

from ashc_cli.errors import DesignError
from ashc_cli.problem.model import build_model
from ashc_cli.problem.spec import parse_spec_text
from ashc_cli.design import upstream
from ashc_cli.design.stages import inverse, kappa, manifold

from .conftest import CUK_PAPER_M

X0 = [10.3256, 2.0561, -4.9785, -6.9732]


def test_m_at_the_papers_point(paper_design, paper_model):
    # eq. egm and Section V-D: xi0 = m(x0) = 0.3677 (4 decimals printed).
    m = paper_model.numeric(paper_design["inverse"].exprs["m"], list(paper_model.x))
    assert m(*X0)[0, 0] == pytest.approx(0.3677, abs=5e-5)


def test_m_is_eq_egm(paper_design, paper_model):
    P = paper_model.params
    E, G_L, R_i = P["E"], P["G_L"], P["R_i"]
    x4 = paper_model.x[3]
    papers = (-E + 2 * x4 + sp.sqrt(E**2 - 4 * G_L * R_i * x4**2)) / (2 * (G_L * R_i + 1) * x4 - 2 * E)
    f = paper_model.numeric(sp.Matrix([paper_design["inverse"].exprs["m"][0] - papers]), [x4])
    assert np.abs(f(np.linspace(-126, 126, 1001))).max() < 1e-12


def test_left_inverse_on_V(paper_design, paper_model):
    # m(p(xi)) = xi on V to 1e-9, checked here on points of our own.
    art = paper_design["inverse"]
    xi = np.linspace(0, 0.95, 977)
    p = paper_model.numeric(paper_design["manifold"].exprs["p"], list(paper_model.xi))(xi)[:, 0, :]
    m = paper_model.numeric(art.exprs["m"], list(paper_model.x))(*p)[0, 0]
    assert np.abs(m - xi).max() < 1e-9
    assert art.values["left_inverse_residual"] < 1e-9


def test_m_real_exactly_for_x4_within_126_91(paper_design, paper_model):
    # eq. mEquation: solvable iff |x4| <= E / (2 sqrt(R_i G_L)) = 126.91.
    lo, hi = paper_design["inverse"].values["m_real_interval"]
    exact = 12.0 / (2 * math.sqrt(0.05 * 44.7e-3))
    assert hi == pytest.approx(exact, rel=1e-12) and lo == pytest.approx(-exact, rel=1e-12)
    assert round(hi, 2) == 126.91
    m = paper_model.numeric(paper_design["inverse"].exprs["m"], list(paper_model.x))
    assert np.isfinite(m(0, 0, 0, -126.9)[0, 0]) and np.isnan(m(0, 0, 0, -126.92)[0, 0])


def test_conditions_and_cover(paper_design):
    art = paper_design["inverse"]
    lo, hi = art.values["kappa_range"][0]
    assert lo <= -120 and hi >= 0  # kappa(V) covers Y = [-120, 0] (eq. SimuLocalRequire)
    assert art.values["condition_ii"] < 1e-9 and art.values["condition_ii_symbolic"]
    assert art.values["condition_i"] < 1e-9
    assert all(c.passed for c in art.checks.values())


def run_inverse_with(*pairs):
    text = CUK_PAPER_M.read_text()
    for old, new in pairs:
        assert old in text
        text = text.replace(old, new)
    model = build_model(parse_spec_text(text))
    man = manifold.run(model, {})
    return inverse.run(model, {"manifold": man, "kappa": kappa.run(model, {"manifold": man})})


def test_V_not_covering_Y_is_refused():
    with pytest.raises(DesignError, match=r"does not cover Y.*\(eq\. \(10\)\)"):
        run_inverse_with(("domain: [[0, 0.95]]", "domain: [[0, 0.9]]"))


def test_p_not_injective_is_refused():
    # On [0, 1] kappa turns (kappa(0) = kappa(1) = 0): no branch is a left inverse.
    with pytest.raises(DesignError, match="not injective"):
        run_inverse_with(("domain: [[0, 0.95]]", "domain: [[0, 1.0]]"))


def test_Y_beyond_where_m_is_real_is_refused():
    with pytest.raises(DesignError, match="where m is real"):
        run_inverse_with(("output_set: [[-120, 0]]", "output_set: [[-130, 0]]"))


# --- where m is certified (values/m_domain): kappa(V), or where m is real within it, or Y ---------------------

def test_m_certified_on_kappa_V_within_where_it_is_real(paper_design):
    # Cuk: m is real for |y| <= 126.91 (a radicand), but it is a left inverse with m(x) in V only for y in
    # kappa(V) = [kappa(0.95), kappa(0)] = [-126.1875, 0], which lies inside: that is the certified set.
    art = paper_design["inverse"]
    lo, hi = art.values["kappa_range"][0]
    assert np.array_equal(art.values["m_domain"], [[lo, hi]])
    assert lo == pytest.approx(-126.1875, abs=1e-4) and hi == 0.0 and math.copysign(1, art.values["m_domain"][0, 1]) == 1
    assert art.meta["m_domain_set"] == "kappa(V)" and "outside V" in art.meta["m_domain"]
    line = inverse.headline(art)
    assert "m real for y in [-126.915, 126.915]; certified for y in kappa(V) = [-126.188, 0]" in line
    assert "inf" not in line and "-0]" not in line
    entry = inverse.summarise(art)
    assert entry["m_domain"] == [[lo, 0.0]] and entry["m_domain_set"] == "kappa(V)"
    assert entry["m_real_interval"] == pytest.approx([-126.914863, 126.914863])
    assert str(art.exprs["h"][0]) == "x4"


def test_outside_certified_set():
    box = np.array([[-126.1875, 0.0]])
    assert not upstream.outside_certified_set(box, [0.0]) and not upstream.outside_certified_set(box, [-126.1875])
    assert not upstream.outside_certified_set(box, [0.5e-9 * 126.1875])     # within DOMAIN_RTOL of the width
    assert upstream.outside_certified_set(box, [1e-6]) and upstream.outside_certified_set(box, [-126.19])
    assert upstream.outside_certified_set(box, [math.nan])
    two = np.array([[0.1, 1.0], [0.1, 0.9]])
    assert upstream.outside_certified_set(two, [0.05, 0.3]) and not upstream.outside_certified_set(two, [0.5, 0.5])
    assert upstream.format_box(two) == "[0.1, 1] x [0.1, 0.9]"


def _design_inverse(text, tmp_path, numeric=None):
    from ashc_cli.design.pipeline import run
    return run(parse_spec_text(text), tmp_path, ["inverse"], numeric=numeric)["inverse"]


def test_chebyshev_inverse_certified_exactly_on_kappa_V(tmp_path):
    # The numeric left inverse is a polynomial fitted on kappa(V); beyond it, it extrapolates (the issue's
    # m(v32 = 90) = 2.8e9). Neither m_real_interval nor m_domain may claim more than kappa(V).
    from ashc_cli.problem.examples import ladder
    art = _design_inverse(ladder(1), tmp_path, numeric=True)
    assert art.meta["method"].startswith("Chebyshev")
    k_range = np.asarray(art.values["kappa_range"])
    assert np.array_equal(art.values["m_domain"], k_range) and np.array_equal(art.values["m_real_interval"], k_range[0])
    assert np.all(np.isfinite(art.values["m_domain"]))
    line = inverse.headline(art)
    assert "inf" not in line and "certified for y in kappa(V) = [" in line
    assert all(np.isfinite(c.value) for c in art.checks.values())
    entry = inverse.summarise(art)
    assert None not in entry["m_real_interval"] and entry["m_domain"] == k_range.tolist()


def test_linear_inverse_real_everywhere_but_certified_on_kappa_V(tmp_path):
    from .conftest import SPECS
    art = _design_inverse((SPECS / "unstable_linear.yaml").read_text(), tmp_path)
    assert list(art.values["m_real_interval"]) == [-np.inf, np.inf]   # linear: proved
    assert np.array_equal(art.values["m_domain"], art.values["kappa_range"])
    assert inverse.headline(art).endswith("m real for every y (linear); certified for y in kappa(V) = [-1.5, 1.5]")


def _m_relation_only(*pairs):
    """The Cuk spec with the tracking scenario dropped and the m-relation scenario edited."""
    from .conftest import CUK
    text = CUK.read_text()
    for old, new in pairs:
        assert old in text
        text = text.replace(old, new)
    return text[:text.index("  tracking:")] + text[text.index("  m_relation:"):]


@pytest.mark.parametrize("pairs, message", [
    # starts above kappa(V), where m is real (x4 = 10 < 126.91) but not certified
    ((("x0: [10.3256, 2.0561, -4.9785, -6.9732]", "x0: [0, 0, 0, 10]"),),
     r"simulate\.m_relation\.x0: y = h\(x0\) = 10 is outside the set where m is certified, y in kappa\(V\) = \[-126\.188, 0\]"),
    # driven below kappa(V) (before m stops being real at -126.91)
    ((("x0: [10.3256, 2.0561, -4.9785, -6.9732]", "x0: [0, 0, 0, 0]"), ('u: "0.3*triangle(t - 2) + 0.1*sin(2*pi*(t - 2)) + 0.45"', 'u: "0.95"')),
     r"simulate\.m_relation: at t = 0\.78\d* s the output y = -126\.188 leaves kappa\(V\) = \[-126\.188, 0\], where m is certified; x = "),
])
def test_m_relation_run_stays_where_m_is_certified(tmp_path, pairs, message):
    from ashc_cli.design.pipeline import run
    with pytest.raises(DesignError, match=message):
        run(parse_spec_text(_m_relation_only(*pairs)), tmp_path, ["simulate"])


# --- the family of left inverses of an affine p (specs/linear_left_inverse.yaml) -------------------------------

def _left_spec():
    from .conftest import SPECS
    return SPECS / "linear_left_inverse.yaml"


@pytest.fixture(scope="module")
def left_design(tmp_path_factory):
    from ashc_cli.design.pipeline import run
    from ashc_cli.problem.spec import load_spec
    spec = load_spec(_left_spec())
    return build_model(spec), run(spec, tmp_path_factory.mktemp("left_inverse"), ["inverse"])


def _hand_derived():
    """P, p0 and C of the spec's header, in exact arithmetic."""
    half = sp.Rational(1, 2)
    P = sp.Matrix([[1, 0], [0, 1], [half, half], [-1, 0]])
    p0 = sp.Matrix([sp.Rational(2, 5), 0, sp.Rational(1, 5), 0])
    C = sp.Matrix([[0, 0, 1, 0]])
    return P, p0, C


def test_left_inverse_spec_manifold_is_the_hand_derived_one(left_design):
    model, arts = left_design
    P, p0, _ = _hand_derived()
    p = arts["manifold"].exprs["p"]
    assert np.abs(np.array(model.substitute(p.jacobian(model.xi)), dtype=float) - np.array(P, dtype=float)).max() < 1e-12
    assert np.abs(np.array(model.substitute(p.xreplace({s: 0 for s in model.xi})), dtype=float) - np.array(p0, dtype=float)).max() < 1e-12


def test_least_norm_left_inverse_against_an_independent_solve(left_design):
    # Every solution of K P = I, C P K = C, in exact arithmetic (sympy.linsolve in the 8 entries of K), then
    # the one of least Frobenius norm (the gradient of ||K||^2 in the free entries vanishes).
    P, p0, C = _hand_derived()
    ks = sp.symbols("k0:8", real=True)
    K = sp.Matrix(2, 4, ks)
    (solution,) = sp.linsolve(list(K * P - sp.eye(2)) + list(C * P * K - C), ks)
    family = K.xreplace(dict(zip(ks, solution)))
    free = sorted(family.free_symbols, key=str)
    assert len(free) == 2                                           # a 2-parameter family of such left inverses
    norm2 = sum(e**2 for e in family)
    (best,) = sp.solve([sp.diff(norm2, f) for f in free], free, dict=True)
    K_exact = family.xreplace(best)
    assert K_exact == sp.Matrix([[3, -5, 10, -3], [-3, 5, 12, 3]]) / 11
    assert sum(e**2 for e in K_exact) == sp.Rational(30, 11)
    # The closed form of the spec's header: K = P^+ + (C P)^+ C (I - P P^+).
    P_plus = (P.T * P).inv() * P.T
    assert K_exact == P_plus + (C * P).pinv() * C * (sp.eye(4) - P * P_plus)

    model, arts = left_design
    art = arts["inverse"]
    assert art.meta["construction"] == inverse.LEAST_NORM == "least-norm left inverse with C(I - P K) = 0"
    Kf, p0f = np.array(K_exact, dtype=float), np.array(p0, dtype=float)[:, 0]
    assert np.abs(np.array(model.substitute(art.exprs["dm_dx"]), dtype=float) - Kf).max() < 1e-9
    assert np.abs(np.asarray(art.values["left_inverse_matrix"]) - Kf).max() < 1e-9
    x = np.random.default_rng(1).uniform(-3, 3, size=(4, 50))
    m = model.numeric(art.exprs["m"], list(model.x))(*x)[:, 0, :]
    assert np.abs(m - Kf @ (x - p0f[:, None])).max() < 1e-9
    assert art.values["condition_ii"] < 1e-12 and art.values["condition_ii_symbolic"]
    assert all(c.passed for c in art.checks.values())
    assert art.meta["m_domain_set"] == "Y" and np.array_equal(art.values["m_domain"], [[-0.5, 0.5]])


def test_the_pseudo_inverse_fails_condition_ii_on_that_spec(left_design):
    P, p0, C = _hand_derived()
    P_plus = (P.T * P).inv() * P.T
    assert P_plus == sp.Matrix([[5, -1, 2, -5], [-1, 9, 4, 1]]) / 11
    R = C * (sp.eye(4) - P * P_plus)
    assert R == sp.Matrix([[-2, -4, 8, 2]]) / 11                     # C^T is not in the range of P
    # x = (0, 0, 1/2, 0) has h(x) = 1/2 in Y, and h(x - p(P^+ (x - p0))) = R (x - p0) = 16/55, not 0.
    x = sp.Matrix([0, 0, sp.Rational(1, 2), 0])
    assert (R * (x - p0))[0] == sp.Rational(16, 55)
    # The artefact's measure of (ii) with P^+ (on its 2000 samples of X_y) is ours on the same samples.
    model, arts = left_design
    art = arts["inverse"]
    samples = inverse.x_y_samples(model, np.asarray(arts["manifold"].value("p_grid")))
    ours = np.abs(np.array(R, dtype=float) @ (samples - np.array(p0, dtype=float))).max()
    assert art.values["condition_ii_pseudo_inverse"] == pytest.approx(ours, rel=1e-9)
    assert round(ours, 2) == 2.92 and inverse.summarise(art)["condition_ii_pseudo_inverse"] == pytest.approx(ours, rel=1e-9)
    assert art.values["condition_ii_matrix_pinv"] == pytest.approx(8 / 11, rel=1e-12) and art.values["condition_ii_matrix"] < 1e-14


def test_choose_left_inverse_keeps_the_pseudo_inverse_when_it_works_and_says_when_none_does():
    P = np.array([[1, 0], [0, 1], [0.5, 0.5], [-1, 0]])
    kept = inverse.choose_left_inverse(P, np.array([[1.0, 0, 0.5, -1]]))       # C^T = the first column of P
    assert kept["construction"] == inverse.PSEUDO_INVERSE and np.allclose(kept["K"], np.linalg.pinv(P)) and kept["solvable"]
    none = inverse.choose_left_inverse(P, np.array([[0, 0, 1.0, 0], [1, 0, 0, 0], [0, 1, 0, 0]]))
    assert none["construction"] == inverse.PSEUDO_INVERSE and none["solvable"] is False and none["system_residual"] > 0.1
    assert inverse.choose_left_inverse(P, None)["construction"] == inverse.PSEUDO_INVERSE   # nonlinear h: no family search


def test_constructions_are_recorded(paper_design):
    assert paper_design["inverse"].meta["construction"] == inverse.KAPPA_INVERSE == "kappa^-1(h(x))"
    assert inverse.summarise(paper_design["inverse"])["construction"] == "kappa^-1(h(x))"


# --- an explicit m (abstract.m): checked, not trusted -------------------------------------------------------

LEAST_NORM_M = '["(3*x1 - 5*x2 + 10*x3 - 3*x4 - 3.2)/11", "(-3*x1 + 5*x2 + 12*x3 + 3*x4 - 1.2)/11"]'
PSEUDO_INVERSE_M = '["(5*x1 - x2 + 2*x3 - 5*x4 - 2.4)/11", "(-x1 + 9*x2 + 4*x3 + x4 - 0.4)/11"]'


def _with_m(m: str) -> str:
    text = _left_spec().read_text()
    assert "  delta: identity\n" in text
    return text.replace("  delta: identity\n", f"  delta: identity\n  m: {m}\n")


def test_explicit_m_that_is_right_is_checked_and_used(tmp_path, left_design):
    model, arts = left_design
    art = _design_inverse(_with_m(LEAST_NORM_M), tmp_path)
    assert art.meta["construction"] == inverse.EXPLICIT == "explicit (spec)"
    assert all(c.passed for c in art.checks.values())
    assert art.values["left_inverse_residual"] < 1e-12 and art.values["condition_ii"] < 1e-12
    # The same m as the constructed one, and the same keys for delta, query and eval.
    x = np.random.default_rng(2).uniform(-3, 3, size=(4, 20))
    ours = model.numeric(art.exprs["m"], list(model.x))(*x)
    theirs = model.numeric(arts["inverse"].exprs["m"], list(model.x))(*x)
    assert np.abs(ours - theirs).max() < 1e-12
    for key in ("m_domain", "kappa_range", "m_real_interval", "left_inverse_residual", "condition_i", "condition_ii", "condition_ii_symbolic", "min_abs_dkappa", "radicands"):
        assert key in art.values, key
    assert set(arts["inverse"].exprs) <= set(art.exprs)
    assert list(art.values["m_real_interval"]) == [-np.inf, np.inf] and art.checks["m_real_on_Y"].evidence == "proved"
    assert art.meta["m_domain_set"] == "Y"


def test_explicit_m_that_fails_condition_ii_is_refused(tmp_path):
    # P^+ (x - p0) written out: a left inverse of p, but C (I - P P^+) != 0.
    from .conftest import ashc
    spec = tmp_path / "explicit_pinv.yaml"
    spec.write_text(_with_m(PSEUDO_INVERSE_M))
    design = ashc("design", str(spec), "--out", str(tmp_path / "out"))
    assert design.returncode == 3
    assert "error: abstract.m: the given m fails condition (ii) of Theorem 6: |h(x - p(m(x)))| reaches 2.92 on X_y" in design.stderr
    check = ashc("check", str(spec), "--out", str(tmp_path / "out"))
    assert check.returncode == 3
    row = next(line for line in check.stdout.splitlines() if "condition (ii)" in line)
    assert row.split()[0] == "fail" and "Problem 1 solved: no" in check.stdout


def test_explicit_m_that_is_no_left_inverse_is_refused(tmp_path):
    with pytest.raises(DesignError, match=r"abstract\.m: the given m is not a left inverse of p on V: max \|m\(p\(xi\)\) - xi\| = 0\.4 ") as err:
        _design_inverse(_with_m('["x1", "x2"]'), tmp_path)
    assert err.value.check == "left_inverse" and err.value.exit_code == 3


def test_explicit_nonlinear_m_the_papers_eq_egm(tmp_path):
    # The paper's eq. egm given explicitly on the Cuk converter (a radicand): checked on V and on X_y.
    egm = '["(-E + 2*x4 + sqrt(E**2 - 4*G_L*R_i*x4**2)) / (2*(G_L*R_i + 1)*x4 - 2*E)"]'
    text = CUK_PAPER_M.read_text().replace("  domain: [[0, 0.95]]\n", f"  domain: [[0, 0.95]]\n  m: {egm}\n")
    art = _design_inverse(text, tmp_path)
    assert art.meta["construction"] == inverse.EXPLICIT and all(c.passed for c in art.checks.values())
    assert art.values["radicands"] == ["E**2 - 4*G_L*R_i*x4**2"] and np.isnan(art.values["m_real_interval"]).all()
    assert np.array_equal(art.values["m_domain"], [[-120.0, 0.0]])
    assert art.values["condition_ii_symbolic"]
    with pytest.raises(DesignError, match="not a left inverse of p on V"):
        # the other branch of the quadratic (eq. mEquation)
        _design_inverse(text.replace("+ sqrt(E**2", "- sqrt(E**2"), tmp_path / "other")


def test_a_series_p_is_affine_exactly_when_its_formula_is():
    from ashc_cli.numerics import chebyshev
    from ashc_cli.design.artefacts import Artefact

    xi = sp.Symbol("xi", real=True)
    box = np.array([[0.0, 0.6]])
    for tail, affine in ((0.0, True), (1e-3, False)):
        coeffs = np.zeros((2, 7))
        coeffs[:, :2] = [[2.0, 3.0], [-1.0, 0.5]]
        coeffs[1, 2] = tail                      # a T_2 term makes p quadratic
        man = Artefact(stage="manifold")
        p = chebyshev.Series.column(coeffs, box)
        man.set_series("dp_dxi", p.jacobian(), [xi])
        assert p.kept_numeric and inverse.p_is_affine(man, None) is affine
        assert (not man.expr("dp_dxi").free_symbols) is affine


def test_output_set_beyond_m_says_what_kappa_reaches(tmp_path):
    """Issue 14: the message says what kappa(V) reaches and what to change, with no Python values in it."""
    from .conftest import CUK, ashc, edited

    spec = edited(CUK, tmp_path, ("output_set: [[-120, 0]]", "output_set: [[-200, 0]]"))
    proc = ashc("design", str(spec), "--out", str(tmp_path / "o"))
    assert proc.returncode == 3
    line = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")][0]
    assert "kappa(V) = [-126.188, 0]" in line and "m is real only for y in [-126.915, 126.915]" in line
    assert "expected an output_set inside [-126.188, 0]" in line
    assert not any(token in line for token in ("True", "False", "[[", "np."))


# --- issue 19: an affine p with a nonlinear h; exact decisions of eq. (10) -----------------------------------

CUBIC_OUTPUT = """
name: cubic_output
concrete:
  states: [x1, x2]
  inputs: [u]
  f_bar: ["-x1 + x2", "-x2"]
  g: [["0"], ["1"]]
  h: ["x1 + 0.3*x1**3"]
  input_bounds: [[-3, 3]]
  output_set: [[-0.5, 0.5]]
  state_box: [[-2, 2], [-2, 2]]
stabilisability: {method: polytopic_lmi, decay_rate: 0.5}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[-1, 1]]
"""


def test_affine_p_with_a_nonlinear_h_gets_a_left_inverse_reading_the_output_state(tmp_path):
    # p(xi) = (xi, xi): P^+ = (x1 + x2) / 2 would break condition (ii) for h = x1 + 0.3 x1^3; m = x1 keeps it exactly.
    from ashc_cli.design.pipeline import DESIGN, run

    arts = run(parse_spec_text(CUBIC_OUTPUT), tmp_path, DESIGN)
    inv = arts["inverse"]
    x1, x2 = sp.symbols("x1 x2", real=True)
    assert sp.simplify(inv.expr("m")[0] - x1) == 0
    for name in ("left_inverse", "condition_i", "condition_ii", "m_real_on_Y"):
        assert inv.checks[name].passed and inv.checks[name].evidence == "proved", name
    assert inv.checks["V_covers_Y"].passed


def test_a_gap_below_the_linear_programs_tolerance_is_found_exactly(tmp_path):
    # kappa(V) = [0, 0.3] against Y = [0, 0.30000000000000004]: the floating-point LP accepts the vertex; the exact
    # decision (in rationals) does not, and says by how much.
    from ashc_cli.design.pipeline import DESIGN, run

    text = """
name: gap
concrete:
  states: [x]
  inputs: [u]
  f_bar: ["-x"]
  g: [["1"]]
  h: ["x"]
  input_bounds: [[-3, 3]]
  output_set: [[0, 0.30000000000000004]]
stabilisability: {method: polytopic_lmi, decay_rate: 1.0}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi"]
  domain: [[0, 0.3]]
"""
    with pytest.raises(DesignError, match=r"kappa\(V\) = \[0\.0, 0\.3\] \(exactly, in rationals\) misses Y = \[0\.0, 0\.30000000000000004\] by 4e-17 \(at the level of rounding"):
        run(parse_spec_text(text), tmp_path / "a", DESIGN)
    arts = run(parse_spec_text(text.replace("[[0, 0.30000000000000004]]", "[[0, 0.3]]")), tmp_path / "b", DESIGN)
    assert arts["inverse"].checks["V_covers_Y"].evidence == "proved"


def test_a_closed_form_inverse_of_two_outputs_is_proved(tmp_path):
    from ashc_cli.design.pipeline import DESIGN, run
    from ashc_cli.problem.spec import load_spec

    from .conftest import SPECS

    arts = run(load_spec(SPECS / "bilinear_two_input.yaml"), tmp_path, DESIGN)
    inv = arts["inverse"]
    for name in ("left_inverse", "condition_i", "condition_ii", "m_real_on_Y", "V_covers_Y"):
        assert inv.checks[name].evidence == "proved", name


def test_a_transcendental_kappa_stops_loudly_at_the_safety_stop_and_the_numeric_path_names_abstract_m(tmp_path, monkeypatch):
    # kappa = xi + 0.0009 tanh(1e5 (xi - 0.123456)): sympy.solve searched for over 20 minutes; now it runs under a safety
    # stop that fails loudly, naming --numeric (issue 39: a clock must never switch paths silently, or the design would
    # depend on the machine's load).  With --numeric the interpolant cannot follow the steep band, and the message says
    # kappa is monotone and names abstract.m.
    import time

    from ashc_cli.problem import model as model_mod
    from ashc_cli.design.pipeline import DESIGN, run

    monkeypatch.setattr(model_mod, "SYMBOLIC_BUDGET", 1.0)
    text = """
name: steep_l
concrete:
  states: [x]
  inputs: [u]
  f_bar: ["-x"]
  g: [["1"]]
  h: ["x"]
  input_bounds: [[-1, 1]]
  output_set: [[-0.8, 0.8]]
stabilisability: {method: polytopic_lmi, decay_rate: 1.0}
abstract:
  states: [xi]
  inputs: [v]
  phi_bar: ["0"]
  l: ["xi + 0.0009*tanh(100000*(xi - 0.123456))"]
  domain: [[-0.9, 0.9]]
"""
    start = time.perf_counter()
    with pytest.raises(DesignError, match=r"abstract\.m: sympy\.solve of kappa\(xi\) = y stopped \(symbolic work took longer than 1 s\), a safety stop .*; expected --numeric"):
        run(parse_spec_text(text), tmp_path / "symbolic", DESIGN)
    assert time.perf_counter() - start < 60
    # when sympy gives up (here: made to), the interpolant is tried, and its failure says kappa is monotone, naming abstract.m
    from ashc_cli.design import inverse_construct

    def gives_up(*args, **kwargs):
        raise NotImplementedError("no closed form")

    monkeypatch.setattr(inverse_construct, "within_budget", gives_up)
    with pytest.raises(DesignError, match=r"abstract\.m: kappa is strictly monotone on V .* \(so p is injective\), but sympy finds no closed form"):
        run(parse_spec_text(text), tmp_path / "numeric", DESIGN)


def test_within_budget_returns_the_result_or_times_out():
    from ashc_cli.problem.model import within_budget

    assert within_budget(sorted, [3, 1, 2]) == [1, 2, 3]
    with pytest.raises(TimeoutError):
        within_budget(__import__("time").sleep, 5, seconds=0.2)


# --- a left inverse on a wide domain, of a fitted p -------------------------------------------------------------

def _motor_inverse(tmp_path, extra: str = ""):
    from ashc_cli.design.pipeline import run

    from .test_manifold import MOTOR

    text = MOTOR.replace("  delta: identity", "  delta: identity" + extra)
    return run(parse_spec_text(text), tmp_path, ["inverse"])


#: The motor's exact left inverse: the input whose equilibrium speed is w.
MOTOR_M = "(R/K)*((b + K**2/R)*w + c*tanh(w))"


def test_the_constructed_m_of_a_fitted_p_on_a_wide_domain_is_kappa_inverse(tmp_path):
    # kappa^-1 as one polynomial of degree 80 had coefficients near 1e13 and missed by 2.9e3; in pieces (each inverting
    # one piece of kappa) it is kappa^-1 to 1e-9, and the exact inverse to within the fit of p.
    arts = _motor_inverse(tmp_path)
    inv, model = arts["inverse"], build_model(parse_spec_text(_motor_text()))
    assert "pieces of degree" in inv.meta["method"] and inv.values["left_inverse_residual"] < 1e-9
    w = np.linspace(-10, 10, 2001)
    m = model.numeric(inv.exprs["m"], list(model.x))(w, 0 * w)[0, 0]
    P = {"b": 0.2, "c": 0.8, "K": 0.1, "R": 2.0}
    exact = P["R"] / P["K"] * ((P["b"] + P["K"] ** 2 / P["R"]) * w + P["c"] * np.tanh(w))
    # p (hence kappa) is accurate to about 1e-7 in w, and dm/dw is about 20: m to a few 1e-6.
    assert np.abs(m - exact).max() < 5e-6
    assert inv.checks["condition_ii"].passed and inv.checks["condition_i"].passed


def test_an_exact_hand_written_m_of_a_fitted_p_is_accepted_with_the_fits_error(tmp_path):
    # The exact m misses m(p(xi)) = xi by |dm/dw| times the error of the fitted p (3e-7 here), not by round-off: the
    # tolerance follows from that error (stored by the manifold stage) instead of refusing the right answer.
    arts = _motor_inverse(tmp_path, f'\n  m: ["{MOTOR_M}"]')
    inv, man = arts["inverse"], arts["manifold"]
    assert inv.meta["construction"] == inverse.EXPLICIT
    assert 1e-9 < inv.values["left_inverse_residual"] <= inv.meta["left_inverse_tol"] < 1e-4
    assert man.values["p_error"].max() > 0
    assert "fit error of p" in inv.checks["left_inverse"].description


def test_a_hand_written_m_off_by_more_than_the_fit_is_still_refused(tmp_path):
    # 1.001 m: off by 1e-3 of xi, far beyond what the fit of p explains.
    with pytest.raises(DesignError, match=r"abstract\.m: the given m is not a left inverse of p on V.*fit error of p"):
        _motor_inverse(tmp_path, f'\n  m: ["1.001*{MOTOR_M}"]')


def _motor_text() -> str:
    from .test_manifold import MOTOR

    return MOTOR


#: Johansson's quadruple tank, nonlinear (Torricelli outflows), in deviation coordinates x = h - H about the levels
#: H of the pump voltages U, with l = xi (pump voltage deviations): written for these tests.  p is the steady state
#: of the voltages U + xi, and kappa(xi) = kc (x1, x2) there; sympy's solve of kappa(m) = y meets a quartic whose
#: branches are not real on V, so m is the numeric kappa^-1 of several abstract states.
QUADRUPLE_TANK = """
name: quadruple_tank_deviation
parameters: {A1: 28.0, A2: 32.0, A3: 28.0, A4: 32.0, a1: 0.071, a2: 0.057, a3: 0.071, a4: 0.057, k1: 3.33, k2: 3.35, g1: 0.7, g2: 0.6, kc: 0.5,
             gr: 981.0, H1: 12.4, H2: 12.7, H3: 1.8, H4: 1.4, U1: 3.0, U2: 3.0}
concrete:
  states: [x1, x2, x3, x4]
  inputs: [u1, u2]
  f_bar: ["-a1/A1*sqrt(2*gr*(H1 + x1)) + a3/A1*sqrt(2*gr*(H3 + x3)) + g1*k1/A1*U1",
          "-a2/A2*sqrt(2*gr*(H2 + x2)) + a4/A2*sqrt(2*gr*(H4 + x4)) + g2*k2/A2*U2",
          "-a3/A3*sqrt(2*gr*(H3 + x3)) + (1 - g2)*k2/A3*U2", "-a4/A4*sqrt(2*gr*(H4 + x4)) + (1 - g1)*k1/A4*U1"]
  g: [["g1*k1/A1", "0"], ["0", "g2*k2/A2"], ["0", "(1 - g2)*k2/A3"], ["(1 - g1)*k1/A4", "0"]]
  h: ["kc*x1", "kc*x2"]
  input_bounds: [[-1.5, 1.5], [-1.5, 1.5]]
  output_set: [[-1.0, 1.0], [-1.0, 1.0]]
  state_box: [[-10, 14], [-10, 14], [-1.7, 2.5], [-1.3, 2.0]]
stabilisability: {method: polytopic_lmi, decay_rate: maximise, feedback: identity}
abstract:
  states: [xi1, xi2]
  inputs: [v1, v2]
  phi_bar: ["0", "0"]
  l: ["xi1", "xi2"]
  domain: [[-1.2, 1.2], [-1.2, 1.2]]
interface: {q: least_squares, saturate: scale}
"""


def _tank_inverse_exact(y1, y2):
    """kappa^-1 of the quadruple tank by hand: at steady state the lower tanks' outflows are the pumps' flows into
    them, a1 sqrt(2 g h1) = g1 k1 v1 + (1 - g2) k2 v2 and a2 sqrt(2 g h2) = (1 - g1) k1 v1 + g2 k2 v2 (the upper
    tanks pass their inflow on), linear in the voltages v = U + xi."""
    A = np.array([[0.7 * 3.33, 0.4 * 3.35], [0.3 * 3.33, 0.6 * 3.35]])
    flows = np.stack([0.071 * np.sqrt(2 * 981.0 * (12.4 + y1 / 0.5)), 0.057 * np.sqrt(2 * 981.0 * (12.7 + y2 / 0.5))])
    return np.linalg.solve(A, flows.reshape(2, -1)).reshape(flows.shape) - 3.0


def test_a_numeric_m_of_two_abstract_states_is_kappa_inverse_to_1e_9(tmp_path):
    from ashc_cli.design.pipeline import run

    arts = run(parse_spec_text(QUADRUPLE_TANK), tmp_path, ["inverse"])
    inv, model = arts["inverse"], build_model(parse_spec_text(QUADRUPLE_TANK))
    assert inv.meta["method"].startswith("tensor Chebyshev series of kappa^-1 on Y")
    assert inv.meta["m_domain_set"] == "Y"
    rng = np.random.default_rng(7)
    y = rng.uniform(-1, 1, (2, 500))
    y[:, :4] = [[-1, -1, 1, 1], [-1, 1, -1, 1]]      # the corners of Y
    x = np.vstack([y / 0.5, np.zeros((2, 500))])     # h(x) = y; m reads h only
    m = model.numeric(inv.exprs["m"], list(model.x))(*x)[:, 0, :]
    assert np.abs(m - _tank_inverse_exact(y[0], y[1])).max() < 1e-9
    for name in ("left_inverse", "condition_i", "condition_ii", "V_covers_Y", "m_real_on_Y"):
        assert inv.checks[name].passed, name
    assert inv.checks["left_inverse"].evidence != "proved"           # a fit: sampled, never proved
    assert inv.values["left_inverse_residual"] < 1e-9 and inv.values["m_fit_error"] < 1e-11


def test_a_numeric_m_whose_preimage_leaves_V_is_refused_naming_the_output(tmp_path, monkeypatch):
    from ashc_cli.design.pipeline import run

    # sympy's fruitless 7 s on the quartic is the other test's; here only the numeric path is under test.
    monkeypatch.setattr(inverse, "closed_form_branches", lambda *args: [])

    text = QUADRUPLE_TANK.replace("domain: [[-1.2, 1.2], [-1.2, 1.2]]", "domain: [[-0.8, 0.8], [-0.8, 0.8]]")
    with pytest.raises(DesignError, match=r"abstract\.domain: .*no solution xi in V for y = \[0\.9, -1\.0\].*0\.0108 outside V.*abstract\.m written by hand"):
        run(parse_spec_text(text), tmp_path, ["inverse"])
    # The exact solution there lies outside V by the 0.0108 the message gives.
    assert _tank_inverse_exact(np.array([0.9]), np.array([-1.0]))[0, 0] == pytest.approx(0.8108, abs=1e-4)


def _bilinear_one_output() -> str:
    import yaml

    from .conftest import SPECS

    data = yaml.safe_load((SPECS / "bilinear_two_input.yaml").read_text())
    data["name"] = "bilinear_one_output"
    data["concrete"].update(h=["x1 + x3"], output_set=[[0.1, 1.0]])
    data["simulate"]["tracking"].update(xi0=[0.3, 0.5], reference_levels=[[0.6], [0.3], [0.8]])
    data["simulate"]["m_relation"]["u"] = ["0.8 + 0.2*sin(t)", "0.4 + 0.2*cos(t)"]
    return yaml.safe_dump(data, sort_keys=False)


def test_more_abstract_states_than_outputs_with_a_nonlinear_p(tmp_path):
    # The bilinear plant with one output y = x1 + x3 and two abstract states: p = (xi1, xi2, 2 xi1 xi2) is nonlinear,
    # so m = K (x - p0) does not exist; the outputs are augmented with the state that completes kappa = xi1 (1 + 2 xi2)
    # to a square map (x2 = xi2), and m = ((x1 + x3) / (1 + 2 x2), x2) is found and proved: m(p(xi)) = xi on V and
    # h(p(m(x))) = h(x) wherever (h(x), x2) is in the certified box.
    from ashc_cli.design.pipeline import run

    arts = run(parse_spec_text(_bilinear_one_output()), tmp_path, ["bound"])
    art = arts["inverse"]
    assert art.meta["augmented_outputs"] == ["x2"] and "outputs augmented with x2" in art.meta["method"]
    x1, x2, x3 = sp.symbols("x1 x2 x3")
    m = art.expr("m").xreplace({s: sp.Symbol(str(s)) for s in art.expr("m").free_symbols})
    assert sp.simplify(m[0] - (x1 + x3) / (1 + 2 * x2)) == 0 and m[1] == x2
    assert np.allclose(art.values["m_domain"], [[0.1, 1.0], [0.0, 1.0]])
    for name in ("left_inverse", "condition_i", "condition_ii", "V_covers_Y"):
        assert art.checks[name].passed and art.checks[name].evidence == "proved", name
    assert "(h, x2)" in inverse.headline(art)


def test_the_m_relation_runs_on_augmented_outputs(tmp_path):
    # simulate's m-relation scenario checks x0 against the certified box in (h, x2) and tracks y with psi.
    import yaml

    from .conftest import ashc

    spec = tmp_path / "bilinear_one_output.yaml"
    spec.write_text(_bilinear_one_output())
    proc = ashc("simulate", str(spec), "--out", str(tmp_path / "d"))
    assert proc.returncode == 0, proc.stderr
    assert "m-relation max|psi - y| = " in proc.stderr
    err = float(proc.stderr.split("m-relation max|psi - y| = ")[1].split()[0])
    assert err < 1e-8
    data = yaml.safe_load(spec.read_text())
    data["simulate"]["m_relation"]["x0"] = [0.3, 1.4, 0.1]     # h(x0) = 0.4 is in Y, but x2 = 1.4 is outside [0, 1]
    spec.write_text(yaml.safe_dump(data, sort_keys=False))
    proc = ashc("simulate", str(spec), "--out", str(tmp_path / "d"))
    assert proc.returncode != 0 and "outside the set where m is certified" in proc.stderr and "(h, x2)" in proc.stderr
