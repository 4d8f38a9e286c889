"""Tensor Chebyshev series on a box: the smooth interpolants behind numeric manifolds and inverses.

A function on the box B = [a_1, b_1] x ... x [a_d, b_d] is written as a series in the products
T_k1(s_1) ... T_kd(s_d) of Chebyshev polynomials, s_i = (2 z_i - a_i - b_i) / (b_i - a_i) in [-1, 1].
A coefficient array has shape (rows, deg + 1, ..., deg + 1) (one series per row).  numpy's Chebyshev module
does the 1-D work; these functions add the tensor product, the derivative along an axis, the fit to values
and the conversion to a sympy polynomial, so that downstream stages can treat the result like any closed
form (Remark solvePDE leaves p to "numerical methods"; this is ours).
"""

from __future__ import annotations

import itertools

import numpy as np
import numpy.polynomial.chebyshev as cheb
import sympy as sp

__all__ = ["nodes", "evaluate", "derivative", "fit", "to_sympy"]

#: Power-basis coefficients below this fraction of the largest are dropped (round-off).
CHOP_RTOL = 1e-13
#: Series up to this degree per axis are expanded into the power basis of the original variables.
EXPAND_MAX_DEGREE = 4


def _scaled(box: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Map points z (d, N) of the box to [-1, 1]^d."""
    a, b = box[:, :1], box[:, 1:]
    return (2.0 * z - (a + b)) / (b - a)


def nodes(box: np.ndarray, count: int) -> np.ndarray:
    """Tensor grid of ``count`` Chebyshev points of the first kind per axis, shape (d, count**d)."""
    box = np.asarray(box, dtype=float)
    s = np.cos(np.pi * (np.arange(count) + 0.5) / count)[::-1]
    axes = [(lo + hi) / 2 + (hi - lo) / 2 * s for lo, hi in box]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh])


def _vander(box: np.ndarray, z: np.ndarray, degree: int) -> np.ndarray:
    """The tensor Chebyshev Vandermonde matrix, shape (N, (degree + 1)**d)."""
    s = _scaled(box, z)
    V = np.ones((z.shape[1], 1))
    for axis in range(len(box)):
        V = np.einsum("Ni,Nj->Nij", V, cheb.chebvander(s[axis], degree)).reshape(z.shape[1], -1)
    return V


def evaluate(coeffs: np.ndarray, box: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Values of each row's series at the points z (d, N): shape (rows, N)."""
    rows, degree = coeffs.shape[0], coeffs.shape[1] - 1
    return coeffs.reshape(rows, -1) @ _vander(box, z, degree).T


def derivative(coeffs: np.ndarray, box: np.ndarray, axis: int) -> np.ndarray:
    """Coefficients of the derivative along ``axis`` (same shape, padded with a zero degree)."""
    scale = 2.0 / (box[axis, 1] - box[axis, 0])
    d = cheb.chebder(coeffs, axis=axis + 1) * scale
    pad = [(0, 0)] * coeffs.ndim
    pad[axis + 1] = (0, 1)
    return np.pad(d, pad)


def fit(values: np.ndarray, box: np.ndarray, z: np.ndarray, degree: int) -> np.ndarray:
    """Least-squares coefficients of degree ``degree`` per axis for values (rows, N) at points z."""
    V = _vander(box, z, degree)
    c, *_ = np.linalg.lstsq(V, values.T, rcond=None)
    return c.T.reshape((values.shape[0],) + (degree + 1,) * len(box))


def to_sympy(coeffs: np.ndarray, box: np.ndarray, symbols) -> sp.Matrix:
    """The series as a column of sympy polynomials (power basis in the scaled variables s_i, float coefficients).

    Terms below ``CHOP_RTOL`` of the largest coefficient are dropped; a polynomial of low degree (an exact
    solution) therefore comes out with few terms.
    """
    d, degree = len(box), coeffs.shape[1] - 1
    # cheb -> power basis along each axis: T has column k = power coefficients of T_k.
    T = np.zeros((degree + 1, degree + 1))
    for k in range(degree + 1):
        T[: k + 1, k] = cheb.cheb2poly(np.eye(degree + 1)[k])[: k + 1]
    scaled = [(2 * sym - float(lo + hi)) / float(hi - lo) for sym, (lo, hi) in zip(symbols, box)]
    rows = []
    for row in coeffs:
        power = row
        for axis in range(d):
            power = np.moveaxis(np.tensordot(T, power, axes=([1], [axis])), 0, axis)
        big = max(float(np.abs(power).max()), 1e-300)
        expr = sp.Integer(0)
        for index in itertools.product(range(degree + 1), repeat=d):
            c = power[index]
            if abs(c) > CHOP_RTOL * big:
                expr += sp.Float(c) * sp.Mul(*[s**k for s, k in zip(scaled, index)])
        # Kept in the scaled variables at high degree (expanding about 0 would lose digits); expanded and
        # chopped at low degree, so an exact polynomial solution reads as one (p = [xi, xi**2]).
        rows.append(_chop(sp.expand(expr)) if degree <= EXPAND_MAX_DEGREE else expr)
    return sp.Matrix(rows)


def _chop(expr: sp.Expr) -> sp.Expr:
    """Drop the terms of an expanded polynomial whose coefficient is round-off."""
    terms = sp.Add.make_args(expr)
    big = max((abs(float(t.as_coeff_Mul()[0])) for t in terms), default=0.0)
    return sp.Add(*[t for t in terms if abs(float(t.as_coeff_Mul()[0])) > CHOP_RTOL * 100 * big])
