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

from ashc_cli.errors import FitError

__all__ = ["nodes", "evaluate", "derivative", "fit", "to_sympy", "power_coefficients", "Series", "PiecewiseSeries", "fit_adaptive", "extreme_points",
           "PIECE_MAX_DEGREE", "MAX_PIECES"]

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
    d = len(box)
    count = int(round(z.shape[1] ** (1.0 / d)))
    if d > 1 and count ** d == z.shape[1] and np.array_equal(z, nodes(box, count)):
        # On the tensor grid of nodes the least-squares problem separates: (V_1 x ... x V_d)^+ = V_1^+ x ... x V_d^+,
        # one small pseudo-inverse per axis instead of a dense solve with (degree + 1)^d columns (at 65^2 nodes
        # and degree 40 that was minutes per degree).
        out = np.asarray(values, dtype=float).reshape((values.shape[0],) + (count,) * d)
        for axis in range(d):
            s = np.cos(np.pi * (np.arange(count) + 0.5) / count)[::-1]
            pinv = np.linalg.pinv(cheb.chebvander(s, degree))                    # (degree + 1, count)
            out = np.moveaxis(np.tensordot(pinv, out, axes=([1], [axis + 1])), 0, axis + 1)
        return out
    V = _vander(box, z, degree)
    c, *_ = np.linalg.lstsq(V, values.T, rcond=None)
    return c.T.reshape((values.shape[0],) + (degree + 1,) * d)


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
        # one Add of all the terms (adding them one by one re-sorted the sum each time: minutes for 2-D degree 20)
        expr = sp.Add(*[sp.Float(power[index]) * sp.Mul(*[s**k for s, k in zip(scaled, index)])
                        for index in itertools.product(range(degree + 1), repeat=d) if power[index] != 0])
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
        # C-contiguous always: numpy's matmul rounds by memory layout (2.4), and a series read back from an artefact
        # must evaluate bit for bit like the one fitted
        object.__setattr__(self, "coeffs", np.ascontiguousarray(self.coeffs, dtype=float))
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
        """The values of :meth:`to_sympy`'s formula at z (d, N), with its coefficients and its scheme.

        The series' values (:meth:`at`) and these differ by the round-off of the formula (for Horner's scheme, of
        the conversion to the power basis, whose coefficients can be far larger than the values), which is what a
        caller measures with it.

        Raises
        ------
        ValueError
            If the formula is not kept numeric (:attr:`kept_numeric`).
        """
        if not self.kept_numeric:
            raise ValueError("formula_at evaluates the formula of a series kept numeric: a degree above EXPAND_MAX_DEGREE")
        z = np.asarray(z, dtype=float).reshape(len(self.box), -1)
        if len(self.box) == 1:
            return _horner_values(self.coeffs, self.box[0], z[0]).reshape(self.shape + (z.shape[1],))
        return _cosine_values(self.coeffs, self.box, z).reshape(self.shape + (z.shape[1],))

    @property
    def kept_numeric(self) -> bool:
        """Whether the series is p itself (evaluated as a series; its formula written for readers only): a degree
        above ``EXPAND_MAX_DEGREE``.  The formula is Horner's scheme in the scaled variable for one axis, the
        cosine form sum c_k prod_i cos(k_i acos(s_i)) for several (:func:`_cosine_exprs`)."""
        return self.degree > EXPAND_MAX_DEGREE

    def to_sympy(self, symbols) -> sp.Matrix:
        """The matrix of the series' formulas in ``symbols``, with float coefficients.

        Kept numeric (:attr:`kept_numeric`): Horner's scheme in the scaled variable s for one axis (c_0 + s (c_1 +
        s (...))), linear in the degree to build, print and compile; the cosine form for several axes, whose size
        is the number of coefficients and whose round-off stays at that of the series (a power basis in two
        variables at degree 36 had coefficients near 3e10 and lost 1e-2 of p).  Otherwise :func:`to_sympy`'s
        expanded forms.
        """
        if not self.kept_numeric:
            return to_sympy(self.coeffs, self.box, symbols).reshape(*self.shape)
        if len(self.box) == 1:
            return sp.Matrix(self.shape[0], self.shape[1], _horner_exprs(self.coeffs, self.box[0], symbols[0]))
        return sp.Matrix(self.shape[0], self.shape[1], _cosine_exprs(self.coeffs, self.box, symbols))

    def abs_bound(self) -> float:
        """A proved bound of max |entry| over the box: the sum of |coefficients| (|T_k| <= 1 on [-1, 1]), rounded up
        for the float sum (relative error below (count) eps for count non-negative terms)."""
        flat = np.abs(self.coeffs).reshape(len(self.coeffs), -1)
        return float(flat.sum(axis=1).max() * (1.0 + 2.0 * flat.shape[1] * np.finfo(float).eps))

    def range_bound(self) -> np.ndarray:
        """A proved enclosure of each entry over the box, (rows, 2): the constant coefficient -/+ the sum of the others'
        |coefficients| (|T_k| <= 1), each end rounded outward past the float error of the sum."""
        flat = self.coeffs.reshape(len(self.coeffs), -1)
        rest = np.abs(flat[:, 1:]).sum(axis=1) * (1.0 + 2.0 * flat.shape[1] * np.finfo(float).eps)
        return np.nextafter(np.c_[flat[:, 0] - rest, flat[:, 0] + rest], np.c_[np.full(len(flat), -np.inf), np.full(len(flat), np.inf)])

    def is_constant(self) -> bool:
        """Whether every entry is constant: of degree 0 in its chopped power basis, as its formula reads (dp/dxi
        constant: p affine)."""
        return _power_is_constant(self.coeffs)


