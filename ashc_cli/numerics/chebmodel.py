"""Chebyshev models: a polynomial in Chebyshev form plus a proved remainder, for bounds that need cancellation.

A Chebyshev model of a function g on t in [-1, 1] is a pair (c, r) with |g(t) - sum_k c_k T_k(t)| <= r for every t
in [-1, 1] (Brisebarre and Joldes, "Chebyshev interpolation polynomial-based tools for rigorous computing", 2010).
Arithmetic on models works on the coefficients, so a residual such as f_bar(p(xi)) + g(p(xi)) l(xi), whose terms
are of size 1e3 and cancel to 1e-9, is bounded by the sum of its residual coefficients' magnitudes plus a remainder
of about the unit round-off times the terms' size: an interval evaluation over V would see the terms' whole range.

Rigour
------
The coefficients are doubles and every operation adds its rounding error to the remainder:

* a sum of two models: at most u |c_k| per coefficient (u = 2^-53);
* a product: numpy's ``chebmul`` convolves the z-series of both factors (exact halvings) and doubles back, so each
  coefficient is a float sum of at most m = len(a) + len(b) products; its error is at most gamma_m = m u / (1 - m u)
  times the sum of those products' magnitudes, in total 2 gamma_m S(a) S(b) with S the sum of |coefficients|;
  the remainders multiply out as S(a) r_b + S(b) r_a + r_a r_b;
* a model is cut back to :data:`MAX_DEGREE` with the cut coefficients' magnitudes added to r (|T_k| <= 1);
* an elementary function f of a model Q: Taylor's expansion at the centre z0 of Q's range, with the coefficients
  enclosed by arb (``arb_series``) at z0, and the Lagrange remainder bounded by the (D+1)-th Taylor coefficient
  enclosed over the whole range (the same series evaluated at the ball of the range) times R^(D+1), R the range's
  half width; Horner's scheme in model arithmetic then composes the polynomial with Q - z0 (its remainder included).

Every bound that is itself computed in floats (S, the error terms, r) is rounded up by :func:`_up` (a relative
1e-13 covers the float error of a sum of up to 10^3 non-negative terms) plus a tiny absolute amount for underflow.
A function that is not defined on a model's range (log of a range reaching 0, a division by a range holding 0), or
whose Taylor remainder is not small there, raises :class:`TooWide` (a narrower piece may do); Abs, Min, Max and
Piecewise raise :class:`UnsupportedExpression`: their kinks have no Taylor expansion.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import numpy.polynomial.chebyshev as cheb
import sympy as sp
from flint import arb, arb_series, ctx

from ashc_cli.errors import UnsupportedExpression
from ashc_cli.numerics._infsup import number_interval, sympy_number

__all__ = ["ChebModel", "TooWide", "MAX_DEGREE", "evaluate", "reexpand", "bound_on_pieces"]

#: The degree models are cut back to (the cut coefficients go into the remainder).
MAX_DEGREE = 96
#: Taylor degrees tried for an elementary function of a model, until the Lagrange remainder is below
#: TAYLOR_RTOL of the function's size on the range.
TAYLOR_DEGREES = (12, 24, 40, 64)
TAYLOR_RTOL = 1e-17
#: A remainder above this fraction of the function's size on the range asks for a narrower range (:class:`TooWide`).
TAYLOR_ACCEPT = 1e-12
_U = 2.0**-53
_TINY = 1e-300


class TooWide(UnsupportedExpression):
    """An elementary function whose Taylor remainder is not small on its argument's range: split the interval."""


def _up(x: float, terms: int = 1) -> float:
    """x (a float sum of ``terms`` non-negative numbers, or a product of a few) rounded up past its float error."""
    return float(x) * (1.0 + 1e-13 + 4.0 * terms * _U) + _TINY


def _gamma(m: int) -> float:
    return m * _U / (1.0 - m * _U)


def _upper(ball: arb) -> float:
    """A double >= every number of the ball (inf for a non-finite ball)."""
    if not ball.is_finite():
        return np.inf
    return _ceil(ball.upper())


def _ceil(x: arb) -> float:
    """The least double >= the exact arb number x (rounded up: float() rounds to nearest)."""
    f = float(x.mid())
    return f if arb(f) >= x else float(np.nextafter(f, np.inf))


