"""The concrete and abstract systems of a spec, symbolic (sympy) and numeric (lambdified).

:func:`build_model` parses every expression of a :class:`~ashc_cli.problem.spec.Spec` through the whitelist
parser and returns a :class:`Model`: the concrete system x' = f_bar(x) + g(x) u, y = h(x) (eq. (13)) and the abstract system's design choices xi' = phi_bar(xi) + delta(xi) v with l(xi)
(eq. (12)).  Parameters stay symbols in the formulas (so results read like the paper's);
:func:`lambdify` substitutes their values and compiles an expression matrix for numpy, with common
subexpressions eliminated.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import sympy as sp

from ashc_cli.errors import SpecError
from ashc_cli.problem.expr import NUMERIC_MODULES, parse_expression
from ashc_cli.problem.grids import domain_grid, maximise_on_box
from ashc_cli.problem.spec import Spec

__all__ = ["Model", "build_model", "lambdify", "compile_flat", "compile_terms", "sparse_jacobian", "tidy", "parameter_symbol", "state_symbol", "TIME"]

#: Above this many states the stages use numbers instead of sympy where both work (measured with
#: `make bench` on the ladder family: at n = 16 sympy.solve of the manifold and of kappa^-1 already take
#: 19 s of a 24 s design, the numeric paths 2 s).
NUMERIC_THRESHOLD = 12

#: The time symbol of spec signals.
TIME = sp.Symbol("t", real=True)


def parameter_symbol(name: str, value: float) -> sp.Symbol:
    """The symbol of a parameter, carrying the sign of its value so sympy can simplify sqrt and abs.

    Parameters
    ----------
    name : str
        The parameter's name (a key of ``parameters``).
    value : float
        Its value; only its sign is used (positive, negative, or real for 0).

    Returns
    -------
    Symbol
    """
    if value > 0:
        return sp.Symbol(name, positive=True)
    if value < 0:
        return sp.Symbol(name, negative=True)
    return sp.Symbol(name, real=True)


def state_symbol(name: str) -> sp.Symbol:
    """The symbol of a state or input (real).

    Parameters
    ----------
    name : str
        The name the spec gives it.

    Returns
    -------
    Symbol
    """
    return sp.Symbol(name, real=True)


def sparse_jacobian(exprs: sp.MatrixBase, symbols: Sequence[sp.Symbol]) -> sp.Matrix:
    """d exprs / d symbols, differentiating only where the symbol occurs (the same matrix as sympy's
    ``jacobian``, 15 times faster on the sparse ladder at n = 128: 0.05 s against 0.8 s), with the derivatives
    of sign, abs, min and max written as functions (:func:`almost_everywhere`).

    Parameters
    ----------
    exprs : sympy Matrix (r, 1)
        The expressions, taken in order (a column).
    symbols : sequence of Symbol
        The c variables.

    Returns
    -------
    sympy Matrix (r, c)
        Dense, or a SparseMatrix when r c > SPARSE_JACOBIAN_ENTRIES.
    """
    index = {s: k for k, s in enumerate(symbols)}
    entries = {}
    for i, e in enumerate(exprs):
        for s in e.free_symbols:
            if s in index:
                d = almost_everywhere(e.diff(s))
                if d != 0:
                    entries[(i, index[s])] = d
    rows, cols = len(exprs), len(symbols)
    if rows * cols > SPARSE_JACOBIAN_ENTRIES:
        return sp.SparseMatrix(rows, cols, entries)    # a large network: a dense matrix of sympy zeros costs seconds
    out = sp.zeros(rows, cols)
    for (i, j), d in entries.items():
        out[i, j] = d
    return out


#: Above this many entries sparse_jacobian returns a sympy SparseMatrix.
SPARSE_JACOBIAN_ENTRIES = 64 * 64


def is_sparse(matrix) -> bool:
    """Whether a sympy matrix stores only its nonzero entries (a large plant's Jacobian, :func:`sparse_jacobian`).

    Parameters
    ----------
    matrix : object
        A sympy matrix (anything else is not sparse).

    Returns
    -------
    bool
    """
    return isinstance(matrix, sp.matrices.sparse.SparseRepMatrix)


def nonzero_entries(matrix: sp.MatrixBase) -> dict[tuple[int, int], sp.Expr]:
    """The entries of a sympy matrix that are not zero, as {(i, j): expression}.

    A SparseMatrix's own dictionary: iterating ``for e in J`` indexes all n^2 entries, which took 150 s of the
    stabilise stage of the 256-state ladder (34 million lookups).

    Parameters
    ----------
    matrix : sympy Matrix

    Returns
    -------
    dict of (int, int) to sympy Expr
    """
    if is_sparse(matrix):
        return {key: e for key, e in matrix.todok().items() if e != 0}
    rows, cols = matrix.shape
    return {(i, j): matrix[i, j] for i in range(rows) for j in range(cols) if matrix[i, j] != 0}


#: The safety stop of a symbolic search (sympy.solve of eq. (14a) or of kappa(m) = y), in seconds: past it the
#: design fails loudly, naming --numeric (the numeric path, no sympy) and the key to write by hand.  A clock, so it is
#: never a silent switch to the numeric path (that would make the design depend on the machine's load).
SYMBOLIC_BUDGET = 60.0


def within_budget(fn, *args, seconds: float | None = None):
    """fn(*args) computed in a forked child process, or raise TimeoutError after ``seconds`` (default
    :data:`SYMBOLIC_BUDGET`).

    sympy cannot be interrupted from a thread, and on a transcendental equation (x + 0.0009 tanh(1e5 (x - c)) = y)
    sympy.solve may search for minutes; the child is killed at the budget and the caller fails loudly (a safety stop).
    The result comes back pickled (sympy expressions pickle).  Where fork is not available, or in a daemonic process (a
    sweep's worker, which may not have children), the call runs inline.

    Parameters
    ----------
    fn : callable
        The work; its result must pickle.
    *args
        Its arguments.
    seconds : float, optional
        The budget in seconds (default :data:`SYMBOLIC_BUDGET`).

    Returns
    -------
    object
        fn(*args).

    Raises
    ------
    TimeoutError
        At the budget, or when the child ends without a result.
    ValueError
        With the repr of the child's exception, when fn raised in the child (run inline, it raises its own).
    """
    import multiprocessing as mp
    import pickle

    seconds = SYMBOLIC_BUDGET if seconds is None else seconds
    if mp.current_process().daemon:      # a sweep's worker may not have children: inline, without the budget
        return fn(*args)
    try:
        ctx = mp.get_context("fork")
    except ValueError:
        return fn(*args)
    reader, writer = ctx.Pipe(duplex=False)

    def child():
        try:
            writer.send(("ok", pickle.dumps(fn(*args))))
        except BaseException as exc:   # noqa: BLE001 (handed back to the parent and raised there)
            writer.send(("error", repr(exc)))
        finally:
            writer.close()

    proc = ctx.Process(target=child, daemon=True)
    proc.start()
    writer.close()
    try:
        if not reader.poll(seconds):
            raise TimeoutError(f"symbolic work took longer than {seconds:g} s")
        kind, payload = reader.recv()
    except EOFError:
        raise TimeoutError("the symbolic search ended without a result") from None
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join()
        reader.close()
    if kind != "ok":
        raise ValueError(payload)
    return pickle.loads(payload)


def almost_everywhere(e: sp.Expr) -> sp.Expr:
    """A derivative with sympy's distributions replaced by functions every evaluator knows.

    d sign(z) = 2 DiracDelta(z) is 0 wherever it is defined (z != 0), so DiracDelta becomes 0; d max(z, 0) =
    Heaviside(z) becomes (1 + sign(z)) / 2, which is 1/2 at the kink, inside Clarke's generalised derivative
    [0, 1] (abs, min and max are Lipschitz: a mean-value argument holds with that derivative).  That sign
    jumps is not lost: :func:`jumps` finds the discontinuous functions of an expression, and the stages that
    need f or h Lipschitz on a set refuse one whose jump lies inside it.

    Parameters
    ----------
    e : sympy Expr
        A derivative (anything ``sympify`` takes).

    Returns
    -------
    sympy Expr
    """
    e = sp.sympify(e)
    if e.has(sp.DiracDelta):
        e = e.replace(lambda a: isinstance(a, sp.DiracDelta), lambda a: sp.S.Zero)
    if e.has(sp.Heaviside):
        e = e.replace(lambda a: isinstance(a, sp.Heaviside), lambda a: (1 + sp.sign(a.args[0])) / 2)
    return e


def jumps(exprs, symbols: Sequence[sp.Symbol]) -> list[sp.Expr]:
    """The discontinuous functions (sign, square, step) in the expressions whose argument depends on ``symbols``.

    Parameters
    ----------
    exprs : list, tuple or sympy Matrix
        The expressions.
    symbols : sequence of Symbol
        E.g. ``model.x``.

    Returns
    -------
    list of sympy Expr
        Each application of sign, square, step or Heaviside once, e.g. ``sign(x1 - 1)``.
    """
    from ashc_cli.problem.expr import square, step

    syms = set(symbols)
    found = []
    for e in (exprs if isinstance(exprs, (list, tuple)) else list(sp.Matrix(exprs))):
        e = sp.sympify(e)
        if not e.has(sp.sign, square, step, sp.Heaviside):
            continue
        for a in sorted(e.atoms(sp.sign, square, step, sp.Heaviside), key=sp.default_sort_key):
            if a.free_symbols & syms and a not in found:
                found.append(a)
    return found


def compile_flat(
    exprs: Sequence[sp.Expr],
    args: Sequence[sp.Symbol],
    values: Mapping[sp.Symbol, float] | None = None,
) -> Callable[..., list]:
    """Compile a flat list of expressions into one numpy function (one call evaluates them all).

    Cheaper per call than :func:`lambdify` (no broadcasting), for the right-hand sides of ODEs:
    ``f(*scalars)`` returns a list of numbers, one per expression.  Common subexpressions are eliminated
    first, except in long lists of small expressions (:func:`_worth_cse`).

    Parameters
    ----------
    exprs : sequence of sympy Expr
        What to evaluate (passed through :func:`almost_everywhere`).
    args : sequence of Symbol
        The arguments of the compiled function, in order.
    values : mapping of Symbol to float, optional
        Values substituted first (the spec's parameters).

    Returns
    -------
    callable
        ``f(*scalars) -> list``, one value per expression.
    """
    subs = {k: sp.Float(v) for k, v in (values or {}).items()}
    flat = [almost_everywhere(sp.sympify(e).xreplace(subs)) for e in exprs]
    return sp.lambdify(list(args), flat, modules=NUMERIC_MODULES, cse=_worth_cse(flat))


#: Lists longer than this, of expressions of at most ``CSE_SMALL_NODES`` nodes each, are compiled without
#: common-subexpression elimination.
CSE_MIN_SKIP = 64
CSE_SMALL_NODES = 32


def _worth_cse(flat: Sequence[sp.Expr]) -> bool:
    """Whether sympy's CSE is worth its cost: not on a long list of small expressions (a large plant's
    equations or sparse Jacobian entries, which share few subtrees), where it took 3/4 of the compile time
    (1.3 s of 1.6 s for the 512-state ladder's f, and most of the n^2 entries of its Jacobian)."""
    if len(flat) <= CSE_MIN_SKIP:
        return True
    for e in flat:
        if e.is_Atom:
            continue
        for k, _ in enumerate(sp.preorder_traversal(e)):
            if k >= CSE_SMALL_NODES:
                return True
    return False


def compile_terms(
    terms: Sequence[sp.MatrixBase],
    args: Sequence[sp.Symbol],
    values: Mapping[sp.Symbol, float] | None = None,
) -> Callable[[np.ndarray], list[np.ndarray]]:
    """Compile several matrices into one fused function of a point or of a batch of points.

    ``f(point)`` with point of shape (d,) returns one array per matrix, of that matrix's shape (r, c);
    ``f(points)`` with shape (d, N) returns arrays of shape (N, r, c).  One compiled call evaluates every
    term (the right-hand sides of the closed loops in ``simulate`` and ``falsify``).

    Parameters
    ----------
    terms : sequence of sympy Matrix
        The matrices, each (r, c).
    args : sequence of Symbol
        The d coordinates of a point, in order.
    values : mapping of Symbol to float, optional
        Values substituted first (the spec's parameters).

    Returns
    -------
    callable
        ``f(points) -> list of ndarray``, shapes as above.
    """
    shapes = [t.shape for t in terms]
    ends = np.cumsum([0] + [r * c for r, c in shapes]).tolist()
    pieces = [(slice(a, b), shape) for a, b, shape in zip(ends[:-1], ends[1:], shapes)]
    fun = compile_flat([e for t in terms for e in t], args, values)

    def evaluate(points: np.ndarray) -> list[np.ndarray]:
        if np.ndim(points) == 1:   # one point: the ODE right-hand side, called thousands of times
            flat = np.array(fun(*points), dtype=float)
            return [flat[where].reshape(shape) for where, shape in pieces]
        N = points.shape[1]
        flat = np.stack([np.broadcast_to(np.asarray(v, dtype=float), (N,)) for v in fun(*points)], axis=1)
        return [flat[:, where].reshape((N,) + shape) for where, shape in pieces]

    return evaluate


def lambdify(
    exprs: sp.MatrixBase | Sequence[sp.Expr],
    args: Sequence[sp.Symbol],
    values: Mapping[sp.Symbol, float] | None = None,
) -> Callable[..., np.ndarray]:
    """Compile an expression matrix for numpy, broadcasting over its arguments.

    Parameters
    ----------
    exprs : sympy Matrix or sequence of expressions
        What to evaluate; a sequence is treated as a column.
    args : sequence of Symbol
        The arguments of the compiled function, in order.
    values : mapping of Symbol to float, optional
        Values substituted first (the spec's parameters).

    Returns
    -------
    callable
        ``f(*arrays)`` returning an array of shape ``exprs.shape + broadcast(arrays).shape``.
        Entries that are not real (e.g. sqrt of a negative number) come out as NaN.
    """
    matrix = sp.Matrix(exprs) if not isinstance(exprs, sp.MatrixBase) else exprs
    shape = matrix.shape
    if is_sparse(matrix):
        return _lambdify_sparse(matrix, args, values)
    compiled = compile_flat(list(matrix), args, values)

    def evaluate(*arrays):
        arrs = [np.asarray(a, dtype=float) for a in arrays]
        bshape = np.broadcast_shapes(*(a.shape for a in arrs)) if arrs else ()
        with np.errstate(all="ignore"):
            out = compiled(*arrs)
            cols = [np.broadcast_to(np.real_if_close(np.asarray(o)), bshape) for o in out]
        stacked = np.stack([np.where(np.iscomplex(c), np.nan, np.real(c)).astype(float) for c in cols], axis=0)
        return stacked.reshape(shape + bshape)

    return evaluate


def _lambdify_sparse(matrix: sp.MatrixBase, args: Sequence[sp.Symbol], values: Mapping[sp.Symbol, float] | None):
    """:func:`lambdify` of a SparseMatrix: only its nonzero entries are compiled (the 256-state ladder's Jacobian
    has 770 of 65536; compiling them all took 10 s), the rest of the array is zero."""
    keys = list(nonzero_entries(matrix))
    rows, cols = (np.array([k[0] for k in keys], dtype=int), np.array([k[1] for k in keys], dtype=int))
    compiled = lambdify([matrix[k] for k in keys], args, values) if keys else None

    def evaluate(*arrays):
        arrs = [np.asarray(a, dtype=float) for a in arrays]
        bshape = np.broadcast_shapes(*(a.shape for a in arrs)) if arrs else ()
        out = np.zeros(matrix.shape + bshape)
        if compiled is not None:
            out[rows, cols] = compiled(*arrs)[:, 0]
        return out

    return evaluate


@dataclass(frozen=True)
class Model:
    """A spec turned into symbols and expressions: the concrete system x' = f(x, u), y = h(x) (eq. (1)) and the
    abstract system xi' = phi(xi, v), psi = kappa(xi) (eq. (2)).

    Attributes
    ----------
    spec : Spec
        The spec it was built from.
    params : dict of str to Symbol
        The parameter symbols; ``values`` maps them to their numbers.
    x, u, xi, v : sympy Matrix
        Column vectors of the concrete state and input and the abstract state and input.
    f_bar, g, h : sympy Matrix
        The concrete drift (n x 1), input matrix (n x m) and output map (p x 1).  f_bar and g are None for a plant
        that is not input-affine (``concrete.f`` not affine in u): its right-hand side is :attr:`f`.
    phi_bar, l : sympy Matrix
        The abstract drift (n_hat x 1) and the concrete input on the manifold l(xi) (m x 1).
    delta : sympy Matrix or None
        The abstract input matrix (n_hat x m_hat); None for ``flatten`` (designed by a stage).
    U, Y : ndarray
        Input box (m x 2) and output region (p x 2).
    V : ndarray or None
        The domain box of xi (n_hat x 2); None for ``auto`` (until the manifold stage has chosen it).
    state_box : ndarray or None
        The box of x the design is certified on (n x 2), if the spec gives one.
    """

    spec: Spec
    params: dict[str, sp.Symbol]
    values: dict[sp.Symbol, float]
    x: sp.Matrix
    u: sp.Matrix
    xi: sp.Matrix
    v: sp.Matrix
    f_bar: sp.Matrix | None
    g: sp.Matrix | None
    h: sp.Matrix
    phi_bar: sp.Matrix
    l: sp.Matrix
    delta: sp.Matrix | None
    U: np.ndarray
    Y: np.ndarray
    V: np.ndarray | None
    state_box: np.ndarray | None = None
    #: Force the numeric fast paths (True), the symbolic ones (False), or choose by size (None).
    numeric_paths: bool | None = None
    names: dict[str, sp.Symbol] = field(default_factory=dict)
    #: The left inverse m(x) the spec gives (``abstract.m``, n_hat x 1 in the concrete states), or None.
    m_given: sp.Matrix | None = None
    #: The manifold p(xi) the spec gives (``abstract.p``, n x 1 in the abstract states), or None.
    p_given: sp.Matrix | None = None
    #: f(x, u) of a plant that is not input-affine (``concrete.f``), or None (then f = f_bar + g u).
    f_general: sp.Matrix | None = None
    #: The disturbances w (d x 1; 0 x 1 without), their input matrix e(x) (n x d, or None) and their box W (d x 2, or None).
    w: sp.Matrix = field(default_factory=lambda: sp.zeros(0, 1))
    e: sp.Matrix | None = None
    W: np.ndarray | None = None
    #: The spec's states left out of the design, outside the output's cone (:class:`ashc_cli.problem.influence.Beside`;
    #: this model is then the plant seen from y), or None.
    beside: object | None = None

    @property
    def n(self) -> int:
        return self.x.shape[0]

    @property
    def m(self) -> int:
        return self.u.shape[0]

    @property
    def p(self) -> int:
        return self.h.shape[0]

    @property
    def n_hat(self) -> int:
        return self.xi.shape[0]

    @property
    def m_hat(self) -> int:
        return self.v.shape[0]

    @property
    def use_numeric(self) -> bool:
        """Whether stages take their numeric fast paths: forced by ``--numeric``, else for n > NUMERIC_THRESHOLD."""
        return self.numeric_paths if self.numeric_paths is not None else self.n > NUMERIC_THRESHOLD

    @property
    def affine(self) -> bool:
        """Whether the plant is input-affine (eq. (13)): f_bar and g exist."""
        return self.f_general is None

    @cached_property
    def f(self) -> sp.Matrix:
        """f(x, u): f_bar(x) + g(x) u (eq. (13)), or the spec's ``concrete.f`` for a plant that is not input-affine."""
        return self.f_general if self.f_general is not None else self.f_bar + self.g * self.u

    def f_on(self, x_values: sp.MatrixBase, u_values: sp.MatrixBase, valued: bool = False) -> sp.Matrix:
        """f(x, u) with x and u replaced: e.g. f(p(xi), l(xi)), the right side of eq. (14a) (Remark 4 for a plant
        that is not input-affine).

        Parameters
        ----------
        x_values, u_values : sympy Matrix (n, 1), (m, 1)
            What x and u become.
        valued : bool
            Whether the parameter values are put in first.

        Returns
        -------
        sympy Matrix (n, 1)
        """
        f = self.valued["f"] if valued else self.f
        return f.xreplace({**dict(zip(self.x, x_values)), **dict(zip(self.u, u_values))})

    def require_affine(self, what: str) -> None:
        """Refuse a plant that is not input-affine where ``what`` needs g(x).

        Parameters
        ----------
        what : str
            What needs it, e.g. ``"falsify"``.

        Raises
        ------
        DesignError
            Naming ``concrete.f``.
        """
        if not self.affine:
            from ashc_cli.errors import DesignError

            raise DesignError("concrete.f", f"is not affine in the inputs, and {what} needs x' = f_bar(x) + g(x) u (eq. (13))",
                              "an input-affine plant (f_bar and g), or the stages that take f(x, u): design and simulate")

    @cached_property
    def C(self) -> np.ndarray | None:
        """The matrix C of a linear output map h(x) = C x, or None if h is not linear in x."""
        jac = sparse_jacobian(self.h, self.x)
        if any(e.free_symbols & set(self.x) for e in jac) or any(sp.simplify(e) != 0 for e in self.h - jac * self.x):
            return None
        return np.array(jac.xreplace({k: sp.Float(v) for k, v in self.values.items()}), dtype=float)

    @cached_property
    def valued(self) -> dict[str, sp.Matrix]:
        """f_bar, g, h, phi_bar and l with the parameter values put in, once (:meth:`substitute`): numbers for the
        stages to differentiate and compile repeatedly (substituting took 1 s per compile at n = 512)."""
        out = {name: self.substitute(getattr(self, name)) for name in ("h", "phi_bar", "l")}
        out["f"] = self.substitute(self.f)
        if self.affine:
            out.update({name: self.substitute(getattr(self, name)) for name in ("f_bar", "g")})
        return out

    def numeric(self, exprs, args: Sequence[sp.Symbol]) -> Callable[..., np.ndarray]:
        """:func:`lambdify` with this model's parameter values."""
        return lambdify(exprs, args, self.values)

    def h_jacobian_bound(self) -> tuple[float, np.ndarray]:
        """L_h of Assumption 1: the sup of ||dh/dx(x)||_2 (linear h: ||C||_2 exactly).

        For a nonlinear h the sup is taken over ``state_box`` (a grid refined by bounded local searches), so
        the constant, and every bound built on it, holds while x stays in that box.

        Returns
        -------
        L_h : float
        at : ndarray
            Where the sup is reached (empty for linear h).
        """
        if self.C is not None:
            return float(np.linalg.norm(self.C, 2)), np.zeros(0)
        if self.state_box is None:
            raise SpecError("concrete.state_box", "missing: h is not linear, so its Lipschitz constant L_h (Assumption 1) is computed over a box of states",
                            "one pair [lo, hi] per state")
        jac = self.numeric(sparse_jacobian(self.h, self.x), list(self.x))
        pts = domain_grid(self.state_box, 20000)
        norms = np.linalg.norm(np.moveaxis(jac(*pts), -1, 0), ord=2, axis=(1, 2))
        return maximise_on_box(pts, norms, lambda x: float(np.linalg.norm(jac(*x), 2)), self.state_box, starts=5)

    def substitute(self, expr):
        """An expression with the parameter values put in (for numbers, never for shown formulas)."""
        return sp.sympify(expr).xreplace({k: sp.Float(v) for k, v in self.values.items()})


#: Expressions with more operations than this are kept as derived: rewriting them gains little, and sympy's
#: simplify (which the kappa stage still asks for) can take minutes on them.
SIMPLIFY_MAX_OPS = 400


def shorter(e: sp.Expr) -> sp.Expr:
    """One fraction with common factors pulled out (``together``, then ``factor_terms``), if that is shorter.

    Both are cheap and deterministic; sympy's ``simplify`` searched far longer (1.2 s on the Cuk converter's
    b(x)) and returned longer expressions on the converters (93 against 88 operations on the Cuk b, 45
    against 33 on the boost b).

    Parameters
    ----------
    e : sympy Expr

    Returns
    -------
    sympy Expr
        The candidate when its ``count_ops`` is no larger, else e.
    """
    candidate = sp.factor_terms(sp.together(e))
    return candidate if sp.count_ops(candidate) <= sp.count_ops(e) else e


def tidy(matrix: sp.Matrix, how=shorter) -> sp.Matrix:
    """Tidy (with ``how``) each entry small enough for sympy to do quickly; keep the rest as derived.

    Entries with float coefficients (a fitted manifold or inverse) are left alone too: rewriting gains
    nothing on them and can stall for minutes on a polynomial of high degree.

    Parameters
    ----------
    matrix : sympy Matrix
    how : callable
        Expr -> Expr, applied to the entries of at most SIMPLIFY_MAX_OPS operations and no Float.

    Returns
    -------
    sympy Matrix
    """
    return matrix.applyfunc(lambda e: how(e) if sp.count_ops(e) <= SIMPLIFY_MAX_OPS and not e.atoms(sp.Float) else e)


def _matrix(rows, names, field_name, shape, offer=None) -> sp.Matrix:
    """Parse a spec list (of expressions, or of rows of expressions) into a matrix of the given shape; ``offer``
    names what the field may use, for the message on an unknown name."""
    entries = []
    for i, row in enumerate(rows):
        if isinstance(row, list):
            entries.extend(parse_expression(e, names, f"{field_name}[{i}][{j}]", offer=offer) for j, e in enumerate(row))
        else:
            entries.append(parse_expression(row, names, f"{field_name}[{i}]", offer=offer))
    return sp.Matrix(shape[0], shape[1], entries)


def _check_finite_with_values(values: dict, fields: list) -> None:
    """Refuse an expression that the parameter values make infinite (1/L_1 with L_1 = 0): otherwise every stage
    would meet sympy's complex infinity.  Only a zero parameter can do that to a parsed expression."""
    zeros = {sym: val for sym, val in values.items() if val == 0}
    if not zeros:
        return
    for field_name, mat in fields:
        if mat is None:
            continue
        for k, expr in enumerate(mat):
            if expr.free_symbols & set(zeros) and expr.xreplace(zeros).has(sp.zoo, sp.nan, sp.oo, -sp.oo):
                used = ", ".join(sorted(f"{s} = 0" for s in expr.free_symbols & set(zeros)))
                raise SpecError(f"{field_name}[{k}]", f"is not finite with the parameter values ({used}: a division by zero)",
                                "parameter values for which every expression is finite")


def _offer(names: dict, allowed: set) -> list[str]:
    """The spec names (keys of ``names``) that stand for a symbol in ``allowed``: what a field may use."""
    return [k for k, sym in names.items() if sym in allowed]


def _check_free(expr_matrix: sp.Matrix, allowed: set, field_name: str, what: str) -> None:
    for k, e in enumerate(expr_matrix):
        extra = e.free_symbols - allowed
        if extra:
            names = ", ".join(sorted(str(s) for s in extra))
            raise SpecError(f"{field_name}[{k}]", f"uses {names}", f"an expression in {what} and parameters only")


def build_model(spec: Spec) -> Model:
    """Parse a spec's expressions into a :class:`Model`.

    Parameters
    ----------
    spec : Spec
        A validated spec.

    Returns
    -------
    Model

    Raises
    ------
    SpecError
        If an expression does not parse or uses a name it may not (e.g. an abstract state in f_bar).
    """
    c, a = spec.concrete, spec.abstract
    params = {k: parameter_symbol(k, v) for k, v in spec.parameters.items()}
    values = {params[k]: float(v) for k, v in spec.parameters.items()}
    x = sp.Matrix([state_symbol(s) for s in c.states])
    u = sp.Matrix([state_symbol(s) for s in c.inputs])
    xi = sp.Matrix([state_symbol(s) for s in a.states])
    v = sp.Matrix([state_symbol(s) for s in a.inputs])
    names: dict[str, sp.Symbol] = {**params}
    names.update({str(s): s for s in (*x, *u, *xi, *v)})
    n, m, nh, mh = len(x), len(u), len(xi), len(v)

    pset = set(params.values())
    on_x, on_xi = _offer(names, pset | set(x)), _offer(names, pset | set(xi))
    h = _matrix(c.h, names, "concrete.h", (len(c.h), 1), on_x)
    _check_free(h, pset | set(x), "concrete.h", "the concrete states")
    f_bar, g, f_general = _dynamics(spec, names, pset, x, u)
    w, e, W = sp.zeros(0, 1), None, None
    if c.disturbances:
        w = sp.Matrix([state_symbol(s) for s in c.disturbances])
        e = _matrix(c.e, names, "concrete.e", (n, len(w)), on_x)
        _check_free(e, pset | set(x), "concrete.e", "the concrete states")
        W = np.array(c.disturbance_bounds, dtype=float)
    phi_bar = _matrix(a.phi_bar, names, "abstract.phi_bar", (nh, 1), on_xi)
    l = _matrix(a.l, names, "abstract.l", (m, 1), on_xi)
    for mat, fname in ((phi_bar, "abstract.phi_bar"), (l, "abstract.l")):
        _check_free(mat, pset | set(xi), fname, "the abstract states")
    if a.delta == "identity":
        delta = sp.eye(nh)
    elif a.delta == "flatten":
        delta = None
    else:
        delta = (_matrix(a.delta, names, "abstract.delta", (nh, mh), on_xi) if isinstance(a.delta, list)
                 else sp.Matrix([[parse_expression(a.delta, names, "abstract.delta", offer=on_xi)]]))
        _check_free(delta, pset | set(xi), "abstract.delta", "the abstract states")
    m_given = None
    if a.m is not None:
        m_given = _matrix(a.m, names, "abstract.m", (nh, 1), on_x)
        _check_free(m_given, pset | set(x), "abstract.m", "the concrete states")
    p_given = None
    if a.p is not None:
        p_given = _matrix(a.p, names, "abstract.p", (n, 1))
        _check_free(p_given, pset | set(xi), "abstract.p", "the abstract states")
    V = None if a.domain == "auto" else np.array(a.domain, dtype=float)
    _check_finite_with_values(values, [("concrete.f_bar", f_bar), ("concrete.g", g), ("concrete.f", f_general), ("concrete.h", h),
                                       ("concrete.e", e), ("abstract.phi_bar", phi_bar), ("abstract.l", l),
                                       ("abstract.delta", delta), ("abstract.m", m_given), ("abstract.p", p_given)])
    return Model(
        spec=spec, params=params, values=values, x=x, u=u, xi=xi, v=v, f_bar=f_bar, g=g, h=h,
        phi_bar=phi_bar, l=l, delta=delta, U=np.array(c.input_bounds, dtype=float),
        Y=np.array(c.output_set, dtype=float), V=V, names=names,
        state_box=None if c.state_box is None else np.array(c.state_box, dtype=float), m_given=m_given, p_given=p_given,
        f_general=f_general, w=w, e=e, W=W,
    )


def _dynamics(spec: Spec, names: dict, pset: set, x: sp.Matrix, u: sp.Matrix) -> tuple[sp.Matrix | None, sp.Matrix | None, sp.Matrix | None]:
    """(f_bar, g, None) of an input-affine plant, or (None, None, f) of one that is not (``concrete.f``).

    An f given whole that is affine in u (df/du free of u) is split into f_bar = f(x, 0) and g = df/du, so every
    stage, the least-squares q included, applies to it.
    """
    c = spec.concrete
    n, m = len(x), len(u)
    if c.f is None:
        offer = _offer(names, pset | set(x))
        f_bar = _matrix(c.f_bar, names, "concrete.f_bar", (n, 1), offer)
        g = _matrix(c.g, names, "concrete.g", (n, m), offer)
        for mat, fname in ((f_bar, "concrete.f_bar"), (g, "concrete.g")):
            _check_free(mat, pset | set(x), fname, "the concrete states")
        return f_bar, g, None
    f = _matrix(c.f, names, "concrete.f", (n, 1), _offer(names, pset | set(x) | set(u)))
    _check_free(f, pset | set(x) | set(u), "concrete.f", "the concrete states and inputs")
    g = sparse_jacobian(f, list(u)).as_mutable() if n * m <= SPARSE_JACOBIAN_ENTRIES else None
    if g is not None and not any(sp.expand(e).free_symbols & set(u) for e in g):
        return f.xreplace({s: sp.S.Zero for s in u}), sp.Matrix(g), None
    if spec.interface.q == "least_squares":
        raise SpecError("interface.q", "least_squares needs g(x) of an input-affine plant, and concrete.f is not affine in the inputs",
                        "zero (the default for a plant written as f(x, u): condition (B) by Proposition 1)")
    return None, None, f