def _power_is_constant(coeffs: np.ndarray) -> bool:
    """Whether each row's power-basis series has every non-constant term below ``CHOP_RTOL`` of its largest."""
    power = np.abs(power_coefficients(coeffs)).reshape(len(coeffs), -1)   # column 0: the constant term
    return bool(np.all(power[:, 1:].max(axis=1, initial=0.0) <= CHOP_RTOL * power.max(axis=1)))


def _scaled_one(lo: float, hi: float) -> tuple[float, float]:
    """(a, b) with s = a z - b mapping [lo, hi] to [-1, 1]: the two coefficients the formula and its values share."""
    return float(2.0 / (hi - lo)), float((lo + hi) / (hi - lo))


def _horner_values(coeffs: np.ndarray, interval, z: np.ndarray) -> np.ndarray:
    """Horner's scheme on the chopped power coefficients of one-axis series (rows, deg + 1) at the points z (N,):
    the numbers the formula of :func:`_horner_exprs` gives, shape (rows, N)."""
    a, b = _scaled_one(*interval)
    s = a * np.asarray(z, dtype=float) - b
    power = _chopped(power_coefficients(coeffs))
    value = np.repeat(power[:, -1:], s.shape[0], axis=1)
    for k in range(power.shape[1] - 2, -1, -1):
        value = power[:, k:k + 1] + s[None, :] * value
    return value


def _horner_exprs(coeffs: np.ndarray, interval, symbol) -> list:
    """Each row of one-axis series (rows, deg + 1) as Horner's scheme in the scaled variable s = a z - b,
    c_0 + s (c_1 + s (...)): linear in the degree to build, print and compile."""
    a, b = _scaled_one(*interval)
    # s written as sympy writes (2 z - (lo + hi)) / (hi - lo), with the same two coefficients as _horner_values.
    s = sp.Float(a) * symbol - sp.Float(b)
    entries = []
    for power in _chopped(power_coefficients(coeffs)):
        expr = sp.Float(power[-1]) if power[-1] != 0 else sp.S.Zero
        for c in power[-2::-1]:
            expr = sp.Add(sp.Float(c), sp.Mul(s, expr)) if c != 0 else sp.Mul(s, expr)
        entries.append(expr)
    return entries


#: Coefficients of the cosine form at most this fraction of a row's largest are left out (their sum is far below
#: the series' own error: a 2-D series of degree 36 has 1369 terms).
COSINE_CHOP_RTOL = 1e-17