class ChebModel:
    """A Chebyshev model (c, r) on t in [-1, 1]: |g(t) - sum_k c_k T_k(t)| <= r.

    Parameters
    ----------
    c : array_like (K,)
        Chebyshev coefficients (doubles, taken as exact).
    r : float
        The remainder (>= 0).
    """

    __slots__ = ("c", "r")

    def __init__(self, c, r: float = 0.0):
        c = np.atleast_1d(np.asarray(c, dtype=float))
        self.c = c if len(c) else np.zeros(1)
        self.r = float(r)
        if not (self.r >= 0.0):
            raise ValueError(f"a remainder must be >= 0, not {r}")

    @classmethod
    def interval(cls, lo: arb, hi: arb) -> ChebModel:
        """The constant model of every number in [lo, hi] (exact arb ends)."""
        mid = float(((lo + hi) / 2).mid())
        return cls([mid], max(_ceil(hi - mid), _ceil(mid - lo), 0.0))

    @classmethod
    def affine(cls, a: float, b: float) -> ChebModel:
        """The model of z = a + b t with a, b exact doubles (the map of [-1, 1] onto an interval of centre a)."""
        return cls([a, b], 0.0)

    @property
    def degree(self) -> int:
        return len(self.c) - 1

    def size(self) -> float:
        """S = sum |c_k|, rounded up: a bound of the polynomial part on [-1, 1]."""
        return _up(np.abs(self.c).sum(), len(self.c))

    def bound(self) -> float:
        """A proved bound of |g(t)| for t in [-1, 1]: S + r, rounded up."""
        return _up(self.size() + self.r, 2)

    def range(self) -> tuple[float, float]:
        """A proved enclosure [lo, hi] of g on [-1, 1]: c_0 -/+ (the other coefficients' magnitudes + r)."""
        rest = _up(_up(np.abs(self.c[1:]).sum(), len(self.c)) + self.r, 2)
        return float(np.nextafter(self.c[0] - rest, -np.inf)), float(np.nextafter(self.c[0] + rest, np.inf))

    def _cut(self, c: np.ndarray, r: float) -> ChebModel:
        if len(c) > MAX_DEGREE + 1:
            tail = np.abs(c[MAX_DEGREE + 1:]).sum()
            c, r = c[: MAX_DEGREE + 1], _up(r + _up(tail, len(c)), 2)
        return ChebModel(c, r)

    def __neg__(self) -> ChebModel:
        return ChebModel(-self.c, self.r)

    def __add__(self, other) -> ChebModel:
        other = _model(other)
        k = max(len(self.c), len(other.c))
        c = np.zeros(k)
        c[: len(self.c)] += self.c
        c[: len(other.c)] += other.c
        err = _U * np.abs(c).sum() / (1.0 - _U)
        return ChebModel(c, _up(self.r + other.r + err, 3 + len(c)))

    __radd__ = __add__

    def __sub__(self, other) -> ChebModel:
        return self + (-_model(other))

    def __rsub__(self, other) -> ChebModel:
        return _model(other) + (-self)

    def __mul__(self, other) -> ChebModel:
        other = _model(other)
        if len(other.c) == 1 and other.r == 0.0:          # a double: one rounding per coefficient
            c = self.c * other.c[0]
            err = _U * np.abs(c).sum() / (1.0 - _U)
            return ChebModel(c, _up(self.r * abs(other.c[0]) + err, 2 + len(c)))
        sa, sb = self.size(), other.size()
        c = cheb.chebmul(self.c, other.c)
        err = 2.0 * _gamma(len(self.c) + len(other.c) + 1) * sa * sb
        r = _up(sa * other.r + sb * self.r + self.r * other.r + err, 4)
        return self._cut(c, r)

    __rmul__ = __mul__

    def powi(self, n: int) -> ChebModel:
        """g^n for an integer n >= 0 (binary powering); negative n through :meth:`unary` ``inv``."""
        if n < 0:
            return self.unary("inv").powi(-n)
        out, base = ChebModel([1.0]), self
        while n:
            if n & 1:
                out = out * base
            n >>= 1
            if n:
                base = base * base
        return out

    def unary(self, name: str) -> ChebModel:
        """f(g) for an elementary f (``exp``, ``log``, ``sin``, ``cos``, ``tan``, ``atan``, ``tanh``, ``sinh``, ``cosh``,
        ``sqrt``, ``inv``), by Taylor's expansion at the centre of g's range with a proved Lagrange remainder."""
        lo, hi = self.range()
        z0 = float(self.c[0])
        R = max(_ceil(arb(hi) - z0), _ceil(z0 - arb(lo)), 0.0)
        whole = arb(lo).union(arb(hi))
        scale = _taylor(name, whole, 0)[0]
        if not scale.is_finite():
            raise TooWide(sp.Symbol(name), f"{name} is not defined or not bounded on the range [{lo:.6g}, {hi:.6g}]")
        size = _upper(abs(scale))
        for D in TAYLOR_DEGREES:
            tail = _taylor(name, whole, D + 1)[D + 1]
            lagrange = _upper(abs(tail)) * _up(R ** (D + 1), D + 1) if R > 0 else 0.0
            if lagrange <= TAYLOR_RTOL * max(size, 1e-300) or D == TAYLOR_DEGREES[-1]:
                break
        if not lagrange <= TAYLOR_ACCEPT * max(size, 1e-300):
            raise TooWide(sp.Symbol(name), f"the Taylor remainder of {name} on [{lo:.6g}, {hi:.6g}] is {lagrange:.3g}: the range is too wide")
        coeffs = _taylor(name, arb(z0), D)
        mids, radius = [], 0.0
        for k in range(D + 1):
            a = coeffs[k]
            m = float(a.mid())
            mids.append(m)
            radius = _up(radius + _upper(abs(a - m)) * _up(R ** k, k + 1), 2)
        shifted = ChebModel(np.r_[0.0, self.c[1:]], self.r)     # g - z0: c_0 - z0 is exactly 0
        acc = ChebModel([mids[D]])
        for k in range(D - 1, -1, -1):
            acc = acc * shifted + mids[k]
        return ChebModel(acc.c, _up(acc.r + radius + lagrange, 3))


