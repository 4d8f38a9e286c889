"""Inf-sup interval arithmetic on exact arb endpoints, with forward-mode derivatives: what
:mod:`ashc_cli.numerics.interval` compiles sympy expressions into.  A private module of ``numerics``.

An interval is a tuple ``(lo, hi)`` of finite exact arbs with ``lo <= hi``, or None for "not finite here" (``sqrt``
of a range reaching below 0, ``log`` of a range reaching 0, division by a range holding 0, a pole of ``tan`` maybe
inside).  Every operation is done by arb at the endpoints and the result's ``lower()``/``upper()`` is taken, so
rounding is always outward and exact results stay exact.  A derivative is a list of intervals (one per argument),
None for zero, or BAD where it is unbounded; the kinks of ``Abs``, ``Min``, ``Max`` and ``triangle`` get Clarke-style
enclosures.  The box helpers at the end are shared by the compiled functions and the box searches.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Sequence

import numpy as np
import sympy as sp
from flint import arb

from ashc_cli.errors import NumericalError, UnsupportedExpression
from ashc_cli.problem.expr import square, step, triangle

# --- outward conversion between arb and float -------------------------------------------------------

INF = math.inf
_DBL_MAX = sys.float_info.max


def fdn(x: arb) -> float:
    """A float <= every point of the arb ``x`` (its lower end rounded down); nan if ``x`` is nan."""
    if not x.is_finite():
        return math.nan if x.is_nan() else -INF
    lo = x.lower()
    f = float(lo)
    if f == INF:  # lo is above the largest double
        return _DBL_MAX
    if f == -INF:
        return f
    if arb(f) > lo:  # exact comparison: both are exact points
        f = math.nextafter(f, -INF)
    return f


def fup(x: arb) -> float:
    """A float >= every point of the arb ``x`` (its upper end rounded up); nan if ``x`` is nan."""
    if not x.is_finite():
        return math.nan if x.is_nan() else INF
    hi = x.upper()
    f = float(hi)
    if f == -INF:
        return -_DBL_MAX
    if f == INF:
        return f
    if arb(f) < hi:
        f = math.nextafter(f, INF)
    return f


def ball_of(lo: float, hi: float) -> arb:
    """An arb ball containing the float interval [lo, hi] (checked)."""
    a, b = arb(lo), arb(hi)  # arb(float) is exact
    ball = a if lo == hi else a.union(b)
    if not (ball.lower() <= a and ball.upper() >= b):  # pragma: no cover - arb's union contract
        raise NumericalError("interval", f"arb ball {ball} does not contain [{lo!r}, {hi!r}]", "a containing ball")
    return ball


# --- inf-sup interval arithmetic on exact arb endpoints -----------------------------------------------
# An interval is a tuple (lo, hi) of finite exact arbs with lo <= hi, or None for "not finite here".

ZERO = arb(0)
_ONE = arb(1)
_MONE = arb(-1)
_PI = arb.pi()
_HALF_PI = _PI / 2
_TWO_PI = _PI * 2
_TWO_OVER_PI = 2 / _PI
Z = (ZERO, ZERO)
I1 = (_ONE, _ONE)
_UNIT = (_MONE, _ONE)


def from_ball(b: arb):
    """The interval of an arb ball's endpoints, None if the ball is not finite."""
    if not b.is_finite():
        return None
    return (b.lower(), b.upper())


def to_ball(a) -> arb:
    """An arb ball containing an interval (nan for None)."""
    if a is None:
        return arb.nan()
    lo, hi = a
    return lo if lo == hi else lo.union(hi)


def iv_add(a, b):
    if a is None or b is None:
        return None
    return ((a[0] + b[0]).lower(), (a[1] + b[1]).upper())


def iv_sub(a, b):
    if a is None or b is None:
        return None
    return ((a[0] - b[1]).lower(), (a[1] - b[0]).upper())


def iv_neg(a):
    if a is None:
        return None
    return (-a[1], -a[0])  # negation of an exact arb is exact


def iv_mul(a, b):
    if a is None or b is None:
        return None
    a0, a1 = a
    b0, b1 = b
    # Sign cases: two endpoint products where the signs are known, four only if both ranges hold 0.
    if a0 >= ZERO:
        if b0 >= ZERO:
            return ((a0 * b0).lower(), (a1 * b1).upper())
        if b1 <= ZERO:
            return ((a1 * b0).lower(), (a0 * b1).upper())
        return ((a1 * b0).lower(), (a1 * b1).upper())
    if a1 <= ZERO:
        if b0 >= ZERO:
            return ((a0 * b1).lower(), (a1 * b0).upper())
        if b1 <= ZERO:
            return ((a1 * b1).lower(), (a0 * b0).upper())
        return ((a0 * b1).lower(), (a0 * b0).upper())
    if b0 >= ZERO:
        return ((a0 * b1).lower(), (a1 * b1).upper())
    if b1 <= ZERO:
        return ((a1 * b0).lower(), (a0 * b0).upper())
    return (min((a0 * b1).lower(), (a1 * b0).lower()), max((a0 * b0).upper(), (a1 * b1).upper()))


