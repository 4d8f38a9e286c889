"""Tensor Chebyshev series: fit, evaluate, differentiate and convert to sympy."""

import numpy as np
import sympy as sp

from ashc_cli.numerics import chebyshev


def test_fit_reproduces_a_polynomial_exactly_and_its_sympy_form():
    box = np.array([[-1.0, 2.0], [0.5, 3.0]])
    z = chebyshev.nodes(box, 6)
    f = lambda a, b: 1 + a * b**2 - 3 * a**2          # noqa: E731
    c = chebyshev.fit(f(*z)[None, :], box, z, 3)
    check = np.stack(np.meshgrid(np.linspace(-1, 2, 7), np.linspace(0.5, 3, 5))).reshape(2, -1)
    assert np.allclose(chebyshev.evaluate(c, box, check)[0], f(*check), atol=1e-12)
    a, b = sp.symbols("a b")
    expr = chebyshev.to_sympy(c, box, [a, b])[0]
    assert sp.simplify(sp.nsimplify(expr, rational=True) - (1 + a * b**2 - 3 * a**2)) == 0


def test_derivative_along_each_axis():
    box = np.array([[0.0, 2.0], [-1.0, 1.0]])
    z = chebyshev.nodes(box, 8)
    c = chebyshev.fit(np.sin(z[0]) * np.exp(z[1])[None, :], box, z, 7)
    check = chebyshev.nodes(box, 5)
    d0 = chebyshev.evaluate(chebyshev.derivative(c, box, 0), box, check)[0]
    d1 = chebyshev.evaluate(chebyshev.derivative(c, box, 1), box, check)[0]
    assert np.allclose(d0, np.cos(check[0]) * np.exp(check[1]), atol=1e-4)
    assert np.allclose(d1, np.sin(check[0]) * np.exp(check[1]), atol=1e-4)


def test_high_degree_stays_in_scaled_variables():
    # Expanding a degree-20 series on [10, 12] about 0 would lose every digit; the sympy form keeps it.
    box = np.array([[10.0, 12.0]])
    z = chebyshev.nodes(box, 21)
    c = chebyshev.fit(np.exp(-z[0])[None, :], box, z, 20)
    x = sp.Symbol("x")
    f = sp.lambdify(x, chebyshev.to_sympy(c, box, [x])[0], "numpy")
    xs = np.linspace(10, 12, 11)
    assert np.allclose(f(xs), np.exp(-xs), rtol=1e-12, atol=0)


def test_series_evaluates_differentiates_and_maps_like_its_formula():
    box = np.array([[0.0, 0.6]])
    z = chebyshev.nodes(box, 25)
    f = np.stack([1 / (1.5 - z[0]), np.exp(z[0]), np.sin(3 * z[0])])
    s = chebyshev.Series.column(chebyshev.fit(f, box, z, 20), box)
    assert s.shape == (3, 1) and s.kept_numeric
    xi = sp.Symbol("xi", real=True)
    formula = s.to_sympy([xi])
    # Horner's scheme in the scaled variable: linear in the degree (no powers to expand or print).
    assert not formula[0].atoms(sp.Pow) and sp.count_ops(formula[0]) <= 4 * (s.degree + 1)
    xs = np.linspace(0.0, 0.6, 13)
    lam = sp.lambdify(xi, formula, "numpy")
    assert np.allclose(np.asarray(lam(xs), dtype=float).reshape(3, -1), s(xs)[:, 0, :], rtol=1e-13, atol=1e-13)
    assert np.allclose(s.formula_at(xs[None, :]), s(xs), rtol=1e-13, atol=1e-13)
    assert np.allclose(s(xs)[:, 0, :], [1 / (1.5 - xs), np.exp(xs), np.sin(3 * xs)], atol=1e-10)
    # The Jacobian is the series of the derivatives, and so is its formula.
    J = s.jacobian()
    assert J.shape == (3, 1)
    assert np.allclose(J(xs)[:, 0, :], [1 / (1.5 - xs) ** 2, np.exp(xs), 3 * np.cos(3 * xs)], atol=1e-7)
    assert np.allclose(np.asarray(sp.lambdify(xi, J.to_sympy([xi]), "numpy")(xs), dtype=float).reshape(3, -1), J(xs)[:, 0, :], rtol=1e-12, atol=1e-12)
    # Constant matrices on either side: C S (kappa = C p) and S B (dp/dxi delta).
    C = np.array([[0.0, 0.0, 1.0], [2.0, -1.0, 0.0]])
    assert np.allclose(s.left(C)(xs), np.einsum("ij,jkN->ikN", C, s(xs)))
    assert np.array_equal(s.left(np.eye(3)[[2]]).coeffs, s.coeffs[[2]])   # a selection is exact
    B = np.array([[2.0, -3.0]])
    assert s.right(B).shape == (3, 2) and np.allclose(s.right(B)(xs), np.einsum("ijN,jk->ikN", s(xs), B))
    # A single point, as a scalar search calls it: shape (3, 1, 1).
    assert s(np.array([0.25])).shape == (3, 1, 1)


