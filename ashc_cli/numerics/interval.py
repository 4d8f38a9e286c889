"""Rigorous enclosures of functions over boxes, on python-flint's arb, for certificates: sympy expressions compiled
to interval extensions with first derivatives (the box searches built on them are :mod:`ashc_cli.numerics.boxsearch`).

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
Clarke-style enclosures for the Lipschitz kinks of ``Abs``, ``Min``, ``Max`` and ``triangle``), from which
:func:`enclose` and the box searches form the mean-value enclosure.  The arithmetic is :mod:`ashc_cli.numerics._infsup`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np
import sympy as sp
from flint import arb

from ashc_cli.errors import UnsupportedExpression
from ashc_cli.numerics._infsup import (
    BAD, I1, SYMPY_UNARY, UNARY, Z, ad_add, ad_minmax, ad_mul, ad_pow_gen, ad_pow_real, ad_powi, ad_unary, ball_of, centre, check_box, fdn,
    from_ball, fup, iv_add, iv_intersect, iv_max, iv_min, iv_mul, iv_pow_gen, iv_pow_real, iv_powi, iv_sub, number_interval, sympy_number,
    to_ball,
)

__all__ = ["UnsupportedExpression", "IntervalFunction", "compile_interval", "enclose"]


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
            self.memo[("sym", s)] = self.const(number_interval(v, s))

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
        return self.op((name,), UNARY[name], ad_unary(name), (kid,))

    def add(self, a: int, b: int) -> int:
        return self.op(("add",), iv_add, ad_add, (a, b))

    def mul(self, a: int, b: int) -> int:
        return self.op(("mul",), iv_mul, ad_mul, (a, b))

    def powi(self, a: int, n: int) -> int:
        return self.op(("powi", n), lambda x: iv_powi(x, n), ad_powi(n), (a,))

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
            return self.const(sympy_number(e))
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
            return self.op(("max" if is_max else "min",), iv_max if is_max else iv_min, ad_minmax(is_max), kids)
        name = SYMPY_UNARY.get(e.func)
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
                return self.const(I1)
            pos = b if abs(n) == 1 else self.powi(b, abs(n))
            return pos if n > 0 else self.unary("recip", pos)
        if ex.is_Rational and ex.q == 2:
            # Half-integer powers through sqrt: x**(p/2) = sqrt(x)**p.
            root = self.unary("sqrt", self.expr(base))
            p = int(ex.p)
            pos = root if abs(p) == 1 else self.powi(root, abs(p))
            return pos if p > 0 else self.unary("recip", pos)
        if ex.is_Number:
            r = sympy_number(ex)
            rb = to_ball(r)
            if not rb.is_finite():
                raise UnsupportedExpression(e, "non-finite exponent")
            return self.op(("powr", str(ex)), lambda x: iv_pow_real(x, rb), ad_pow_real(rb), (self.expr(base),))
        # A variable exponent: exp(y log x), defined where x > 0.
        return self.op(("pow",), iv_pow_gen, ad_pow_gen, (self.expr(base), self.expr(ex)))




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
        self.n_in = comp.n_in
        self._outs = outs
        self._kinds = comp.kinds
        self._consts = comp.consts
        self._ops = comp.ops
        self._tapes: dict = {}
        d = comp.n_in
        self._units = [[I1 if i == k else Z for i in range(d)] for k in range(d)]

    def __len__(self) -> int:
        return len(self._outs)

    def __call__(self, xs: Sequence[arb]) -> list[arb]:
        if len(xs) != self.n_in:
            raise ValueError(f"expected {self.n_in} arguments, got {len(xs)}")
        ivs = [from_ball(x if isinstance(x, arb) else arb(x)) for x in xs]
        return [to_ball(a) for a in self.eval_intervals(ivs)]

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

    def eval_intervals(self, ivs: list, which: tuple[int, ...] | None = None) -> list:
        """Natural interval enclosures of the outputs ``which`` (all by default) on intervals ``ivs``."""
        which = tuple(range(len(self._outs))) if which is None else which
        return self._run(self._tape(which, False), list(ivs))

    def enclose_box(self, lo: Sequence[float], hi: Sequence[float], c: Sequence[float], which: tuple[int, ...] | None = None):
        """Enclosures on the float box [lo, hi] (natural form intersected with the mean-value form at
        the point ``c`` of the box), the enclosures at ``c`` itself, and the gradient enclosures on the
        box (a list of intervals, None for a constant, BAD if unbounded), for the outputs ``which``."""
        which = tuple(range(len(self._outs))) if which is None else which
        X = [(arb(a), arb(b)) for a, b in zip(lo, hi)]
        C = [(arb(x),) * 2 for x in c]
        boxed = self._run(self._tape(which, True), [(x, u) for x, u in zip(X, self._units)])
        at_c = self._run(self._tape(which, False), C)
        D = None
        result = []
        for (nat, g), fc in zip(boxed, at_c):
            enc = nat
            if nat is not None and fc is not None and g is not None and g is not BAD:
                if D is None:  # X - c, the same for every output
                    D = [iv_sub(x, cc) for x, cc in zip(X, C)]
                mv = fc
                for gi, di in zip(g, D):
                    if gi is not Z:
                        mv = iv_add(mv, iv_mul(gi, di))
                if mv is not None:
                    lo_, hi_ = iv_intersect(nat, mv)
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
    lo, hi = check_box(box)
    if isinstance(fun, IntervalFunction):
        if len(lo) != fun.n_in:
            raise ValueError(f"box has {len(lo)} rows, the function takes {fun.n_in} arguments")
        encs, _, _ = fun.enclose_box(lo, hi, centre(lo, hi))
        # Straight from the exact interval ends: an arb ball would widen them (30-bit radius).
        return [(math.nan, math.nan) if e is None else (fdn(e[0]), fup(e[1])) for e in encs]
    balls = list(fun([ball_of(a, b) for a, b in zip(lo, hi)]))
    out = []
    for y in balls:
        if not y.is_finite():
            out.append((math.nan, math.nan))
        else:
            out.append((fdn(y), fup(y)))
    return out
