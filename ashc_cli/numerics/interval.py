"""Rigorous enclosures of functions over boxes, on python-flint's arb, for certificates.

The stages use this module to *prove* things numerically: an upper bound on the supremum of a function
over a box (:func:`sup_on_box`), a lower bound on its infimum (:func:`inf_on_box`), the sign of a
function on a box (:func:`prove_positive`), positive definiteness of a float matrix
(:func:`psd_lower_bound`, :func:`prove_psd`) and a bound on the largest eigenvalue of an interval matrix
(:func:`lambda_max_upper`).  Soundness comes first: a bound this module calls rigorous truly holds for the
exact real numbers, whatever the rounding.

How the enclosures are made
---------------------------
:func:`compile_interval` walks a sympy expression once and builds a tape of Python closures (common
subtrees are shared, so each distinct subtree runs once per call).  The closures work in *inf-sup*
interval arithmetic whose endpoints are exact arb numbers (radius 0): every operation is done by arb at
the endpoints and the result's ``lower()``/``upper()`` is taken, so rounding is always outward and exact
results stay exact (``2 - 2*x`` on ``x in [0, 1]`` has lower end exactly 0, so ``sqrt`` of it is defined).
Plain arb *balls* are not used for the range arithmetic itself because a ball cannot hold ``[0, h]``
exactly (its radius has a 30-bit mantissa, e.g. ``arb(0).union(arb(1))`` reaches below 0), and mid-radius
products and ``exp`` of wide balls overshoot badly (``exp([1, 2])`` as a ball reaches below 0).
The public entry points still speak arb balls: the compiled function takes one ball per argument and
returns one ball per expression.

A value that is not defined or not bounded on the box (``sqrt`` of a range reaching below 0, ``log`` of a
range reaching 0, division by a range holding 0, a pole of ``tan`` maybe inside) makes the enclosure
non-finite (``nan`` ball / ``(nan, nan)``), never a finite value: callers check ``is_finite()``.

The compiled function also carries first derivatives (forward mode, in the same interval arithmetic, with
Clarke-style enclosures for the Lipschitz kinks of ``Abs``, ``Min``, ``Max`` and ``triangle``).  The box
searches intersect the natural enclosure with the mean-value form
``f(c) + sum_i G_i (X_i - c_i)``, whose overestimate shrinks with the square of the box width; that is what
makes tight tolerances reachable in a few thousand boxes.
"""

from __future__ import annotations

import heapq
import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import sympy as sp
from flint import arb, arb_mat

from ashc_cli.errors import NumericalError, UnsupportedExpression
from ashc_cli.problem.expr import square, step, triangle

__all__ = [
    "UnsupportedExpression",
    "IntervalFunction",
    "compile_interval",
    "enclose",
    "SupResult",
    "InfResult",
    "sup_on_box",
    "inf_on_box",
    "prove_positive",
    "psd_lower_bound",
    "UnsupportedExpression",
    "prove_psd",
    "lambda_max_upper",
]


# --- outward conversion between arb and float -------------------------------------------------------

_INF = math.inf
_DBL_MAX = sys.float_info.max


def _fdn(x: arb) -> float:
    """A float <= every point of the arb ``x`` (its lower end rounded down); nan if ``x`` is nan."""
    if not x.is_finite():
        return math.nan if x.is_nan() else -_INF
    lo = x.lower()
    f = float(lo)
    if f == _INF:  # lo is above the largest double
        return _DBL_MAX
    if f == -_INF:
        return f
    if arb(f) > lo:  # exact comparison: both are exact points
        f = math.nextafter(f, -_INF)
    return f


def _fup(x: arb) -> float:
    """A float >= every point of the arb ``x`` (its upper end rounded up); nan if ``x`` is nan."""
    if not x.is_finite():
        return math.nan if x.is_nan() else _INF
    hi = x.upper()
    f = float(hi)
    if f == -_INF:
        return -_DBL_MAX
    if f == _INF:
        return f
    if arb(f) < hi:
        f = math.nextafter(f, _INF)
    return f


def _ball(lo: float, hi: float) -> arb:
    """An arb ball containing the float interval [lo, hi] (checked)."""
    a, b = arb(lo), arb(hi)  # arb(float) is exact
    ball = a if lo == hi else a.union(b)
    if not (ball.lower() <= a and ball.upper() >= b):  # pragma: no cover - arb's union contract
        raise NumericalError("interval", f"arb ball {ball} does not contain [{lo!r}, {hi!r}]", "a containing ball")
    return ball


# --- inf-sup interval arithmetic on exact arb endpoints -----------------------------------------------
# An interval is a tuple (lo, hi) of finite exact arbs with lo <= hi, or None for "not finite here".

_ZERO = arb(0)
_ONE = arb(1)
_MONE = arb(-1)
_PI = arb.pi()
_HALF_PI = _PI / 2
_TWO_PI = _PI * 2
_TWO_OVER_PI = 2 / _PI
_Z = (_ZERO, _ZERO)
_I1 = (_ONE, _ONE)
_UNIT = (_MONE, _ONE)


def _iv_ball(b: arb):
    """The interval of an arb ball's endpoints, None if the ball is not finite."""
    if not b.is_finite():
        return None
    return (b.lower(), b.upper())


def _iv_to_ball(a) -> arb:
    """An arb ball containing an interval (nan for None)."""
    if a is None:
        return arb.nan()
    lo, hi = a
    return lo if lo == hi else lo.union(hi)


def _add(a, b):
    if a is None or b is None:
        return None
    return ((a[0] + b[0]).lower(), (a[1] + b[1]).upper())


def _sub(a, b):
    if a is None or b is None:
        return None
    return ((a[0] - b[1]).lower(), (a[1] - b[0]).upper())


def _neg(a):
    if a is None:
        return None
    return (-a[1], -a[0])  # negation of an exact arb is exact


def _mul(a, b):
    if a is None or b is None:
        return None
    a0, a1 = a
    b0, b1 = b
    # Sign cases: two endpoint products where the signs are known, four only if both ranges hold 0.
    if a0 >= _ZERO:
        if b0 >= _ZERO:
            return ((a0 * b0).lower(), (a1 * b1).upper())
        if b1 <= _ZERO:
            return ((a1 * b0).lower(), (a0 * b1).upper())
        return ((a1 * b0).lower(), (a1 * b1).upper())
    if a1 <= _ZERO:
        if b0 >= _ZERO:
            return ((a0 * b1).lower(), (a1 * b0).upper())
        if b1 <= _ZERO:
            return ((a1 * b1).lower(), (a0 * b0).upper())
        return ((a0 * b1).lower(), (a0 * b0).upper())
    if b0 >= _ZERO:
        return ((a0 * b1).lower(), (a1 * b1).upper())
    if b1 <= _ZERO:
        return ((a1 * b0).lower(), (a0 * b0).upper())
    return (min((a0 * b1).lower(), (a1 * b0).lower()), max((a0 * b0).upper(), (a1 * b1).upper()))


