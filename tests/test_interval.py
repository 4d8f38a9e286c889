"""Tests of the rigorous enclosure toolkit (ashc_cli.numerics.interval, boxsearch)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy as sp
from flint import arb
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ashc_cli.errors import NumericalError
from ashc_cli.problem.expr import FUNCTIONS, NUMERIC_MODULES, SIGNAL_FUNCTIONS, square, step, triangle
from ashc_cli.numerics.boxsearch import inf_on_box, lambda_max_upper, prove_positive, prove_psd, psd_lower_bound, sup_on_box
from ashc_cli.numerics.interval import IntervalFunction, UnsupportedExpression, compile_interval, enclose

x, y = sp.symbols("x y", real=True)


def _samples(box: np.ndarray, n: int, rng) -> np.ndarray:
    """Random points of a box plus its corners and centre, shape (m, d)."""
    d = len(box)
    pts = rng.uniform(box[:, 0], box[:, 1], size=(n, d))
    corners = np.array(np.meshgrid(*box, indexing="ij")).reshape(d, -1).T
    return np.vstack([pts, corners, box.mean(axis=1)[None, :]])


def _assert_contains(expr, box, n=400, seed=0, args=(x, y)):
    """enclose() of expr over box holds numpy's values at sampled points (a few ulps of slack)."""
    f = compile_interval([expr], list(args))
    (lo, hi), = enclose(f, box)
    assert math.isfinite(lo) and math.isfinite(hi), (expr, box)
    fn = sp.lambdify(list(args), expr, modules=NUMERIC_MODULES)
    P = _samples(np.asarray(box, float), n, np.random.default_rng(seed))
    vals = np.broadcast_to(np.asarray(fn(*P.T), dtype=float), (len(P),))
    slack = 1e-12 * (1.0 + np.abs(vals))  # numpy's own rounding, not the enclosure's
    assert np.all(vals >= lo - slack), (expr, box, lo, vals.min())
    assert np.all(vals <= hi + slack), (expr, box, hi, vals.max())
    return lo, hi


EXPRS = [
    sp.sin(x) * sp.cos(y),
    sp.sqrt(x**2 + y**2),
    sp.exp(x - y),
    sp.tanh(3 * x) * y,
    sp.Rational(1, 3) * x - y / 7,
    x**3 - y**5,
    x**2 * y**2 - x * y,
    sp.Abs(x - y) + sp.Abs(x),
    sp.Max(x, y**2) - sp.Min(x, y, sp.Rational(1, 2)),
    sp.atan(x * y) + sp.sinh(x) - sp.cosh(y),
    1 / (2 + sp.sin(x * y)),
    sp.log(3 + x) * sp.sign(y + 5),
    (1 + x**2) ** sp.Float(0.7) + 2**x,
    sp.asin(x / 2) + sp.acos(y / 3),
    sp.tan(x / 2),
    (4 + x + y) ** sp.Rational(3, 2) - (5 + x) ** sp.Rational(-1, 2),
    sp.pi * x + sp.E * y**2,
]
BOXES = [np.array([[-1.0, 1.0], [-2.0, 2.0]]), np.array([[0.25, 0.5], [-0.1, 0.3]]), np.array([[-1.5, -1.4], [1.0, 1.0]])]


@pytest.mark.parametrize("expr", EXPRS, ids=[str(i) for i in range(len(EXPRS))])
def test_enclosures_contain_sampled_values(expr):
    for k, box in enumerate(BOXES):
        _assert_contains(expr, box, seed=k)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.floats(-3, 3), st.floats(0, 2), st.floats(-3, 3), st.floats(0, 2), st.integers(0, len(EXPRS) - 1)
)
def test_random_boxes_hypothesis(a, wa, b, wb, k):
    box = np.array([[a, a + wa], [b, b + wb]])
    expr = EXPRS[k]
    f = compile_interval([expr], [x, y])
    (lo, hi), = enclose(f, box)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return  # outside a domain somewhere on the box (asin, log, tan, ...): allowed to be non-finite
    fn = sp.lambdify([x, y], expr, modules=NUMERIC_MODULES)
    P = _samples(box, 60, np.random.default_rng(k))
    with np.errstate(all="ignore"):
        vals = np.broadcast_to(np.asarray(fn(*P.T), dtype=float), (len(P),))
    assert np.all(np.isfinite(vals)), "a finite enclosure on a box where the function is undefined"
    slack = 1e-12 * (1.0 + np.abs(vals))
    assert np.all(vals >= lo - slack) and np.all(vals <= hi + slack)


