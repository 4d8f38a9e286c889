"""Tensor Chebyshev series on a box: the smooth interpolants behind numeric manifolds and inverses.

A function on the box B = [a_1, b_1] x ... x [a_d, b_d] is written as a series in the products
T_k1(s_1) ... T_kd(s_d) of Chebyshev polynomials, s_i = (2 z_i - a_i - b_i) / (b_i - a_i) in [-1, 1].
A coefficient array has shape (rows, deg + 1, ..., deg + 1) (one series per row).  numpy's Chebyshev module
does the 1-D work; these functions add the tensor product, the derivative along an axis, the fit to values
and the conversion to a sympy polynomial, so that downstream stages can treat the result like any closed
form (Remark 5 leaves p to "numerical methods"; this is ours).

:class:`Series` keeps a fitted matrix (p, dp/dxi, dp/dxi delta) numeric: the design stages evaluate it with
numpy, and its sympy form (:meth:`Series.to_sympy`, Horner in the scaled variable for one axis) is built only
for the readers of the artefact that need formulas (``simulate``, ``falsify``, ``eval``).  On a ladder of
n = 512 states, sympy took minutes to differentiate, compile and print the power-basis form of p.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import numpy.polynomial.chebyshev as cheb
import sympy as sp

__all__ = ["nodes", "evaluate", "derivative", "fit", "to_sympy", "power_coefficients", "Series"]

#: Power-basis coefficients below this fraction of the largest are dropped (round-off).
CHOP_RTOL = 1e-13
#: Series up to this degree per axis are expanded into the power basis of the original variables.
EXPAND_MAX_DEGREE = 4


def _scaled(box: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Map points z (d, N) of the box to [-1, 1]^d."""
    a, b = box[:, :1], box[:, 1:]
    return (2.0 * z - (a + b)) / (b - a)


def nodes(box: np.ndarray, count: int) -> np.ndarray:
    """Tensor grid of ``count`` Chebyshev points of the first kind per axis, shape (d, count**d).

    Parameters
    ----------
    box : ndarray (d, 2)
        One [lo, hi] row per axis.
    count : int
        Points per axis.

    Returns
    -------
    ndarray (d, count**d)
        The points as columns, each axis's points ascending, the last axis varying fastest.
    """
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
    """Values of each row's series at the points z (d, N): shape (rows, N).

    Parameters
    ----------
    coeffs : ndarray (rows, deg + 1, ..., deg + 1)
        One series per row, d axes of coefficients.
    box : ndarray (d, 2)
        The box the series lives on.
    z : ndarray (d, N)
        The points, as columns.

    Returns
    -------
    ndarray (rows, N)
    """
    rows, degree = coeffs.shape[0], coeffs.shape[1] - 1
    return coeffs.reshape(rows, -1) @ _vander(box, z, degree).T


def derivative(coeffs: np.ndarray, box: np.ndarray, axis: int) -> np.ndarray:
    """Coefficients of the derivative along ``axis`` (same shape, padded with a zero degree).

    Parameters
    ----------
    coeffs : ndarray (rows, deg + 1, ..., deg + 1)
        One series per row.
    box : ndarray (d, 2)
        The box the series lives on (the derivative is in its unscaled variable).
    axis : int
        The variable, 0 to d - 1 (axis ``axis + 1`` of ``coeffs``).

    Returns
    -------
    ndarray
        The same shape as ``coeffs``.
    """
    scale = 2.0 / (box[axis, 1] - box[axis, 0])
    d = cheb.chebder(coeffs, axis=axis + 1) * scale
    pad = [(0, 0)] * coeffs.ndim
    pad[axis + 1] = (0, 1)
    return np.pad(d, pad)


def fit(values: np.ndarray, box: np.ndarray, z: np.ndarray, degree: int) -> np.ndarray:
    """Least-squares coefficients of degree ``degree`` per axis for values (rows, N) at points z.

    Parameters
    ----------
    values : ndarray (rows, N)
        The values to fit, one row per series.
    box : ndarray (d, 2)
        The box of the series.
    z : ndarray (d, N)
        The points the values were taken at (e.g. :func:`nodes`).
    degree : int
        The degree per axis.

    Returns
    -------
    ndarray (rows, degree + 1, ..., degree + 1)
    """
    V = _vander(box, z, degree)
    c, *_ = np.linalg.lstsq(V, values.T, rcond=None)
    return c.T.reshape((values.shape[0],) + (degree + 1,) * len(box))