def _recip(a):
    if a is None:
        return None
    a0, a1 = a
    if a0 > _ZERO or a1 < _ZERO:  # 1/x decreases on each side of 0
        return ((_ONE / a1).lower(), (_ONE / a0).upper())
    return None  # the range holds 0: unbounded


def _powi(a, n: int):
    """a**n for an integer n >= 2; tight for even n (x**2 of [-1, 2] is [0, 4])."""
    if a is None:
        return None
    a0, a1 = a
    if n % 2:
        return ((a0**n).lower(), (a1**n).upper())
    if a0 >= _ZERO:
        return ((a0**n).lower(), (a1**n).upper())
    if a1 <= _ZERO:
        return ((a1**n).lower(), (a0**n).upper())
    return (_ZERO, max((a0**n).upper(), (a1**n).upper()))


def _sqr(a):
    return _powi(a, 2)


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
    return lambda a: _neg(inc(a))


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
    if a is None or a[0] < _ZERO:
        return None
    return _sqrt_inc(a)


def _log(a):
    if a is None or not a[0] > _ZERO:
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
    if a0 >= _ZERO:
        return a
    if a1 <= _ZERO:
        return (-a1, -a0)
    return (_ZERO, max(-a0, a1))


def _cosh(a):
    return _cosh_pos(_abs(a))


def _sign(a):
    # sign is discontinuous at 0, but its range is still enclosed: a subset of {-1, 0, 1}.
    if a is None:
        return None
    a0, a1 = a
    if a0 > _ZERO:
        return _I1
    if a1 < _ZERO:
        return (_MONE, _MONE)
    if a0 == _ZERO and a1 == _ZERO:
        return _Z
    return (_MONE if a0 < _ZERO else _ZERO, _ONE if a1 > _ZERO else _ZERO)


def _step(a):
    """Unit step (1 for t >= 0, else 0), as :class:`ashc_cli.problem.expr.step`."""
    if a is None:
        return None
    if a[0] >= _ZERO:
        return _I1
    if a[1] < _ZERO:
        return _Z
    return (_ZERO, _ONE)


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
_cos = _periodic(arb.cos, _ZERO, _PI)


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
    return _sign(_sin(a))


def _triangle(a):
    """The paper's triangle wave nabla(t) = (2/pi) acos(cos t) - 1, as :class:`ashc_cli.problem.expr.triangle`."""
    c = _cos(a)  # already clamped to [-1, 1]
    t = _sub(_mul((_TWO_OVER_PI.lower(), _TWO_OVER_PI.upper()), _acos(c)), _I1)
    return None if t is None else _intersect(t, _UNIT)  # its values lie in [-1, 1]


def _min(*args):
    if any(a is None for a in args):
        return None
    return (min(a[0] for a in args), min(a[1] for a in args))


def _max(*args):
    if any(a is None for a in args):
        return None
    return (max(a[0] for a in args), max(a[1] for a in args))


def _pow_real(a, r: arb):
    """x**r for a real constant exponent r (a ball), x >= 0; for each r in the ball x**r is monotone."""
    if a is None:
        return None
    a0, a1 = a
    if a0 < _ZERO:
        return None
    if a0 == _ZERO:
        if not r > _ZERO:
            return None  # 0 to a negative (or maybe negative) power
        if a1 == _ZERO:
            return _Z
        y1 = a1**r
        return (_ZERO, y1.upper()) if y1.is_finite() else None
    y0, y1 = a0**r, a1**r
    if not (y0.is_finite() and y1.is_finite()):
        return None
    # Increasing or decreasing depending on the sign of r: the hull of both ends covers either.
    return (min(y0.lower(), y1.lower()), max(y0.upper(), y1.upper()))


def _pow_gen(a, b):
    """x**y for a variable exponent: exp(y log x), defined for x > 0."""
    return _exp(_mul(b, _log(a)))


def _hull(a, b):
    return (min(a[0], b[0]), max(a[1], b[1]))


def _intersect(a, b):
    return (max(a[0], b[0]), min(a[1], b[1]))


# --- gradients (forward mode) ---------------------------------------------------------------------------
# A gradient is None (identically zero), _BAD (no finite enclosure: the mean-value form is not used) or a
# list of intervals, one per argument.

_BAD = object()


def _gscale(p, g):
    if g is None or g is _BAD:
        return g
    if p is None:
        return _BAD
    return [e if e is _Z else _mul(p, e) for e in g]


def _gadd(g, h):
    if g is _BAD or h is _BAD:
        return _BAD
    if g is None:
        return h
    if h is None:
        return g
    return [y if x is _Z else x if y is _Z else _add(x, y) for x, y in zip(g, h)]


def _ghull(grads):
    """Componentwise hull of several gradients (None counts as zero)."""
    if any(g is _BAD for g in grads):
        return _BAD
    real = [g for g in grads if g is not None]
    if not real:
        return None
    d = len(real[0])
    if len(real) < len(grads):
        real.append([_Z] * d)
    return [(min(g[i][0] for g in real), max(g[i][1] for g in real)) for i in range(d)]


# Partial derivatives of the unary operations: d(a, out) -> interval, or None where unbounded/undefined.


def _d_sqrt(a, out):
    return _recip(_add(out, out)) if a[0] > _ZERO else None


def _d_abs(a, out):
    if a[0] > _ZERO:
        return _I1
    if a[1] < _ZERO:
        return (_MONE, _MONE)
    return _UNIT  # Clarke gradient of |x| at the kink


def _d_jump(a, out):
    # sign and step are constant on a range that keeps off the jump (step is 1 on [0, ...] as well).
    return _Z if (a[0] > _ZERO or a[1] < _ZERO) else None


def _d_step(a, out):
    return _Z if (a[0] >= _ZERO or a[1] < _ZERO) else None


def _d_square(a, out):
    s = _sin(a)
    return None if s is None else _d_jump(s, out)


def _d_triangle(a, out):
    s = _sin(a)
    if s is None:
        return None
    k = (_TWO_OVER_PI.lower(), _TWO_OVER_PI.upper())
    if s[0] > _ZERO:
        return k
    if s[1] < _ZERO:
        return _neg(k)
    return _hull(k, _neg(k))  # Lipschitz with constant 2/pi


def _one_plus_sq(x):
    return _add(_I1, _sqr(x))


