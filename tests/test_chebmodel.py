"""Chebyshev models (numerics/chebmodel.py) and the fitted p's PDE residual proved with them (design/series_proofs.py):
every bound must hold at every point, checked in 60-digit arithmetic, and stay near the true size (so a loose bound fails)."""

import re

import mpmath
import numpy as np
import pytest
import sympy as sp
import yaml

from ashc_cli.design import series_proofs
from ashc_cli.errors import DesignError
from ashc_cli.design.stages import manifold
from ashc_cli.numerics import chebyshev
from ashc_cli.numerics.chebmodel import ChebModel, TooWide, bound_on_pieces, evaluate, reexpand
from ashc_cli.problem.model import build_model
from ashc_cli.problem.spec import parse_spec_text

mpmath.mp.dps = 60
T = sp.Symbol("t")


def _cheb_mp(c, t):
    """sum c_k T_k(t) in 60 digits (T_k(t) = cos(k acos t))."""
    t = mpmath.mpf(t)
    return mpmath.fsum(mpmath.mpf(float(ck)) * mpmath.chebyt(k, t) for k, ck in enumerate(c))


@pytest.mark.parametrize("expr", [sp.exp(3 * T) * sp.sin(2 * T), 1 / (T + sp.Rational(5, 2)), sp.tanh(4 * T + 1), sp.sqrt(T + 2) - T**3,
                                  sp.exp(40 * (sp.Rational(1, 20) * T + sp.Rational(1, 50))) - 1])
def test_a_model_holds_its_function_at_every_point(expr):
    # The model's polynomial plus remainder contains the function (in 60 digits) at 401 points of [-1, 1], the
    # remainder is round-off sized, and the bound of |f| (the sum of |coefficients| + r) is within 1.5 of its maximum.
    fn = sp.lambdify(T, expr, "mpmath")

    def build(centre, half):
        return [evaluate(expr, {T: ChebModel.affine(centre, half)}, {})]

    bound, pieces = bound_on_pieces(build)
    m = build(0.0, 1.0)[0] if pieces == 1 else None
    points = np.linspace(-1, 1, 401)
    true_max = max(abs(fn(mpmath.mpf(float(t)))) for t in points)
    assert true_max <= bound[0] <= 1.5 * true_max + 1e-12
    if m is not None:
        assert m.r < 1e-12 * max(1.0, float(true_max))
        assert all(abs(_cheb_mp(m.c, t) - fn(mpmath.mpf(float(t)))) <= m.r for t in points)


def test_a_range_too_wide_for_taylor_is_split_and_log_of_zero_refused():
    # tanh on [-3, 5] has poles at +-i pi / 2 within reach of one expansion: the interval is halved until each
    # piece's Lagrange remainder is small; log(t + 1) reaches log 0 at t = -1 and is refused after the last split.
    bound, pieces = bound_on_pieces(lambda c, h: [evaluate(sp.tanh(4 * T + 1), {T: ChebModel.affine(c, h)}, {})])
    assert pieces > 1 and np.tanh(5) <= bound[0] <= 1.5
    with pytest.raises(TooWide):
        bound_on_pieces(lambda c, h: [evaluate(sp.log(T + 1), {T: ChebModel.affine(c, h)}, {})], max_depth=3)


def test_products_carry_their_rounding():
    # (1 + t)^40 - sum binom(40, k) t^k is 0; in floats the coefficients of both sides differ by round-off, and the
    # model's remainder must cover it at every point.
    a = ChebModel.affine(1.0, 1.0).powi(40)
    exact = [mpmath.binomial(40, k) for k in range(41)]
    for t in np.linspace(-1, 1, 101):
        true = mpmath.fsum(e * mpmath.mpf(float(t)) ** k for k, e in enumerate(exact))
        assert abs(_cheb_mp(a.c, t) - true) <= a.r
    assert a.r < 1e-3 * 2.0**40 * 1e-10


@pytest.mark.parametrize("centre,half", [(0.5, 0.5), (-0.25, 0.25), (0.8125, 0.0625)])
def test_reexpand_holds_the_series_on_the_piece(centre, half):
    rng = np.random.default_rng(3)
    c = rng.normal(size=(4, 25)) / np.arange(1, 26) ** 2
    new, r = reexpand(c, centre, half)
    for tau in np.linspace(-1, 1, 41):
        t = centre + half * tau
        for i in range(4):
            assert abs(_cheb_mp(c[i], t) - _cheb_mp(new[i], tau)) <= r[i]
    assert r.max() < 1e-12