def power_coefficients(coeffs: np.ndarray) -> np.ndarray:
    """The series in the power basis of the scaled variables s_i: same shape, entry [row, k_1, ..., k_d] the
    coefficient of s_1**k_1 ... s_d**k_d.

    Parameters
    ----------
    coeffs : ndarray (rows, deg + 1, ..., deg + 1)
        Chebyshev coefficients, one series per row.

    Returns
    -------
    ndarray
        The same shape as ``coeffs``.
    """
    d, degree = coeffs.ndim - 1, coeffs.shape[1] - 1
    # cheb -> power basis along each axis: T has column k = power coefficients of T_k.
    T = np.zeros((degree + 1, degree + 1))
    for k in range(degree + 1):
        T[: k + 1, k] = cheb.cheb2poly(np.eye(degree + 1)[k])[: k + 1]
    out = np.empty(np.shape(coeffs))
    for r, row in enumerate(np.asarray(coeffs, dtype=float)):
        # Row by row: the same sums in the same order whatever the number of rows (reproducible formulas).
        power = row
        for axis in range(d):
            power = np.moveaxis(np.tensordot(T, power, axes=([1], [axis])), 0, axis)
        out[r] = power
    return out


def _chopped(power: np.ndarray) -> np.ndarray:
    """Power coefficients with those below ``CHOP_RTOL`` of their row's largest set to 0 (round-off)."""
    flat = power.reshape(power.shape[0], -1)
    big = np.maximum(np.abs(flat).max(axis=1, keepdims=True), 1e-300)
    return np.where(np.abs(flat) > CHOP_RTOL * big, flat, 0.0).reshape(power.shape)


def _scaled_symbols(box: np.ndarray, symbols) -> list:
    return [(2 * sym - float(lo + hi)) / float(hi - lo) for sym, (lo, hi) in zip(symbols, np.asarray(box, dtype=float))]


def to_sympy(coeffs: np.ndarray, box: np.ndarray, symbols) -> sp.Matrix:
    """The series as a column of sympy polynomials (power basis in the scaled variables s_i, float coefficients).

    Terms below ``CHOP_RTOL`` of the largest coefficient are dropped; a polynomial of low degree (an exact
    solution) therefore comes out with few terms.

    Parameters
    ----------
    coeffs : ndarray (rows, deg + 1, ..., deg + 1)
        One series per row.
    box : ndarray (d, 2)
        The box of the series.
    symbols : sequence of Symbol
        The d variables, in the order of the box's rows.

    Returns
    -------
    sympy Matrix (rows, 1)
        Expanded in ``symbols`` up to degree ``EXPAND_MAX_DEGREE``, above it kept in the scaled variables.
    """
    d, degree = len(box), coeffs.shape[1] - 1
    scaled = _scaled_symbols(box, symbols)
    rows = []
    for power in _chopped(power_coefficients(coeffs)):
        expr = sp.Integer(0)
        for index in itertools.product(range(degree + 1), repeat=d):
            if power[index] != 0:
                expr += sp.Float(power[index]) * sp.Mul(*[s**k for s, k in zip(scaled, index)])
        # Kept in the scaled variables at high degree (expanding about 0 would lose digits); expanded and
        # chopped at low degree, so an exact polynomial solution reads as one (p = [xi, xi**2]).
        rows.append(_chop(sp.expand(expr)) if degree <= EXPAND_MAX_DEGREE else expr)
    return sp.Matrix(rows)