def _recip(a):
    if a is None:
        return None
    a0, a1 = a
    if a0 > ZERO or a1 < ZERO:  # 1/x decreases on each side of 0
        return ((_ONE / a1).lower(), (_ONE / a0).upper())
    return None  # the range holds 0: unbounded


def iv_powi(a, n: int):
    """a**n for an integer n >= 2; tight for even n (x**2 of [-1, 2] is [0, 4])."""
    if a is None:
        return None
    a0, a1 = a
    if n % 2:
        return ((a0**n).lower(), (a1**n).upper())
    if a0 >= ZERO:
        return ((a0**n).lower(), (a1**n).upper())
    if a1 <= ZERO:
        return ((a1**n).lower(), (a0**n).upper())
    return (ZERO, max((a0**n).upper(), (a1**n).upper()))


def _sqr(a):
    return iv_powi(a, 2)


def _increasing(f):
    """The interval extension of an increasing arb function (evaluated at the two endpoints)."""

    def g(a):
        if a is None:
            return None
        a0, a1 = a
        if a0 == a1:  # a point: one evaluation
            y = f(a0)
            return (y.lower(), y.upper()) if y.is_finite() else None
        y0, y1 = f(a0), f(a1)
        if y0.is_finite() and y1.is_finite():
            return (y0.lower(), y1.upper())
        return None

    return g


def _decreasing(f):
    inc = _increasing(lambda x: -f(x))
    return lambda a: iv_neg(inc(a))


_exp = _increasing(arb.exp)
_atan = _increasing(arb.atan)
_tanh = _increasing(arb.tanh)
_sinh = _increasing(arb.sinh)
_asinh = _increasing(arb.asinh)
_cosh_pos = _increasing(arb.cosh)
_sqrt_inc = _increasing(arb.sqrt)
_log_inc = _increasing(arb.log)
_asin_inc = _increasing(arb.asin)
_acos_dec = _decreasing(arb.acos)
_atanh_inc = _increasing(arb.atanh)
_acosh_inc = _increasing(arb.acosh)


def _sqrt(a):
    if a is None or a[0] < ZERO:
        return None
    return _sqrt_inc(a)


def _log(a):
    if a is None or not a[0] > ZERO:
        return None
    return _log_inc(a)


def _asin(a):
    if a is None or a[0] < _MONE or a[1] > _ONE:
        return None
    return _asin_inc(a)


def _acos(a):
    if a is None or a[0] < _MONE or a[1] > _ONE:
        return None
    return _acos_dec(a)


def _atanh(a):
    if a is None or not (a[0] > _MONE and a[1] < _ONE):
        return None
    return _atanh_inc(a)


def _acosh(a):
    if a is None or a[0] < _ONE:
        return None
    return _acosh_inc(a)


def _abs(a):
    if a is None:
        return None
    a0, a1 = a
    if a0 >= ZERO:
        return a
    if a1 <= ZERO:
        return (-a1, -a0)
    return (ZERO, max(-a0, a1))


def _cosh(a):
    return _cosh_pos(_abs(a))


def iv_sign(a):
    # sign is discontinuous at 0, but its range is still enclosed: a subset of {-1, 0, 1}.
    if a is None:
        return None
    a0, a1 = a
    if a0 > ZERO:
        return I1
    if a1 < ZERO:
        return (_MONE, _MONE)
    if a0 == ZERO and a1 == ZERO:
        return Z
    return (_MONE if a0 < ZERO else ZERO, _ONE if a1 > ZERO else ZERO)


def _step(a):
    """Unit step (1 for t >= 0, else 0), as :class:`ashc_cli.problem.expr.step`."""
    if a is None:
        return None
    if a[0] >= ZERO:
        return I1
    if a[1] < ZERO:
        return Z
    return (ZERO, _ONE)


def _hits(a0: arb, a1: arb, phase: arb, period: arb) -> bool:
    """Whether [a0, a1] may hold a point phase + k*period (k integer); never a false 'no'."""
    t0 = ((a0 - phase) / period).lower().ceil()
    t1 = ((a1 - phase) / period).upper().floor()
    return t1 >= t0


