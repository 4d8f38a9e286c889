"""Tests of stage 4, the left inverse m and conditions (i), (ii), SimuLocalRequire."""

import math

import numpy as np
import pytest
import sympy as sp

from ashc_cli.errors import DesignError
from ashc_cli.model import build_model
from ashc_cli.spec import parse_spec_text
from ashc_cli.stages import inverse, kappa, manifold

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
    with pytest.raises(DesignError, match=r"does not cover Y.*SimuLocalRequire"):
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
    assert not inverse.outside_certified_set(box, [0.0]) and not inverse.outside_certified_set(box, [-126.1875])
    assert not inverse.outside_certified_set(box, [0.5e-9 * 126.1875])     # within DOMAIN_RTOL of the width
    assert inverse.outside_certified_set(box, [1e-6]) and inverse.outside_certified_set(box, [-126.19])
    assert inverse.outside_certified_set(box, [math.nan])
    two = np.array([[0.1, 1.0], [0.1, 0.9]])
    assert inverse.outside_certified_set(two, [0.05, 0.3]) and not inverse.outside_certified_set(two, [0.5, 0.5])
    assert inverse.format_box(two) == "[0.1, 1] x [0.1, 0.9]"


def _design_inverse(text, tmp_path, numeric=None):
    from ashc_cli.pipeline import run
    return run(parse_spec_text(text), tmp_path, ["inverse"], numeric=numeric)["inverse"]


def test_chebyshev_inverse_certified_exactly_on_kappa_V(tmp_path):
    # The numeric left inverse is a polynomial fitted on kappa(V); beyond it, it extrapolates (the issue's
    # m(v32 = 90) = 2.8e9). Neither m_real_interval nor m_domain may claim more than kappa(V).
    from ashc_cli.examples import ladder
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
    from ashc_cli.pipeline import run
    with pytest.raises(DesignError, match=message):
        run(parse_spec_text(_m_relation_only(*pairs)), tmp_path, ["simulate"])
