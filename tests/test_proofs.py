"""Tests of the proof helpers (ashc_cli/numerics/proofs.py): symbolic identities, ball bounds, matrix inequalities."""

import numpy as np
import pytest
import sympy as sp
from flint import arb

from ashc_cli.numerics import proofs

x, y = sp.symbols("x y", real=True)


def test_symbolic_zero_accepts_identities_and_refuses_the_rest():
    assert proofs.symbolic_zero([sp.sin(x) ** 2 + sp.cos(x) ** 2 - 1, (x**2 - 1) / (x - 1) - x - 1])
    assert not proofs.symbolic_zero([x - 1e-30 * x])           # tiny but not zero
    assert not proofs.symbolic_zero([sp.sqrt(x**2) - x])        # only for x >= 0: no sign assumption is made


def test_affine_in():
    assert proofs.affine_in(sp.Matrix([[2 * x + y * 3, 1]]), [x])
    assert proofs.affine_in(sp.Matrix([[x * y]]), [x])            # affine in x for fixed y
    assert not proofs.affine_in(sp.Matrix([[x * y]]), [x, y])
    assert not proofs.affine_in(sp.Matrix([[x**2]]), [x])


def test_lower_upper_are_exact_on_doubles_and_outward_otherwise():
    assert proofs.lower(arb(0)) == 0.0 and proofs.upper(arb(0)) == 0.0
    third = arb(1) / 3
    # Below / above every point of the ball (its ends, compared exactly), whatever the float rounding does.
    assert arb(proofs.lower(third)) <= third.lower() and arb(proofs.upper(third)) >= third.upper()
    assert proofs.upper(arb("nan")) == np.inf and proofs.lower(arb("nan")) == -np.inf


def test_psd_lower_bound_balls_is_below_the_smallest_eigenvalue_of_every_member():
    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    S = Q @ np.diag([0.01, 0.5, 1, 2, 3, 4]) @ Q.T
    radius = 1e-6
    balls = [[arb(S[i, j], radius) for j in range(6)] for i in range(6)]
    bound = proofs.psd_lower_bound_balls(balls)
    assert bound <= 0.01 - radius                    # every member within the radius has lambda_min >= 0.01 - 6 radius
    assert bound > 0.01 - 6 * radius - 1e-9
    indefinite = [[arb(v) for v in row] for row in np.diag([1.0, -1e-3])]
    assert proofs.psd_lower_bound_balls(indefinite) < 0


@pytest.mark.parametrize("columns", [1, 2])
def test_norm_expr_is_the_spectral_norm_of_sqrt_M_w(columns):
    rng = np.random.default_rng(columns)
    A = rng.normal(size=(3, 3))
    M = A @ A.T + np.eye(3)
    w = sp.Matrix(3, columns, lambda i, j: (i + 1) * x + j * sp.sin(x) - i * j)
    expr = proofs.norm_expr(M, w)
    L = np.linalg.cholesky(M)
    for value in (-1.3, 0.0, 0.7, 2.0):
        W = np.array(w.subs(x, value), dtype=float)
        assert float(expr.subs(x, value)) == pytest.approx(np.linalg.norm(L.T @ W, 2), rel=1e-12)


class _Values:
    values = {}


def test_sup_of_a_norm_on_an_interval_is_a_proved_upper_bound():
    # ||sqrt(M) w|| with w = (x, 1 - x) on [0, 1] and M = diag(1, 4): sqrt(x^2 + 4 (1 - x)^2), largest at x = 0: 2.
    M = np.diag([1.0, 4.0])
    fun = proofs.compile_claims(_Values(), [proofs.norm_expr(M, sp.Matrix([x, 1 - x]))], [x])
    upper, ok, at = proofs.sup_on_box(fun, np.array([[0.0, 1.0]]))
    assert ok and 2.0 <= upper <= 2.0 * (1 + 1e-6) and at[0] == pytest.approx(0.0, abs=1e-6)
    lo, hi, ok = proofs.range_on_box(fun, np.array([[0.0, 1.0]]))
    assert ok and lo <= np.sqrt(4 / 5) <= hi                  # the minimum, at x = 4/5, is sqrt(4/5)


def test_box_function_encloses_every_term():
    f = proofs.BoxFunction(_Values(), {"a": sp.Matrix([[x**2, sp.exp(x)]]), "b": sp.Matrix([x * y])}, [x, y])
    out = f(proofs.ball_box(np.array([[-1.0, 2.0], [0.5, 1.0]])))
    assert out["a"][0][0].lower() <= 0 and out["a"][0][0].upper() >= 4
    assert out["a"][0][1].lower() <= np.exp(-1) and out["a"][0][1].upper() >= np.exp(2)
    assert out["b"][0][0].lower() <= -1 and out["b"][0][0].upper() >= 2