def _periodic(f, max_phase: arb, min_phase: arb):
    """Range of sin or cos: the endpoint values, and +-1 where a peak or trough may lie inside."""

    def g(a):
        if a is None:
            return None
        a0, a1 = a
        if a0 == a1:
            y = f(a0)
            if not y.is_finite():
                return None
            lo, hi = y.lower(), y.upper()
        else:
            if not (a1 - a0 < _TWO_PI):
                return _UNIT
            y0, y1 = f(a0), f(a1)
            if not (y0.is_finite() and y1.is_finite()):
                return None
            lo, hi = min(y0.lower(), y1.lower()), max(y0.upper(), y1.upper())
            if _hits(a0, a1, max_phase, _TWO_PI):
                hi = _ONE
            if _hits(a0, a1, min_phase, _TWO_PI):
                lo = _MONE
        # The true values lie in [-1, 1]; clamping the rounded ends keeps asin/acos of them defined.
        return (_MONE if lo < _MONE else lo, _ONE if hi > _ONE else hi)

    return g


_sin = _periodic(arb.sin, _HALF_PI, -_HALF_PI)
_cos = _periodic(arb.cos, ZERO, _PI)


_tan_inc = _increasing(arb.tan)


def _tan(a):
    if a is None:
        return None
    a0, a1 = a
    if a0 != a1 and (not (a1 - a0 < _PI) or _hits(a0, a1, _HALF_PI, _PI)):
        return None  # a pole may lie inside
    return _tan_inc(a)


def _square_wave(a):
    """sign(sin t), as :class:`ashc_cli.problem.expr.square`."""
    return iv_sign(_sin(a))


def _triangle(a):
    """The paper's triangle wave nabla(t) = (2/pi) acos(cos t) - 1, as :class:`ashc_cli.problem.expr.triangle`."""
    c = _cos(a)  # already clamped to [-1, 1]
    t = iv_sub(iv_mul((_TWO_OVER_PI.lower(), _TWO_OVER_PI.upper()), _acos(c)), I1)
    return None if t is None else iv_intersect(t, _UNIT)  # its values lie in [-1, 1]


def iv_min(*args):
    if any(a is None for a in args):
        return None
    return (min(a[0] for a in args), min(a[1] for a in args))


def iv_max(*args):
    if any(a is None for a in args):
        return None
    return (max(a[0] for a in args), max(a[1] for a in args))


def iv_pow_real(a, r: arb):
    """x**r for a real constant exponent r (a ball), x >= 0; for each r in the ball x**r is monotone."""
    if a is None:
        return None
    a0, a1 = a
    if a0 < ZERO:
        return None
    if a0 == ZERO:
        if not r > ZERO:
            return None  # 0 to a negative (or maybe negative) power
        if a1 == ZERO:
            return Z
        y1 = a1**r
        return (ZERO, y1.upper()) if y1.is_finite() else None
    y0, y1 = a0**r, a1**r
    if not (y0.is_finite() and y1.is_finite()):
        return None
    # Increasing or decreasing depending on the sign of r: the hull of both ends covers either.
    return (min(y0.lower(), y1.lower()), max(y0.upper(), y1.upper()))


def iv_pow_gen(a, b):
    """x**y for a variable exponent: exp(y log x), defined for x > 0."""
    return _exp(iv_mul(b, _log(a)))


def _hull(a, b):
    return (min(a[0], b[0]), max(a[1], b[1]))


def iv_intersect(a, b):
    return (max(a[0], b[0]), min(a[1], b[1]))


# --- gradients (forward mode) ---------------------------------------------------------------------------
# A gradient is None (identically zero), BAD (no finite enclosure: the mean-value form is not used) or a
# list of intervals, one per argument.

BAD = object()


def _gscale(p, g):
    if g is None or g is BAD:
        return g
    if p is None:
        return BAD
    return [e if e is Z else iv_mul(p, e) for e in g]


def _gadd(g, h):
    if g is BAD or h is BAD:
        return BAD
    if g is None:
        return h
    if h is None:
        return g
    return [y if x is Z else x if y is Z else iv_add(x, y) for x, y in zip(g, h)]


def _ghull(grads):
    """Componentwise hull of several gradients (None counts as zero)."""
    if any(g is BAD for g in grads):
        return BAD
    real = [g for g in grads if g is not None]
    if not real:
        return None
    d = len(real[0])
    if len(real) < len(grads):
        real.append([Z] * d)
    return [(min(g[i][0] for g in real), max(g[i][1] for g in real)) for i in range(d)]