def test_seeded_random_boxes_ball_interface():
    """The arb-ball interface also holds the sampled values, on many random boxes."""
    f = compile_interval(EXPRS[:12], [x, y])
    fns = [sp.lambdify([x, y], e, modules=NUMERIC_MODULES) for e in EXPRS[:12]]
    rng = np.random.default_rng(7)
    for _ in range(15):
        c = rng.uniform(-1, 1, 2)
        w = rng.uniform(0, 0.5, 2)
        box = np.stack([c - w, c + w], axis=1)
        balls = [arb(lo).union(arb(hi)) for lo, hi in box]
        outs = f(balls)
        P = _samples(box, 40, rng)
        for out, fn in zip(outs, fns):
            if not out.is_finite():
                continue
            vals = np.broadcast_to(np.asarray(fn(*P.T), dtype=float), (len(P),))
            lo, hi = float(out.lower()), float(out.upper())
            slack = 1e-12 * (1.0 + np.abs(vals))
            assert np.all(vals >= lo - slack) and np.all(vals <= hi + slack)


def test_every_whitelisted_function_is_supported():
    """Each spec function (and signal function) compiles and encloses its numeric version."""
    for name, (func, arity) in {**FUNCTIONS, **SIGNAL_FUNCTIONS}.items():
        expr = func(x, y) if arity is None else func(x if name != "log" else x + 2)
        for box in (np.array([[-1.0, 1.0], [0.0, 0.5]]), np.array([[0.2, 0.3], [-0.5, 0.5]]), np.array([[-7.0, 9.0], [1.0, 2.0]])):
            if name in ("sqrt", "log") and box[0, 0] < 0:
                box = box.copy()
                box[0] = [0.0, 1.0]
            if name == "tan":
                box = np.array([[-1.0, 1.0], [0.0, 0.5]])
            _assert_contains(expr, box)


def test_signal_functions_tight():
    f = compile_interval([triangle(x), square(x), step(x)], [x])
    tri, sq, st_ = enclose(f, np.array([[0.0, math.pi / 2]]))
    assert tri[0] <= -1.0 <= 0.0 <= tri[1] <= 0.0 + 1e-9
    assert sq == (0.0, 1.0)  # sign(sin) on [0, pi/2]: 0 at t = 0, then 1
    assert st_ == (1.0, 1.0)
    assert enclose(f, np.array([[-3.0, -2.0]]))[2] == (0.0, 0.0)
    assert enclose(f, np.array([[-1.0, 2 * math.pi + 1]]))[0] == (-1.0, 1.0)


def test_even_power_is_tight():
    f = compile_interval([x**2, x**4, x**3], [x])
    (lo2, hi2), (lo4, hi4), (lo3, hi3) = enclose(f, np.array([[-1.0, 2.0]]))
    assert (lo2, hi2) == (0.0, 4.0)
    assert (lo4, hi4) == (0.0, 16.0)
    assert (lo3, hi3) == (-1.0, 8.0)
    assert enclose(compile_interval([x ** sp.Float(2.0)], [x]), np.array([[-1.0, 2.0]]))[0] == (0.0, 4.0)
    # Through the ball interface the ends widen only by the ball's radius rounding (~2**-30 of it).
    out = f([arb(-1.0).union(arb(2.0))])[0]
    assert out.lower() >= -1e-7 and out.upper() >= 4 and out.upper() <= 4 + 1e-7