_PARTIALS: dict[str, Callable] = {
    "exp": lambda a, out: out,
    "log": lambda a, out: _recip(a),
    "sqrt": _d_sqrt,
    "sin": lambda a, out: _cos(a),
    "cos": lambda a, out: _neg(_sin(a)),
    "tan": lambda a, out: _one_plus_sq(out),
    "tanh": lambda a, out: _sub(_I1, _sqr(out)),
    "sinh": lambda a, out: _cosh(a),
    "cosh": lambda a, out: _sinh(a),
    "atan": lambda a, out: _recip(_one_plus_sq(a)),
    "asin": lambda a, out: _recip(_sqrt(_sub(_I1, _sqr(a)))),
    "acos": lambda a, out: _neg(_recip(_sqrt(_sub(_I1, _sqr(a))))),
    "asinh": lambda a, out: _recip(_sqrt(_one_plus_sq(a))),
    "acosh": lambda a, out: _recip(_sqrt(_sub(_sqr(a), _I1))),
    "atanh": lambda a, out: _recip(_sub(_I1, _sqr(a))),
    "abs": _d_abs,
    "sign": _d_jump,
    "step": _d_step,
    "square": _d_square,
    "triangle": _d_triangle,
    "neg": lambda a, out: (_MONE, _MONE),
    "recip": lambda a, out: _neg(_sqr(out)),
}

_UNARY: dict[str, Callable] = {
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
    "sign": _sign,
    "step": _step,
    "square": _square_wave,
    "triangle": _triangle,
    "neg": _neg,
    "recip": _recip,
}

