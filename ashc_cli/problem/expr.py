"""Whitelist parser from spec expression strings to sympy, and a safe reader of stored ``srepr`` strings.

A spec is untrusted input, so nothing here calls ``eval``, ``exec`` or ``sympy.sympify`` on its text.
The text is parsed by :func:`ast.parse` into a syntax tree, and the tree is walked node by node: only
numbers, declared names, the arithmetic operators and a fixed list of functions become sympy objects;
any other node (attribute access, indexing, lambdas, comprehensions, strings, f-strings, keyword
arguments, ...) is refused with a :class:`~ashc_cli.errors.SpecError` naming the field.  Size limits keep
a hostile expression from costing time: its length, its nesting depth and the size of literal powers.

The same approach reads the ``srepr`` strings that artefacts store (:func:`from_srepr`): only calls of
whitelisted sympy constructors with literal arguments are allowed.
"""

from __future__ import annotations

import ast
import difflib
import math
import re
import warnings
from collections.abc import Mapping

import numpy as np
import sympy as sp

from ashc_cli.errors import ArtefactError, SpecError

__all__ = [
    "FUNCTIONS",
    "SIGNAL_FUNCTIONS",
    "RESERVED_NAMES",
    "MAX_LENGTH",
    "MAX_DEPTH",
    "parse_expression",
    "from_srepr",
    "NUMERIC_MODULES",
    "triangle",
    "square",
    "step",
]

#: Longest expression text accepted, in characters.
MAX_LENGTH = 2000
#: Deepest nesting of the syntax tree accepted.
MAX_DEPTH = 60
#: Largest magnitude of a literal exponent, and of log10 of a literal power's value.
MAX_LITERAL_EXPONENT = 100
MAX_LITERAL_LOG10 = 300


# --- time-signal functions of the spec (the paper's nabla and friends) ---------------------------------


def _np_triangle(t):
    """Numeric triangle wave: (2/pi) int_0^t sign(sin s) ds - 1 (period 2 pi, -1 at t = 0)."""
    tau = np.mod(np.asarray(t, dtype=float), 2.0 * np.pi)
    return np.where(tau < np.pi, -1.0 + 2.0 * tau / np.pi, 3.0 - 2.0 * tau / np.pi)


def _np_square(t):
    """Numeric square wave: sign(sin t)."""
    return np.sign(np.sin(np.asarray(t, dtype=float)))


def _np_step(t):
    """Numeric unit step: 1 for t >= 0, else 0."""
    return np.where(np.asarray(t, dtype=float) >= 0.0, 1.0, 0.0)


def _np_lambertw(z, k=0):
    """Numeric Lambert W (sympy.solve writes it into closed forms such as the inverse of x e^-x): scipy's, real where
    the branch is real (complex values become NaN in :func:`ashc_cli.problem.model.lambdify`)."""
    from scipy.special import lambertw

    return np.real_if_close(lambertw(z, int(k)), tol=1e6)


class triangle(sp.Function):
    """The paper's nabla(t) = (2/pi) int_0^t sign(sin s) ds - 1: a triangle wave of period 2 pi in [-1, 1]."""

    nargs = 1


class square(sp.Function):
    """Square wave sign(sin t)."""

    nargs = 1


class step(sp.Function):
    """Unit step: 1 for t >= 0, else 0."""

    nargs = 1


#: Functions a spec expression may call, with their arity (``None``: two or more arguments).
FUNCTIONS: dict[str, tuple[object, int | None]] = {
    "sqrt": (sp.sqrt, 1),
    "exp": (sp.exp, 1),
    "log": (sp.log, 1),
    "sin": (sp.sin, 1),
    "cos": (sp.cos, 1),
    "tan": (sp.tan, 1),
    "tanh": (sp.tanh, 1),
    "atan": (sp.atan, 1),
    "abs": (sp.Abs, 1),
    "sign": (sp.sign, 1),
    "min": (sp.Min, None),
    "max": (sp.Max, None),
}
#: Functions only time signals (``simulate.*.u``) may call.
SIGNAL_FUNCTIONS: dict[str, tuple[object, int | None]] = {
    "triangle": (triangle, 1),
    "square": (square, 1),
    "step": (step, 1),
}
#: Names a spec may not use for its own states, inputs or parameters.
RESERVED_NAMES = frozenset(FUNCTIONS) | frozenset(SIGNAL_FUNCTIONS) | {"pi", "t"}