def _tanh(s: arb_series) -> arb_series:
    return 1 - 2 / ((2 * s).exp() + 1)


#: f of a power series in arb: the Taylor coefficients of f at the series' constant term.
_SERIES = {"exp": arb_series.exp, "log": arb_series.log, "sin": arb_series.sin, "cos": arb_series.cos, "tan": arb_series.tan,
           "atan": arb_series.atan, "sqrt": arb_series.sqrt, "inv": lambda s: 1 / s, "tanh": _tanh,
           "sinh": lambda s: (s.exp() - 1 / s.exp()) / 2, "cosh": lambda s: (s.exp() + 1 / s.exp()) / 2}


def _series_all(name: str, s: arb_series) -> arb_series:
    """f of a power series in arb (:data:`_SERIES`)."""
    if name not in _SERIES:
        raise UnsupportedExpression(sp.Symbol(name), f"{name} has no Chebyshev model")
    return _SERIES[name](s)


def _taylor(name: str, at: arb, order: int) -> list[arb]:
    """The Taylor coefficients 0..order of f at the ball ``at`` (each encloses the coefficient at every point of it)."""
    cap = ctx.cap
    try:
        ctx.cap = order + 2              # python-flint truncates every series to ctx.cap terms
        coeffs = list(_series_all(name, arb_series([at, 1], prec=order + 1)).coeffs())
    except (ValueError, ZeroDivisionError):        # arb refuses a series division by a ball that holds 0
        raise TooWide(sp.Symbol(name), f"{name} is not defined on the ball {at.str(5)}") from None
    finally:
        ctx.cap = cap
    return coeffs + [arb(0)] * (order + 1 - len(coeffs))


def _model(x) -> ChebModel:
    if isinstance(x, ChebModel):
        return x
    return ChebModel([float(x)])          # a double (exact): callers pass enclosures of other numbers as models


_UNARY = {sp.exp: "exp", sp.log: "log", sp.sin: "sin", sp.cos: "cos", sp.tan: "tan", sp.atan: "atan", sp.tanh: "tanh",
          sp.sinh: "sinh", sp.cosh: "cosh"}