def _ladder_spec(stages: int = 3) -> str:
    from ashc_cli.problem.examples import rc_ladder

    data = yaml.safe_load(rc_ladder(stages))
    data.pop("simulate", None)
    return yaml.safe_dump(data)


def _residual_mp(model, series, xi):
    """rho(xi) row by row in 60 digits (phi_bar = 0: rho = -(f_bar(p) + g(p) l)), p the series' exact polynomial."""
    piece = series.pieces[0] if isinstance(series, chebyshev.PiecewiseSeries) else series
    lo, hi = (float(v) for v in piece.box[0])
    s = (2 * mpmath.mpf(xi) - mpmath.mpf(lo) - mpmath.mpf(hi)) / (mpmath.mpf(hi) - mpmath.mpf(lo))
    p = [_cheb_mp(row, s) for row in piece.coeffs.reshape(model.n, -1)]
    F = model.f_bar + model.g * model.l
    env = {**{x: v for x, v in zip(model.x, p)}, model.xi[0]: mpmath.mpf(xi), **{k: mpmath.mpf(v) for k, v in model.values.items()}}
    return [abs(sp.lambdify(list(env), e, "mpmath")(*env.values())) for e in F]


def test_the_fitted_ladder_residual_is_proved_and_tight():
    # The nonlinear RC ladder (diodes exp(40 v)): p fitted by Newton continuation; the proved bound of each row of
    # the residual holds at 201 points in 60 digits and is within 100 times its sampled maximum.
    model = build_model(parse_spec_text(_ladder_spec()))
    art = manifold.run(model, {})
    series = art.series["p"]
    proof = series_proofs.prove_pde_residual(model, series)
    assert proof["bounds"] is not None, proof["how"]
    lo, hi = model.V[0]
    worst = np.zeros(model.n)
    for xi in np.linspace(lo, hi, 201):
        worst = np.maximum(worst, [float(v) for v in _residual_mp(model, series, float(xi))])
    assert np.all(worst <= proof["bounds"])
    assert proof["bounds"].max() <= 100 * worst.max()
    chk = art.checks["pde_residual"]
    assert chk.evidence == "proved" and chk.value == proof["bounds"].max()
    assert np.array_equal(art.values["residual_proved"], proof["bounds"])


def test_a_perturbed_p_gets_a_larger_proved_residual():
    # A p that does not solve eq. (14a) (1e-6 T_8 added to one row): the proved bound of that row covers the
    # residual this makes, sampled in 60 digits, so a bound that ignored the series' high coefficients would fail.
    model = build_model(parse_spec_text(_ladder_spec()))
    series = manifold.run(model, {}).series["p"]
    c = series.coeffs.copy()
    c[1, -1] += 1e-6
    bent = chebyshev.Series(c, series.box, series.shape)
    proof = series_proofs.prove_pde_residual(model, bent)
    lo, hi = model.V[0]
    worst = np.zeros(model.n)
    for xi in np.linspace(lo, hi, 301):
        worst = np.maximum(worst, [float(v) for v in _residual_mp(model, bent, float(xi))])
    assert worst.max() > 1e-6
    assert np.all(worst <= proof["bounds"])


def test_residual_norm_bound_covers_the_weighted_norm():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(6, 6))
    M = A @ A.T + np.eye(6)
    b = rng.uniform(0, 1, 6)
    L = np.linalg.cholesky(M)
    worst = max(np.linalg.norm(L.T @ (b * s)) for s in np.array(np.meshgrid(*[[-1, 1]] * 6)).reshape(6, -1).T)
    assert worst <= series_proofs.residual_norm_bound(M, b) <= np.sqrt(b @ np.abs(M) @ b) * (1 + 1e-12)