#: Extra modules for :func:`sympy.lambdify` so the signal functions evaluate numerically.
NUMERIC_MODULES = [{"triangle": _np_triangle, "square": _np_square, "step": _np_step, "LambertW": _np_lambertw}, "numpy"]

_BINOPS = {ast.Add, ast.Sub, ast.Mult, ast.Div, ast.Pow}


class _Builder:
    """Walks an expression's syntax tree and builds the sympy expression, refusing anything else."""

    def __init__(self, names: Mapping[str, sp.Basic], field: str, functions: Mapping[str, tuple], offer=None):
        self.names = names
        self.field = field
        self.functions = functions
        self.offer = list(names) if offer is None else [n for n in offer if n in names]

    def fail(self, what: str, expected: str) -> SpecError:
        return SpecError(self.field, what, expected)

    def build(self, node: ast.AST, depth: int = 0) -> sp.Expr:
        if depth > MAX_DEPTH:
            raise self.fail(f"expression nested deeper than {MAX_DEPTH} levels", "a simpler expression")
        if isinstance(node, ast.Expression):
            return self.build(node.body, depth + 1)
        if isinstance(node, ast.Constant):
            return self.constant(node.value)
        if isinstance(node, ast.Name):
            return self.name(node.id)
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            operand = self.build(node.operand, depth + 1)
            return -operand if isinstance(node.op, ast.USub) else operand
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            left = self.build(node.left, depth + 1)
            right = self.build(node.right, depth + 1)
            return self.binop(node.op, left, right)
        if isinstance(node, ast.Call):
            return self.call(node, depth)
        raise self.fail(f"'{_describe(node)}' is not allowed", "arithmetic (+ - * / ** ^) on numbers, declared names and the functions " + ", ".join(self.functions))

    def constant(self, value) -> sp.Expr:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(f"literal {value!r} is not a number", "a real number")
        if isinstance(value, float):
            if not math.isfinite(value):
                raise self.fail(f"literal {value!r} is not finite", "a finite number")
            return sp.Rational(repr(value))  # exact: 0.3 -> 3/10, so formulas stay exact
        return sp.Integer(value)

    def name(self, ident: str) -> sp.Expr:
        if ident in self.names:
            return self.names[ident]
        if ident == "pi":
            return sp.pi
        known = _listing(sorted(self.offer, key=_natural))
        if ident in self.functions:
            raise self.fail(f"unknown name '{ident}' ({ident} is a function: call it as {ident}(...))",
                            f"one of the declared names ({known}) or pi")
        hint = _did_you_mean(ident, [*self.offer, "pi"])
        raise self.fail(f"unknown name '{ident}'{hint}", f"one of the declared names ({known}) or pi")

    def binop(self, op: ast.operator, left: sp.Expr, right: sp.Expr) -> sp.Expr:
        if isinstance(op, ast.Add):
            return left + right
        if isinstance(op, ast.Sub):
            return left - right
        if isinstance(op, ast.Mult):
            return left * right
        if isinstance(op, ast.Div):
            if right.is_zero:
                raise self.fail("division by zero", "a non-zero divisor")
            return left / right
        # Power: keep literal powers small so sympy never builds a huge number.
        if right.is_Number:
            if abs(float(right)) > MAX_LITERAL_EXPONENT:
                raise self.fail(f"exponent {right} is too large", f"|exponent| <= {MAX_LITERAL_EXPONENT}")
            if left.is_Number and left != 0:
                if abs(float(right)) * abs(math.log10(abs(float(left)))) > MAX_LITERAL_LOG10:
                    raise self.fail(f"the power {left}**{right} is too large", f"a value below 1e{MAX_LITERAL_LOG10}")
            if left.is_zero and right.is_negative:
                raise self.fail("division by zero (0 to a negative power)", "a non-zero base")
        return left**right

    def call(self, node: ast.Call, depth: int) -> sp.Expr:
        if not isinstance(node.func, ast.Name) or node.func.id not in self.functions:
            what = f"call of '{_describe(node.func)}' is not allowed"
            if isinstance(node.func, ast.Name) and node.func.id in SIGNAL_FUNCTIONS:
                what += " here (a time signal: only in simulate.m_relation.u and simulate.tracking.reference)"
            elif isinstance(node.func, ast.Name) and (node.func.id in self.names or node.func.id == "pi"):
                what += f" ({node.func.id} is a name, not a function: write {node.func.id}*(...) for a product)"
            elif isinstance(node.func, ast.Name):
                what += _did_you_mean(node.func.id, self.functions)
            raise self.fail(what, "one of the functions " + ", ".join(self.functions))
        if node.keywords:
            raise self.fail(f"keyword arguments in a call of {node.func.id} are not allowed", "positional arguments")
        func, arity = self.functions[node.func.id]
        args = []
        for a in node.args:
            if isinstance(a, ast.Starred):
                raise self.fail("starred arguments are not allowed", "positional arguments")
            args.append(self.build(a, depth + 1))
        if arity is None and len(args) < 2:
            raise self.fail(f"{node.func.id} takes two or more arguments, got {len(args)}", "two or more arguments")
        if arity is not None and len(args) != arity:
            raise self.fail(f"{node.func.id} takes {arity} argument(s), got {len(args)}", f"{arity} argument(s)")
        return func(*args)