# Partial derivatives of the unary operations: d(a, out) -> interval, or None where unbounded/undefined.


def _d_sqrt(a, out):
    return _recip(iv_add(out, out)) if a[0] > ZERO else None


def _d_abs(a, out):
    if a[0] > ZERO:
        return I1
    if a[1] < ZERO:
        return (_MONE, _MONE)
    return _UNIT  # Clarke gradient of |x| at the kink


def _d_jump(a, out):
    # sign and step are constant on a range that keeps off the jump (step is 1 on [0, ...] as well).
    return Z if (a[0] > ZERO or a[1] < ZERO) else None


def _d_step(a, out):
    return Z if (a[0] >= ZERO or a[1] < ZERO) else None


def _d_square(a, out):
    s = _sin(a)
    return None if s is None else _d_jump(s, out)


def _d_triangle(a, out):
    s = _sin(a)
    if s is None:
        return None
    k = (_TWO_OVER_PI.lower(), _TWO_OVER_PI.upper())
    if s[0] > ZERO:
        return k
    if s[1] < ZERO:
        return iv_neg(k)
    return _hull(k, iv_neg(k))  # Lipschitz with constant 2/pi


def _one_plus_sq(x):
    return iv_add(I1, _sqr(x))


_PARTIALS: dict[str, Callable] = {
    "exp": lambda a, out: out,
    "log": lambda a, out: _recip(a),
    "sqrt": _d_sqrt,
    "sin": lambda a, out: _cos(a),
    "cos": lambda a, out: iv_neg(_sin(a)),
    "tan": lambda a, out: _one_plus_sq(out),
    "tanh": lambda a, out: iv_sub(I1, _sqr(out)),
    "sinh": lambda a, out: _cosh(a),
    "cosh": lambda a, out: _sinh(a),
    "atan": lambda a, out: _recip(_one_plus_sq(a)),
    "asin": lambda a, out: _recip(_sqrt(iv_sub(I1, _sqr(a)))),
    "acos": lambda a, out: iv_neg(_recip(_sqrt(iv_sub(I1, _sqr(a))))),
    "asinh": lambda a, out: _recip(_sqrt(_one_plus_sq(a))),
    "acosh": lambda a, out: _recip(_sqrt(iv_sub(_sqr(a), I1))),
    "atanh": lambda a, out: _recip(iv_sub(I1, _sqr(a))),
    "abs": _d_abs,
    "sign": _d_jump,
    "step": _d_step,
    "square": _d_square,
    "triangle": _d_triangle,
    "neg": lambda a, out: (_MONE, _MONE),
    "recip": lambda a, out: iv_neg(_sqr(out)),
}

UNARY: dict[str, Callable] = {
    "exp": _exp,
    "log": _log,
    "sqrt": _sqrt,
    "sin": _sin,
    "cos": _cos,
    "tan": _tan,
    "tanh": _tanh,
    "sinh": _sinh,
    "cosh": _cosh,
    "atan": _atan,
    "asin": _asin,
    "acos": _acos,
    "asinh": _asinh,
    "acosh": _acosh,
    "atanh": _atanh,
    "abs": _abs,
    "sign": iv_sign,
    "step": _step,
    "square": _square_wave,
    "triangle": _triangle,
    "neg": iv_neg,
    "recip": _recip,
}

SYMPY_UNARY: dict[object, str] = {
    sp.exp: "exp",
    sp.log: "log",
    sp.sin: "sin",
    sp.cos: "cos",
    sp.tan: "tan",
    sp.tanh: "tanh",
    sp.sinh: "sinh",
    sp.cosh: "cosh",
    sp.atan: "atan",
    sp.asin: "asin",
    sp.acos: "acos",
    sp.asinh: "asinh",
    sp.acosh: "acosh",
    sp.atanh: "atanh",
    sp.Abs: "abs",
    sp.sign: "sign",
    step: "step",
    square: "square",
    triangle: "triangle",
}


def ad_unary(name: str):
    value, partial = UNARY[name], _PARTIALS[name]

    def ad(a, g):
        out = value(a)
        if out is None:
            return None, BAD
        if g is None or g is BAD:
            return out, g
        p = partial(a, out)
        return out, (BAD if p is None else _gscale(p, g))

    return ad


def ad_add(a, ga, b, gb):
    return iv_add(a, b), _gadd(ga, gb)


def ad_mul(a, ga, b, gb):
    out = iv_mul(a, b)
    if out is None:
        return None, BAD
    return out, _gadd(_gscale(b, ga), _gscale(a, gb))


