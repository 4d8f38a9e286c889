"""The interface's numba functions printed as C and as plain Python: ``ashc export`` writes the law the compiled
loops run, from the same source (:mod:`ashc_cli.closedloop.interface`), so that a change to the law is one edit.

The functions are written in a small subset of Python that this module reads with :mod:`ast`: parameters annotated
``F1`` (1-D float array), ``F2`` (2-D float array, row-major), ``int`` or ``float`` (``ashc_cli.closedloop.laws``'
F1, F2: numba's types, which numba ignores as annotations); statements are
assignments (to a name, an element or several names at once), ``+=``, ``for`` over ``range``, ``if`` / ``elif`` /
``else``, a bare ``return`` and calls of other such functions; expressions are arithmetic, comparisons, ``and`` /
``or`` / ``not``, ``a if c else b``, ``min`` / ``max`` of two, ``np.inf``, ``A.shape[k]``, ``x.size`` and
indexing.  Anything else is a :class:`Untranslatable` naming the function and the line, which the tests turn into
a failure: a law edited beyond the subset cannot reach an export that differs from the loops.

In C an array parameter ``A`` becomes ``A`` with its extents ``A_rows``, ``A_cols`` (``x_n`` for a vector), and
``A[i, j]`` becomes ``A[(i) * A_cols + (j)]``; Python's ``min(a, b)`` (the first unless the second is smaller) and
``max`` keep their meaning with NaN as ``ASHC_MIN`` / ``ASHC_MAX``; a work array ``w = np.empty((r, c))`` is a C99
variable-length array with its extents.  The Python form is the function's own source without its decorator.
"""

from __future__ import annotations

import ast
import inspect
import re
import textwrap
from collections.abc import Callable, Sequence

from ashc_cli.errors import Untranslatable

#: The parameter annotations read (as written in the source), their kinds, and the kinds' C types.
ANNOTATIONS = {"F1": "f1", "F2": "f2", "int": "int", "float": "float"}
KINDS = {"f1": "double *", "f2": "double *", "int": "int", "float": "double"}
#: The C macros that give Python's min and max of two numbers (NaN in the first argument is kept, as Python does).
C_MIN_MAX = ["#define ASHC_MIN(a, b) ((b) < (a) ? (b) : (a))", "#define ASHC_MAX(a, b) ((b) > (a) ? (b) : (a))"]
_OPS = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*", ast.Div: "/"}
_CMP = {ast.Lt: "<", ast.Gt: ">", ast.LtE: "<=", ast.GtE: ">=", ast.Eq: "==", ast.NotEq: "!="}


def kinds(fn: Callable) -> dict[str, str]:
    """The annotated kind (``f1``, ``f2``, ``int``, ``float``) of each parameter of ``fn``, in order.

    Parameters
    ----------
    fn : function or numba dispatcher

    Returns
    -------
    dict of str to str
    """
    tree = _tree(fn)
    out = {}
    for a in tree.args.args:
        kind = ANNOTATIONS.get(a.annotation.id) if isinstance(a.annotation, ast.Name) else None
        if kind is None:
            raise Untranslatable(f"{tree.name}: parameter {a.arg!r} needs an annotation among {sorted(ANNOTATIONS)}")
        out[a.arg] = kind
    return out


def calls(fn: Callable) -> set[str]:
    """The names of the functions ``fn``'s body calls by name (its callees among the printed laws, and builtins).

    Parameters
    ----------
    fn : function or numba dispatcher
    """
    return {n.func.id for n in ast.walk(_tree(fn)) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}


def python_source(fn: Callable) -> str:
    """The function's source without its decorator and annotations, its docstring cut to the first paragraph:
    plain Python over numpy arrays (``np``).

    Parameters
    ----------
    fn : function or numba dispatcher
    """
    tree = _tree(fn)
    lines = textwrap.dedent(inspect.getsource(getattr(fn, "py_func", fn))).splitlines()
    first = tree.body[0]
    head = f"def {tree.name}({', '.join(a.arg for a in tree.args.args)}):"
    lines[tree.lineno - 1:first.lineno - 1] = [head] + [""] * (first.lineno - tree.lineno - 1)   # the signature on one line
    keep = lines[tree.lineno - 1:]
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        doc = " ".join(first.value.value.split("\n\n")[0].split())
        pad = " " * first.col_offset
        keep = [head, f'{pad}"""{doc}"""'] + lines[first.end_lineno:]
    return "\n".join(keep) + "\n"