def _did_you_mean(word: str, candidates) -> str:
    """The hint for an unknown name, as the spec loader gives for an unknown key.

    Parameters
    ----------
    word : str
        The unknown name.
    candidates : iterable of str
        The names it could have meant.

    Returns
    -------
    str
        ``" (did you mean 'x1'?)"``, to follow the unknown name, for the candidate equal to ``word`` but for case, else the closest one
        (:func:`difflib.get_close_matches`); ``""`` if none is close.
    """
    candidates = list(candidates)
    folded = [c for c in candidates if c.lower() == word.lower()]
    close = folded or difflib.get_close_matches(word, candidates, n=1) or difflib.get_close_matches(
        word.lower(), candidates, n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _natural(name: str) -> list:
    """Sort key putting x2 before x10."""
    return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name)]


def _listing(names: list[str], limit: int = 40) -> str:
    """The names for an error message.

    Parameters
    ----------
    names : list of str
        The names, in the order to show them.
    limit : int
        Most names shown; past it, the first ``limit`` and how many there are in all.

    Returns
    -------
    str
        ``"a, b, c"``, ``"none"`` for no names.
    """
    if not names:
        return "none"
    if len(names) <= limit:
        return ", ".join(names)
    return ", ".join(names[:limit]) + f", ... ({len(names)} in all)"


def _describe(node: ast.AST) -> str:
    """A short, safe description of a syntax node for an error message."""
    try:
        text = ast.unparse(node)
    except Exception:  # pragma: no cover - unparse of odd nodes
        text = type(node).__name__
    return text if len(text) <= 40 else text[:37] + "..."


def parse_expression(
    text: object,
    names: Mapping[str, sp.Basic],
    field: str,
    *,
    signal: bool = False,
    offer=None,
) -> sp.Expr:
    """Parse one spec expression into sympy through the whitelist.

    Parameters
    ----------
    text : str or number
        The expression as written in the spec (``^`` is read as ``**``).
    names : mapping of str to sympy object
        The names the expression may use (states, inputs, parameters, ``t``) and what each stands for.
    field : str
        The spec field the text came from, used in error messages (e.g. ``concrete.f_bar[0]``).
    signal : bool
        Whether the time-signal functions ``triangle``, ``square`` and ``step`` are allowed.
    offer : iterable of str, optional
        The names this field may use, listed (and suggested) when an unknown name is met [default: all of
        ``names``]; e.g. f_bar is offered the states and parameters only, not u, v or xi.

    Returns
    -------
    sympy.Expr
        The parsed expression.

    Raises
    ------
    SpecError
        If the text is not a number or a string, is too long or too deep, does not parse, uses
        anything outside the whitelist, divides by a literal zero or is not finite.
    """
    if isinstance(text, bool) or not isinstance(text, (str, int, float)):
        raise SpecError(field, f"{type(text).__name__} value {_short(text)} is not an expression", "a string such as \"x1 + 2*sin(x2)\"")
    source = str(text).strip()
    if not source:
        raise SpecError(field, "empty expression", "an expression such as \"0\" or \"x1 - x2\"")
    if len(source) > MAX_LENGTH:
        raise SpecError(field, f"expression is {len(source)} characters long", f"at most {MAX_LENGTH}")
    source = source.replace("^", "**")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. "invalid decimal literal": the error below says it
            tree = ast.parse(source, mode="eval")
    except SyntaxError as exc:
        raise SpecError(field, f"syntax error in '{_short(source)}' at column {exc.offset}", "an expression in ordinary math syntax") from None
    except (RecursionError, MemoryError, ValueError):
        raise SpecError(field, "expression could not be parsed (too deep or malformed)", "a simpler expression") from None
    functions = {**FUNCTIONS, **SIGNAL_FUNCTIONS} if signal else FUNCTIONS
    try:
        expr = _Builder(names, field, functions, offer).build(tree)
    except RecursionError:
        raise SpecError(field, "expression nested too deeply", "a simpler expression") from None
    if expr.has(sp.zoo, sp.nan, sp.oo, -sp.oo):
        raise SpecError(field, f"'{_short(source)}' is not finite (a division by zero?)", "a finite expression")
    return expr