@dataclass(frozen=True)
class Series:
    """A matrix of tensor Chebyshev series on a box, kept numeric.

    Attributes
    ----------
    coeffs : ndarray, shape (rows, deg + 1, ..., deg + 1)
        One series per entry of the matrix, entries in row-major order (rows = shape[0] * shape[1]).
    box : ndarray, shape (d, 2)
        The box the series lives on (its variables are scaled to [-1, 1] there).
    shape : tuple of int
        The shape of the matrix.
    """

    coeffs: np.ndarray
    box: np.ndarray
    shape: tuple[int, int]

    def __post_init__(self):
        object.__setattr__(self, "coeffs", np.asarray(self.coeffs, dtype=float))
        object.__setattr__(self, "box", np.asarray(self.box, dtype=float).reshape(-1, 2))
        object.__setattr__(self, "shape", (int(self.shape[0]), int(self.shape[1])))
        if self.coeffs.shape[0] != self.shape[0] * self.shape[1] or self.coeffs.ndim != len(self.box) + 1:
            raise ValueError(f"coefficients of shape {self.coeffs.shape} do not fit a {self.shape} matrix on a {len(self.box)}-box")

    @classmethod
    def column(cls, coeffs: np.ndarray, box: np.ndarray) -> Series:
        """A column vector, one series per row of ``coeffs``."""
        return cls(coeffs, box, (np.shape(coeffs)[0], 1))

    @property
    def degree(self) -> int:
        """The degree per axis."""
        return self.coeffs.shape[1] - 1

    def at(self, z: np.ndarray) -> np.ndarray:
        """Values at the points z (d, N): shape ``shape + (N,)``."""
        z = np.asarray(z, dtype=float).reshape(len(self.box), -1)
        return evaluate(self.coeffs, self.box, z).reshape(self.shape + (z.shape[1],))

    def __call__(self, *arrays) -> np.ndarray:
        """Like a :func:`ashc_cli.problem.model.lambdify` function: one array per variable (broadcast), values of shape
        ``shape + broadcast shape``."""
        arrs = np.broadcast_arrays(*[np.asarray(a, dtype=float) for a in arrays])
        bshape = arrs[0].shape
        return self.at(np.stack([a.ravel() for a in arrs])).reshape(self.shape + bshape)

    def jacobian(self) -> Series:
        """d/dz of a column (n x 1): the n x d matrix of the derivatives along each axis."""
        if self.shape[1] != 1:
            raise ValueError("the Jacobian of a series is taken of a column")
        d = len(self.box)
        parts = np.stack([derivative(self.coeffs, self.box, axis) for axis in range(d)], axis=1)
        return Series(parts.reshape((self.shape[0] * d,) + self.coeffs.shape[1:]), self.box, (self.shape[0], d))

    def left(self, A: np.ndarray) -> Series:
        """The series of A S for a constant matrix A (k x r): e.g. kappa = C p for a linear output map."""
        A = np.asarray(A, dtype=float)
        c = self.coeffs.reshape(self.shape + (-1,))
        out = np.einsum("ij,jkl->ikl", A, c)
        return Series(out.reshape((A.shape[0] * self.shape[1],) + self.coeffs.shape[1:]), self.box, (A.shape[0], self.shape[1]))

    def right(self, B: np.ndarray) -> Series:
        """The series of S B for a constant matrix B (c x k): e.g. dp/dxi delta for a constant delta."""
        B = np.asarray(B, dtype=float)
        c = self.coeffs.reshape(self.shape + (-1,))
        out = np.einsum("ijl,jk->ikl", c, B)
        return Series(out.reshape((self.shape[0] * B.shape[1],) + self.coeffs.shape[1:]), self.box, (self.shape[0], B.shape[1]))

    def formula_at(self, z: np.ndarray) -> np.ndarray:
        """The values of :meth:`to_sympy`'s Horner formula at z (d, N), with its coefficients and its scheme.

        The series' values (:meth:`at`) and these differ by the round-off of the conversion to the power basis
        (whose coefficients can be far larger than the values), which is what a caller measures with it.

        Raises
        ------
        ValueError
            If the formula is not Horner's scheme (:attr:`horner`).
        """
        if not self.horner:
            raise ValueError("formula_at evaluates the Horner formula: one axis and a degree above EXPAND_MAX_DEGREE")
        z = np.asarray(z, dtype=float).reshape(len(self.box), -1)
        lo, hi = self.box[0]
        s = float(2.0 / (hi - lo)) * z[0] - float((lo + hi) / (hi - lo))
        power = _chopped(power_coefficients(self.coeffs))
        value = np.repeat(power[:, -1:], z.shape[1], axis=1)
        for k in range(self.degree - 1, -1, -1):
            value = power[:, k:k + 1] + s[None, :] * value
        return value.reshape(self.shape + (z.shape[1],))

    @property
    def horner(self) -> bool:
        """Whether the formula is Horner's scheme (one axis, degree above ``EXPAND_MAX_DEGREE``)."""
        return len(self.box) == 1 and self.degree > EXPAND_MAX_DEGREE

    def to_sympy(self, symbols) -> sp.Matrix:
        """The matrix of polynomials in ``symbols``, with float coefficients.

        One axis above ``EXPAND_MAX_DEGREE``: Horner's scheme in the scaled variable s (c_0 + s (c_1 + s (...))),
        linear in the degree to build, print and compile; otherwise :func:`to_sympy`'s forms.
        """
        if not self.horner:
            return to_sympy(self.coeffs, self.box, symbols).reshape(*self.shape)
        lo, hi = self.box[0]
        # s written as sympy writes (2 xi - (lo + hi)) / (hi - lo), with the same two coefficients as formula_at.
        s = sp.Float(float(2.0 / (hi - lo))) * symbols[0] - sp.Float(float((lo + hi) / (hi - lo)))
        entries = []
        for power in _chopped(power_coefficients(self.coeffs)):
            expr = sp.Float(power[-1]) if power[-1] != 0 else sp.S.Zero
            for c in power[-2::-1]:
                expr = sp.Add(sp.Float(c), sp.Mul(s, expr)) if c != 0 else sp.Mul(s, expr)
            entries.append(expr)
        return sp.Matrix(self.shape[0], self.shape[1], entries)


def _chop(expr: sp.Expr) -> sp.Expr:
    """Drop the terms of an expanded polynomial whose coefficient is round-off."""
    terms = sp.Add.make_args(expr)
    big = max((abs(float(t.as_coeff_Mul()[0])) for t in terms), default=0.0)
    return sp.Add(*[t for t in terms if abs(float(t.as_coeff_Mul()[0])) > CHOP_RTOL * 100 * big])