def test_the_residual_term_is_spent_by_the_budget_and_counted_by_the_governor():
    # A bound with a fitted p's residual: the budget pays residual_term before any v; the governor runs while the
    # residual alone fits below its level (rho_bar^2 / eps < (lambda - eps) W_max) and is refused, saying so, when not.
    from ashc_cli.closedloop import plan as gplan
    from ashc_cli.design.artefacts import Artefact

    values = {"alpha_h": 1.0, "gain": 2.0, "lambda": 2.0, "epsilon": 1.0, "w0_max_certified": np.inf, "v_max_certified": np.inf}
    fitted = {**values, "residual_term": 0.1, "rho_bar": 0.1 / np.sqrt(2.0)}
    ok = gplan.guaranteed_plan(1.0, "auto", 0.0, {"bound": Artefact(stage="bound", values=fitted)})
    assert ok.mode == "governor" and ok.budget_v_max == pytest.approx((1.0 - 0.1) / 2.0)
    # EPS = 0.08 is below the budget's residual term 0.1 but above rho_bar = 0.0707: only the governor certifies it
    between = gplan.guaranteed_plan(0.08, "auto", 0.0, {"bound": Artefact(stage="bound", values=fitted)})
    assert between.mode == "governor" and "p's residual term" in between.budget_refusal
    with pytest.raises(DesignError, match="cannot be guaranteed"):
        gplan.guaranteed_plan(0.06, "governor", 0.0, {"bound": Artefact(stage="bound", values=fitted)})
    try:
        gplan.guaranteed_plan(0.06, "governor", 0.0, {"bound": Artefact(stage="bound", values=fitted)})
    except DesignError as exc:
        assert "PDE residual" in str(exc)

def test_a_piecewise_is_decided_on_the_range_or_hulled_across_a_break():
    # Decided: on [-1, -0.5] the condition t < 0 holds everywhere, so the model is the first branch's, exactly;
    # straddling t = 0.25 the model is the hull of both branches (their mean, half the gap in the remainder).
    f = sp.Piecewise((T, T < 0), (T + sp.Rational(1, 1000), True))
    left = evaluate(f, {T: ChebModel.affine(-0.75, 0.25)}, {})
    assert left.r == 0.0 and np.allclose(left.c, [-0.75, 0.25])
    both = evaluate(f, {T: ChebModel.affine(0.0, 1.0)}, {})
    for t in np.linspace(-1, 1, 201):
        value = t if t < 0 else t + 1e-3
        assert abs(np.polynomial.chebyshev.chebval(t, both.c) - value) <= both.r
    assert both.r < 1e-3


def _inverse_of(text):
    from ashc_cli.design.stages import inverse, kappa

    model = build_model(parse_spec_text(text))
    man = manifold.run(model, {})
    kap = kappa.run(model, {"manifold": man})
    return model, man, inverse.run(model, {"manifold": man, "kappa": kap})


def test_the_fitted_ladders_inverse_rows_are_proved_and_hold_in_60_digits():
    # m is a Chebyshev interpolant of kappa^-1 and p a fitted series: the left inverse, kappa's monotonicity and
    # conditions (i), (ii) are proved by Chebyshev models; the proved |m(kappa(xi)) - xi| holds at 301 points of V
    # (m's formula and p's series in 60 digits) and is within 100 times the largest of them.
    model, man, inv = _inverse_of(_ladder_spec())
    for name in ("left_inverse", "kappa_monotone", "condition_i", "condition_ii"):
        assert inv.checks[name].evidence == "proved", (name, inv.meta.get("proof_fitted_p"))
    y = sp.Symbol("y", real=True)
    m_of_y = sp.lambdify(y, inv.expr("m_of_y")[0], "mpmath")
    series = man.series["p"]
    out = int(np.flatnonzero(np.asarray(model.C)[0])[0])
    lo, hi = (float(v) for v in series.box[0])
    worst = 0.0
    for xi in np.linspace(*model.V[0], 301):
        s = (2 * mpmath.mpf(float(xi)) - mpmath.mpf(lo) - mpmath.mpf(hi)) / (mpmath.mpf(hi) - mpmath.mpf(lo))
        kappa = _cheb_mp(series.coeffs.reshape(model.n, -1)[out], s)
        worst = max(worst, abs(m_of_y(kappa) - mpmath.mpf(float(xi))))
    proved = inv.checks["left_inverse"].value
    assert worst <= proved <= 100 * max(float(worst), 1e-13)


def test_a_bent_m_gets_a_larger_proved_left_inverse_bound():
    # m's formula plus 1e-8 ((y - y0) / w)^2 (y0, w the middle and half width of kappa(V)): m(kappa(xi)) - xi reaches
    # 1e-8 at the ends of V, and the proved bound covers it without being loose.
    from ashc_cli.design import series_proofs

    model, man, inv = _inverse_of(_ladder_spec())
    y = sp.Symbol("y", real=True)
    k_lo, k_hi = np.asarray(inv.value("kappa_range"))[0]
    bent = inv.expr("m_of_y")[0] + sp.Float(1e-8) * ((y - sp.Float((k_lo + k_hi) / 2)) / sp.Float((k_hi - k_lo) / 2)) ** 2
    fitted = series_proofs.prove_fitted_inverse(model, man.series["p"], bent, y, 1e-6)
    assert 0.99e-8 <= fitted["left"] <= 1.5e-8