def _short(value: object, limit: int = 60) -> str:
    text = str(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


# --- stored expressions -------------------------------------------------------------------------------

_SREPR_CALLS: dict[str, object] = {
    name: getattr(sp, name)
    for name in (
        "Symbol", "Dummy", "Integer", "Rational", "Float", "Add", "Mul", "Pow", "Abs", "sign", "exp", "log",
        "sin", "cos", "tan", "tanh", "atan", "asin", "acos", "Min", "Max", "Tuple",
        # A piecewise Chebyshev fit's formula (numerics.chebyshev.PiecewiseSeries): pieces chosen by comparisons.
        "Piecewise", "StrictLessThan",
    )
}
_SREPR_CALLS["ExprCondPair"] = lambda expr, cond: (expr, cond)   # a Piecewise argument
_SREPR_CALLS.update({"triangle": triangle, "square": square, "step": step})
_SREPR_NAMES = {"pi": sp.pi, "E": sp.E, "oo": sp.oo, "zoo": sp.zoo, "nan": sp.nan, "I": sp.I, "true": sp.true}


def from_srepr(text: str, where: str = "artefact") -> sp.Expr:
    """Rebuild an expression stored with :func:`sympy.srepr`, without evaluating any code.

    Parameters
    ----------
    text : str
        The ``srepr`` string, e.g. ``Mul(Integer(2), Symbol('x', real=True))``.
    where : str
        Where the string came from, for the error message.

    Returns
    -------
    sympy.Expr

    Raises
    ------
    ArtefactError
        If the string holds anything but whitelisted constructors and literals.
    """
    try:
        tree = ast.parse(text, mode="eval")
        return _srepr_node(tree.body)
    except (SyntaxError, RecursionError, ValueError, TypeError) as exc:
        raise ArtefactError(where, f"stored expression could not be read ({type(exc).__name__})", "an ashc-written srepr string") from None


def _srepr_node(node: ast.AST):
    if isinstance(node, ast.Constant) and isinstance(node.value, (str, int, float, bool)):
        return node.value
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        return -_srepr_node(node.operand)
    if isinstance(node, ast.Name) and node.id in _SREPR_NAMES:
        return _SREPR_NAMES[node.id]
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in _SREPR_CALLS:
        args = [_srepr_node(a) for a in node.args]
        kwargs = {}
        for kw in node.keywords:
            if kw.arg is None or not isinstance(kw.value, ast.Constant):
                raise ValueError("bad keyword")
            kwargs[kw.arg] = kw.value.value
        if node.func.id in ("Min", "Max"):
            # Stored from an evaluated Min/Max: rebuilding it evaluated again searched for redundant arguments with
            # factor_terms each time (15 s to read a two-variable Chebyshev formula with 1400 clipped cosines).
            kwargs["evaluate"] = False
        return _SREPR_CALLS[node.func.id](*args, **kwargs)
    raise ValueError(f"node {type(node).__name__} not allowed")