def test_exact_zero_ends_keep_domains():
    """2 - 2x on [0, 1] has lower end exactly 0, so sqrt of it is defined; so is sqrt(x**2 + y**2)."""
    f = compile_interval([sp.sqrt(2 - 2 * x), sp.sqrt(x**2 + y**2), sp.sqrt(x * y)], [x, y])
    encs = enclose(f, np.array([[0.0, 1.0], [0.0, 0.1]]))
    assert encs[0] == (0.0, pytest.approx(math.sqrt(2)))
    assert encs[1][0] == 0.0 and encs[2][0] == 0.0
    assert all(math.isfinite(v) for e in encs for v in e)


def test_domain_violations_are_not_finite():
    box = np.array([[-1.0, 1.0]])
    for expr in (sp.sqrt(x), sp.log(x + 1), 1 / x, sp.tan(2 * x), sp.asin(2 * x), x ** sp.Rational(1, 3),
                 sp.Min(1, sp.sqrt(x)), sp.sign(sp.sqrt(x)), sp.Abs(sp.log(x + 1)), x ** sp.Float(-0.5)):
        f = compile_interval([expr], [x])
        lo, hi = enclose(f, box)[0]
        assert math.isnan(lo) and math.isnan(hi), expr
        assert not f([arb(0, 1)])[0].is_finite(), expr
    # A constant subexpression outside its domain as well.
    assert not compile_interval([sp.sqrt(x - 3)], [x], )([arb(1)])[0].is_finite()


def test_sup_of_sqrt_over_domain_edge_is_not_proved():
    f = compile_interval([sp.sqrt(x)], [x])
    r = sup_on_box(f, np.array([[-1.0, 1.0]]), max_boxes=200)
    assert not r.proved and r.upper == math.inf
    assert 0 < r.lower <= 1.0 and r.argmax[0] > 0
    # On [0, 1] it is fine: the left end is exactly 0.
    r = sup_on_box(f, np.array([[0.0, 1.0]]), rtol=1e-9)
    assert r.proved and r.upper >= 1.0 and r.lower <= 1.0


def test_rationals_and_floats_are_exact():
    third = compile_interval([sp.Rational(1, 3)], [])([])[0]
    assert (third * 3).contains(1)  # holds exactly 1/3 ...
    assert not third.is_exact() and not third.contains(arb(1.0 / 3.0) + 1e-16)  # ... not the double
    lo, hi = enclose(compile_interval([sp.Rational(1, 3)], []), np.zeros((0, 2)))[0]
    assert lo < 1.0 / 3.0 < hi and hi - lo < 1e-15
    # (x/3)*3 - x, unevaluated, on a thin ball: holds 0 with a tiny radius.
    e = sp.Add(sp.Mul(sp.Mul(x, sp.Rational(1, 3), evaluate=False), 3, evaluate=False), -x, evaluate=False)
    out = compile_interval([e], [x])([arb(0.7, 1e-15)])[0]
    assert out.contains(0) and float(out.rad()) < 1e-13
    # A Float is its exact double, a parameter value too.
    f = compile_interval([sp.Float(0.1) * y, x * y], [y], values={x: 0.1})
    a, b = f([arb(1)])
    assert a.is_exact() and b.is_exact() and a == arb(0.1) and b == arb(0.1)


def test_common_subexpressions_are_shared():
    s = sp.sin(x * y)
    f = compile_interval([s**2 + s, sp.exp(s)], [x, y])
    steps, _, _ = f._tape((0, 1), False)
    # x*y, sin, square, add, exp: each distinct subtree once
    assert len(steps) == 5


def test_unsupported_expressions():
    for bad in (sp.Function("f")(x), sp.floor(x), sp.I * x, sp.oo * x, sp.gamma(x), sp.Mod(x, 2), sp.GoldenRatio * x):
        with pytest.raises(UnsupportedExpression) as info:
            compile_interval([bad], [x])
        assert isinstance(info.value, ValueError)
    with pytest.raises(ValueError, match="free symbol"):
        compile_interval([x + y], [x])
    with pytest.raises(ValueError):
        compile_interval([x], [x], values={x: 1.0})