def evaluate(expr: sp.Expr, env: Mapping[sp.Symbol, ChebModel], values: Mapping[sp.Symbol, float], memo: dict | None = None) -> ChebModel:
    """The Chebyshev model of a sympy expression whose symbols are models (``env``) or parameter values (``values``).

    Parameters
    ----------
    expr : sympy Expr
    env : mapping of Symbol to ChebModel
        The variables, as models on t in [-1, 1].
    values : mapping of Symbol to float
        Parameters, each the double itself (as the ball-arithmetic proofs take them).
    memo : dict, optional
        Shared between calls, so that common subexpressions are modelled once.

    Returns
    -------
    ChebModel

    Raises
    ------
    UnsupportedExpression
        For Abs, Min, Max, Piecewise and other functions without a Taylor expansion, and for a function not defined
        on its argument's range.
    """
    memo = {} if memo is None else memo
    if expr in memo:
        return memo[expr]
    if isinstance(expr, sp.Symbol):
        if expr in env:
            out = env[expr]
        elif expr in values:
            out = ChebModel.interval(*number_interval(values[expr], expr))
        else:
            raise UnsupportedExpression(expr, "a symbol that is neither a variable nor a parameter")
    elif isinstance(expr, (sp.Number, sp.NumberSymbol)):
        out = ChebModel.interval(*sympy_number(expr))
    elif isinstance(expr, sp.Add):
        out = ChebModel([0.0])
        for a in expr.args:
            out = out + evaluate(a, env, values, memo)
    elif isinstance(expr, sp.Mul):
        out = ChebModel([1.0])
        for a in expr.args:
            out = out * evaluate(a, env, values, memo)
    elif isinstance(expr, sp.Pow):
        out = _power(expr, env, values, memo)
    elif isinstance(expr, sp.Piecewise):
        out = _piecewise(expr.args, env, values, memo)
    elif expr.func in _UNARY and len(expr.args) == 1:
        out = evaluate(expr.args[0], env, values, memo).unary(_UNARY[expr.func])
    else:
        raise UnsupportedExpression(expr, f"{expr.func.__name__} has no Chebyshev model (a kink or a branch)")
    memo[expr] = out
    return out


_RELATIONS = {sp.StrictLessThan: (True, True), sp.LessThan: (True, False), sp.StrictGreaterThan: (False, True), sp.GreaterThan: (False, False)}


def _piecewise(branches: tuple, env, values, memo) -> ChebModel:
    """A Piecewise whose conditions are decided on the models' ranges; where one is not (a piece straddles a break),
    the hull of the two sides: the mean of both models with half their difference added to the remainder."""
    (branch, cond), rest = branches[0], branches[1:]
    if cond is sp.true or not rest:
        if cond is not sp.true and not rest:
            raise UnsupportedExpression(sp.Piecewise(*branches), "a Piecewise without a last branch for every other case")
        return evaluate(branch, env, values, memo)
    if type(cond) not in _RELATIONS:
        raise UnsupportedExpression(cond, "a condition other than <, <=, >, >=")
    less, strict = _RELATIONS[type(cond)]
    lo, hi = evaluate(cond.lhs - cond.rhs, env, values, memo).range()
    true = (hi < 0 if strict else hi <= 0) if less else (lo > 0 if strict else lo >= 0)
    false = (lo >= 0 if strict else lo > 0) if less else (hi <= 0 if strict else hi < 0)
    if true:
        return evaluate(branch, env, values, memo)
    if false:
        return _piecewise(rest, env, values, memo)
    a, b = evaluate(branch, env, values, memo), _piecewise(rest, env, values, memo)
    mid, half = (a + b) * 0.5, (a - b) * 0.5
    return ChebModel(mid.c, _up(mid.r + half.bound(), 2))


def _power(expr: sp.Pow, env, values, memo) -> ChebModel:
    base, ex = expr.args
    if ex.is_Integer:
        return evaluate(base, env, values, memo).powi(int(ex))
    b = evaluate(base, env, values, memo)
    if ex == sp.Rational(1, 2):
        return b.unary("sqrt")
    if ex == sp.Rational(-1, 2):
        return b.unary("sqrt").unary("inv")
    return (b.unary("log") * evaluate(ex, env, values, memo)).unary("exp")