def ad_powi(n: int):
    k = (arb(n), arb(n))

    def ad(a, g):
        out = iv_powi(a, n)
        if out is None:
            return None, BAD
        if g is None or g is BAD:
            return out, g
        p = iv_mul(k, a if n == 2 else iv_powi(a, n - 1))
        return out, _gscale(p, g)

    return ad


def ad_pow_real(r: arb):
    rm1 = r - 1
    k = (r.lower(), r.upper())

    def ad(a, g):
        out = iv_pow_real(a, r)
        if out is None:
            return None, BAD
        if g is None or g is BAD:
            return out, g
        # d/dx x**r = r x**(r-1); at x = 0 with r < 1 it is unbounded (None -> BAD).
        return out, _gscale(iv_mul(k, iv_pow_real(a, rm1)), g)

    return ad


def ad_pow_gen(a, ga, b, gb):
    out = iv_pow_gen(a, b)
    if out is None:
        return None, BAD
    px = iv_mul(b, iv_mul(out, _recip(a)))  # y x**y / x
    py = iv_mul(_log(a), out)  # log(x) x**y
    return out, _gadd(_gscale(px, ga), _gscale(py, gb))


def ad_minmax(is_max: bool):
    value = iv_max if is_max else iv_min

    def ad(*pairs):
        ivs = pairs[0::2]
        grads = pairs[1::2]
        out = value(*ivs)
        if out is None:
            return None, BAD
        # The arguments that may be the active one: those that can reach the extreme value.
        if is_max:
            active = [g for a, g in zip(ivs, grads) if a[1] >= out[0]]
        else:
            active = [g for a, g in zip(ivs, grads) if a[0] <= out[1]]
        return out, (active[0] if len(active) == 1 else _ghull(active))

    return ad


# --- compiler -------------------------------------------------------------------------------------------



def number_interval(v, where) -> tuple:
    """The exact interval of a parameter value (python float or int)."""
    if isinstance(v, (bool, np.bool_)):
        raise ValueError(f"value of {where} is a bool, not a number")
    if isinstance(v, (int, np.integer)):
        a = arb(int(v))
        return (a, a)
    if isinstance(v, sp.Basic):
        if not isinstance(v, (sp.Number, sp.NumberSymbol)):
            raise ValueError(f"value of {where} is the expression {v}, not a number")
        return sympy_number(v)
    f = float(v)
    if not math.isfinite(f):
        raise ValueError(f"value of {where} is {f}, not a finite number")
    a = arb(f)  # exact: the double itself
    return (a, a)


def sympy_number(e) -> tuple:
    """The interval of a sympy number: exact where arb can hold it, else a tight outward enclosure."""
    if isinstance(e, sp.Integer):
        a = arb(int(e))
        return (a, a)
    if isinstance(e, sp.Rational):
        return from_ball(arb(int(e.p)) / arb(int(e.q)))
    if isinstance(e, sp.Float):
        sign, man, exp, _ = e._mpf_
        if man == 0:
            if exp == 0:
                return Z
            raise UnsupportedExpression(e, "not a finite number")
        a = arb(int(man)) * arb(2) ** int(exp)  # exact unless the mantissa is longer than the precision
        iv = from_ball(-a if sign else a)
        if iv is None:
            raise UnsupportedExpression(e, "not a finite number")
        return iv
    if e is sp.pi:
        return from_ball(arb.pi())
    if e is sp.E:
        return from_ball(arb(1).exp())
    raise UnsupportedExpression(e, "only finite real numbers, pi and E are supported")


# --- the compiled function ------------------------------------------------------------------------------



# --- box helpers --------------------------------------------------------------------------------------


def check_box(box) -> tuple[list[float], list[float]]:
    b = np.asarray(box, dtype=float)
    if b.ndim != 2 or b.shape[1] != 2:
        raise ValueError(f"box must have shape (d, 2), got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError("box has non-finite bounds")
    if np.any(b[:, 0] > b[:, 1]):
        raise ValueError("box has a row with lo > hi")
    return [float(x) for x in b[:, 0]], [float(x) for x in b[:, 1]]


def midpoint(a: float, b: float) -> float:
    """A float in [a, b] near its middle (without overflow for huge a, b)."""
    m = a + 0.5 * (b - a)
    return m if a <= m <= b else 0.5 * a + 0.5 * b


def centre(lo: Sequence[float], hi: Sequence[float]) -> list[float]:
    return [midpoint(a, b) for a, b in zip(lo, hi)]