def test_known_sups():
    r = sup_on_box(compile_interval([x * (1 - x)], [x]), np.array([[0.0, 1.0]]), rtol=1e-6)
    assert r.proved and 0.25 <= r.upper <= 0.25 * (1 + 1e-6) and r.lower <= 0.25
    r = sup_on_box(compile_interval([sp.sin(x)], [x]), np.array([[0.0, 3.0]]), rtol=1e-6)
    assert r.proved and 1.0 <= r.upper <= 1.0 + 1e-6 and r.lower <= 1.0
    assert abs(r.argmax[0] - math.pi / 2) < 1e-2
    # sup of x*y - x**2 on [0, 2] x [0, 3] is max_y y**2/4 = 9/4 at (3/2, 3).
    r = sup_on_box(compile_interval([x * y - x**2], [x, y]), np.array([[0.0, 2.0], [0.0, 3.0]]), rtol=1e-8)
    assert r.proved and 2.25 <= r.upper <= 2.25 * (1 + 1e-8) and r.lower <= 2.25
    assert np.allclose(r.argmax, [1.5, 3.0], atol=1e-3)
    r = sup_on_box(compile_interval([sp.sqrt(3 - x**2)], [x]), np.array([[-1.0, 1.0]]), rtol=1e-9)
    assert r.proved and math.sqrt(3) <= r.upper <= math.sqrt(3) * (1 + 1e-9)


def test_known_infs_and_index_and_seeds():
    f = compile_interval([x * (1 - x), sp.cos(x) + y**2], [x, y])
    box = np.array([[0.0, 4.0], [-1.0, 1.0]])
    r = inf_on_box(f, box, index=1, rtol=0, atol=1e-7)
    assert r.proved and r.lower <= -1.0 <= r.upper <= -1.0 + 1e-7
    assert abs(r.argmin[0] - math.pi) < 1e-2
    r = inf_on_box(f, box, index=0, atol=1e-9, rtol=0)
    assert r.proved and r.lower <= -12.0 <= r.upper  # x(1-x) at x = 4
    seed = np.array([[0.5, 0.0]])
    r = sup_on_box(f, box, seeds=seed, rtol=1e-6)
    assert r.lower == 0.25 and r.upper >= 0.25 and np.array_equal(r.argmax, seed[0])


def test_budget_keeps_upper_rigorous():
    e = sp.sin(5 * x) * sp.cos(3 * y) + x * y
    f = compile_interval([e], [x, y])
    box = np.array([[-2.0, 2.0], [-2.0, 2.0]])
    P = _samples(box, 4000, np.random.default_rng(3))
    true_max = np.max(np.sin(5 * P[:, 0]) * np.cos(3 * P[:, 1]) + P[:, 0] * P[:, 1])
    for max_boxes in (1, 5, 40):
        r = sup_on_box(f, box, rtol=0.0, max_boxes=max_boxes)
        assert not r.proved and r.upper >= true_max and r.boxes <= max_boxes + 1
    r = sup_on_box(f, box, rtol=1e-4)
    assert r.proved and r.upper >= true_max >= r.lower - 1e-3


def test_generic_callable_path():
    def fun(b):
        return [b[0] * (1 - b[0]), b[0].sqrt()]

    r = sup_on_box(fun, np.array([[0.0, 1.0]]), rtol=1e-3)
    assert r.proved and 0.25 <= r.upper <= 0.25 * (1 + 1e-3)
    (lo, hi), (slo, shi) = enclose(fun, np.array([[0.25, 0.5]]))
    assert lo <= 0.1875 and hi >= 0.25 and slo <= 0.5 and shi >= math.sqrt(0.5)
    assert prove_positive(lambda b: [b[0] * b[0] + arb(0.001)], np.array([[-1.0, 1.0]]))[0]