def _restriction(K: int, centre: float, half: float) -> tuple[np.ndarray, np.ndarray]:
    """R with T_k(centre + half tau) = sum_j R[k, j] T_j(tau), k, j < K: midpoints and proved radii (arb, 128 bits)."""
    prec = ctx.prec
    try:
        ctx.prec = 128
        m, h = arb(centre), arb(half)
        rows = [[arb(1)], [m, h]]
        for _ in range(2, K):
            prev, prev2 = rows[-1], rows[-2]
            nxt = [arb(0)] * (len(prev) + 1)
            for j, a in enumerate(prev):          # 2 (m + h T_1) T_j = 2 m T_j + h (T_(j+1) + T_|j-1|)
                nxt[j] += 2 * m * a
                nxt[j + 1] += h * a
                nxt[abs(j - 1)] += h * a
            for j, a in enumerate(prev2):
                nxt[j] -= a
            rows.append(nxt)
        mid, rad = np.zeros((K, K)), np.zeros((K, K))
        for k in range(K):
            for j, a in enumerate(rows[k]):
                mid[k, j] = float(a.mid())
                rad[k, j] = _ceil(abs(a - mid[k, j]).upper())
    finally:
        ctx.prec = prec
    return mid, rad


def reexpand(coeffs: np.ndarray, centre: float, half: float) -> tuple[np.ndarray, np.ndarray]:
    """Chebyshev series on [-1, 1] restricted to [centre - half, centre + half], as models in the new variable.

    The new coefficients are R^T c with R[k, j] the coefficient of T_j(tau) in T_k(centre + half tau), formed in
    128-bit ball arithmetic; the float product's error (gamma_K |R| |c|) and R's radii go into the remainders.

    Parameters
    ----------
    coeffs : ndarray (rows, K)
        The series (exact doubles).
    centre, half : float
        The sub-interval of [-1, 1].

    Returns
    -------
    c : ndarray (rows, K)
        The coefficients in tau.
    r : ndarray (rows,)
        Proved remainders: |sum_k coeffs_k T_k(centre + half tau) - sum_k c_k T_k(tau)| <= r on tau in [-1, 1].
    """
    coeffs = np.asarray(coeffs, dtype=float)
    rows, K = coeffs.shape
    if centre == 0.0 and half == 1.0:
        return coeffs.copy(), np.zeros(rows)
    mid, rad = _restriction(K, centre, half)
    c = coeffs @ mid
    a = np.abs(coeffs)
    err = (2.0 * _gamma(K + 1) * (a @ np.abs(mid)) + a @ rad).sum(axis=1)
    return c, np.array([_up(x, K * K + K) for x in err])


def bound_on_pieces(build, max_depth: int = 6) -> tuple[np.ndarray, int]:
    """Proved bounds of |g_i(t)| on [-1, 1] for models built piece by piece, bisecting where a piece is too wide.

    Parameters
    ----------
    build : callable (centre, half) -> list of ChebModel
        The models of the functions g_i on the piece [centre - half, centre + half] of [-1, 1], in its own variable;
        it may raise :class:`TooWide` (then the piece is halved).
    max_depth : int
        At most 2**max_depth pieces; a piece still too wide at that depth raises its :class:`TooWide`.

    Returns
    -------
    bounds : ndarray (functions,)
        sup over t in [-1, 1] of |g_i(t)| <= bounds[i].
    pieces : int
        The pieces used.
    """
    todo, bounds, pieces = [(0.0, 1.0, 0)], None, 0
    while todo:
        centre, half, depth = todo.pop()
        try:
            models = build(centre, half)
        except TooWide:
            if depth >= max_depth:
                raise
            todo += [(centre + half / 2.0, half / 2.0, depth + 1), (centre - half / 2.0, half / 2.0, depth + 1)]
            continue
        here = np.array([m.bound() for m in models])
        bounds = here if bounds is None else np.maximum(bounds, here)
        pieces += 1
    return bounds, pieces