_SYMPY_UNARY: dict[object, str] = {
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


def _ad_unary(name: str):
    value, partial = _UNARY[name], _PARTIALS[name]

    def ad(a, g):
        out = value(a)
        if out is None:
            return None, _BAD
        if g is None or g is _BAD:
            return out, g
        p = partial(a, out)
        return out, (_BAD if p is None else _gscale(p, g))

    return ad


def _ad_add(a, ga, b, gb):
    return _add(a, b), _gadd(ga, gb)


def _ad_mul(a, ga, b, gb):
    out = _mul(a, b)
    if out is None:
        return None, _BAD
    return out, _gadd(_gscale(b, ga), _gscale(a, gb))


def _ad_powi(n: int):
    k = (arb(n), arb(n))

    def ad(a, g):
        out = _powi(a, n)
        if out is None:
            return None, _BAD
        if g is None or g is _BAD:
            return out, g
        p = _mul(k, a if n == 2 else _powi(a, n - 1))
        return out, _gscale(p, g)

    return ad


def _ad_pow_real(r: arb):
    rm1 = r - 1
    k = (r.lower(), r.upper())

    def ad(a, g):
        out = _pow_real(a, r)
        if out is None:
            return None, _BAD
        if g is None or g is _BAD:
            return out, g
        # d/dx x**r = r x**(r-1); at x = 0 with r < 1 it is unbounded (None -> _BAD).
        return out, _gscale(_mul(k, _pow_real(a, rm1)), g)

    return ad


def _ad_pow_gen(a, ga, b, gb):
    out = _pow_gen(a, b)
    if out is None:
        return None, _BAD
    px = _mul(b, _mul(out, _recip(a)))  # y x**y / x
    py = _mul(_log(a), out)  # log(x) x**y
    return out, _gadd(_gscale(px, ga), _gscale(py, gb))


def _ad_minmax(is_max: bool):
    value = _max if is_max else _min

    def ad(*pairs):
        ivs = pairs[0::2]
        grads = pairs[1::2]
        out = value(*ivs)
        if out is None:
            return None, _BAD
        # The arguments that may be the active one: those that can reach the extreme value.
        if is_max:
            active = [g for a, g in zip(ivs, grads) if a[1] >= out[0]]
        else:
            active = [g for a, g in zip(ivs, grads) if a[0] <= out[1]]
        return out, (active[0] if len(active) == 1 else _ghull(active))

    return ad


# --- compiler -------------------------------------------------------------------------------------------


class _Compiler:
    """Turns sympy trees into slots: inputs, constants (intervals) and operations on earlier slots."""

    def __init__(self, args: Sequence[sp.Symbol], values: Mapping[sp.Symbol, float]):
        self.n_in = len(args)
        self.kinds: list[str] = []
        self.consts: list = []  # interval per slot (constants only)
        self.ops: list = []  # (value_fn, ad_fn, kids) per slot (operations only)
        self.memo: dict = {}
        for k, s in enumerate(args):
            self._new("in", None, None)
            self.memo[("sym", s)] = k
        for s, v in values.items():
            if ("sym", s) in self.memo:
                raise ValueError(f"symbol {s} is both an argument and a fixed value")
            self.memo[("sym", s)] = self.const(_number_interval(v, s))

    def _new(self, kind: str, const, op) -> int:
        self.kinds.append(kind)
        self.consts.append(const)
        self.ops.append(op)
        return len(self.kinds) - 1

    def const(self, iv) -> int:
        return self._new("const", iv, None)

    def op(self, key: tuple, value_fn, ad_fn, kids: tuple[int, ...]) -> int:
        """A slot for an operation on earlier slots; folded to a constant if all operands are constants."""
        full = (key, kids)
        if full in self.memo:
            return self.memo[full]
        if all(self.kinds[k] == "const" for k in kids):
            slot = self.const(value_fn(*[self.consts[k] for k in kids]))
        else:
            slot = self._new("op", None, (value_fn, ad_fn, kids))
        self.memo[full] = slot
        return slot

    def unary(self, name: str, kid: int) -> int:
        return self.op((name,), _UNARY[name], _ad_unary(name), (kid,))

    def add(self, a: int, b: int) -> int:
        return self.op(("add",), _add, _ad_add, (a, b))

    def mul(self, a: int, b: int) -> int:
        return self.op(("mul",), _mul, _ad_mul, (a, b))

    def powi(self, a: int, n: int) -> int:
        return self.op(("powi", n), lambda x: _powi(x, n), _ad_powi(n), (a,))

    def expr(self, e) -> int:
        key = ("expr", e)
        if key in self.memo:
            return self.memo[key]
        slot = self._build(e)
        self.memo[key] = slot
        return slot

    def _build(self, e) -> int:
        if isinstance(e, sp.Symbol):
            if ("sym", e) in self.memo:
                return self.memo[("sym", e)]
            raise ValueError(f"free symbol {e} is neither an argument nor given a value")
        if isinstance(e, (sp.Number, sp.NumberSymbol)):
            return self.const(_sympy_number(e))
        if isinstance(e, sp.Add):
            slots = [self.expr(t) for t in e.args]
            acc = slots[0]
            for s in slots[1:]:
                acc = self.add(acc, s)
            return acc
        if isinstance(e, sp.Mul):
            coeff, rest = e.as_coeff_Mul()
            if coeff == -1:  # exact negation instead of a product
                return self.unary("neg", self.expr(rest))
            slots = [self.expr(t) for t in e.args]
            acc = slots[0]
            for s in slots[1:]:
                acc = self.mul(acc, s)
            return acc
        if isinstance(e, sp.Pow):
            return self._pow(e)
        if isinstance(e, (sp.Min, sp.Max)):
            is_max = isinstance(e, sp.Max)
            kids = tuple(self.expr(a) for a in e.args)
            return self.op(("max" if is_max else "min",), _max if is_max else _min, _ad_minmax(is_max), kids)
        name = _SYMPY_UNARY.get(e.func)
        if name is not None:
            if len(e.args) != 1:
                raise UnsupportedExpression(e, f"{name} with {len(e.args)} arguments")
            return self.unary(name, self.expr(e.args[0]))
        raise UnsupportedExpression(e)

    def _pow(self, e) -> int:
        base, ex = e.args
        if ex.is_Float:
            sign, man, exp2, _ = ex._mpf_
            if (man == 0 and exp2 == 0) or (man != 0 and 0 <= exp2 <= 20 and man << exp2 <= 10**6):
                # An exactly integral Float (mantissa odd, exponent >= 0): x**2.0 is x**2, defined for x < 0.
                ex = sp.Integer((-1) ** sign * (man << exp2))
        if ex.is_Integer:
            n = int(ex)
            b = self.expr(base)
            if n == 0:
                return self.const(_I1)
            pos = b if abs(n) == 1 else self.powi(b, abs(n))
            return pos if n > 0 else self.unary("recip", pos)
        if ex.is_Rational and ex.q == 2:
            # Half-integer powers through sqrt: x**(p/2) = sqrt(x)**p.
            root = self.unary("sqrt", self.expr(base))
            p = int(ex.p)
            pos = root if abs(p) == 1 else self.powi(root, abs(p))
            return pos if p > 0 else self.unary("recip", pos)
        if ex.is_Number:
            r = _sympy_number(ex)
            rb = _iv_to_ball(r)
            if not rb.is_finite():
                raise UnsupportedExpression(e, "non-finite exponent")
            return self.op(("powr", str(ex)), lambda x: _pow_real(x, rb), _ad_pow_real(rb), (self.expr(base),))
        # A variable exponent: exp(y log x), defined where x > 0.
        return self.op(("pow",), _pow_gen, _ad_pow_gen, (self.expr(base), self.expr(ex)))


def _number_interval(v, where) -> tuple:
    """The exact interval of a parameter value (python float or int)."""
    if isinstance(v, (bool, np.bool_)):
        raise ValueError(f"value of {where} is a bool, not a number")
    if isinstance(v, (int, np.integer)):
        a = arb(int(v))
        return (a, a)
    if isinstance(v, sp.Basic):
        if not isinstance(v, (sp.Number, sp.NumberSymbol)):
            raise ValueError(f"value of {where} is the expression {v}, not a number")
        return _sympy_number(v)
    f = float(v)
    if not math.isfinite(f):
        raise ValueError(f"value of {where} is {f}, not a finite number")
    a = arb(f)  # exact: the double itself
    return (a, a)


def _sympy_number(e) -> tuple:
    """The interval of a sympy number: exact where arb can hold it, else a tight outward enclosure."""
    if isinstance(e, sp.Integer):
        a = arb(int(e))
        return (a, a)
    if isinstance(e, sp.Rational):
        return _iv_ball(arb(int(e.p)) / arb(int(e.q)))
    if isinstance(e, sp.Float):
        sign, man, exp, _ = e._mpf_
        if man == 0:
            if exp == 0:
                return _Z
            raise UnsupportedExpression(e, "not a finite number")
        a = arb(int(man)) * arb(2) ** int(exp)  # exact unless the mantissa is longer than the precision
        iv = _iv_ball(-a if sign else a)
        if iv is None:
            raise UnsupportedExpression(e, "not a finite number")
        return iv
    if e is sp.pi:
        return _iv_ball(arb.pi())
    if e is sp.E:
        return _iv_ball(arb(1).exp())
    raise UnsupportedExpression(e, "only finite real numbers, pi and E are supported")


# --- the compiled function ------------------------------------------------------------------------------


def _value_step(fn, kids):
    if len(kids) == 1:
        (i,) = kids
        return lambda v: fn(v[i])
    if len(kids) == 2:
        i, j = kids
        return lambda v: fn(v[i], v[j])
    return lambda v: fn(*[v[k] for k in kids])


def _ad_step(fn, kids):
    if len(kids) == 1:
        (i,) = kids
        return lambda v: fn(*v[i])
    if len(kids) == 2:
        i, j = kids
        return lambda v: fn(*v[i], *v[j])
    return lambda v: fn(*[x for k in kids for x in v[k]])


class IntervalFunction:
    """Interval extension of a list of sympy expressions (made by :func:`compile_interval`).

    Call it with one arb ball per argument; it returns one arb ball per expression that contains the
    expression's range over the box of the balls (a nan ball where that range is not finite).  Inside,
    the work is done on exact interval ends; only the returned balls are wider, by about 2**-30 of their
    radius, since python-flint rounds a ball's radius up.  :func:`enclose`, :func:`sup_on_box`,
    :func:`inf_on_box` and :func:`prove_positive` use the exact ends directly.

    Attributes
    ----------
    args : tuple of sympy.Symbol
    exprs : tuple of sympy.Expr
    """

    def __init__(self, comp: _Compiler, outs: list[int], args: tuple, exprs: tuple):
        self.args = args
        self.exprs = exprs
        self._n_in = comp.n_in
        self._outs = outs
        self._kinds = comp.kinds
        self._consts = comp.consts
        self._ops = comp.ops
        self._tapes: dict = {}
        d = comp.n_in
        self._units = [[_I1 if i == k else _Z for i in range(d)] for k in range(d)]

    def __len__(self) -> int:
        return len(self._outs)

    def __call__(self, xs: Sequence[arb]) -> list[arb]:
        if len(xs) != self._n_in:
            raise ValueError(f"expected {self._n_in} arguments, got {len(xs)}")
        ivs = [_iv_ball(x if isinstance(x, arb) else arb(x)) for x in xs]
        return [_iv_to_ball(a) for a in self._eval(ivs)]

    # The tape for some outputs: only the slots they need, in order.
    def _tape(self, which: tuple[int, ...], ad: bool):
        key = (which, ad)
        tape = self._tapes.get(key)
        if tape is not None:
            return tape
        need = set()
        stack = [self._outs[k] for k in which]
        while stack:
            s = stack.pop()
            if s in need:
                continue
            need.add(s)
            if self._kinds[s] == "op":
                stack.extend(self._ops[s][2])
        steps = []
        init = []
        for s, kind in enumerate(self._kinds):
            c = self._consts[s]
            init.append(((c, None) if ad else c) if kind == "const" else None)
            if kind == "op" and s in need:
                value_fn, ad_fn, kids = self._ops[s]
                steps.append((s, _ad_step(ad_fn, kids) if ad else _value_step(value_fn, kids)))
        tape = (steps, init, [self._outs[k] for k in which])
        self._tapes[key] = tape
        return tape

    def _run(self, tape, inputs: list) -> list:
        steps, init, outs = tape
        v = init[:]
        v[: len(inputs)] = inputs
        for s, fn in steps:
            v[s] = fn(v)
        return [v[o] for o in outs]

    def _eval(self, ivs: list, which: tuple[int, ...] | None = None) -> list:
        """Natural interval enclosures of the outputs ``which`` (all by default) on intervals ``ivs``."""
        which = tuple(range(len(self._outs))) if which is None else which
        return self._run(self._tape(which, False), list(ivs))

    def _enclose_box(self, lo: Sequence[float], hi: Sequence[float], c: Sequence[float], which: tuple[int, ...] | None = None):
        """Enclosures on the float box [lo, hi] (natural form intersected with the mean-value form at
        the point ``c`` of the box), the enclosures at ``c`` itself, and the gradient enclosures on the
        box (a list of intervals, None for a constant, _BAD if unbounded), for the outputs ``which``."""
        which = tuple(range(len(self._outs))) if which is None else which
        X = [(arb(a), arb(b)) for a, b in zip(lo, hi)]
        C = [(arb(x),) * 2 for x in c]
        boxed = self._run(self._tape(which, True), [(x, u) for x, u in zip(X, self._units)])
        at_c = self._run(self._tape(which, False), C)
        D = None
        result = []
        for (nat, g), fc in zip(boxed, at_c):
            enc = nat
            if nat is not None and fc is not None and g is not None and g is not _BAD:
                if D is None:  # X - c, the same for every output
                    D = [_sub(x, cc) for x, cc in zip(X, C)]
                mv = fc
                for gi, di in zip(g, D):
                    if gi is not _Z:
                        mv = _add(mv, _mul(gi, di))
                if mv is not None:
                    lo_, hi_ = _intersect(nat, mv)
                    enc = (lo_, hi_) if lo_ <= hi_ else nat  # (never empty: both hold the range)
            result.append(enc)
        return result, at_c, [g for _, g in boxed]


def compile_interval(
    exprs: Sequence[sp.Expr],
    args: Sequence[sp.Symbol],
    values: Mapping[sp.Symbol, float] | None = None,
) -> IntervalFunction:
    """Compile sympy expressions into a rigorous interval extension on arb balls.

    Parameters
    ----------
    exprs : sequence of sympy.Expr
        A flat list of expressions (numbers are accepted too).
    args : sequence of sympy.Symbol
        The symbols the compiled function takes, in order.
    values : mapping of sympy.Symbol to float, optional
        Parameters fixed at compile time; each is taken as its exact double (or exact int).

    Returns
    -------
    IntervalFunction
        ``fun(balls) -> list[arb]``: for one arb ball per arg, one arb ball per expression containing
        the expression's range over the box the balls span; a nan ball where the range is not finite
        (outside the domain of sqrt, log, asin, acos, atanh, acosh, a real power; a division by a
        range holding 0; a pole of tan maybe inside).

    Raises
    ------
    UnsupportedExpression
        For a node that cannot be enclosed (e.g. ``floor``, an undefined function, ``oo``, ``I``).
    ValueError
        For a free symbol that is neither an argument nor given a value, or a bad value.

    Notes
    -----
    Supported: numbers (Integer, Rational, Float exactly; pi, E), Add, Mul, Pow (integer powers,
    tight even powers, half-integer powers via sqrt, other constant and variable exponents), sqrt, exp,
    log, sin, cos, tan, tanh, sinh, cosh, atan, asin, acos, asinh, acosh, atanh, Abs, sign, Min, Max, and
    the signal functions ``triangle``, ``square``, ``step`` of :mod:`ashc_cli.problem.expr`.  ``sign`` and
    ``step`` on a range holding their jump are enclosed by the hull of their values there (e.g.
    ``sign`` by [-1, 1]).
    """
    values = dict(values or {})
    args = tuple(args)
    if len(set(args)) != len(args):
        raise ValueError("compile_interval: repeated argument symbol")
    for s in args:
        if not isinstance(s, sp.Symbol):
            raise ValueError(f"compile_interval: argument {s!r} is not a sympy Symbol")
    comp = _Compiler(args, values)
    flat = []
    for e in exprs:
        if isinstance(e, bool):
            raise ValueError("compile_interval: a bool is not an expression")
        if isinstance(e, int):
            e = sp.Integer(e)
        elif isinstance(e, float):
            e = sp.Float(e, precision=53) if math.isfinite(e) else sp.nan  # the exact double
        elif not isinstance(e, sp.Basic):
            raise ValueError(f"compile_interval: {type(e).__name__} is not a sympy expression")
        if e.has(sp.DiracDelta, sp.Heaviside):   # sympy's derivatives of sign, min and max, as functions
            from ashc_cli.problem.model import almost_everywhere

            e = almost_everywhere(e)
        flat.append(e)
    try:
        outs = [comp.expr(e) for e in flat]
    except RecursionError:
        raise UnsupportedExpression(flat[0], "expression nested too deeply") from None
    return IntervalFunction(comp, outs, args, tuple(flat))


# --- box helpers --------------------------------------------------------------------------------------


def _check_box(box) -> tuple[list[float], list[float]]:
    b = np.asarray(box, dtype=float)
    if b.ndim != 2 or b.shape[1] != 2:
        raise ValueError(f"box must have shape (d, 2), got {b.shape}")
    if not np.all(np.isfinite(b)):
        raise ValueError("box has non-finite bounds")
    if np.any(b[:, 0] > b[:, 1]):
        raise ValueError("box has a row with lo > hi")
    return [float(x) for x in b[:, 0]], [float(x) for x in b[:, 1]]


def _mid(a: float, b: float) -> float:
    """A float in [a, b] near its middle (without overflow for huge a, b)."""
    m = a + 0.5 * (b - a)
    return m if a <= m <= b else 0.5 * a + 0.5 * b


def _centre(lo: Sequence[float], hi: Sequence[float]) -> list[float]:
    return [_mid(a, b) for a, b in zip(lo, hi)]


def enclose(fun, box: np.ndarray) -> list[tuple[float, float]]:
    """Outward-rounded float enclosures of each output of ``fun`` over a box.

    Parameters
    ----------
    fun : IntervalFunction or callable
        A compiled function, or any ``fun(list[arb]) -> list[arb]`` interval extension.
    box : ndarray, shape (d, 2)
        One [lo, hi] row per argument.

    Returns
    -------
    list of (float, float)
        ``(lo, hi)`` per output with ``lo <= f(x) <= hi`` for every x of the box; ``(nan, nan)`` where
        the enclosure is not finite.  For a compiled function the mean-value form about the centre is
        used as well when it is tighter.
    """
    lo, hi = _check_box(box)
    if isinstance(fun, IntervalFunction):
        if len(lo) != fun._n_in:
            raise ValueError(f"box has {len(lo)} rows, the function takes {fun._n_in} arguments")
        encs, _, _ = fun._enclose_box(lo, hi, _centre(lo, hi))
        # Straight from the exact interval ends: an arb ball would widen them (30-bit radius).
        return [(math.nan, math.nan) if e is None else (_fdn(e[0]), _fup(e[1])) for e in encs]
    balls = list(fun([_ball(a, b) for a, b in zip(lo, hi)]))
    out = []
    for y in balls:
        if not y.is_finite():
            out.append((math.nan, math.nan))
        else:
            out.append((_fdn(y), _fup(y)))
    return out


class _Evaluator:
    """Evaluates one output of a function on float boxes and points, as intervals (maybe negated)."""

    def __init__(self, fun, index: int, negate: bool, d: int):
        self.fun = fun
        self.index = index
        self.negate = negate
        self.compiled = isinstance(fun, IntervalFunction)
        if self.compiled:
            if not 0 <= index < len(fun):
                raise ValueError(f"index {index} out of range for {len(fun)} outputs")
            if fun._n_in != d:
                raise ValueError(f"box has {d} rows, the function takes {fun._n_in} arguments")

    def _sign(self, a):
        return _neg(a) if (self.negate and a is not None) else a

    def box(self, lo: list[float], hi: list[float], c: list[float]):
        """Evaluate on a box: ``(enc, fc, smear, up)``.

        ``enc`` encloses the function on the box and ``fc`` at the point ``c`` (intervals or None);
        ``smear[k]`` bounds how much the function can change along dimension k on the box
        (|df/dx_k| * width_k) and ``up[k]`` is the sign of df/dx_k where it is known (0 where not);
        both None without a finite gradient enclosure (e.g. for a plain callable).
        """
        if not self.compiled:
            enc = _iv_ball(self.fun([_ball(a, b) for a, b in zip(lo, hi)])[self.index])
            return self._sign(enc), self.point(c), None, None
        encs, at_c, grads = self.fun._enclose_box(lo, hi, c, (self.index,))
        enc, g = encs[0], grads[0]
        smear = up = None
        if enc is not None and isinstance(g, list):
            smear = [max(-_fdn(gk[0]), _fup(gk[1])) * (b - a) for gk, a, b in zip(g, lo, hi)]
            sgn = -1 if self.negate else 1
            up = [sgn if gk[0] > _ZERO else -sgn if gk[1] < _ZERO else 0 for gk in g]
        return self._sign(enc), self._sign(at_c[0]), smear, up

    def point(self, x: Sequence[float]):
        if self.compiled:
            a = [(arb(v),) * 2 for v in x]
            return self._sign(self.fun._eval(a, (self.index,))[0])
        return self._sign(_iv_ball(self.fun([arb(float(v)) for v in x])[self.index]))


def _widest(lo: list[float], hi: list[float], scale: list[float], smear: list[float] | None = None) -> tuple[int, float] | None:
    """The dimension to bisect and its split point, if any.

    With a gradient enclosure, the dimension along which the function may change most (largest
    smear |df/dx_k| * width_k: dimensions the function does not depend on are never split);
    otherwise, or to break ties, the widest relative to the original box.
    """
    if smear is not None and max(smear, default=0.0) > 0.0:
        order = sorted(range(len(lo)), key=lambda k: (-smear[k], -(hi[k] - lo[k]) / scale[k]))
    else:
        order = sorted(range(len(lo)), key=lambda k: -(hi[k] - lo[k]) / scale[k])
    for k in order:
        a, b = lo[k], hi[k]
        m = _mid(a, b)
        if a < m < b:
            return k, m
    return None


def _toward(lo: list[float], hi: list[float], c: list[float], direction: list[int]) -> list[float]:
    """The point of the box at c moved to the upper/lower face wherever direction is +1/-1."""
    return [b if s > 0 else a if s < 0 else m for a, b, m, s in zip(lo, hi, c, direction)]


# --- suprema and infima ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class SupResult:
    """Result of :func:`sup_on_box`.

    Attributes
    ----------
    upper : float
        A rigorous upper bound of sup_box f (``inf`` if the enclosure stayed non-finite somewhere).
    lower : float
        A value f is proved to reach or exceed at ``argmax`` (the lower end of an arb enclosure of f
        there), so ``lower <= sup_box f``; ``-inf`` if no point evaluation was finite.
    argmax : ndarray, shape (d,)
        The point where ``lower`` was found (nan if none).
    boxes : int
        Number of boxes evaluated.
    proved : bool
        Whether ``upper`` is finite and ``upper - lower <= rtol*|lower| + atol``.
    """

    upper: float
    lower: float
    argmax: np.ndarray
    boxes: int
    proved: bool


@dataclass(frozen=True)
class InfResult:
    """Result of :func:`inf_on_box`.

    Attributes
    ----------
    lower : float
        A rigorous lower bound of inf_box f (``-inf`` if the enclosure stayed non-finite somewhere).
    upper : float
        A value f is proved to reach or fall below at ``argmin`` (the upper end of an arb enclosure of f
        there), so ``upper >= inf_box f``; ``inf`` if no point evaluation was finite.
    argmin : ndarray, shape (d,)
        The point where ``upper`` was found (nan if none).
    boxes : int
        Number of boxes evaluated.
    proved : bool
        Whether ``lower`` is finite and ``upper - lower <= rtol*|upper| + atol``.
    """

    lower: float
    upper: float
    argmin: np.ndarray
    boxes: int
    proved: bool


def _branch_and_bound(fun, box, index, negate, rtol, atol, max_boxes, time_budget, seeds):
    """Maximise output ``index`` of fun (of -fun when negate); returns (upper, lower, argmax, boxes, proved)."""
    lo0, hi0 = _check_box(box)
    d = len(lo0)
    if rtol < 0 or atol < 0:
        raise ValueError("rtol and atol must be >= 0")
    ev = _Evaluator(fun, index, negate, d)
    scale = [(b - a) if b > a else 1.0 for a, b in zip(lo0, hi0)]
    start = time.perf_counter()
    best = -_INF  # incumbent: a proved lower bound of the sup
    arg: list[float] | None = None

    def offer(iv, x):
        nonlocal best, arg
        if iv is not None:
            v = _fdn(iv[0])
            if v > best:
                best, arg = v, list(x)

    if seeds is not None:
        S = np.atleast_2d(np.asarray(seeds, dtype=float))
        if S.size and S.shape[1] != d:
            raise ValueError(f"seeds must have shape (k, {d}), got {S.shape}")
        for s in S:
            if np.all(np.isfinite(s)):
                p = np.clip(s, lo0, hi0)  # a seed just outside the box (rounding) still helps
                offer(ev.point([float(v) for v in p]), p)

    counter = 0
    heap: list = []
    dropped = -_INF  # the largest upper bound of a box dropped for upper <= incumbent
    final = -_INF  # the largest upper bound of a box too small to split

    def push(lo, hi):
        nonlocal counter, dropped
        c = _centre(lo, hi)
        enc, fc, smear, updir = ev.box(lo, hi, c)
        counter += 1
        offer(fc, c)
        if updir is not None and any(updir):
            # Where the sign of the gradient is known, the best point is on that face (boundary maxima).
            p = _toward(lo, hi, c, updir)
            offer(ev.point(p), p)
        up = _INF if enc is None else _fup(enc[1])
        if up <= best:
            dropped = max(dropped, up)
        else:
            heapq.heappush(heap, (-up, counter, lo, hi, smear))

    push(lo0, hi0)
    proved = False
    while True:
        upper = max(-heap[0][0] if heap else -_INF, dropped, final)
        if math.isfinite(upper) and best > -_INF and upper - best <= rtol * abs(best) + atol:
            proved = True
            break
        if not heap or counter >= max_boxes or time.perf_counter() - start > time_budget:
            break
        neg_up, _, lo, hi, smear = heapq.heappop(heap)
        if -neg_up <= best:
            dropped = max(dropped, -neg_up)
            continue
        cut = _widest(lo, hi, scale, smear)
        if cut is None:
            final = max(final, -neg_up)
            continue
        k, m = cut
        push(lo, hi[:k] + [m] + hi[k + 1 :])
        push(lo[:k] + [m] + lo[k + 1 :], hi)
    if not math.isfinite(upper):
        upper = _INF
    argv = np.array(arg, dtype=float) if arg is not None else np.full(d, math.nan)
    return upper, best, argv, counter, proved


def sup_on_box(
    fun,
    box: np.ndarray,
    *,
    index: int = 0,
    rtol: float = 1e-3,
    atol: float = 0.0,
    max_boxes: int = 20000,
    time_budget: float = 20.0,
    seeds: np.ndarray | None = None,
) -> SupResult:
    """A rigorous upper bound of the supremum of one output of ``fun`` over a box (branch and bound).

    Parameters
    ----------
    fun : IntervalFunction or callable
        A compiled function (fast path: natural and mean-value enclosures) or any interval extension
        ``fun(list[arb]) -> list[arb]``.
    box : ndarray, shape (d, 2)
        One [lo, hi] row per argument.
    index : int
        Which output of ``fun`` to maximise.
    rtol, atol : float
        Stop once ``upper - lower <= rtol*|lower| + atol``.
    max_boxes : int
        Budget of box evaluations.
    time_budget : float
        Budget of wall time in seconds (checked between bisections).
    seeds : ndarray, shape (k, d), optional
        Points evaluated first to start the incumbent (e.g. a grid argmax); clipped into the box.

    Returns
    -------
    SupResult
        ``upper`` is a rigorous bound whenever it is finite, even when ``proved`` is False (budget).

    Notes
    -----
    Boxes are kept in a priority queue keyed by their enclosure's upper end; the worst is bisected, the
    halves are enclosed and their centres evaluated (raising the incumbent), and boxes whose upper end
    is <= the incumbent are dropped.  A box with a non-finite enclosure has upper end ``inf`` and is
    split first.  For a compiled function the enclosure is the natural one intersected with the
    mean-value form, the split dimension is the one along which f may change most (|df/dx_k| times the
    width; the widest relative to the original box without a gradient), and where the sign of a partial
    derivative is known the point on the matching face is evaluated too (boundary maxima).
    """
    upper, lower, arg, boxes, proved = _branch_and_bound(fun, box, index, False, rtol, atol, max_boxes, time_budget, seeds)
    return SupResult(upper=upper, lower=lower, argmax=arg, boxes=boxes, proved=proved)


def inf_on_box(
    fun,
    box: np.ndarray,
    *,
    index: int = 0,
    rtol: float = 1e-3,
    atol: float = 0.0,
    max_boxes: int = 20000,
    time_budget: float = 20.0,
    seeds: np.ndarray | None = None,
) -> InfResult:
    """A rigorous lower bound of the infimum of one output of ``fun`` over a box.

    The mirror of :func:`sup_on_box` (it maximises ``-f``); see there for the parameters.

    Returns
    -------
    InfResult
        ``lower`` is rigorous whenever finite; ``upper`` is a value reached at ``argmin``.
    """
    upper, lower, arg, boxes, proved = _branch_and_bound(fun, box, index, True, rtol, atol, max_boxes, time_budget, seeds)
    return InfResult(lower=-upper + 0.0, upper=-lower + 0.0, argmin=arg, boxes=boxes, proved=proved)  # (+0.0: no -0.0)


def prove_positive(
    fun,
    box: np.ndarray,
    *,
    index: int = 0,
    max_boxes: int = 20000,
    time_budget: float = 20.0,
) -> tuple[bool, float]:
    """Prove f > 0 on a whole box, or refute it at a point, by splitting the box.

    Parameters
    ----------
    fun : IntervalFunction or callable
        As for :func:`sup_on_box`.
    box : ndarray, shape (d, 2)
    index : int
        Which output of ``fun``.
    max_boxes, time_budget
        Budgets, as for :func:`sup_on_box`.

    Returns
    -------
    (bool, float)
        ``(True, m)`` with ``0 < m <= inf_box f`` rigorous when proved (``m`` may round to 0.0 only if
        the true bound is below the smallest double); ``(False, v)`` with ``v >= f(x) `` and ``v <= 0``
        for a point x of the box once one is found (f is not positive); ``(False, b)`` on budget, ``b``
        the best rigorous lower bound of f over the box so far (``-inf`` if some enclosure stayed
        non-finite).
    """
    lo0, hi0 = _check_box(box)
    d = len(lo0)
    ev = _Evaluator(fun, index, False, d)
    scale = [(b - a) if b > a else 1.0 for a, b in zip(lo0, hi0)]
    start = time.perf_counter()
    heap: list = []
    counter = 0
    proved_min = None  # smallest lower end among boxes proved positive (an exact arb)
    stuck_min = _INF  # lower bounds of boxes too small to split that are not proved

    def visit(lo, hi):
        """Enclose a box; returns a refuting value, or None after queueing/recording the box."""
        nonlocal counter, proved_min
        c = _centre(lo, hi)
        enc, fc, smear, updir = ev.box(lo, hi, c)
        counter += 1
        if fc is not None and fc[1] <= _ZERO:
            return _fup(fc[1])
        if enc is not None and enc[0] > _ZERO:
            proved_min = enc[0] if proved_min is None else min(proved_min, enc[0])
            return None
        if updir is not None and any(updir):
            fp = ev.point(_toward(lo, hi, c, [-u for u in updir]))  # the face where f is lowest
            if fp is not None and fp[1] <= _ZERO:
                return _fup(fp[1])
        low = -_INF if enc is None else _fdn(enc[0])
        heapq.heappush(heap, (low, counter, lo, hi, smear))
        return None

    v = visit(lo0, hi0)
    if v is not None:
        return False, v
    while heap:
        if counter >= max_boxes or time.perf_counter() - start > time_budget:
            break
        low, _, lo, hi, smear = heapq.heappop(heap)
        cut = _widest(lo, hi, scale, smear)
        if cut is None:
            stuck_min = min(stuck_min, low)
            continue
        k, m = cut
        for sub in ((lo, hi[:k] + [m] + hi[k + 1 :]), (lo[:k] + [m] + lo[k + 1 :], hi)):
            v = visit(*sub)
            if v is not None:
                return False, v
    bounds = [stuck_min] + ([heap[0][0]] if heap else [])
    if proved_min is not None:
        bounds.append(_fdn(proved_min))
    if not heap and stuck_min == _INF:
        return True, _fdn(proved_min)
    return False, min(bounds)


# --- matrices -------------------------------------------------------------------------------------------


def psd_lower_bound(S: np.ndarray) -> float:
    """A rigorous lower bound on the smallest eigenvalue of a symmetric float matrix.

    Parameters
    ----------
    S : ndarray, shape (n, n)
        Entries are taken as exact doubles; if S is not exactly symmetric, its symmetric part
        (S + S^T)/2 is used (formed exactly in arb).

    Returns
    -------
    float
        ``b`` with ``lambda_min((S + S^T)/2) >= b``; ``-inf`` if nothing could be proved.

    Raises
    ------
    ValueError
        If S is not a non-empty square matrix.
    NumericalError
        If S has non-finite entries.

    Notes
    -----
    With ``tau`` just below numpy's estimate of lambda_min, a float Cholesky factor L of S - tau I is
    computed and the residual R = S - tau I - L L^T is enclosed in arb.  As L L^T is positive
    semidefinite for any real L, Weyl's inequality gives lambda_min(S) >= tau - ||R||_2 >= tau - ||R||_F.
    If the Cholesky fails, tau is lowered (a few times).
    """
    S = np.asarray(S, dtype=float)
    if S.ndim != 2 or S.shape[0] != S.shape[1] or S.shape[0] == 0:
        raise ValueError(f"psd_lower_bound needs a non-empty square matrix, got shape {S.shape}")
    if not np.all(np.isfinite(S)):
        raise NumericalError("psd_lower_bound", "the matrix has non-finite entries", "a finite symmetric matrix")
    n = S.shape[0]
    if np.array_equal(S, S.T):
        A = S
        A_arb = arb_mat(S.tolist())
    else:
        A = 0.5 * (S + S.T)
        A_arb = (arb_mat(S.tolist()) + arb_mat(S.T.tolist())) * arb(0.5)
    amax = float(np.max(np.abs(A)))
    try:
        with np.errstate(all="ignore"):
            lam = float(np.linalg.eigvalsh(A)[0])
            norm = float(np.linalg.norm(A / amax)) * amax if amax > 0 else 0.0  # scaled: no overflow
    except np.linalg.LinAlgError:
        return -_INF
    if not (math.isfinite(lam) and math.isfinite(norm)):
        return -_INF
    # Shift below the estimate by a few times the Cholesky backward error, then more if it fails.
    base = 8.0 * (n + 1) * np.finfo(float).eps * max(norm, np.finfo(float).tiny)
    eye = np.eye(n)
    for k in range(8):
        tau = lam - base * 100.0**k
        if not math.isfinite(tau):
            break
        try:
            with np.errstate(all="ignore"):
                L = np.linalg.cholesky(A - tau * eye)
        except np.linalg.LinAlgError:
            continue
        if not np.all(np.isfinite(L)):
            continue
        La = arb_mat(L.tolist())
        R = A_arb - La * La.transpose()
        t = arb(tau)
        sq = arb(0)
        for i in range(n):
            for j in range(n):
                r = R[i, j] - t if i == j else R[i, j]
                m = r.abs_upper()
                sq += m * m
        if not sq.is_finite():
            continue
        return _fdn(t - sq.sqrt().upper())
    return -_INF


def prove_psd(S: np.ndarray, margin: float = 0.0) -> bool:
    """Whether lambda_min of the symmetric float matrix S is proved >= ``margin`` (see :func:`psd_lower_bound`)."""
    return psd_lower_bound(S) >= margin


def lambda_max_upper(G) -> float:
    """A rigorous upper bound of the largest eigenvalue of a symmetric matrix known entrywise as arbs.

    Parameters
    ----------
    G : list of lists of arb, or arb_mat, shape (n, n)
        Enclosures of the entries of a real symmetric matrix (e.g. of A^T A computed in arb).

    Returns
    -------
    float
        ``max_i (g_ii + sum_{j != i} |g_ij|)`` over the upper ends of the balls (Gershgorin), rounded
        up; ``inf`` if an entry is not finite.
    """
    if isinstance(G, arb_mat):
        rows = [[G[i, j] for j in range(G.ncols())] for i in range(G.nrows())]
    else:
        rows = [[x if isinstance(x, arb) else arb(x) for x in row] for row in G]
    n = len(rows)
    if n == 0 or any(len(r) != n for r in rows):
        raise ValueError("lambda_max_upper needs a non-empty square matrix")
    if not all(g.is_finite() for row in rows for g in row):
        return _INF
    best = -_INF
    for i, row in enumerate(rows):
        s = row[i].upper()
        for j, g in enumerate(row):
            if j != i:
                s = s + g.abs_upper()
        best = max(best, _fup(s))
    return best