def _cosine_terms(coeffs: np.ndarray) -> list[list[tuple[tuple[int, ...], float]]]:
    """Per row, the (multi-index, coefficient) pairs the cosine form keeps (``COSINE_CHOP_RTOL``)."""
    rows = []
    for row in np.asarray(coeffs, dtype=float):
        big = float(np.abs(row).max(initial=0.0))
        rows.append([(index, float(row[index])) for index in itertools.product(*[range(k) for k in row.shape])
                     if row[index] != 0 and abs(row[index]) > COSINE_CHOP_RTOL * big])
    return rows


def _cosine_values(coeffs: np.ndarray, box: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The numbers the formula of :func:`_cosine_exprs` gives at the points z (d, N), shape (rows, N)."""
    angles = []
    for (lo, hi), zi in zip(np.asarray(box, dtype=float), np.asarray(z, dtype=float)):
        a, b = _scaled_one(lo, hi)
        angles.append(np.arccos(np.clip(a * zi - b, -1.0, 1.0)))
    degree = coeffs.shape[1] - 1
    cosines = [np.cos(np.arange(degree + 1)[:, None] * t[None, :]) for t in angles]   # per axis (deg + 1, N)
    out = np.zeros((len(coeffs), z.shape[1]))
    for r, terms in enumerate(_cosine_terms(coeffs)):
        for index, c in terms:
            out[r] += c * np.prod([cosines[axis][k] for axis, k in enumerate(index)], axis=0)
    return out


def _cosine_exprs(coeffs: np.ndarray, box: np.ndarray, symbols) -> list:
    """Each row of a tensor series (rows, deg + 1, ..., deg + 1) in the cosine form sum_k c_k prod_i cos(k_i t_i),
    t_i = acos(s_i) with s_i = a_i z_i - b_i clipped to [-1, 1] (T_k(s) = cos(k acos s) there).

    Evaluated term by term like the series (no power basis, so no digits lost at high degree), in ball arithmetic
    each term is bounded by |c_k|, and numpy and numba print acos, cos, Min and Max.  Nested by axis,
    sum_k1 cos(k1 t_1) (sum_k2 cos(k2 t_2) (...)), so that the printed sums stay as short as one degree (Python's
    compiler gave up on one flat sum of thousands of terms).  Outside the box the series is continued as its value
    at the nearest face (the box is where p is fitted and claimed).  Not for differentiating (the clip has no
    derivative on the faces): the series' :meth:`Series.jacobian` has its own formula.
    """
    angles = []
    for (lo, hi), sym in zip(np.asarray(box, dtype=float), symbols):
        a, b = _scaled_one(lo, hi)
        angles.append(sp.acos(sp.Min(sp.S.One, sp.Max(-sp.S.One, sp.Float(a) * sym - sp.Float(b)))))

    def nested(block: np.ndarray, axis: int, keep) -> sp.Expr:
        if block.ndim == 0:
            return sp.Float(float(block)) if keep(block) else sp.S.Zero
        parts = []
        for k in range(block.shape[0]):
            inner = nested(block[k], axis + 1, keep)
            if inner != 0:
                parts.append(inner if k == 0 else sp.Mul(sp.cos(k * angles[axis]), inner))
        return sp.Add(*parts)

    rows = []
    for row in np.asarray(coeffs, dtype=float):
        big = float(np.abs(row).max(initial=0.0))
        rows.append(nested(row, 0, lambda c, big=big: c != 0 and abs(c) > COSINE_CHOP_RTOL * big))
    return rows


def _chop(expr: sp.Expr) -> sp.Expr:
    """Drop the terms of an expanded polynomial whose coefficient is round-off."""
    terms = sp.Add.make_args(expr)
    big = max((abs(float(t.as_coeff_Mul()[0])) for t in terms), default=0.0)
    return sp.Add(*[t for t in terms if abs(float(t.as_coeff_Mul()[0])) > CHOP_RTOL * 100 * big])


#: One Chebyshev piece's degree is raised at most to this before its interval is split in two: up to here a
#: series that meets a tolerance of 1e-9 converges fast enough that its Horner formula (power coefficients in
#: the piece's own scaled variable) keeps its digits; at degree 80 on one wide interval they reached 1e13.
PIECE_MAX_DEGREE = 32
#: At most this many pieces on one interval; an interval is not split below this fraction of the whole.
MAX_PIECES = 64
MIN_PIECE_FRACTION = 2.0 ** -12


@dataclass(frozen=True)
class PiecewiseSeries:
    """A matrix of one-variable Chebyshev series on consecutive intervals (one :class:`Series` per piece),
    kept numeric like a :class:`Series`, with the same methods.

    Its formula (:meth:`to_sympy`) is a sympy ``Piecewise`` of each piece's Horner formula in its own scaled
    variable, nested as a balanced tree of comparisons; the first and last pieces extend beyond the ends.

    Attributes
    ----------
    pieces : tuple of Series
        One-axis series of one shape, on intervals that meet end to end, in increasing order.
    """

    pieces: tuple

    def __post_init__(self):
        pieces = tuple(self.pieces)
        object.__setattr__(self, "pieces", pieces)
        if not pieces or any(len(s.box) != 1 or s.shape != pieces[0].shape for s in pieces):
            raise ValueError("the pieces must be one-axis series of one shape")
        ends = np.array([s.box[0] for s in pieces])
        if np.any(ends[1:, 0] != ends[:-1, 1]) or np.any(ends[:, 1] <= ends[:, 0]):
            raise ValueError("the pieces' intervals must meet end to end, in increasing order")

    @classmethod
    def from_arrays(cls, coeffs: np.ndarray, breaks: np.ndarray, shape) -> PiecewiseSeries:
        """The series stored as arrays: coeffs (pieces, rows, deg + 1), breaks (pieces + 1,)."""
        breaks = np.asarray(breaks, dtype=float)
        return cls(tuple(Series(c, [[lo, hi]], shape) for c, lo, hi in zip(np.asarray(coeffs, dtype=float), breaks[:-1], breaks[1:])))

    @property
    def breaks(self) -> np.ndarray:
        """The ends of the pieces, increasing: shape (pieces + 1,)."""
        return np.r_[[s.box[0, 0] for s in self.pieces], self.pieces[-1].box[0, 1]]

    @property
    def coeffs(self) -> np.ndarray:
        """The pieces' coefficients, padded to one degree: shape (pieces, rows, deg + 1)."""
        out = np.zeros((len(self.pieces), self.pieces[0].coeffs.shape[0], self.degree + 1))
        for k, s in enumerate(self.pieces):
            out[k, :, : s.degree + 1] = s.coeffs
        return out

    @property
    def shape(self) -> tuple[int, int]:
        return self.pieces[0].shape

    @property
    def box(self) -> np.ndarray:
        """The whole interval, shape (1, 2)."""
        return np.array([[self.breaks[0], self.breaks[-1]]])

    @property
    def degree(self) -> int:
        """The highest degree of a piece."""
        return max(s.degree for s in self.pieces)

    @property
    def kept_numeric(self) -> bool:
        """Always: the formula is Horner's scheme, piece by piece."""
        return True

    def _piece_of(self, z: np.ndarray) -> np.ndarray:
        """The index of the piece each point (N,) falls in (the end pieces take what lies beyond them)."""
        return np.clip(np.searchsorted(self.breaks[1:-1], z, side="right"), 0, len(self.pieces) - 1)

    def _by_piece(self, z: np.ndarray, values) -> np.ndarray:
        z = np.asarray(z, dtype=float).reshape(1, -1)
        out = np.empty(self.shape + (z.shape[1],))
        which = self._piece_of(z[0])
        for k, s in enumerate(self.pieces):
            mask = which == k
            if mask.any():
                out[..., mask] = values(s, z[:, mask])
        return out

    def at(self, z: np.ndarray) -> np.ndarray:
        """Values at the points z (1, N): shape ``shape + (N,)``."""
        return self._by_piece(z, lambda s, zk: s.at(zk))

    def __call__(self, *arrays) -> np.ndarray:
        """As :meth:`Series.__call__`."""
        (arr,) = arrays
        arr = np.asarray(arr, dtype=float)
        return self.at(arr.reshape(1, -1)).reshape(self.shape + arr.shape)

    def formula_at(self, z: np.ndarray) -> np.ndarray:
        """The values of :meth:`to_sympy`'s formula at z (1, N), piece by piece with its coefficients and scheme."""
        return self._by_piece(z, lambda s, zk: _horner_values(s.coeffs, s.box[0], zk[0]).reshape(self.shape + (zk.shape[1],)))

    def jacobian(self) -> PiecewiseSeries:
        """d/dz of a column, piece by piece."""
        return PiecewiseSeries(tuple(s.jacobian() for s in self.pieces))

    def left(self, A: np.ndarray) -> PiecewiseSeries:
        """A S for a constant matrix A, piece by piece."""
        return PiecewiseSeries(tuple(s.left(A) for s in self.pieces))

    def right(self, B: np.ndarray) -> PiecewiseSeries:
        """S B for a constant matrix B, piece by piece."""
        return PiecewiseSeries(tuple(s.right(B) for s in self.pieces))

    def is_constant(self) -> bool:
        """Whether every piece is constant and all pieces agree (to ``CHOP_RTOL`` of the largest value)."""
        values = np.array([s.coeffs[:, 0] for s in self.pieces])
        return all(s.is_constant() for s in self.pieces) and bool(np.ptp(values, axis=0).max() <= CHOP_RTOL * max(np.abs(values).max(), 1e-300))

    def jumps(self) -> tuple[np.ndarray, np.ndarray]:
        """How far neighbouring pieces disagree at each inner break: max over entries of |left - right| for the
        values and for the first derivatives, each of shape (pieces - 1,)."""
        inner = self.breaks[1:-1]
        left = [s.at(np.array([[b]]))[..., 0] for s, b in zip(self.pieces[:-1], inner)]
        right = [s.at(np.array([[b]]))[..., 0] for s, b in zip(self.pieces[1:], inner)]
        d = self.jacobian()
        dleft = [s.at(np.array([[b]]))[..., 0] for s, b in zip(d.pieces[:-1], inner)]
        dright = [s.at(np.array([[b]]))[..., 0] for s, b in zip(d.pieces[1:], inner)]
        value = np.array([np.abs(a - b).max() for a, b in zip(left, right)])
        slope = np.array([np.abs(a - b).max() for a, b in zip(dleft, dright)])
        return value, slope

    def to_sympy(self, symbols) -> sp.Matrix:
        """The matrix as sympy ``Piecewise`` entries: each piece's Horner formula, chosen by comparisons of the
        variable with the breaks (a balanced tree: depth log2 of the number of pieces)."""
        z = symbols[0]
        forms = [_horner_exprs(s.coeffs, s.box[0], z) for s in self.pieces]
        breaks = self.breaks

        def tree(lo: int, hi: int, row: int):
            if hi - lo == 1:
                return forms[lo][row]
            mid = (lo + hi) // 2
            return sp.Piecewise((tree(lo, mid, row), z < sp.Float(float(breaks[mid]))), (tree(mid, hi, row), True))

        rows = self.shape[0] * self.shape[1]
        return sp.Matrix(self.shape[0], self.shape[1], [tree(0, len(self.pieces), r) for r in range(rows)])


def _through_ends(coeffs: np.ndarray, at_lo: np.ndarray | None, at_hi: np.ndarray | None) -> np.ndarray:
    """One-axis series (rows, deg + 1) changed in their constant and linear terms to take the values at_lo at
    s = -1 and at_hi at s = 1 (an end given as None is left where it is): a fit moved by its error at the ends
    it shares with a neighbour, so that neighbouring pieces meet (T_k(1) = 1, T_k(-1) = (-1)^k)."""
    out = np.array(coeffs, dtype=float)
    if at_lo is None and at_hi is None:
        return out
    if out.shape[1] < 2:
        out = np.pad(out, ((0, 0), (0, 1)))
    k = np.arange(out.shape[1])
    miss_hi = 0.0 if at_hi is None else at_hi - out.sum(axis=1)
    miss_lo = 0.0 if at_lo is None else at_lo - out @ (-1.0) ** k
    out[:, 0] += 0.5 * (miss_hi + miss_lo)
    out[:, 1] += 0.5 * (miss_hi - miss_lo)
    return out


def extreme_points(box: np.ndarray, count: int) -> np.ndarray:
    """The Chebyshev points of the second kind (the extremes of T_(count-1), ends included) of a one-axis box.

    Parameters
    ----------
    box : ndarray (1, 2)
        [[lo, hi]].
    count : int
        How many points (at least 2).

    Returns
    -------
    ndarray (1, count)
        Ascending, with lo and hi exactly at the ends.
    """
    lo, hi = (float(v) for v in np.asarray(box, dtype=float).reshape(2))
    s = np.cos(np.pi * np.arange(count) / (count - 1))[::-1]
    z = (lo + hi) / 2 + (hi - lo) / 2 * s
    z[0], z[-1] = lo, hi
    return z[None, :]


def fit_adaptive(sample, interval, accept, max_degree: int = PIECE_MAX_DEGREE, max_pieces: int = MAX_PIECES, breaks=()):
    """A one-variable Chebyshev interpolant on ``interval``, split into pieces where one series is not enough.

    On each interval the function is sampled at ``max_degree + 1`` Chebyshev points of the second kind (the
    ends included) and fitted by least squares, then moved to pass through the sampled ends (so neighbouring
    pieces agree at their common end to the accuracy of ``sample``); the lowest degree that passes ``accept``
    is kept.  An interval where no degree
    passes is split in two, until ``max_pieces`` pieces or a piece narrower than ``MIN_PIECE_FRACTION`` of the
    whole.

    Parameters
    ----------
    sample : callable
        ``sample(z)`` for points z (1, N) returns the values (rows, N).
    interval : sequence of two floats
        [lo, hi].
    accept : callable
        ``accept(series)`` for a :class:`Series` on one interval returns (passed, measure): whether it is good
        enough there, and the number judged (smaller is better).
    max_degree : int
        The highest degree of a piece.
    max_pieces : int
        The most pieces.
    breaks : sequence of float
        Points inside ``interval`` where pieces must meet from the start (where the function is known to be
        only piecewise smooth: kappa^-1 of a piecewise p).

    Returns
    -------
    Series or PiecewiseSeries
        A single (column) series when one interval was enough.

    Raises
    ------
    ashc_cli.errors.FitError
        With the interval where the fit failed and the best measure reached there.
    """
    lo, hi = float(interval[0]), float(interval[1])
    min_width = (hi - lo) * MIN_PIECE_FRACTION
    ends = np.unique(np.r_[lo, [float(b) for b in breaks if lo < float(b) < hi], hi])
    todo, done = list(zip(ends[:-1], ends[1:])), []
    while todo:
        a, b = todo.pop(0)
        box = np.array([[a, b]])
        z = extreme_points(box, max_degree + 1)
        values = sample(z)
        best = np.inf
        for degree in range(1, max_degree + 1):
            # Least squares on the max_degree + 1 points (nearly the best fit of this degree), through the ends.
            piece = Series.column(_through_ends(fit(values, box, z, degree), values[:, 0] if a > lo else None, values[:, -1] if b < hi else None), box)
            passed, measure = accept(piece)
            best = min(best, measure)
            if passed:
                done.append(piece)
                break
        else:
            if len(done) + len(todo) + 2 > max_pieces:
                raise FitError((a, b), best, f"{max_pieces} pieces of degree <= {max_degree} are not enough")
            if (b - a) / 2 < min_width:
                raise FitError((a, b), best, f"the pieces near [{a:.6g}, {b:.6g}] are already {MIN_PIECE_FRACTION:g} of the interval wide")
            mid = 0.5 * (a + b)
            todo[:0] = [(a, mid), (mid, b)]
    done.sort(key=lambda s: s.box[0, 0])
    return done[0] if len(done) == 1 else PiecewiseSeries(tuple(done))