def header(fn: Callable, known: dict[str, list[tuple[str, str, bool]]]) -> list[tuple[str, str, bool]]:
    """(name, kind, written) of each parameter of ``fn``: what a caller of its C form must pass, and whether the
    function writes the array (itself or through a callee among ``known``).

    Parameters
    ----------
    fn : function or numba dispatcher
    known : dict
        The callees' headers by name.
    """
    p = _Printer(_tree(fn), kinds(fn), known)
    return [(name, kind, name in p.written) for name, kind in p.params.items()]


def c_function(fn: Callable, known: dict[str, list[tuple[str, str, bool]]], static: bool = True) -> list[str]:
    """The C99 text of ``fn``.

    Parameters
    ----------
    fn : function or numba dispatcher
        Written in the subset (module docstring).
    known : dict
        The functions it may call, by name, with their headers (:func:`header`).
    static : bool
        Whether the C function is ``static``.

    Returns
    -------
    list of str
        The lines: a comment (the docstring's first line), the signature and the body.

    Raises
    ------
    Untranslatable
    """
    tree = _tree(fn)
    return _Printer(tree, kinds(fn), known, _where(fn)).function(static)


def _where(fn: Callable) -> tuple[str, int]:
    """(file, line of the source's first line) of fn."""
    f = getattr(fn, "py_func", fn)
    return inspect.getsourcefile(f) or "?", inspect.getsourcelines(f)[1]


def _tree(fn: Callable) -> ast.FunctionDef:
    source = textwrap.dedent(inspect.getsource(getattr(fn, "py_func", fn)))
    node = ast.parse(source).body[0]
    if not isinstance(node, ast.FunctionDef):
        raise Untranslatable(f"{fn!r} is not a function")
    return node


