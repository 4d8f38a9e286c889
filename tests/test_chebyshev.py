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
    assert s.shape == (3, 1) and s.horner
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
    assert not s.horner and s.to_sympy([x]) == chebyshev.to_sympy(s.coeffs, box, [x])
    assert sp.simplify(sp.nsimplify(s.to_sympy([x])[1], rational=True) - x**2) == 0