def test_low_degree_series_keep_the_expanded_formula():
    box = np.array([[-1.0, 2.0]])
    z = chebyshev.nodes(box, 6)
    s = chebyshev.Series.column(chebyshev.fit(np.stack([z[0], z[0] ** 2]), box, z, 3), box)
    x = sp.Symbol("x", real=True)
    assert not s.kept_numeric and s.to_sympy([x]) == chebyshev.to_sympy(s.coeffs, box, [x])
    assert sp.simplify(sp.nsimplify(s.to_sympy([x])[1], rational=True) - x**2) == 0


def test_fit_adaptive_splits_where_one_series_is_not_enough_and_the_pieces_meet():
    # Runge's function has poles at +-0.1i: degree 32 on [-1, 1] misses it by about 1e-2, pieces reach 1e-12.
    import pytest

    from ashc_cli.errors import FitError

    f = lambda z: 1 / (1 + 100 * z**2)   # noqa: E731
    grid = {}

    def accept(piece):
        t = np.linspace(*piece.box[0], 201)
        err = float(np.abs(piece.at(t[None, :])[0] - f(t)).max())
        grid[tuple(piece.box[0])] = err
        return err <= 1e-12, err

    s = chebyshev.fit_adaptive(lambda z: f(z), (-1.0, 1.0), accept)
    assert isinstance(s, chebyshev.PiecewiseSeries) and 1 < len(s.pieces) <= chebyshev.MAX_PIECES
    t = np.random.default_rng(1).uniform(-1, 1, 5000)
    assert np.abs(s(t)[0, 0] - f(t)).max() < 1e-11
    value, slope = s.jumps()
    assert value.max() < 1e-14 and slope.max() < 1e-8          # the pieces pass through the sampled ends
    # Breaks asked for are kept; an impossible tolerance names where it failed.
    assert 0.3 in chebyshev.fit_adaptive(lambda z: f(z), (-1.0, 1.0), accept, breaks=[0.3]).breaks
    with pytest.raises(FitError) as info:
        chebyshev.fit_adaptive(lambda z: np.abs(z - 0.123), (-1.0, 1.0), lambda p: (False, 1.0), max_pieces=8)
    assert "8 pieces" in info.value.reason


def test_a_piecewise_series_evaluates_differentiates_and_maps_like_its_formula():
    box = [(-2.0, -0.5), (-0.5, 1.0), (1.0, 3.0)]
    f = lambda z: np.stack([np.sin(z), np.exp(-z)])   # noqa: E731
    pieces = []
    for lo, hi in box:
        b = np.array([[lo, hi]])
        z = chebyshev.extreme_points(b, 25)
        pieces.append(chebyshev.Series.column(chebyshev.fit(f(z[0]), b, z, 24), b))
    s = chebyshev.PiecewiseSeries(tuple(pieces))
    assert s.shape == (2, 1) and s.kept_numeric and np.array_equal(s.breaks, [-2.0, -0.5, 1.0, 3.0])
    xs = np.linspace(-2.5, 3.5, 601)   # beyond the ends too: the end pieces extend
    inside = (xs >= -2) & (xs <= 3)
    assert np.allclose(s(xs)[:, 0, inside], f(xs[inside]), atol=1e-12)
    xi = sp.Symbol("xi", real=True)
    formula = s.to_sympy([xi])
    assert formula[0].has(sp.Piecewise)
    lam = sp.lambdify(xi, formula, "numpy")
    assert np.allclose(np.asarray(lam(xs), dtype=float).reshape(2, -1), s(xs)[:, 0, :], rtol=1e-13, atol=1e-13)
    assert np.allclose(s.formula_at(xs[None, :]), s(xs), rtol=1e-13, atol=1e-13)
    assert np.allclose(s.jacobian()(xs)[:, 0, inside], [np.cos(xs[inside]), -np.exp(-xs[inside])], atol=1e-10)
    C = np.array([[1.0, 2.0]])
    assert np.allclose(s.left(C)(xs), np.einsum("ij,jkN->ikN", C, s(xs)))
    assert not s.is_constant()
    # Stored as arrays and rebuilt.
    again = chebyshev.PiecewiseSeries.from_arrays(s.coeffs, s.breaks, s.shape)
    assert np.array_equal(again(xs), s(xs))