class _Printer:
    """One function's C text (see the module docstring for the subset)."""

    def __init__(self, tree: ast.FunctionDef, params: dict[str, str], known: dict[str, list[tuple[str, str, bool]]],
                 where: tuple[str, int] = ("?", 1)):
        self.tree, self.params, self.known, self.where = tree, params, known, where
        self.written = {t.value.id for node in ast.walk(tree) for t in _targets(node)
                        if isinstance(t, ast.Subscript) and isinstance(t.value, ast.Name)}
        # an array handed to a callee that writes it is written here too
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in known:
                for arg, (_, kind, written) in zip(node.args, known[node.func.id]):
                    if isinstance(arg, ast.Name) and kind in ("f1", "f2") and written:
                        self.written.add(arg.id)
        self.ints: set[str] = set()
        self.locals: dict[str, str] = {}
        self.arrays: dict[str, str] = {}          # work arrays made here (np.empty): C99 variable-length arrays

    def kind(self, name: str) -> str | None:
        """A parameter's or work array's kind (f1, f2, int, float), else None."""
        return self.params.get(name) or self.arrays.get(name)

    def fail(self, node: ast.AST, what: str):
        path, first = self.where
        line = first + getattr(node, "lineno", 1) - 1
        raise Untranslatable(f"{self.tree.name} ({path}:{line}): {what} is outside the subset ashc_cli.outputs.translate prints to C")

    # --- declarations ---------------------------------------------------------------------------------------

    def signature(self) -> str:
        parts = []
        for name, kind in self.params.items():
            if kind in ("f1", "f2"):
                const = "" if name in self.written else "const "
                dims = [f"int {name}_n"] if kind == "f1" else [f"int {name}_rows", f"int {name}_cols"]
                parts += [f"{const}double *{name}", *dims]
            else:
                parts.append(f"{KINDS[kind]}{name}" if KINDS[kind].endswith("*") else f"{KINDS[kind]} {name}")
        return f"void {self.tree.name}({', '.join(parts)})"

    def _collect(self) -> None:
        """The local scalars: int where a loop variable or a shape / size / int constant, else double."""
        for node in ast.walk(self.tree):
            if isinstance(node, ast.For):
                if not isinstance(node.target, ast.Name):
                    self.fail(node, "a loop over something other than one name")
                self.ints.add(node.target.id)
                self.locals[node.target.id] = "int"
        for node in ast.walk(self.tree):
            if isinstance(node, ast.Assign):
                pairs = []
                for t in node.targets:
                    if isinstance(t, ast.Tuple) and isinstance(node.value, ast.Tuple) and len(t.elts) == len(node.value.elts):
                        pairs += list(zip(t.elts, node.value.elts))
                    else:
                        pairs.append((t, node.value))
                for t, value in pairs:
                    if isinstance(t, ast.Name) and _is_empty(value):
                        if t.id in self.params or t.id in self.arrays:
                            self.fail(node, f"a second array bound to {t.id!r}")
                        self.arrays[t.id] = "f2" if isinstance(value.args[0], ast.Tuple) else "f1"
                        continue
                    if isinstance(t, ast.Name) and t.id not in self.params and t.id not in self.locals:
                        self.locals[t.id] = "int" if self._is_int(value) else "double"
                        if self.locals[t.id] == "int":
                            self.ints.add(t.id)
            elif isinstance(node, ast.AugAssign) and isinstance(node.target, ast.Name) and node.target.id not in self.params \
                    and node.target.id not in self.locals:
                self.locals[node.target.id] = "double"

    def _is_int(self, value: ast.AST) -> bool:
        if isinstance(value, ast.Constant):
            return isinstance(value.value, int) and not isinstance(value.value, bool)
        if isinstance(value, ast.Attribute) and value.attr == "size":
            return True
        if isinstance(value, ast.Subscript) and isinstance(value.value, ast.Attribute) and value.value.attr == "shape":
            return True
        if isinstance(value, ast.Name):
            return value.id in self.ints or self.kind(value.id) == "int"
        return False

    def function(self, static: bool) -> list[str]:
        self._collect()
        doc = ast.get_docstring(self.tree)
        first = " ".join(doc.split("\n\n")[0].split()).replace("*/", "* /").replace("``", "") if doc else ""
        head = [f"/* {first} */"] if first else []
        body = [stmt for stmt in self.tree.body if not (isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant))]
        decls = []
        for kind in ("int", "double"):
            names = [n for n, k in self.locals.items() if k == kind]
            if names:
                decls.append(f"    {kind} {', '.join(names)};")
        code = [line for stmt in body for line in self.statement(stmt, 1)]
        text = "\n".join(code)
        unused = [f"    (void){n};" for n in self._names() if not re.search(rf"\b{n}\b", text)]
        return [*head, ("static " if static else "") + self.signature(), "{", *decls, *unused, *code, "}", ""]

    def _names(self) -> list[str]:
        """The C parameters: each array's pointer and extents, each scalar."""
        out = []
        for name, kind in self.params.items():
            out += [name] + ([f"{name}_n"] if kind == "f1" else [f"{name}_rows", f"{name}_cols"] if kind == "f2" else [])
        return out

    # --- statements -------------------------------------------------------------------------------------------

    def statement(self, node: ast.stmt, depth: int) -> list[str]:
        pad = "    " * depth
        if isinstance(node, ast.Assign):
            if len(node.targets) != 1:
                self.fail(node, "a chained assignment")
            t = node.targets[0]
            if isinstance(t, ast.Name) and t.id in self.arrays:
                shape = node.value.args[0]
                dims = [self.expr(e) for e in shape.elts] if isinstance(shape, ast.Tuple) else [self.expr(shape)]
                if len(dims) == 1:
                    return [f"{pad}const int {t.id}_n = {dims[0]};", f"{pad}double {t.id}[{t.id}_n];"]
                if len(dims) != 2:
                    self.fail(node, "a work array of more than two dimensions")
                return [f"{pad}const int {t.id}_rows = {dims[0]}, {t.id}_cols = {dims[1]};",
                        f"{pad}double {t.id}[{t.id}_rows * {t.id}_cols];"]
            if isinstance(t, ast.Tuple):
                if not (isinstance(node.value, ast.Tuple) and len(node.value.elts) == len(t.elts)):
                    self.fail(node, "unpacking other than of a tuple written out")
                return [f"{pad}{self.expr(a)} = {self.expr(b)};" for a, b in zip(t.elts, node.value.elts)]
            return [f"{pad}{self.expr(t)} = {self.expr(node.value)};"]
        if isinstance(node, ast.AugAssign):
            if type(node.op) not in _OPS:
                self.fail(node, f"the operator {type(node.op).__name__}=")
            return [f"{pad}{self.expr(node.target)} {_OPS[type(node.op)]}= {self.expr(node.value)};"]
        if isinstance(node, ast.For):
            it = node.iter
            if not (isinstance(it, ast.Call) and isinstance(it.func, ast.Name) and it.func.id == "range" and 1 <= len(it.args) <= 2) or node.orelse:
                self.fail(node, "a loop other than for ... in range(stop) or range(start, stop)")
            lo, hi = ("0", self.expr(it.args[0])) if len(it.args) == 1 else (self.expr(it.args[0]), self.expr(it.args[1]))
            v = node.target.id
            return [f"{pad}for ({v} = {lo}; {v} < {hi}; {v}++) {{", *self.block(node.body, depth + 1), f"{pad}}}"]
        if isinstance(node, ast.If):
            lines = [f"{pad}if ({self.expr(node.test)}) {{", *self.block(node.body, depth + 1)]
            rest = node.orelse
            while len(rest) == 1 and isinstance(rest[0], ast.If):
                lines += [f"{pad}}} else if ({self.expr(rest[0].test)}) {{", *self.block(rest[0].body, depth + 1)]
                rest = rest[0].orelse
            if rest:
                lines += [f"{pad}}} else {{", *self.block(rest, depth + 1)]
            return lines + [f"{pad}}}"]
        if isinstance(node, ast.Return):
            if node.value is not None:
                self.fail(node, "a return with a value")
            return [f"{pad}return;"]
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Call):
            return [f"{pad}{self.call(node.value)};"]
        self.fail(node, f"the statement {type(node).__name__}")

    def block(self, body: Sequence[ast.stmt], depth: int) -> list[str]:
        return [line for stmt in body for line in self.statement(stmt, depth)]

    # --- expressions ------------------------------------------------------------------------------------------

    def expr(self, node: ast.AST) -> str:
        if isinstance(node, ast.Constant):
            if isinstance(node.value, bool) or not isinstance(node.value, (int, float)):
                self.fail(node, f"the constant {node.value!r}")
            return repr(node.value) if isinstance(node.value, int) else _float(node.value)
        if isinstance(node, ast.Name):
            if node.id not in self.params and node.id not in self.locals and node.id not in self.arrays:
                self.fail(node, f"the name {node.id!r} (neither a parameter nor assigned here)")
            return node.id
        if isinstance(node, ast.BinOp) and type(node.op) in _OPS:
            return f"({self.expr(node.left)} {_OPS[type(node.op)]} {self.expr(node.right)})"
        if isinstance(node, ast.UnaryOp):
            if isinstance(node.op, ast.USub):
                return f"(-{self.expr(node.operand)})"
            if isinstance(node.op, ast.Not):
                return f"(!{self.expr(node.operand)})"
        if isinstance(node, ast.Compare) and len(node.ops) == 1 and type(node.ops[0]) in _CMP:
            return f"({self.expr(node.left)} {_CMP[type(node.ops[0])]} {self.expr(node.comparators[0])})"
        if isinstance(node, ast.BoolOp):
            op = " && " if isinstance(node.op, ast.And) else " || "
            return "(" + op.join(self.expr(v) for v in node.values) + ")"
        if isinstance(node, ast.IfExp):
            return f"({self.expr(node.test)} ? {self.expr(node.body)} : {self.expr(node.orelse)})"
        if isinstance(node, ast.Attribute):
            if isinstance(node.value, ast.Name) and node.value.id == "np" and node.attr == "inf":
                return "HUGE_VAL"
            if node.attr == "size" and isinstance(node.value, ast.Name) and self.kind(node.value.id) == "f1":
                return f"{node.value.id}_n"
        if isinstance(node, ast.Subscript):
            return self.subscript(node)
        if isinstance(node, ast.Call):
            return self.call(node)
        self.fail(node, f"the expression {ast.unparse(node)!r}")

    def subscript(self, node: ast.Subscript) -> str:
        base = node.value
        if isinstance(base, ast.Attribute) and base.attr == "shape" and isinstance(base.value, ast.Name) \
                and self.kind(base.value.id) == "f2" and isinstance(node.slice, ast.Constant) and node.slice.value in (0, 1):
            return f"{base.value.id}_{'rows' if node.slice.value == 0 else 'cols'}"
        if not isinstance(base, ast.Name) or self.kind(base.id) not in ("f1", "f2"):
            self.fail(node, f"indexing {ast.unparse(base)!r}")
        if self.kind(base.id) == "f2":
            if not (isinstance(node.slice, ast.Tuple) and len(node.slice.elts) == 2):
                self.fail(node, f"a 2-D array {base.id!r} indexed other than [i, j]")
            i, j = (self.expr(e) for e in node.slice.elts)
            return f"{base.id}[{i} * {base.id}_cols + {j}]"
        if isinstance(node.slice, (ast.Tuple, ast.Slice)):
            self.fail(node, f"a 1-D array {base.id!r} indexed other than [i]")
        return f"{base.id}[{self.expr(node.slice)}]"

    def call(self, node: ast.Call) -> str:
        if node.keywords or not isinstance(node.func, (ast.Name, ast.Attribute)):
            self.fail(node, f"the call {ast.unparse(node)!r}")
        if isinstance(node.func, ast.Attribute):
            if isinstance(node.func.value, ast.Name) and node.func.value.id == "math" and node.func.attr in ("sqrt", "exp", "fabs"):
                return f"{node.func.attr}({', '.join(self.expr(a) for a in node.args)})"
            self.fail(node, f"the call {ast.unparse(node)!r}")
        name = node.func.id
        if name in ("min", "max") and len(node.args) == 2:
            return f"ASHC_{name.upper()}({self.expr(node.args[0])}, {self.expr(node.args[1])})"
        if name == "abs" and len(node.args) == 1:
            return f"fabs({self.expr(node.args[0])})"
        if name not in self.known:
            self.fail(node, f"the call of {name!r} (not among {sorted(self.known)})")
        want = self.known[name]
        if len(node.args) != len(want):
            self.fail(node, f"{name} with {len(node.args)} arguments ({len(want)} expected)")
        args = []
        for arg, (_, kind, _) in zip(node.args, want):
            if kind in ("f1", "f2"):
                if not (isinstance(arg, ast.Name) and self.kind(arg.id) == kind):
                    self.fail(node, f"{ast.unparse(arg)!r} passed to {name} as a {kind} array (only a parameter of that kind)")
                args += [arg.id, *([f"{arg.id}_n"] if kind == "f1" else [f"{arg.id}_rows", f"{arg.id}_cols"])]
            else:
                args.append(self.expr(arg))
        return f"{name}({', '.join(args)})"


def _is_empty(value: ast.AST) -> bool:
    """``np.empty(n)`` or ``np.empty((r, c))``."""
    return (isinstance(value, ast.Call) and isinstance(value.func, ast.Attribute) and value.func.attr == "empty"
            and isinstance(value.func.value, ast.Name) and value.func.value.id == "np" and len(value.args) == 1 and not value.keywords)


def _targets(node: ast.AST) -> list[ast.AST]:
    if isinstance(node, ast.Assign):
        out = []
        for t in node.targets:
            out += list(t.elts) if isinstance(t, ast.Tuple) else [t]
        return out
    if isinstance(node, ast.AugAssign):
        return [node.target]
    return []


def _float(value: float) -> str:
    text = repr(float(value))
    if text in ("inf", "-inf"):
        return "HUGE_VAL" if text == "inf" else "(-HUGE_VAL)"
    return text if any(c in text for c in ".en") else text + ".0"