def test_a_sampled_residual_marks_the_bound_sampled():
    # A fitted p whose residual could not be proved (the row stays sampled): the bound names it, prints G with
    # "(sampled)", and still carries the grid's residual as its term.
    from ashc_cli.design.artefacts import Artefact, Check
    from ashc_cli.design.stages import bound

    arts = {"stabilise": Artefact(stage="stabilise", checks={k: Check(1.0, True, "", "proved") for k in ("lmi_margin", "M_positive")}),
            "manifold": Artefact(stage="manifold", values={"residual_rows": np.array([1e-9, 2e-9])},
                                 checks={"pde_residual": Check(2e-9, True, "grid"), "l_in_U": Check(0.0, True, "", "proved")}),
            "bound": Artefact(stage="bound", checks={k: Check(1.0, True, "", "proved") for k in ("h_lipschitz", "alpha_h", "condition_B", "certified_region")})}
    assert bound.bound_sampled(arts) == ["manifold.pde_residual"]
    assert bound.gain_text({"gain": 2.0, "bound_evidence": "sampled"}) == "2 (sampled)"
    term = bound._residual(arts["manifold"], np.eye(2), 1.0, 2.0, 1.0)
    assert term["evidence_residual"] == "sampled" and term["rho_bar"] >= np.sqrt(5e-18)


def test_a_residual_that_leaves_no_v_empties_the_region(tmp_path):
    # From an independent review: the CSTR with pde_tolerance 0.05 (a degree-1 p, residual 0.0865 in the metric)
    # left ||v||_inf <= -0.0126 and the region check passed; now the region fails and says why.
    from ashc_cli.design.pipeline import run

    from .conftest import SPECS

    data = yaml.safe_load((SPECS / "cstr.yaml").read_text())
    data["abstract"]["pde_tolerance"] = 0.05
    chk = run(parse_spec_text(yaml.safe_dump(data)), tmp_path, ["bound"])["bound"].checks["certified_region"]
    assert not chk.passed and "leaves no v that keeps" in chk.description


def test_a_piecewise_p_whose_pieces_jump_keeps_its_residual_sampled():
    # e = p(xi) - x jumps where xi crosses a break of a piecewise p; the bound carries rho only, so a p whose pieces
    # do not meet exactly (proved jumps > 0: here the ladder's p split at the middle of V, each half interpolated
    # again) keeps the PDE row sampled and says why.
    from ashc_cli.design.artefacts import Check

    model = build_model(parse_spec_text(_ladder_spec()))
    art = manifold.run(model, {})
    s = art.series["p"]
    lo, hi = (float(v) for v in s.box[0])
    mid = (lo + hi) / 2
    halves = []
    for a, b in ((lo, mid), (mid, hi)):
        t = np.cos(np.pi * (np.arange(14) + 0.5) / 14)
        values = s(a + (b - a) * (t + 1) / 2)[:, 0, :]
        halves.append(chebyshev.Series(np.polynomial.chebyshev.chebfit(t, values.T, 13).T, [[a, b]], (model.n, 1)))
    pw = chebyshev.PiecewiseSeries(tuple(halves))
    assert series_proofs.jumps(pw).max() > 0
    art.checks["pde_residual"] = Check(1e-12, True, "grid")
    manifold._prove_residual(model, pw, art)
    assert art.checks["pde_residual"].evidence == "sampled" and "jump" in art.meta["residual_proof"]


def test_the_report_and_the_design_line_print_the_residual_term(tmp_path):
    # The published bound of a fitted p carries its residual's term wherever it is printed: the design's line and
    # the HTML report (with rho_bar).
    from .conftest import SPECS, ashc

    out = tmp_path / "d"
    design = ashc("design", str(SPECS / "rc_ladder.yaml"), "--out", str(out))
    assert design.returncode == 0 and re.search(r"\|\|v\|\|_inf \+ [0-9.]+e-[0-9]+ when", design.stdout), design.stdout
    report = ashc("report", str(SPECS / "rc_ladder.yaml"), "--out", str(out), "--runs", "8", "--t-final", "2")
    assert report.returncode == 0, report.stderr
    assert re.search(r"p(&#x27;|')s PDE residual, rho_bar = [0-9.]+e-", (out / "report.html").read_text())