def test_prove_positive():
    box = np.array([[-1.0, 1.0]])
    ok, low = prove_positive(compile_interval([x**2 + sp.Rational(1, 1000)], [x]), box)
    assert ok and 0 < low <= 1e-3
    ok, val = prove_positive(compile_interval([x**2 - sp.Rational(1, 1000)], [x]), box)
    assert not ok and val <= 0
    ok, low = prove_positive(compile_interval([x**2 + y**2 - x * y + sp.Rational(1, 100)], [x, y]), np.array([[-1.0, 1.0], [-1.0, 1.0]]))
    assert ok and 0 < low <= 0.01
    ok, low = prove_positive(compile_interval([sp.sqrt(x) + 1], [x]), box, max_boxes=50)
    assert not ok and low == -math.inf  # sqrt is undefined on [-1, 0)
    near = x**2 - 2 * x * y + y**2 + sp.Rational(1, 10**12)  # (x - y)**2 + 1e-12, written out
    ok, low = prove_positive(compile_interval([near], [x, y]), np.array([[-1.0, 1.0], [-1.0, 1.0]]), max_boxes=200)
    assert not ok and low <= 1e-12  # budget: a rigorous lower bound, not a proof


def test_psd_lower_bound():
    b = psd_lower_bound(np.diag([1.0, 2.0, 3.0]))
    assert 1 - 1e-6 < b <= 1.0
    rng = np.random.default_rng(1)
    Q, _ = np.linalg.qr(rng.standard_normal((40, 40)))
    S = (Q * np.linspace(0.3, 5.0, 40)) @ Q.T
    S = 0.5 * (S + S.T)
    lam = np.linalg.eigvalsh(S)[0]
    b = psd_lower_bound(S)
    assert lam - 1e-6 < b <= lam + 1e-12 and prove_psd(S, 0.29) and not prove_psd(S, 0.31)
    # Nearly singular but positive definite: still proved.
    T = (Q * np.concatenate([[1e-8], np.linspace(0.5, 1.0, 39)])) @ Q.T
    T = 0.5 * (T + T.T)
    assert 0 < psd_lower_bound(T) <= np.linalg.eigvalsh(T)[0] + 1e-15
    # Not exactly symmetric: its symmetric part is used.
    U = S.copy()
    U[0, 1] += 1e-9
    assert lam - 1e-6 < psd_lower_bound(U) <= lam + 1e-9
    # Indefinite and singular: never a positive bound.
    V = (Q * np.linspace(-0.2, 5.0, 40)) @ Q.T
    bv = psd_lower_bound(0.5 * (V + V.T))
    assert bv < 0 and bv <= -0.2 + 1e-9
    assert psd_lower_bound(np.array([[1.0, 1.0], [1.0, 1.0]])) <= 0
    assert not prove_psd(np.array([[1.0, 2.0], [2.0, 1.0]]))
    big = rng.standard_normal((128, 128))
    assert 0 < psd_lower_bound(big @ big.T + np.eye(128)) <= 1.0 + np.linalg.eigvalsh(big @ big.T)[0] + 1e-6
    with pytest.raises(NumericalError):
        psd_lower_bound(np.array([[1.0, np.nan], [np.nan, 1.0]]))
    with pytest.raises(ValueError):
        psd_lower_bound(np.ones((2, 3)))


def test_lambda_max_upper():
    A = np.array([[1.0, 2.0], [0.5, -1.0], [0.1, 3.0]])
    Aa = [[arb(v) for v in row] for row in A]
    G = [[sum((Aa[k][i] * Aa[k][j] for k in range(3)), arb(0)) for j in range(2)] for i in range(2)]
    ub = lambda_max_upper(G)
    assert ub >= np.linalg.eigvalsh(A.T @ A)[-1]
    assert ub <= np.abs(A.T @ A).sum(axis=1).max() * (1 + 1e-12)
    assert lambda_max_upper([[arb(2), arb(0)], [arb(0), arb(5)]]) == 5.0
    assert lambda_max_upper([[arb.nan()]]) == math.inf


def test_compiled_function_interface():
    f = compile_interval([x + y, x * y], [x, y])
    assert isinstance(f, IntervalFunction) and len(f) == 2
    with pytest.raises(ValueError):
        f([arb(1)])
    s, p = f([arb(1, 0.5), 2.0])
    assert s.contains(arb(2.5).union(arb(3.5))) and p.contains(arb(1).union(arb(3)))
    with pytest.raises(ValueError):
        enclose(f, np.array([[0.0, 1.0]]))
    with pytest.raises(ValueError):
        sup_on_box(f, np.array([[1.0, 0.0], [0.0, 1.0]]))
