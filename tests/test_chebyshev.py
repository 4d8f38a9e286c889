"""Tensor Chebyshev series: fit, evaluate, differentiate and convert to sympy."""

import numpy as np
import sympy as sp

from ashc_cli import chebyshev


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
